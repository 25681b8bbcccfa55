//! Small fixed-size linear algebra: 3-vectors, 3x3 matrices (row-major `[[f64; 3]; 3]`), and a small
//! dense symmetric solver used by the projection (regularised Cholesky with an eigen-decomposition
//! least-squares fallback).
//!
//! Length: about 320 lines of code; the rest are the tests of each routine (eigen-solvers, polar, SVD, the
//! regularised solve and its fallback).

/// A 3-vector.
pub type Vec3 = [f64; 3];
/// A 3x3 matrix, row-major: `m[row][col]`.
pub type Mat3 = [[f64; 3]; 3];

#[inline]
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
#[inline]
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
#[inline]
pub fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
#[inline]
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
#[inline]
pub fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// Determinant of a 3x3 matrix.
#[inline]
pub fn det(m: &Mat3) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// The entries of [`cofactor`] as index quadruples: `cof[i][k] = m[a][b] m[c][d] - m[a][d] m[c][b]` for
/// `(a, b, c, d) = COFACTOR_PAIRS[i][k]`, for kernels that compute it on many matrices in lanes (same
/// operations, same bits).
pub const COFACTOR_PAIRS: [[(usize, usize, usize, usize); 3]; 3] = [
    [(1, 1, 2, 2), (1, 2, 2, 0), (1, 0, 2, 1)],
    [(0, 2, 2, 1), (0, 0, 2, 2), (0, 1, 2, 0)],
    [(0, 1, 1, 2), (0, 2, 1, 0), (0, 0, 1, 1)],
];

/// Cofactor matrix: `cof(F) = det(F) F^-T`, defined (and smooth) for every F, including singular ones.
/// It is the derivative of `det` with respect to F.
#[inline]
pub fn cofactor(m: &Mat3) -> Mat3 {
    [
        [
            m[1][1] * m[2][2] - m[1][2] * m[2][1],
            m[1][2] * m[2][0] - m[1][0] * m[2][2],
            m[1][0] * m[2][1] - m[1][1] * m[2][0],
        ],
        [
            m[0][2] * m[2][1] - m[0][1] * m[2][2],
            m[0][0] * m[2][2] - m[0][2] * m[2][0],
            m[0][1] * m[2][0] - m[0][0] * m[2][1],
        ],
        [
            m[0][1] * m[1][2] - m[0][2] * m[1][1],
            m[0][2] * m[1][0] - m[0][0] * m[1][2],
            m[0][0] * m[1][1] - m[0][1] * m[1][0],
        ],
    ]
}

/// Inverse of a 3x3 matrix, `None` if it is singular (det == 0) or not finite.
pub fn inverse(m: &Mat3) -> Option<Mat3> {
    let d = det(m);
    if d == 0.0 || !d.is_finite() {
        return None;
    }
    let c = cofactor(m);
    let mut inv = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            inv[i][j] = c[j][i] / d;
        }
    }
    Some(inv)
}

#[inline]
pub fn transpose(m: &Mat3) -> Mat3 {
    [
        [m[0][0], m[1][0], m[2][0]],
        [m[0][1], m[1][1], m[2][1]],
        [m[0][2], m[1][2], m[2][2]],
    ]
}

#[inline]
pub fn matmul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    c
}

/// Frobenius inner product `A : B`.
#[inline]
pub fn ddot(a: &Mat3, b: &Mat3) -> f64 {
    let mut s = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            s += a[i][j] * b[i][j];
        }
    }
    s
}

/// Solve a small dense symmetric positive semi-definite system `a x = b` (`a` row-major n x n) robustly.
///
/// Adds `delta * a_ii` to each diagonal entry (`delta * trace/n` to an entry that is not positive) and tries a
/// Cholesky factorisation; if that
/// fails (not positive definite in floating point) or yields a non-finite result, it falls back to the
/// minimum-norm least-squares solution from a Jacobi eigen-decomposition (rank-revealing, cut-off relative
/// to the largest eigenvalue). Returns the solution and whether the fallback was used.
pub fn solve_symmetric_psd(a: &[f64], b: &[f64], n: usize, delta: f64) -> (Vec<f64>, bool) {
    let (mut l, mut x) = (vec![0.0; n * n], vec![0.0; n]);
    let lstsq = solve_symmetric_psd_into(a, b, n, delta, &mut l, &mut x);
    (x, lstsq)
}

