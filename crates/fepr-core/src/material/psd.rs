//! Positive semi-definite projection of a material's stress derivative `dP/dF` (9 x 9): negative eigenvalues
//! clamped to zero, so that Newton-type solves get a descent direction.

use super::StressDerivative;
use crate::math::symmetric_eigen_fixed;

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
