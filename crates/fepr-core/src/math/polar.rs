//! The rotation factor of the polar decomposition for many matrices at once, bit for bit
//! [`crate::math::polar_rotation`]'s.
//!
//! One scaled Newton iteration on one 3x3 matrix is a short dependency chain (two square roots and a
//! division per iteration), so the scalar routine is latency-bound (about 150 ns on this machine). Here
//! [`LANES`] matrices run the same iteration side by side in structure-of-arrays form; every lane performs
//! exactly the scalar operations in the scalar order (no fused multiply-adds) and stops updating at the
//! iteration the scalar routine would have returned, so its result has the same bits. Lanes the fast path
//! rejects (inverted, nearly singular, no convergence) are handed to the scalar routine, which takes its SVD
//! path for them. Used by the Projective Dynamics local step and the ARAP energy (fepr-spec section 5).

use crate::math::simd::avx2_dispatch;
use crate::math::{polar_rotation, Mat3, COFACTOR_PAIRS};

/// Matrices per batch (8 with AVX2 measured 2.8x faster than the scalar routine, against 2.2x for 4 and 2.5x
/// for 16; AVX-512 lanes were slower on this machine).
pub const LANES: usize = 8;
pub(crate) type Lanes = [f64; LANES];

/// `out[k] = polar_rotation(&f[k]).0` for every `k` (`f.len() == out.len()`), faster in batches of
/// [`LANES`].
pub fn polar_rotations(f: &[Mat3], out: &mut [Mat3]) {
    assert_eq!(f.len(), out.len(), "one output per matrix");
    polar_rotations_simd(f, out);
}

avx2_dispatch! {
    /// [`polar_rotations_portable`] compiled for AVX2 where the CPU has it (wider lanes; the same bits).
    fn polar_rotations_simd<'a>(f: &'a [Mat3], out: &'a mut [Mat3]) => polar_rotations_portable
}

#[inline(always)]
fn polar_rotations_portable(f: &[Mat3], out: &mut [Mat3]) {
    let mut fc = f.chunks_exact(LANES);
    let mut oc = out.chunks_exact_mut(LANES);
    for (fb, ob) in (&mut fc).zip(&mut oc) {
        polar_block(
            fb.try_into().expect("full block"),
            ob.try_into().expect("full block"),
        );
    }
    for (fr, or) in fc.remainder().iter().zip(oc.into_remainder()) {
        *or = polar_rotation(fr).0;
    }
}

/// One block: the matrices into lanes, [`polar_lanes`], and back.
#[inline(always)]
fn polar_block(f: &[Mat3; LANES], out: &mut [Mat3; LANES]) {
    let mut fl = [[[0.0; LANES]; 3]; 3];
    for l in 0..LANES {
        for i in 0..3 {
            for j in 0..3 {
                fl[i][j][l] = f[l][i][j];
            }
        }
    }
    let mut r = [[[0.0; LANES]; 3]; 3];
    polar_lanes(&fl, &mut r, EXACT);
    for l in 0..LANES {
        for i in 0..3 {
            for j in 0..3 {
                out[l][i][j] = r[i][j][l];
            }
        }
    }
}

/// Stop when the squared Frobenius norm of a Newton step is at most this: `linalg::polar_rotation`'s rule
/// (the step is then at most 1e-8 and the error, quadratic, at round-off).
pub(crate) const EXACT: f64 = 1e-16;

/// A looser stop for the Projective Dynamics local step: a step of at most 1e-5 leaves an error of about
/// 1e-10 (quadratic convergence), far below what 10 PD iterations resolve, and saves the last of the
/// usually 4 iterations (measured on the bunny's PD states: 3.9 iterations per 8 tets on average).
pub(crate) const PD_LOCAL: f64 = 1e-10;

/// The rotations of [`LANES`] matrices in structure-of-arrays form (`f[i][j][l]` is entry `(i, j)` of
/// matrix `l`; `r` likewise): the fast path of `polar_rotation` in lanes, stopping a lane once its squared
/// step is at most `stop` ([`EXACT`]: bit for bit `polar_rotation(f_l).0`), then the scalar routine for
/// the lanes it rejected. For kernels that hold `F` in lanes already.
#[inline(always)]
pub(crate) fn polar_lanes(f: &[[Lanes; 3]; 3], r: &mut [[Lanes; 3]; 3], stop: f64) {
    let mut x = *f;
    // Lane states: still iterating, scaled iteration, and handed to the scalar routine.
    let mut active = [false; LANES];
    let mut scaled = [true; LANES];
    let mut rejected = [false; LANES];
    // scale2 = ddot(F, F) and det(F) as linalg computes them (same operations, same order).
    let mut scale2 = [0.0; LANES];
    for i in 0..3 {
        for j in 0..3 {
            for l in 0..LANES {
                scale2[l] += f[i][j][l] * f[i][j][l];
            }
        }
    }
    for l in 0..LANES {
        let d0 = f[0][0][l] * (f[1][1][l] * f[2][2][l] - f[1][2][l] * f[2][1][l])
            - f[0][1][l] * (f[1][0][l] * f[2][2][l] - f[1][2][l] * f[2][0][l])
            + f[0][2][l] * (f[1][0][l] * f[2][1][l] - f[1][1][l] * f[2][0][l]);
        let bound = (scale2[l] / 3.0) * (scale2[l] / 3.0).sqrt();
        active[l] = d0 > 1e-9 * bound && bound.is_finite();
        rejected[l] = !active[l];
    }
    let mut c = [[[0.0; LANES]; 3]; 3];
    for _ in 0..30 {
        if !active.iter().any(|&a| a) {
            break;
        }
        newton_update(
            &mut x,
            &mut c,
            &mut active,
            &mut scaled,
            &mut rejected,
            stop,
        );
    }
    *r = x;
    for l in 0..LANES {
        if active[l] || rejected[l] {
            // No convergence in 30 iterations, or rejected: exactly what the scalar routine returns.
            let mut fl = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    fl[i][j] = f[i][j][l];
                }
            }
            let rl = polar_rotation(&fl).0;
            for i in 0..3 {
                for j in 0..3 {
                    r[i][j][l] = rl[i][j];
                }
            }
        }
    }
}