/// [`solve_symmetric_psd`] into caller-owned memory: `x` (length `n`) gets the solution, `l` (length at
/// least `n * n`) is scratch for the factor. No allocation unless the least-squares fallback runs. Returns
/// whether it did.
pub fn solve_symmetric_psd_into(
    a: &[f64],
    b: &[f64],
    n: usize,
    delta: f64,
    l: &mut [f64],
    x: &mut [f64],
) -> bool {
    debug_assert_eq!(a.len(), n * n);
    // Relative to each row's own diagonal, not to the trace: where one row's diagonal dwarfs the others (the
    // energy row of a fast body, whose kinetic energy is nearly a combination of the momentum rows), a shift of
    // the trace's size would swamp the small rows and leave their residuals unsolved.
    let trace: f64 = (0..n).map(|i| a[i * n + i]).sum();
    let floor = if trace > 0.0 {
        delta * trace / n as f64
    } else {
        0.0
    };
    let (l, x) = (&mut l[..n * n], &mut x[..n]);
    l.copy_from_slice(a);
    for i in 0..n {
        let d = a[i * n + i];
        l[i * n + i] += if d > 0.0 { delta * d } else { floor };
    }
    x.copy_from_slice(&b[..n]);
    if cholesky_solve_in_place(l, x, n) && x.iter().all(|v| v.is_finite()) {
        return false;
    }
    x.copy_from_slice(&eigen_least_squares(a, b, n));
    true
}

/// Factor `l` (n x n, row-major, lower triangle used) in place by Cholesky and solve `L L^T y = b` in `y`
/// (holding `b` on entry); false if the matrix is not positive definite in floating point. The factor's
/// diagonal holds the reciprocals `1 / L_ii`, so that the substitutions multiply where they divided: the
/// divisions sat in their dependency chains, and the projection substitutes several times per iteration (its
/// serial small solve on the 1k box: 2.1 -> 1.8 us, temporary timers).
fn cholesky_solve_in_place(l: &mut [f64], y: &mut [f64], n: usize) -> bool {
    // In-place lower Cholesky factor, its rows sliced so that the inner loops run without bounds checks (the same
    // operations in the same order as indexing them).
    let l = &mut l[..n * n];
    for j in 0..n {
        let (upper, lower) = l.split_at_mut((j + 1) * n);
        let row_j = &mut upper[j * n..];
        let mut d = row_j[j];
        for ljk in &row_j[..j] {
            d -= ljk * ljk;
        }
        if d <= 0.0 || !d.is_finite() {
            return false;
        }
        let inv_d = 1.0 / d.sqrt();
        row_j[j] = inv_d;
        let row_j = &row_j[..j];
        for row_i in lower.chunks_exact_mut(n) {
            let mut s = row_i[j];
            for (lik, ljk) in row_i[..j].iter().zip(row_j) {
                s -= lik * ljk;
            }
            row_i[j] = s * inv_d;
        }
    }
    cholesky_substitute(l, y, n);
    true
}

/// Solve `L L^T y = b` in `y` (holding `b` on entry) with the lower Cholesky factor `L` that a successful
/// [`solve_symmetric_psd_into`] (one that returned false) left in its scratch `l` (its diagonal holding
/// `1 / L_ii`): another right-hand side of the same (shifted) matrix, without factoring it again.
pub fn cholesky_substitute(l: &[f64], y: &mut [f64], n: usize) {
    // Sliced once, so that the loops run without bounds checks; each `y_i` accumulates in a register, its
    // terms in the same order as `y[i] -= l_ik y[k]` would (the same bits).
    let (l, y) = (&l[..n * n], &mut y[..n]);
    for i in 0..n {
        let (solved, rest) = y.split_at_mut(i);
        let row = &l[i * n..i * n + i];
        let mut yi = rest[0];
        for (lik, yk) in row.iter().zip(solved.iter()) {
            yi -= lik * yk;
        }
        rest[0] = yi * l[i * n + i];
    }
    for i in (0..n).rev() {
        let (head, solved) = y.split_at_mut(i + 1);
        let mut yi = head[i];
        // Column i below the diagonal: l[k n + i] for k > i (none for the last row).
        let below = l.get((i + 1) * n + i..).unwrap_or_default();
        for (yk, lki) in solved.iter().zip(below.iter().step_by(n)) {
            yi -= lki * yk;
        }
        head[i] = yi * l[i * n + i];
    }
}

