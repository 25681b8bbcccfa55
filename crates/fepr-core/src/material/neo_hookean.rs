//! The seed's log Neo-Hookean with its C2 extension below `j0`.

use super::psd::{project_psd_invariant, InvariantForm};
use super::{cofactor_derivative, flatten, lame_parameters, ln, Hyperelastic, StressDerivative};
use crate::error::{invalid, Result};
use crate::math::{cofactor, ddot, det, Mat3};

/// The seed's log Neo-Hookean, `Psi = mu/2 (tr F^T F - 3) - mu l(J) + lambda/2 l(J)^2`, where `l(J) = log J`
/// for `J >= j0` and its C2 quadratic extension below `j0` (fepr-spec section 4):
/// `l(J) = log j0 + (J - j0)/j0 - (J - j0)^2 / (2 j0^2)`. The extension keeps energy and forces finite and
/// restoring for inverted elements (J <= 0); it is used identically in forces, Hessian and energy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NeoHookean {
    /// First Lame parameter `mu` (shear modulus), Pa.
    pub mu: f64,
    /// Second Lame parameter `lambda`, Pa.
    pub lambda: f64,
    /// Below this J the logarithm is replaced by its C2 extension (default 0.1).
    pub j0: f64,
}

impl NeoHookean {
    /// Default `j0` of the C2 extension.
    pub const DEFAULT_J0: f64 = 0.1;

    /// From Young's modulus (Pa) and Poisson ratio, with the default `j0 = 0.1`.
    pub fn new(youngs_modulus: f64, poisson_ratio: f64) -> Result<Self> {
        Self::with_j0(youngs_modulus, poisson_ratio, Self::DEFAULT_J0)
    }

    /// From Young's modulus (Pa), Poisson ratio and the extension threshold `0 < j0 <= 1`.
    pub fn with_j0(youngs_modulus: f64, poisson_ratio: f64, j0: f64) -> Result<Self> {
        let (mu, lambda) = lame_parameters(youngs_modulus, poisson_ratio)?;
        if !(j0.is_finite() && j0 > 0.0 && j0 <= 1.0) {
            return Err(invalid("j0", format!("must satisfy 0 < j0 <= 1, got {j0}")));
        }
        Ok(Self { mu, lambda, j0 })
    }

    /// `(l, l', l'')` of the extended logarithm at J.
    #[inline]
    fn extended_log(&self, j: f64) -> (f64, f64, f64) {
        if j >= self.j0 {
            (ln(j), 1.0 / j, -1.0 / (j * j))
        } else {
            let j0 = self.j0;
            let d = j - j0;
            (
                ln(j0) + d / j0 - d * d / (2.0 * j0 * j0),
                1.0 / j0 - d / (j0 * j0),
                -1.0 / (j0 * j0),
            )
        }
    }

    /// Volumetric part `g(J) = -mu l + lambda/2 l^2` and its first two derivatives in J.
    #[inline]
    fn volumetric(&self, j: f64) -> (f64, f64, f64) {
        let (l, dl, ddl) = self.extended_log(j);
        let g = -self.mu * l + 0.5 * self.lambda * l * l;
        let dg = (-self.mu + self.lambda * l) * dl;
        let ddg = self.lambda * dl * dl + (-self.mu + self.lambda * l) * ddl;
        (g, dg, ddg)
    }
}

impl Hyperelastic for NeoHookean {
    fn energy_density(&self, f: &Mat3) -> f64 {
        let ic = ddot(f, f);
        0.5 * self.mu * (ic - 3.0) + self.volumetric(det(f)).0
    }

    #[inline]
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        let ic = ddot(f, f);
        let j = det(f);
        let (g, dg, _) = self.volumetric(j);
        let c = cofactor(f);
        let mut p = [[0.0; 3]; 3];
        for i in 0..3 {
            for k in 0..3 {
                p[i][k] = self.mu * f[i][k] + dg * c[i][k];
            }
        }
        (0.5 * self.mu * (ic - 3.0) + g, p)
    }

    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        let j = det(f);
        let (_, dg, ddg) = self.volumetric(j);
        let c = flatten(&cofactor(f));
        let mut d = cofactor_derivative(f);
        for a in 0..9 {
            for b in 0..9 {
                d[a][b] = dg * d[a][b] + ddg * c[a] * c[b];
            }
            d[a][a] += self.mu;
        }
        d
    }

    /// Analytic eigen-system (`material::psd::project_psd_invariant`, crate-private):
    /// `dP/dF = mu I + g'(J) d2J + g''(J) c c^T`.
    fn stress_derivative_psd(&self, f: &Mat3) -> StressDerivative {
        let (_, dg, ddg) = self.volumetric(det(f));
        let form = InvariantForm {
            identity: self.mu,
            hessian_j: dg,
            cofactor: ddg,
            gradient: 0.0,
        };
        project_psd_invariant(&self.stress_derivative(f), f, form)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::psd::tests::assert_analytic_projection_matches;

    #[test]
    fn extension_is_c2_at_j0() {
        let m = NeoHookean::new(1e3, 0.3).unwrap();
        let below = m.extended_log(m.j0 * (1.0 - 1e-12));
        let at = m.extended_log(m.j0);
        assert!((below.0 - at.0).abs() < 1e-10);
        assert!((below.1 - at.1).abs() < 1e-8);
        assert!((below.2 - at.2).abs() < 1e-6 * at.2.abs());
    }

    #[test]
    fn inverted_elements_have_finite_restoring_energy() {
        let m = NeoHookean::new(1e3, 0.3).unwrap();
        // Energy decreases from an inverted F towards the identity along a straight path.
        let f_inv = [[-0.5, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let e_inv = m.energy_density(&f_inv);
        assert!(e_inv.is_finite() && e_inv > 0.0);
        let p = m.first_piola(&f_inv);
        // Force on F[0][0] pushes it back up (towards positive J): dPsi/dF00 < 0.
        assert!(p[0][0] < 0.0, "stress {p:?}");
    }

    #[test]
    fn analytic_psd_projection_matches_the_eigen_decomposition() {
        for m in [
            NeoHookean::new(1e3, 0.3).unwrap(),
            NeoHookean::with_j0(5e4, 0.45, 0.3).unwrap(),
            NeoHookean::new(1e5, -0.5).unwrap(),
        ] {
            assert_analytic_projection_matches(&m, 1e-11);
        }
    }
}
