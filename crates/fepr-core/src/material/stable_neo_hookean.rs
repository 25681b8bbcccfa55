//! Stable Neo-Hookean (Smith, de Goes, Kim 2018).

use super::{cofactor_derivative, flatten, lame_parameters, Hyperelastic, StressDerivative};
use crate::error::Result;
use crate::math::{cofactor, ddot, det, matmul, svd3, symmetric_eigen_fixed, transpose, Mat3};

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

    /// Analytic eigen-system (Smith, de Goes, Kim 2018 and 2019), as [`super::NeoHookean`]'s: with the
    /// rotation-variant SVD `F = U diag(s) V^T` and the orthonormal basis `vec(U E_ij V^T)`,
    /// `dP/dF = a I + b d2J + lambda' c c^T + (2 mu' / (I_C + 1)^2) f f^T` (`a = mu' (1 - 1/(I_C + 1))`,
    /// `b = lambda' (J - alpha)`, `c = cof F`, `f = vec F`) is block diagonal: for each pair `i < j` (`k` the third
    /// index) the twist and flip modes have eigenvalues `a + b s_k` and `a - b s_k`, and the diagonal modes span
    /// the 3x3 block `a I + b [[0, s2, s1], [s2, 0, s0], [s1, s0, 0]] + lambda' c c^T + (2 mu' / (I_C + 1)^2) s s^T`
    /// (here `c = (s1 s2, s0 s2, s0 s1)`). Each negative eigenvalue's `lambda q q^T` is subtracted, so an element
    /// that is already positive semi-definite is returned unchanged. Why analytic: near rest the flip modes'
    /// eigenvalues are zero by construction (the rest-stability offset alpha), so the generic test (a Cholesky
    /// factorisation, then a 9 x 9 Jacobi eigen-decomposition) sent most elements through the eigen-decomposition,
    /// which took over half of a backward Euler contact step on the armadillo.
    fn stress_derivative_psd(&self, f: &Mat3) -> StressDerivative {
        let mut d = self.stress_derivative(f);
        let ic = ddot(f, f);
        let a = self.mu * (1.0 - 1.0 / (ic + 1.0));
        let bf = 2.0 * self.mu / ((ic + 1.0) * (ic + 1.0));
        let b = self.lambda * (det(f) - self.alpha);
        let (u, s, v) = svd3(f);
        // Adds `-lambda vec(U Q V^T) vec(U Q V^T)^T`.
        let mut remove = |lambda: f64, q: &Mat3| {
            let m = matmul(&matmul(&u, q), &transpose(&v));
            let flat = flatten(&m);
            for r in 0..9 {
                let fr = -lambda * flat[r];
                for c in 0..9 {
                    d[r][c] += fr * flat[c];
                }
            }
        };
        let h = std::f64::consts::FRAC_1_SQRT_2;
        for (i, j, k) in [(0, 1, 2), (0, 2, 1), (1, 2, 0)] {
            for (sign, lambda) in [(-1.0, a + b * s[k]), (1.0, a - b * s[k])] {
                if lambda < 0.0 {
                    let mut q = [[0.0; 3]; 3];
                    q[i][j] = h;
                    q[j][i] = sign * h;
                    remove(lambda, &q);
                }
            }
        }
        let c = [s[1] * s[2], s[0] * s[2], s[0] * s[1]];
        let mut a3 = [
            [0.0, b * s[2], b * s[1]],
            [b * s[2], 0.0, b * s[0]],
            [b * s[1], b * s[0], 0.0],
        ];
        for (i, row) in a3.iter_mut().enumerate() {
            row[i] += a;
            for (j, x) in row.iter_mut().enumerate() {
                *x += self.lambda * c[i] * c[j] + bf * s[i] * s[j];
            }
        }
        let (w, vecs) = symmetric_eigen_fixed(&a3);
        for (n, &lambda) in w.iter().enumerate() {
            if lambda < 0.0 {
                let mut q = [[0.0; 3]; 3];
                for (i, row) in q.iter_mut().enumerate() {
                    row[i] = vecs[i][n];
                }
                remove(lambda, &q);
            }
        }
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::tests::samples;

    #[test]
    fn analytic_psd_projection_matches_the_eigen_decomposition() {
        let mut cases = samples();
        cases.extend([
            // rest (zero flip eigenvalues), repeated singular values, a rotation, nearly singular, flat, inverted
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            [[0.8, 0.0, 0.0], [0.0, 0.8, 0.0], [0.0, 0.0, 1.3]],
            [[1.1, 0.0, 0.0], [0.0, 1.1, 0.0], [0.0, 0.0, 1.1]],
            [[0.0, -0.9, 0.0], [0.9, 0.0, 0.0], [0.0, 0.0, 0.95]],
            [[1.0, 0.2, 0.0], [0.0, 1.0, 0.1], [0.0, 0.0, 1e-7]],
            [[1.0, 0.2, 0.0], [0.0, 1.0, 0.1], [0.0, 0.0, 0.0]],
            [[-0.3, 0.2, 0.1], [0.1, -0.4, 0.1], [0.05, 0.0, -0.2]],
        ]);
        for k in 0..40 {
            let t = k as f64;
            let (a, b, c) = ((0.7 * t).sin(), (1.3 * t).cos(), (0.4 * t).sin());
            cases.push([
                [1.0 + 0.5 * a, 0.3 * b, -0.2 * c],
                [0.2 * c, 0.9 - 0.6 * b * c, 0.25 * a],
                [-0.1 * a, 0.3 * c, 1.0 + 0.4 * b],
            ]);
        }
        for m in [
            StableNeoHookean::new(1e3, 0.3).unwrap(),
            StableNeoHookean::new(1e5, 0.4).unwrap(),
            StableNeoHookean::new(5e4, 0.49).unwrap(),
        ] {
            for f in &cases {
                let analytic = m.stress_derivative_psd(f);
                let reference = crate::material::project_psd(&m.stress_derivative(f));
                let scale = reference
                    .iter()
                    .flatten()
                    .fold(0.0f64, |s, v| s.max(v.abs()));
                for r in 0..9 {
                    for c in 0..9 {
                        let err = (analytic[r][c] - reference[r][c]).abs();
                        assert!(
                            err <= 1e-9 * scale,
                            "{m:?} F = {f:?}: [{r}][{c}] {} vs {} (err {err:e})",
                            analytic[r][c],
                            reference[r][c]
                        );
                    }
                }
            }
        }
    }
}