/// Cyclic Jacobi eigen-decomposition of a symmetric matrix: returns (eigenvalues, eigenvectors as columns
/// of a row-major n x n matrix).
pub fn symmetric_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut m = a.to_vec();
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    for _sweep in 0..100 {
        let mut off = 0.0;
        let mut total = 0.0;
        for i in 0..n {
            for j in 0..n {
                let x = m[i * n + j] * m[i * n + j];
                total += x;
                if i != j {
                    off += x;
                }
            }
        }
        if off <= 1e-30 * total || off == 0.0 {
            break;
        }
        for p in 0..n {
            for q in (p + 1)..n {
                let apq = m[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let app = m[p * n + p];
                let aqq = m[q * n + q];
                let theta = (aqq - app) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let mkp = m[k * n + p];
                    let mkq = m[k * n + q];
                    m[k * n + p] = c * mkp - s * mkq;
                    m[k * n + q] = s * mkp + c * mkq;
                }
                for k in 0..n {
                    let mpk = m[p * n + k];
                    let mqk = m[q * n + k];
                    m[p * n + k] = c * mpk - s * mqk;
                    m[q * n + k] = s * mpk + c * mqk;
                }
                for k in 0..n {
                    let vkp = v[k * n + p];
                    let vkq = v[k * n + q];
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..n).map(|i| m[i * n + i]).collect(), v)
}

/// Minimum-norm least-squares solution of a symmetric system via its eigen-decomposition; eigenvalues
/// below `1e-12 * max|eigenvalue|` are treated as zero (rank-revealing).
pub fn eigen_least_squares(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let (w, v) = symmetric_eigen(a, n);
    let wmax = w.iter().fold(0.0f64, |acc, x| acc.max(x.abs()));
    let mut x = vec![0.0; n];
    if wmax.is_nan() || wmax <= 0.0 || !wmax.is_finite() {
        return x;
    }
    for k in 0..n {
        if w[k].abs() <= 1e-12 * wmax {
            continue;
        }
        let mut proj = 0.0;
        for i in 0..n {
            proj += v[i * n + k] * b[i];
        }
        let coef = proj / w[k];
        for i in 0..n {
            x[i] += coef * v[i * n + k];
        }
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cofactor_is_det_times_inverse_transpose() {
        let m = [[2.0, 0.3, -0.1], [0.2, 1.5, 0.4], [-0.3, 0.1, 0.9]];
        let inv = inverse(&m).unwrap();
        let c = cofactor(&m);
        let d = det(&m);
        for i in 0..3 {
            for j in 0..3 {
                assert!((c[i][j] - d * inv[j][i]).abs() < 1e-14);
            }
        }
        let id = matmul(&m, &inv);
        for i in 0..3 {
            for j in 0..3 {
                let e = if i == j { 1.0 } else { 0.0 };
                assert!((id[i][j] - e).abs() < 1e-14);
            }
        }
    }

    #[test]
    fn symmetric_solver_handles_singular_consistent_systems() {
        // Rank-1 matrix [1 1; 1 1] with consistent right-hand side: minimum-norm solution (0.5, 0.5).
        let a = [1.0, 1.0, 1.0, 1.0];
        let (x, _) = solve_symmetric_psd(&a, &[1.0, 1.0], 2, 1e-12);
        let r0 = x[0] + x[1] - 1.0;
        assert!(r0.abs() < 1e-9, "residual {r0}");
        let x = eigen_least_squares(&a, &[1.0, 1.0], 2);
        assert!((x[0] - 0.5).abs() < 1e-12 && (x[1] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn symmetric_solver_matches_direct_solution() {
        let a = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0];
        let b = [1.0, 2.0, 3.0];
        let (x, fb) = solve_symmetric_psd(&a, &b, 3, 0.0);
        assert!(!fb);
        let y = eigen_least_squares(&a, &b, 3);
        for i in 0..3 {
            let r: f64 = (0..3).map(|j| a[i * 3 + j] * x[j]).sum::<f64>() - b[i];
            assert!(r.abs() < 1e-13);
            assert!((x[i] - y[i]).abs() < 1e-12);
        }
    }

    /// The factor that `solve_symmetric_psd_into` leaves (reciprocal diagonal) solves another right-hand side
    /// with `cholesky_substitute`: a 10 x 10 system like the projection's.
    #[test]
    fn the_factor_left_solves_another_right_hand_side() {
        let n = 10;
        let a: Vec<f64> = (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                if i == j {
                    2.0 + i as f64
                } else {
                    0.3 / (1.0 + (i as f64 - j as f64).abs())
                }
            })
            .collect();
        let (mut l, mut x) = (vec![0.0; n * n], vec![0.0; n]);
        let b: Vec<f64> = (0..n).map(|i| 1.0 - 0.2 * i as f64).collect();
        assert!(!solve_symmetric_psd_into(&a, &b, n, 0.0, &mut l, &mut x));
        let mut y: Vec<f64> = (0..n).map(|i| (i as f64).sin()).collect();
        let c = y.clone();
        cholesky_substitute(&l, &mut y, n);
        for (sol, rhs) in [(&x, &b), (&y, &c)] {
            for i in 0..n {
                let r: f64 = (0..n).map(|j| a[i * n + j] * sol[j]).sum::<f64>() - rhs[i];
                assert!(r.abs() < 1e-13, "row {i}: residual {r}");
            }
        }
    }
}

/// Maximum number of Jacobi sweeps of [`symmetric_eigen_fixed`]; convergence is quadratic, so a well-scaled
/// 3x3 or 9x9 matrix needs 4 to 8; the cap only bounds pathological (non-finite) input.
pub const JACOBI_MAX_SWEEPS: usize = 50;

/// Cyclic Jacobi eigen-decomposition of a fixed-size symmetric matrix, without allocation: returns the
/// eigenvalues (unsorted) and the eigenvectors as the columns of `v` (`a = v diag(w) v^T`). Only the upper
/// triangle of `a` is read.
///
/// Rutishauser's variant (Numerical Recipes' `jacobi`): the diagonal is updated through accumulated
/// corrections, and after the first sweeps an off-diagonal entry is set to zero when it is negligible
/// against *both* diagonal entries it couples, so every eigenvalue is accurate relative to its own size
/// (graded matrices such as `F^T F` of a nearly flat tet keep their small eigenvalues), not only relative
/// to the largest. It stops when every off-diagonal entry is exactly zero, or after
/// [`JACOBI_MAX_SWEEPS`] sweeps. Repeated eigenvalues need no special case (an orthonormal basis of the
/// eigenspace is returned). Sequential, so the result does not depend on the thread count.
pub fn symmetric_eigen_fixed<const N: usize>(a: &[[f64; N]; N]) -> ([f64; N], [[f64; N]; N]) {
    let mut m = *a;
    let mut v = [[0.0; N]; N];
    let mut d = [0.0; N];
    for i in 0..N {
        v[i][i] = 1.0;
        d[i] = m[i][i];
    }
    let mut b = d;
    let mut z = [0.0; N];
    #[inline(always)]
    fn rot(g: f64, h: f64, s: f64, tau: f64) -> (f64, f64) {
        (g - s * (h + g * tau), h + s * (g - h * tau))
    }
    for sweep in 0..JACOBI_MAX_SWEEPS {
        let mut sm = 0.0;
        for p in 0..N {
            for q in (p + 1)..N {
                sm += m[p][q].abs();
            }
        }
        if sm == 0.0 || !sm.is_finite() {
            break;
        }
        // Early sweeps skip the small entries (they shrink by themselves as the large ones are rotated).
        let thresh = if sweep < 3 {
            0.2 * sm / (N * N) as f64
        } else {
            0.0
        };
        for p in 0..N {
            for q in (p + 1)..N {
                let apq = m[p][q];
                let g = 100.0 * apq.abs();
                if sweep > 3 && d[p].abs() + g == d[p].abs() && d[q].abs() + g == d[q].abs() {
                    m[p][q] = 0.0;
                } else if apq.abs() > thresh {
                    let hd = d[q] - d[p];
                    let t = if hd.abs() + g == hd.abs() {
                        apq / hd
                    } else {
                        let theta = 0.5 * hd / apq;
                        let t = 1.0 / (theta.abs() + (1.0 + theta * theta).sqrt());
                        if theta < 0.0 {
                            -t
                        } else {
                            t
                        }
                    };
                    let c = 1.0 / (1.0 + t * t).sqrt();
                    let s = t * c;
                    let tau = s / (1.0 + c);
                    let hh = t * apq;
                    z[p] -= hh;
                    z[q] += hh;
                    d[p] -= hh;
                    d[q] += hh;
                    m[p][q] = 0.0;
                    for j in 0..p {
                        (m[j][p], m[j][q]) = rot(m[j][p], m[j][q], s, tau);
                    }
                    for j in (p + 1)..q {
                        (m[p][j], m[j][q]) = rot(m[p][j], m[j][q], s, tau);
                    }
                    for j in (q + 1)..N {
                        (m[p][j], m[q][j]) = rot(m[p][j], m[q][j], s, tau);
                    }
                    for row in v.iter_mut() {
                        (row[p], row[q]) = rot(row[p], row[q], s, tau);
                    }
                }
            }
        }
        for i in 0..N {
            b[i] += z[i];
            d[i] = b[i];
            z[i] = 0.0;
        }
    }
    (d, v)
}

/// Eigen-decomposition of a symmetric 3x3 matrix ([`symmetric_eigen_fixed`]): eigenvalues sorted in
/// decreasing order and the matching eigenvectors as the columns of a rotation (det +1).
pub fn symmetric_eigen3(a: &Mat3) -> (Vec3, Mat3) {
    let (w, vv) = symmetric_eigen_fixed(a);
    // Sort by decreasing eigenvalue (a fixed 3-element network; NaN-safe: comparisons with NaN are false).
    let mut order = [0usize, 1, 2];
    if w[order[0]] < w[order[1]] {
        order.swap(0, 1);
    }
    if w[order[1]] < w[order[2]] {
        order.swap(1, 2);
    }
    if w[order[0]] < w[order[1]] {
        order.swap(0, 1);
    }
    let mut v = [[0.0; 3]; 3];
    let mut ws = [0.0; 3];
    for (c, &k) in order.iter().enumerate() {
        ws[c] = w[k];
        for r in 0..3 {
            v[r][c] = vv[r][k];
        }
    }
    if det(&v) < 0.0 {
        for row in v.iter_mut() {
            row[2] = -row[2];
        }
    }
    (ws, v)
}

/// Polar decomposition `F = R S` with `R` a rotation (det +1) and `S` symmetric. Returns `(R, S)`.
///
/// Fast path, for `det F > 0` and not nearly singular: Higham's scaled Newton iteration
/// `X <- (g X + X^-T / g) / 2` (`X^-T = cof(X) / det X`, `g` the Frobenius-norm scaling, switched off near
/// convergence), which converges quadratically to the rotation for any positive-determinant F and is
/// insensitive to repeated singular values; it stops when an update changes X by less than 1e-8 (the error left,
/// about its square, is then below round-off) and `S = sym(R^T F)`. Otherwise (inverted, nearly singular, or no
/// convergence in 30 iterations) it falls back to [`polar_rotation_svd`]. Allocation-free.
pub fn polar_rotation(f: &Mat3) -> (Mat3, Mat3) {
    let scale2 = ddot(f, f);
    let d0 = det(f);
    // |det F| <= (|F|_F^2 / 3)^{3/2}; below 1e-9 of that, F is nearly singular (or inverted): use the SVD.
    let bound = (scale2 / 3.0) * (scale2 / 3.0).sqrt();
    if d0 > 1e-9 * bound && bound.is_finite() {
        let mut x = *f;
        let mut scaled = true;
        for _ in 0..30 {
            let c = cofactor(&x);
            let dx = x[0][0] * c[0][0] + x[0][1] * c[0][1] + x[0][2] * c[0][2];
            if dx <= 0.0 || !dx.is_finite() {
                break;
            }
            let g = if scaled {
                // g^2 = |X^-1|_F / |X|_F = |cof X|_F / (det X |X|_F)
                ((ddot(&c, &c).sqrt() / dx) / ddot(&x, &x).sqrt()).sqrt()
            } else {
                1.0
            };
            let (a, b) = (0.5 * g, 0.5 / (g * dx));
            let mut diff = 0.0;
            for i in 0..3 {
                for j in 0..3 {
                    let nx = a * x[i][j] + b * c[i][j];
                    let e = nx - x[i][j];
                    diff += e * e;
                    x[i][j] = nx;
                }
            }
            if diff <= 1e-16 {
                let rtf = matmul(&transpose(&x), f);
                let mut s = [[0.0; 3]; 3];
                for i in 0..3 {
                    for j in 0..3 {
                        s[i][j] = 0.5 * (rtf[i][j] + rtf[j][i]);
                    }
                }
                return (x, s);
            }
            if diff <= 1e-4 {
                scaled = false;
            }
        }
    }
    polar_rotation_svd(f)
}

/// Rotation-variant singular value decomposition `F = U diag(sigma) V^T` with `U`, `V` rotations (det +1),
/// through the eigen-decomposition of `F^T F`: `sigma` in decreasing order of magnitude, and for inverted `F`
/// (det < 0) the last singular value is negative; for singular `F` the missing directions of `U` complete a
/// right-handed frame. Allocation-free. Returns `(U, sigma, V)`.
pub fn svd3(f: &Mat3) -> (Mat3, Vec3, Mat3) {
    let ftf = matmul(&transpose(f), f);
    let (w, v) = symmetric_eigen3(&ftf);
    let mut sigma = [0.0; 3];
    for c in 0..3 {
        sigma[c] = w[c].max(0.0).sqrt();
    }
    // U columns: F v_c / sigma_c for the two largest; the third completes a right-handed frame.
    let fv = matmul(f, &v);
    let col = |m: &Mat3, c: usize| [m[0][c], m[1][c], m[2][c]];
    let mut u0 = col(&fv, 0);
    let n0 = norm(u0);
    u0 = if n0 > 0.0 {
        scale(u0, 1.0 / n0)
    } else {
        [1.0, 0.0, 0.0]
    };
    let mut u1 = col(&fv, 1);
    u1 = sub(u1, scale(u0, dot(u0, u1)));
    let n1 = norm(u1);
    u1 = if n1 > 1e-300 {
        scale(u1, 1.0 / n1)
    } else {
        // Any unit vector orthogonal to u0.
        let t = if u0[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let p = sub(t, scale(u0, dot(u0, t)));
        scale(p, 1.0 / norm(p))
    };
    let u2 = cross(u0, u1);
    // Singular values from F V (not from the square roots of the eigenvalues of F^T F, which lose the small
    // ones); det F < 0: the third singular value is negative in the rotation-variant SVD.
    if n0 > 0.0 {
        sigma[0] = n0;
    }
    sigma[1] = dot(u1, col(&fv, 1));
    sigma[2] = dot(u2, col(&fv, 2));
    let u = [
        [u0[0], u1[0], u2[0]],
        [u0[1], u1[1], u2[1]],
        [u0[2], u1[2], u2[2]],
    ];
    (u, sigma, v)
}

/// Polar decomposition through [`svd3`] (`R = U V^T`, `S = V diag(sigma) V^T`), defined for every F: for
/// inverted `F` (det < 0) the smallest singular value takes the sign, so that `R` stays a rotation (the
/// closest rotation in the Frobenius norm). Allocation-free. Returns `(R, S)`.
pub fn polar_rotation_svd(f: &Mat3) -> (Mat3, Mat3) {
    let (u, sigma, v) = svd3(f);
    let r = matmul(&u, &transpose(&v));
    let mut s = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            s[i][j] = (0..3).map(|k| v[i][k] * sigma[k] * v[j][k]).sum();
        }
    }
    (r, s)
}

#[cfg(test)]
mod polar_tests {
    use super::*;

    #[test]
    fn polar_decomposition_reconstructs_f_with_a_rotation() {
        let cases: [Mat3; 4] = [
            [[1.2, 0.3, -0.1], [0.1, 0.8, 0.2], [-0.2, 0.1, 1.1]],
            [[-0.9, 0.1, 0.0], [0.05, 1.0, 0.1], [0.0, 0.2, 0.9]],
            [[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1e-9]],
            [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
        ];
        for f in cases {
            let (r, s) = polar_rotation(&f);
            let rs = matmul(&r, &s);
            let rtr = matmul(&transpose(&r), &r);
            assert!((det(&r) - 1.0).abs() < 1e-12, "{f:?}");
            for i in 0..3 {
                for j in 0..3 {
                    assert!((rs[i][j] - f[i][j]).abs() < 1e-10, "{f:?}: RS = {rs:?}");
                    assert!((rtr[i][j] - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
                    assert!((s[i][j] - s[j][i]).abs() < 1e-12);
                }
            }
        }
    }

    /// xorshift64*: a deterministic generator for the randomised tests.
    struct Rng(u64);
    impl Rng {
        fn uniform(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            ((self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64) / (1u64 << 53) as f64 * 2.0
                - 1.0
        }
    }

    /// A random rotation of size N (Gram-Schmidt of a random matrix, twice for orthogonality).
    fn random_orthogonal<const N: usize>(rng: &mut Rng) -> [[f64; N]; N] {
        let mut q = [[0.0; N]; N];
        for row in q.iter_mut() {
            for x in row.iter_mut() {
                *x = rng.uniform();
            }
        }
        for _ in 0..2 {
            for c in 0..N {
                for k in 0..c {
                    let d: f64 = (0..N).map(|r| q[r][c] * q[r][k]).sum();
                    for r in 0..N {
                        q[r][c] -= d * q[r][k];
                    }
                }
                let n: f64 = (0..N).map(|r| q[r][c] * q[r][c]).sum::<f64>().sqrt();
                for row in q.iter_mut() {
                    row[c] /= n;
                }
            }
        }
        q
    }

    /// `Q diag(w) Q^T`, symmetrised exactly.
    fn with_spectrum<const N: usize>(q: &[[f64; N]; N], w: &[f64; N]) -> [[f64; N]; N] {
        let mut a = [[0.0; N]; N];
        for i in 0..N {
            for j in 0..=i {
                let s: f64 = (0..N).map(|k| q[i][k] * w[k] * q[j][k]).sum();
                a[i][j] = s;
                a[j][i] = s;
            }
        }
        a
    }

    fn sorted(mut w: Vec<f64>) -> Vec<f64> {
        w.sort_by(|a, b| a.partial_cmp(b).unwrap());
        w
    }

    /// Checks the fixed-size decomposition of `a` against its definition and the general Jacobi solver.
    fn check_eigen<const N: usize>(a: &[[f64; N]; N], label: &str) {
        let (w, v) = symmetric_eigen_fixed(a);
        let norm_a = a.iter().flatten().map(|x| x * x).sum::<f64>().sqrt();
        let tol = 1e-14 * norm_a.max(f64::MIN_POSITIVE);
        for i in 0..N {
            for j in 0..N {
                let rec: f64 = (0..N).map(|k| v[i][k] * w[k] * v[j][k]).sum();
                assert!(
                    (rec - a[i][j]).abs() <= 4.0 * tol,
                    "{label}: V W V^T [{i}][{j}]"
                );
                let vtv: f64 = (0..N).map(|k| v[k][i] * v[k][j]).sum();
                let e = if i == j { 1.0 } else { 0.0 };
                assert!(
                    (vtv - e).abs() <= 1e-14,
                    "{label}: V^T V [{i}][{j}] = {vtv}"
                );
            }
        }
        let flat: Vec<f64> = a.iter().flatten().copied().collect();
        let (w_old, _) = symmetric_eigen(&flat, N);
        for (x, y) in sorted(w.to_vec()).iter().zip(sorted(w_old)) {
            assert!(
                (x - y).abs() <= 4.0 * tol,
                "{label}: eigenvalue {x} vs old {y}"
            );
        }
    }

    #[test]
    fn fixed_size_eigen_matches_the_general_solver_on_random_and_degenerate_matrices() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        for trial in 0..200 {
            let q3 = random_orthogonal::<3>(&mut rng);
            let q9 = random_orthogonal::<9>(&mut rng);
            let r = [rng.uniform(), rng.uniform(), rng.uniform()];
            let spectra3 = [
                r,                               // random
                [r[0], r[0], r[1]],              // a repeated pair
                [r[0], r[0], r[0]],              // a multiple of the identity (rotated)
                [0.0, 0.0, r[0]],                // rank 1
                [0.0, 0.0, 0.0],                 // zero
                [1e12, 1.0, 1e-12],              // condition number 1e24
                [1.0, 1.0 + 1e-13, 1.0 - 1e-13], // nearly repeated
                [-2.0 * r[0].abs(), 1e-15, 3.0], // indefinite
            ];
            for (k, w) in spectra3.iter().enumerate() {
                check_eigen(
                    &with_spectrum(&q3, w),
                    &format!("3x3 trial {trial} spectrum {k}"),
                );
            }
            let mut w9 = [0.0; 9];
            for x in w9.iter_mut() {
                *x = rng.uniform();
            }
            check_eigen(&with_spectrum(&q9, &w9), &format!("9x9 random {trial}"));
            // Neo-Hookean-like: a repeated block, zeros and negatives.
            let w9 = [1.0, 1.0, 1.0, -0.3, -0.3, 0.0, 0.0, 5.0, 1e-9];
            check_eigen(&with_spectrum(&q9, &w9), &format!("9x9 degenerate {trial}"));
        }
        // Already diagonal, and exactly zero: no rotation at all.
        let (w, v) = symmetric_eigen_fixed(&[[2.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 0.0]]);
        assert_eq!(w, [2.0, -1.0, 0.0]);
        assert_eq!(v, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        let (w, _) = symmetric_eigen_fixed(&[[0.0; 9]; 9]);
        assert_eq!(w, [0.0; 9]);
    }

    #[test]
    fn fixed_size_eigen_keeps_small_eigenvalues_of_graded_matrices_accurate() {
        // A = D H D with H well conditioned and D = diag(1e6, 1, 1e-6): the eigenvalues span 24 orders of
        // magnitude and are each determined to relative accuracy by the entries; their product is det A.
        let h = [[2.0, 0.5, 0.3], [0.5, 1.5, -0.2], [0.3, -0.2, 1.0]];
        let dd = [1e6, 1.0, 1e-6];
        let mut a = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] = dd[i] * h[i][j] * dd[j];
            }
        }
        let (w, _) = symmetric_eigen3(&a);
        let det_a = det(&h); // det(D)^2 = 1
        let prod = w[0] * w[1] * w[2];
        assert!(w[2] > 0.0 && w[2] < 1e-11, "{w:?}");
        assert!((prod - det_a).abs() <= 1e-12 * det_a, "{prod} vs {det_a}");
    }

    /// `cond` = sigma_1 / (sigma_2 + sigma_3) (>= 1): the sensitivity of R to F.
    fn check_polar(f: &Mat3, cond: f64, label: &str) -> (Mat3, Mat3) {
        let (r, s) = polar_rotation(f);
        let rs = matmul(&r, &s);
        let rtr = matmul(&transpose(&r), &r);
        let nf = ddot(f, f).sqrt();
        assert!(
            (det(&r) - 1.0).abs() < 1e-14,
            "{label}: det R = {}",
            det(&r)
        );
        for i in 0..3 {
            for j in 0..3 {
                let e = if i == j { 1.0 } else { 0.0 };
                assert!((rtr[i][j] - e).abs() < 2e-15, "{label}: R^T R");
                let err = (rs[i][j] - f[i][j]).abs();
                assert!(err < 1e-14 * nf * cond, "{label}: RS - F = {err}");
                assert!(
                    (s[i][j] - s[j][i]).abs() < 1e-15 * nf,
                    "{label}: S symmetric"
                );
            }
        }
        (r, s)
    }

    #[test]
    fn polar_newton_path_matches_the_eigen_path() {
        let mut rng = Rng(12345);
        for trial in 0..500 {
            let q = random_orthogonal::<3>(&mut rng);
            let mut p = random_orthogonal::<3>(&mut rng);
            if det(&p) < 0.0 {
                p = [
                    [-p[0][0], p[0][1], p[0][2]],
                    [-p[1][0], p[1][1], p[1][2]],
                    [-p[2][0], p[2][1], p[2][2]],
                ];
            }
            let mut qq = q;
            if det(&qq) < 0.0 {
                qq = [
                    [-q[0][0], q[0][1], q[0][2]],
                    [-q[1][0], q[1][1], q[1][2]],
                    [-q[2][0], q[2][1], q[2][2]],
                ];
            }
            let r = [rng.uniform(), rng.uniform(), rng.uniform()];
            let sigmas = [
                [1.0 + 0.1 * r[0], 1.0 + 0.1 * r[1], 1.0 + 0.1 * r[2]], // within 10% of a rotation
                [1.0, 1.0, 1.0],                                        // a pure rotation
                [1.1, 1.1, 0.9],                                        // repeated singular values
                [3.0 + r[0], 1.0, 1e-6],                                // nearly flat
                [1e3, 1.0, 1e-3],                                       // condition 1e6
                [1.0 + r[0].abs(), 0.5, 0.5 + 1e-13],                   // nearly repeated
            ];
            for (k, sg) in sigmas.iter().enumerate() {
                // F = P diag(sigma) Q^T with P, Q rotations: R = P Q^T exactly.
                let mut f = [[0.0; 3]; 3];
                for i in 0..3 {
                    for j in 0..3 {
                        f[i][j] = (0..3).map(|m| p[i][m] * sg[m] * qq[j][m]).sum();
                    }
                }
                let label = format!("trial {trial} sigma {k}");
                // dR is bounded by eps |F| / (sigma_2 + sigma_3).
                let cond = (sg[0] / (sg[1] + sg[2])).max(1.0);
                let sens = 1e-14 * cond;
                let (rn, sn) = check_polar(&f, cond, &label);
                let (re, _) = polar_rotation_svd(&f);
                let r_exact = matmul(&p, &transpose(&qq));
                for i in 0..3 {
                    for j in 0..3 {
                        assert!(
                            (rn[i][j] - r_exact[i][j]).abs() <= sens,
                            "{label}: R vs exact"
                        );
                        // The eigen path works on F^T F (condition number squared): looser.
                        let sens_eig = 1e-14 * (sg[0] / sg[2]).max(1.0);
                        assert!(
                            (re[i][j] - r_exact[i][j]).abs() <= sens_eig,
                            "{label}: eigen path R vs exact {}",
                            (re[i][j] - r_exact[i][j]).abs()
                        );
                    }
                }
                let (ws, _) = symmetric_eigen3(&sn);
                assert!(ws[2] >= -1e-14 * sg[0], "{label}: S not PSD {ws:?}");
            }
        }
        // Inverted and singular deformation gradients go through the eigen path and stay rotations.
        for f in [
            [[-0.9, 0.1, 0.0], [0.05, 1.0, 0.1], [0.0, 0.2, 0.9]],
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]],
            [[0.0; 3]; 3],
        ] {
            let (r, s) = polar_rotation(&f);
            assert!((det(&r) - 1.0).abs() < 1e-14);
            let rs = matmul(&r, &s);
            for i in 0..3 {
                for j in 0..3 {
                    assert!((rs[i][j] - f[i][j]).abs() < 1e-14);
                }
            }
        }
    }
}
