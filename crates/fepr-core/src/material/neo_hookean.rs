//! The seed's log Neo-Hookean with its C2 extension below `j0`.

use super::{cofactor_derivative, flatten, lame_parameters, ln, Hyperelastic, StressDerivative};
use crate::error::{invalid, Result};
use crate::math::{cofactor, ddot, det, matmul, svd3, symmetric_eigen_fixed, transpose, Mat3};

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

    /// Analytic eigen-system (after Smith, de Goes, Kim 2019). With the rotation-variant SVD
    /// `F = U diag(s) V^T` and the orthonormal basis `vec(U E_ij V^T)`, `dP/dF = mu I + g'(J) d2J + g''(J) c c^T`
    /// (`c = cof F`) is block diagonal: for each pair `i < j` (`k` the third index) the twist
    /// `(E_ij - E_ji)/sqrt 2` and flip `(E_ij + E_ji)/sqrt 2` modes have eigenvalues `mu + g' s_k` and
    /// `mu - g' s_k`, and the diagonal modes span the 3x3 block
    /// `mu I + g' [[0, s2, s1], [s2, 0, s0], [s1, s0, 0]] + g'' (s1 s2, s0 s2, s0 s1)(...)^T`.
    /// The projection subtracts `lambda q q^T` for each negative eigenvalue, so an element that is already
    /// positive semi-definite is returned unchanged.
    fn stress_derivative_psd(&self, f: &Mat3) -> StressDerivative {
        let mut d = self.stress_derivative(f);
        let (_, dg, ddg) = self.volumetric(det(f));
        let (u, s, v) = svd3(f);
        // Adds `-lambda vec(U Q V^T) vec(U Q V^T)^T`.
        let mut remove = |lambda: f64, q: &Mat3| {
            let uq = matmul(&u, q);
            let m = matmul(&uq, &transpose(&v));
            let flat = flatten(&m);
            for a in 0..9 {
                let fa = -lambda * flat[a];
                for b in 0..9 {
                    d[a][b] += fa * flat[b];
                }
            }
        };
        let h = std::f64::consts::FRAC_1_SQRT_2;
        for (i, j, k) in [(0, 1, 2), (0, 2, 1), (1, 2, 0)] {
            for (sign, lambda) in [(-1.0, self.mu + dg * s[k]), (1.0, self.mu - dg * s[k])] {
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
            [0.0, dg * s[2], dg * s[1]],
            [dg * s[2], 0.0, dg * s[0]],
            [dg * s[1], dg * s[0], 0.0],
        ];
        for (i, row) in a3.iter_mut().enumerate() {
            row[i] += self.mu;
            for (j, x) in row.iter_mut().enumerate() {
                *x += ddg * c[i] * c[j];
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
        let mut cases = samples();
        cases.extend([
            // repeated singular values (compressed and stretched), a rotation, nearly singular, flat
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
            NeoHookean::new(1e3, 0.3).unwrap(),
            NeoHookean::with_j0(5e4, 0.45, 0.3).unwrap(),
            NeoHookean::new(1e5, -0.5).unwrap(),
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
                            err <= 1e-11 * scale,
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
