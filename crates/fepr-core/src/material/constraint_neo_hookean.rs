//! The Neo-Hookean energy in the constraint form of XPBD (Macklin and Mueller 2021).

use super::{cofactor_derivative, flatten, lame_parameters, Hyperelastic, StressDerivative};
use crate::error::Result;
use crate::math::{cofactor, ddot, det, Mat3};

/// The Neo-Hookean energy in the constraint form of XPBD (Macklin and Mueller 2021, "A constraint-based
/// formulation of stable Neo-Hookean materials"):
/// `Psi = mu/2 (I_C - 3) + lambda'/2 (J - alpha)^2 - lambda'/2 (alpha - 1)^2`, `alpha = 1 + mu/lambda'`, with
/// `lambda' = lambda + mu` so that it matches linear elasticity at rest, and `Psi(I) = 0`. It is the sum of the
/// energies `C^2 / (2 compliance)` of the two per-element XPBD constraints, deviatoric `C_D = sqrt(I_C)`
/// (compliance `1 / (mu V)`) and hydrostatic `C_H = J - alpha` (compliance `1 / (lambda' V)`), up to the
/// constant: the energy the `xpbd` integrator's compliance encodes (fepr-spec section 5). Defined for every F.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConstraintNeoHookean {
    /// Shear modulus `mu`, Pa.
    pub mu: f64,
    /// `lambda' = lambda + mu`, Pa.
    pub lambda: f64,
    /// Rest-stability offset `alpha = 1 + mu / lambda'`.
    pub alpha: f64,
}

impl ConstraintNeoHookean {
    /// From Young's modulus (Pa) and Poisson ratio.
    pub fn new(youngs_modulus: f64, poisson_ratio: f64) -> Result<Self> {
        let (mu, lambda) = lame_parameters(youngs_modulus, poisson_ratio)?;
        // lambda + mu = E / (2 (1 + nu) (1 - 2 nu)) > 0 for every admissible nu.
        let lambda_s = lambda + mu;
        Ok(Self {
            mu,
            lambda: lambda_s,
            alpha: 1.0 + mu / lambda_s,
        })
    }
}

impl Hyperelastic for ConstraintNeoHookean {
    fn energy_density(&self, f: &Mat3) -> f64 {
        self.energy_and_stress(f).0
    }

    #[inline]
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        let ic = ddot(f, f);
        let j = det(f);
        let c = cofactor(f);
        let b = self.lambda * (j - self.alpha);
        let mut p = [[0.0; 3]; 3];
        for i in 0..3 {
            for k in 0..3 {
                p[i][k] = self.mu * f[i][k] + b * c[i][k];
            }
        }
        let a1 = self.alpha - 1.0;
        let psi = 0.5 * self.mu * (ic - 3.0)
            + 0.5 * self.lambda * ((j - self.alpha) * (j - self.alpha) - a1 * a1);
        (psi, p)
    }

    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        let j = det(f);
        let c = flatten(&cofactor(f));
        let b = self.lambda * (j - self.alpha);
        let mut d = cofactor_derivative(f);
        for r in 0..9 {
            for s in 0..9 {
                d[r][s] = b * d[r][s] + self.lambda * c[r] * c[s];
            }
            d[r][r] += self.mu;
        }
        d
    }
}