/// One scaled Newton iteration on every lane, applied to the active ones (the operations of
/// `linalg::polar_rotation`'s loop body, in its order). Lanes that converge or fail leave `active`.
#[inline(always)]
fn newton_update(
    x: &mut [[Lanes; 3]; 3],
    c: &mut [[Lanes; 3]; 3],
    active: &mut [bool; LANES],
    scaled: &mut [bool; LANES],
    rejected: &mut [bool; LANES],
    stop: f64,
) {
    // cof(X), as linalg::cofactor.
    for i in 0..3 {
        for k in 0..3 {
            let (a, b, cc, d) = COFACTOR_PAIRS[i][k];
            for l in 0..LANES {
                c[i][k][l] = x[a][b][l] * x[cc][d][l] - x[a][d][l] * x[cc][b][l];
            }
        }
    }
    let mut dx = [0.0; LANES];
    let mut cc2 = [0.0; LANES];
    let mut xx2 = [0.0; LANES];
    for l in 0..LANES {
        dx[l] = x[0][0][l] * c[0][0][l] + x[0][1][l] * c[0][1][l] + x[0][2][l] * c[0][2][l];
    }
    for i in 0..3 {
        for j in 0..3 {
            for l in 0..LANES {
                cc2[l] += c[i][j][l] * c[i][j][l];
                xx2[l] += x[i][j][l] * x[i][j][l];
            }
        }
    }
    // g^2 = |X^-1|_F / |X|_F = |cof X|_F / (det X |X|_F); 1 once a lane's iteration is unscaled. Computed for
    // every lane and selected afterwards (no branch in the SIMD loop), and skipped, with its three square
    // roots, once no lane is scaled (near convergence).
    let mut g = [1.0; LANES];
    if scaled.iter().zip(active.iter()).any(|(&s, &a)| s && a) {
        for l in 0..LANES {
            let g_scaled = ((cc2[l].sqrt() / dx[l]) / xx2[l].sqrt()).sqrt();
            g[l] = if scaled[l] { g_scaled } else { 1.0 };
        }
    }
    let mut a = [0.0; LANES];
    let mut b = [0.0; LANES];
    for l in 0..LANES {
        a[l] = 0.5 * g[l];
        b[l] = 0.5 / (g[l] * dx[l]);
    }
    for l in 0..LANES {
        let bad = dx[l] <= 0.0 || !dx[l].is_finite();
        rejected[l] |= active[l] && bad;
        active[l] &= !bad;
    }
    let mut diff = [0.0; LANES];
    for i in 0..3 {
        for j in 0..3 {
            for l in 0..LANES {
                let nx = a[l] * x[i][j][l] + b[l] * c[i][j][l];
                let e = nx - x[i][j][l];
                diff[l] += e * e;
                x[i][j][l] = if active[l] { nx } else { x[i][j][l] };
            }
        }
    }
    for l in 0..LANES {
        if active[l] && diff[l] <= stop {
            active[l] = false; // converged: x holds the scalar routine's result
        } else if active[l] && diff[l] <= 1e-4 {
            scaled[l] = false;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::matmul;

    /// Deformation gradients of every kind the fast path and the fallback see: rotations times stretches,
    /// large stretches, inverted, singular, a non-finite one.
    fn cases() -> Vec<Mat3> {
        let mut fs = Vec::new();
        for k in 0..203 {
            let t = k as f64;
            let (a, b, c) = ((0.37 * t).sin(), (0.11 * t).cos(), (0.23 * t).sin());
            let amp = [0.01, 0.1, 0.5, 2.0][k % 4];
            let s = [
                [1.0 + amp * a, 0.3 * amp * b, 0.2 * amp * c],
                [0.3 * amp * b, 1.0 - 0.8 * amp * c.abs(), 0.4 * amp * a],
                [0.2 * amp * c, 0.4 * amp * a, 1.0 + 0.9 * amp * b],
            ];
            let (ca, sa) = (t.cos(), t.sin());
            let r = [[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]];
            let mut f = matmul(&r, &s);
            match k % 17 {
                3 => f[2] = [-f[2][0], -f[2][1], -f[2][2]], // inverted
                5 => f[1] = f[0],                           // singular
                7 => f = [[1e-12, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                11 => f[0][1] = f64::NAN,
                _ => {}
            }
            fs.push(f);
        }
        fs
    }

    #[test]
    fn batched_polar_rotations_match_the_scalar_routine_bit_for_bit() {
        let fs = cases();
        let mut rs = vec![[[0.0; 3]; 3]; fs.len()];
        polar_rotations(&fs, &mut rs);
        let mut portable = vec![[[0.0; 3]; 3]; fs.len()];
        polar_rotations_portable(&fs, &mut portable);
        for (k, f) in fs.iter().enumerate() {
            let want = polar_rotation(f).0;
            for i in 0..3 {
                for j in 0..3 {
                    assert_eq!(
                        rs[k][i][j].to_bits(),
                        want[i][j].to_bits(),
                        "matrix {k} entry ({i}, {j}): {f:?}"
                    );
                    assert_eq!(portable[k][i][j].to_bits(), want[i][j].to_bits());
                }
            }
        }
    }
}
