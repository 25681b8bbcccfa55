//! Choices the simulation makes from the base integrator, so that a Rust user gets what a Python user or a
//! scene file gets: the warm-start threshold of the projection's `"auto"` mode and the material whose energy
//! the projection conserves.

use crate::error::Result;
use crate::material::{material_by_name, Material};

/// The projection's warm-start threshold after Projective Dynamics under `"auto"`: always (any scaled energy
/// error above the tolerance). PD at dt = 1/30 loses 10-90% of H per step on the bunny; with the warm start
/// its projection costs one energy + gradient evaluation instead of 5.6 iterations.
pub const PD_WARM_START: f64 = 0.0;

/// The projection's warm-start threshold after XPBD under `"auto"`: above 5% of the energy scale (XPBD loses
/// a quarter of H per step on sliver-rich meshes).
pub const XPBD_WARM_START: f64 = 0.05;

/// The warm-start threshold ([`crate::projection::ProjectionSettings::warm_start_threshold`]) that the
/// `"auto"` mode gives after the integrator named `integrator` (infinity: off).
pub fn auto_warm_start_threshold(integrator: &str) -> f64 {
    match integrator {
        "projective_dynamics" => PD_WARM_START,
        "xpbd" => XPBD_WARM_START,
        _ => f64::INFINITY,
    }
}

/// The material model whose energy the integrator named `integrator` minimises, where it is fixed by the
/// integrator: Projective Dynamics minimises the ARAP energy, XPBD's constraints encode the constraint
/// Neo-Hookean energy; the projection must conserve that energy (fepr-spec section 5). None: any material.
pub fn conserved_material_name(integrator: &str) -> Option<&'static str> {
    match integrator {
        "projective_dynamics" => Some("arap"),
        "xpbd" => Some("constraint_neo_hookean"),
        _ => None,
    }
}

/// The material a simulation with the integrator named `integrator` uses when `material` (with its Young's
/// modulus, Poisson ratio and `j0`) is asked for: [`conserved_material_name`] built from the same moduli where
/// the integrator fixes one, else `material` itself.
pub fn material_for_integrator(
    integrator: &str,
    material: &str,
    youngs_modulus: f64,
    poisson_ratio: f64,
    j0: f64,
) -> Result<Material> {
    let name = conserved_material_name(integrator).unwrap_or(material);
    material_by_name(name, youngs_modulus, poisson_ratio, j0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrators::INTEGRATOR_NAMES;
    use crate::material::MATERIAL_NAMES;

    #[test]
    fn policy_names_known_integrators_and_materials() {
        for n in INTEGRATOR_NAMES {
            if let Some(m) = conserved_material_name(n) {
                assert!(MATERIAL_NAMES.contains(&m), "{m}");
            }
            let w = auto_warm_start_threshold(n);
            assert!(w >= 0.0, "{n}: {w}");
        }
        assert_eq!(auto_warm_start_threshold("symplectic_euler"), f64::INFINITY);
        assert!(matches!(
            material_for_integrator("projective_dynamics", "neo_hookean", 1e5, 0.3, 0.1),
            Ok(Material::Arap(_))
        ));
        assert!(matches!(
            material_for_integrator("implicit_euler", "stable_neo_hookean", 1e5, 0.3, 0.1),
            Ok(Material::StableNeoHookean(_))
        ));
    }
}
