//! Stable Neo-Hookean (Smith, de Goes, Kim 2018).

use super::psd::{project_psd_invariant, InvariantForm};
use super::{cofactor_derivative, flatten, lame_parameters, Hyperelastic, StressDerivative};
use crate::error::Result;
use crate::math::{cofactor, ddot, det, Mat3};

/// Stable Neo-Hookean (Smith, de Goes, Kim 2018):
/// `Psi = mu'/2 (I_C - 3) + lambda'/2 (J - alpha)^2 - mu'/2 log(I_C + 1) - Psi0`, with
/// `mu' = 4/3 mu`, `lambda' = lambda + 5/6 mu` (matching linear elasticity), `alpha = 1 + mu'/lambda' - mu'/(4 lambda')`,
/// and the constant `Psi0` chosen so that `Psi(I) = 0`. Defined for every F, inverted ones included.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StableNeoHookean {
    /// Reparameterised shear modulus `mu' = 4/3 mu`, Pa.
    pub mu: f64,
    /// Reparameterised bulk term `lambda' = lambda + 5/6 mu`, Pa.
    pub lambda: f64,
    /// Rest-stability offset `alpha`.
    pub alpha: f64,
    /// Energy density of the raw formula at `F = I` (subtracted so that the rest energy is zero).
    pub rest_offset: f64,
}

impl StableNeoHookean {
    /// From Young's modulus (Pa) and Poisson ratio.
    pub fn new(youngs_modulus: f64, poisson_ratio: f64) -> Result<Self> {
        let (mu, lambda) = lame_parameters(youngs_modulus, poisson_ratio)?;
        let mu_s = 4.0 / 3.0 * mu;
        let lambda_s = lambda + 5.0 / 6.0 * mu;
        let alpha = 1.0 + mu_s / lambda_s - mu_s / (4.0 * lambda_s);
        let rest_offset = 0.5 * lambda_s * (1.0 - alpha) * (1.0 - alpha) - 0.5 * mu_s * 4.0f64.ln();
        Ok(Self {
            mu: mu_s,
            lambda: lambda_s,
            alpha,
            rest_offset,
        })
    }
}

impl Hyperelastic for StableNeoHookean {
    fn energy_density(&self, f: &Mat3) -> f64 {
        let ic = ddot(f, f);
        let j = det(f);
        0.5 * self.mu * (ic - 3.0) + 0.5 * self.lambda * (j - self.alpha) * (j - self.alpha)
            - 0.5 * self.mu * (ic + 1.0).ln()
            - self.rest_offset
    }

    #[inline]
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        let ic = ddot(f, f);
        let j = det(f);
        let c = cofactor(f);
        let a = self.mu * (1.0 - 1.0 / (ic + 1.0));
        let b = self.lambda * (j - self.alpha);
        let mut p = [[0.0; 3]; 3];
        for i in 0..3 {
            for k in 0..3 {
                p[i][k] = a * f[i][k] + b * c[i][k];
            }
        }
        let psi = 0.5 * self.mu * (ic - 3.0)
            + 0.5 * self.lambda * (j - self.alpha) * (j - self.alpha)
            - 0.5 * self.mu * (ic + 1.0).ln()
            - self.rest_offset;
        (psi, p)
    }

    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        let ic = ddot(f, f);
        let j = det(f);
        let c = flatten(&cofactor(f));
        let ff = flatten(f);
        let a = self.mu * (1.0 - 1.0 / (ic + 1.0));
        let bf = 2.0 * self.mu / ((ic + 1.0) * (ic + 1.0));
        let b = self.lambda * (j - self.alpha);
        let mut d = cofactor_derivative(f);
        for r in 0..9 {
            for s in 0..9 {
                d[r][s] = b * d[r][s] + self.lambda * c[r] * c[s] + bf * ff[r] * ff[s];
            }
            d[r][r] += a;
        }
        d
    }

    /// Analytic eigen-system (`material::psd::project_psd_invariant`, crate-private):
    /// `dP/dF = a I + b d2J + lambda' c c^T + (2 mu' / (I_C + 1)^2) f f^T` with `a = mu' (1 - 1/(I_C + 1))`, `b = lambda' (J - alpha)`.
    fn stress_derivative_psd(&self, f: &Mat3) -> StressDerivative {
        let ic = ddot(f, f);
        let form = InvariantForm {
            identity: self.mu * (1.0 - 1.0 / (ic + 1.0)),
            hessian_j: self.lambda * (det(f) - self.alpha),
            cofactor: self.lambda,
            gradient: 2.0 * self.mu / ((ic + 1.0) * (ic + 1.0)),
        };
        project_psd_invariant(&self.stress_derivative(f), f, form)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::psd::tests::assert_analytic_projection_matches;

    #[test]
    fn analytic_psd_projection_matches_the_eigen_decomposition() {
        for m in [
            StableNeoHookean::new(1e3, 0.3).unwrap(),
            StableNeoHookean::new(1e5, 0.4).unwrap(),
            StableNeoHookean::new(5e4, 0.49).unwrap(),
        ] {
            assert_analytic_projection_matches(&m, 1e-9);
        }
    }
}
