//! Small fixed-size linear algebra: 3-vectors, 3x3 matrices (row-major `[[f64; 3]; 3]`), and a small
//! dense symmetric solver used by the projection (regularised Cholesky with an eigen-decomposition
//! least-squares fallback).

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
/// Adds `delta * trace/n` to the diagonal and tries a Cholesky factorisation; if that
/// fails (not positive definite in floating point) or yields a non-finite result, it falls back to the
/// minimum-norm least-squares solution from a Jacobi eigen-decomposition (rank-revealing, cut-off relative
/// to the largest eigenvalue). Returns the solution and whether the fallback was used.
pub fn solve_symmetric_psd(a: &[f64], b: &[f64], n: usize, delta: f64) -> (Vec<f64>, bool) {
    debug_assert_eq!(a.len(), n * n);
    let trace: f64 = (0..n).map(|i| a[i * n + i]).sum();
    let shift = if trace > 0.0 {
        delta * trace / n as f64
    } else {
        0.0
    };
    let mut l = a.to_vec();
    for i in 0..n {
        l[i * n + i] += shift;
    }
    if let Some(x) = cholesky_solve(&mut l, b, n) {
        if x.iter().all(|v| v.is_finite()) {
            return (x, false);
        }
    }
    (eigen_least_squares(a, b, n), true)
}

fn cholesky_solve(l: &mut [f64], b: &[f64], n: usize) -> Option<Vec<f64>> {
    // In-place lower Cholesky factor.
    for j in 0..n {
        let mut d = l[j * n + j];
        for k in 0..j {
            d -= l[j * n + k] * l[j * n + k];
        }
        if d <= 0.0 || !d.is_finite() {
            return None;
        }
        let d = d.sqrt();
        l[j * n + j] = d;
        for i in (j + 1)..n {
            let mut s = l[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            l[i * n + j] = s / d;
        }
    }
    let mut y = b.to_vec();
    for i in 0..n {
        for k in 0..i {
            y[i] -= l[i * n + k] * y[k];
        }
        y[i] /= l[i * n + i];
    }
    for i in (0..n).rev() {
        for k in (i + 1)..n {
            y[i] -= l[k * n + i] * y[k];
        }
        y[i] /= l[i * n + i];
    }
    Some(y)
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
}

/// Polar decomposition `F = R S` with `R` a rotation (det +1) and `S` symmetric, via the eigen-decomposition
/// of `F^T F` (`F = U Sigma V^T`, `R = U V^T`). For inverted `F` (det < 0) the smallest singular value takes
/// the sign, so that `R` stays a rotation (the closest rotation in the Frobenius norm). Returns `(R, S)`.
pub fn polar_rotation(f: &Mat3) -> (Mat3, Mat3) {
    let ftf = matmul(&transpose(f), f);
    let flat: Vec<f64> = ftf.iter().flatten().copied().collect();
    let (w, vflat) = symmetric_eigen(&flat, 3);
    // Sort eigenpairs by decreasing eigenvalue.
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| w[b].partial_cmp(&w[a]).unwrap_or(std::cmp::Ordering::Equal));
    let mut v = [[0.0; 3]; 3];
    let mut sigma = [0.0; 3];
    for (c, &k) in order.iter().enumerate() {
        sigma[c] = w[k].max(0.0).sqrt();
        for r in 0..3 {
            v[r][c] = vflat[r * 3 + k];
        }
    }
    if det(&v) < 0.0 {
        for r in 0..3 {
            v[r][2] = -v[r][2];
        }
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
    // det F < 0: the third singular value is negative in the rotation-variant SVD.
    let s2 = dot(u2, col(&fv, 2));
    sigma[2] = s2;
    let u = [
        [u0[0], u1[0], u2[0]],
        [u0[1], u1[1], u2[1]],
        [u0[2], u1[2], u2[2]],
    ];
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
}
