//! The material models by name (Python: `fepr.NeoHookean(...).model`, scene files: `[material] model`). This
//! list is the one source; the Python bindings export it as `fepr._core.MATERIALS`.

use super::{Arap, ConstraintNeoHookean, Material, NeoHookean, StableNeoHookean};
use crate::error::{invalid, Result};

/// The names [`material_by_name`] accepts.
pub const MATERIAL_NAMES: &[&str] = &[
    "neo_hookean",
    "stable_neo_hookean",
    "arap",
    "constraint_neo_hookean",
];

/// The material `name` with Young's modulus `youngs_modulus` (Pa) and Poisson ratio `poisson_ratio`; `j0` is
/// the log extension threshold of `"neo_hookean"` (ignored by the others). Errors name the parameter.
pub fn material_by_name(
    name: &str,
    youngs_modulus: f64,
    poisson_ratio: f64,
    j0: f64,
) -> Result<Material> {
    Ok(match name {
        "neo_hookean" => {
            Material::NeoHookean(NeoHookean::with_j0(youngs_modulus, poisson_ratio, j0)?)
        }
        "stable_neo_hookean" => {
            Material::StableNeoHookean(StableNeoHookean::new(youngs_modulus, poisson_ratio)?)
        }
        "arap" => Material::Arap(Arap::new(youngs_modulus, poisson_ratio)?),
        "constraint_neo_hookean" => Material::ConstraintNeoHookean(ConstraintNeoHookean::new(
            youngs_modulus,
            poisson_ratio,
        )?),
        other => {
            return Err(invalid(
                "model",
                format!(
                    "unknown material model '{other}' (known: {})",
                    MATERIAL_NAMES.join(", ")
                ),
            ))
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_listed_material_builds() {
        for n in MATERIAL_NAMES {
            assert!(material_by_name(n, 1e5, 0.3, 0.1).is_ok(), "{n}");
        }
        let e = material_by_name("rubber", 1e5, 0.3, 0.1).unwrap_err();
        assert!(e.to_string().contains("neo_hookean"), "{e}");
    }
}
