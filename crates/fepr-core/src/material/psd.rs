//! Positive semi-definite projection of a material's stress derivative `dP/dF` (9 x 9): negative eigenvalues
//! clamped to zero, so that Newton-type solves get a descent direction.

use super::{flatten, StressDerivative};
use crate::math::{matmul, svd3, symmetric_eigen_fixed, transpose, Mat3};

/// True when a symmetric 9 x 9 matrix is positive definite (a Cholesky factorisation succeeds): the cheap
/// test that lets most elements skip the eigen-decomposition.
fn is_positive_definite(d: &StressDerivative) -> bool {
    let mut l = [[0.0f64; 9]; 9];
    for j in 0..9 {
        let mut diag = d[j][j];
        for k in 0..j {
            diag -= l[j][k] * l[j][k];
        }
        if diag.is_nan() || diag <= 0.0 {
            return false;
        }
        let djj = diag.sqrt();
        l[j][j] = djj;
        for i in (j + 1)..9 {
            let mut s = d[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            l[i][j] = s / djj;
        }
    }
    true
}

/// Clamp the negative eigenvalues of a symmetric 9 x 9 matrix to zero.
pub fn project_psd(d: &StressDerivative) -> StressDerivative {
    if is_positive_definite(d) {
        return *d;
    }
    let (w, v) = symmetric_eigen_fixed(d);
    if w.iter().all(|x| *x >= 0.0) {
        return *d;
    }
    let mut out = [[0.0; 9]; 9];
    for (k, &wk) in w.iter().enumerate() {
        if wk <= 0.0 {
            continue;
        }
        for i in 0..9 {
            let vi = v[i][k] * wk;
            for j in 0..9 {
                out[i][j] += vi * v[j][k];
            }
        }
    }
    out
}

/// The coefficients of an isotropic stress derivative of the form
/// `dP/dF = identity I + hessian_j d2J + cofactor c c^T + gradient f f^T` (`c = vec cof F`, `f = vec F`, `d2J` the
/// second derivative of `det F`): the Neo-Hookean models' (Pa).
#[derive(Clone, Copy, Debug)]
pub(crate) struct InvariantForm {
    pub identity: f64,
    pub hessian_j: f64,
    pub cofactor: f64,
    pub gradient: f64,
}

/// `d = dP/dF` at `f`, of the form `form`, with its negative eigenvalues clamped to zero, analytically (after
/// Smith, de Goes, Kim 2019). With the rotation-variant SVD `F = U diag(s) V^T` and the orthonormal basis
/// `vec(U E_ij V^T)` the form is block diagonal: for each pair `i < j` (`k` the third index) the twist
/// `(E_ij - E_ji)/sqrt 2` and flip `(E_ij + E_ji)/sqrt 2` modes have eigenvalues `identity + hessian_j s_k` and
/// `identity - hessian_j s_k`, and the diagonal modes span the 3x3 block
/// `identity I + hessian_j [[0, s2, s1], [s2, 0, s0], [s1, s0, 0]] + cofactor c c^T + gradient s s^T`
/// (here `c = (s1 s2, s0 s2, s0 s1)`). Each negative eigenvalue's `lambda q q^T` is subtracted, so an element that
/// is already positive semi-definite is returned unchanged. Why not [`project_psd`]: near rest the Stable
/// Neo-Hookean flip modes' eigenvalues are zero by construction, so its Cholesky test sent most elements through
/// the 9 x 9 eigen-decomposition (over half of a backward Euler contact step on the armadillo).
pub(crate) fn project_psd_invariant(
    d: &StressDerivative,
    f: &Mat3,
    form: InvariantForm,
) -> StressDerivative {
    let mut d = *d;
    let (u, s, v) = svd3(f);
    // Adds `-lambda vec(U Q V^T) vec(U Q V^T)^T`.
    let mut remove = |lambda: f64, q: &Mat3| {
        let m = matmul(&matmul(&u, q), &transpose(&v));
        let flat = flatten(&m);
        for a in 0..9 {
            let fa = -lambda * flat[a];
            for b in 0..9 {
                d[a][b] += fa * flat[b];
            }
        }
    };
    let (a, b) = (form.identity, form.hessian_j);
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
            let mut rank_one = form.cofactor * c[i] * c[j];
            if form.gradient != 0.0 {
                rank_one += form.gradient * s[i] * s[j];
            }
            *x += rank_one;
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::material::Hyperelastic;

    /// Deformation gradients for the analytic projections: the derivative tests' samples, rest (zero flip
    /// eigenvalues), repeated singular values, a rotation, nearly singular, flat, inverted, and 40 generic ones.
    fn cases() -> Vec<Mat3> {
        let mut cases = crate::material::tests::samples();
        cases.extend([
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
        cases
    }

    /// Asserts that `m`'s analytic projection equals [`project_psd`] (the eigen-decomposition) to `tolerance`
    /// relative to the largest entry, on every case.
    pub(crate) fn assert_analytic_projection_matches<M: Hyperelastic + std::fmt::Debug>(
        m: &M,
        tolerance: f64,
    ) {
        for f in &cases() {
            let analytic = m.stress_derivative_psd(f);
            let reference = project_psd(&m.stress_derivative(f));
            let scale = reference
                .iter()
                .flatten()
                .fold(0.0f64, |s, v| s.max(v.abs()));
            for r in 0..9 {
                for c in 0..9 {
                    let err = (analytic[r][c] - reference[r][c]).abs();
                    assert!(
                        err <= tolerance * scale,
                        "{m:?} F = {f:?}: [{r}][{c}] {} vs {} (err {err:e})",
                        analytic[r][c],
                        reference[r][c]
                    );
                }
            }
        }
    }
}
