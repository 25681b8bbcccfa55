//! XPBD's tet update ([`super::xpbd`]'s `project_tet`) for [`LANES`] tets of one colour side by side: the
//! Gauss-Newton step of each tet's two constraints and its first trial point, with every lane running the scalar
//! update's operations in the same order (so the same bits), laid out by component and lane so that the compiler
//! turns each line into packed arithmetic. The update was three quarters of an XPBD step on the bunny, one tet at a
//! time. A lane whose full step the guard refuses (not a descent, or it inverts an upright tet: rare, sliver tets
//! in large motion) is redone by the scalar update, which halves its step.

use crate::math::Vec3;

/// Tets updated side by side.
pub(super) const LANES: usize = 4;
/// One value per lane.
pub(super) type Lanes = [f64; LANES];

/// The inputs of [`LANES`] tet updates, by corner or constraint, component and lane.
#[derive(Default)]
pub(super) struct TetLanes {
    /// Corner positions before the update, m.
    pub p: [[Lanes; 3]; 4],
    /// Shape-function gradients, 1/m.
    pub g: [[Lanes; 3]; 4],
    /// Inverse masses of the corners, 1/kg (0: pinned).
    pub w: [Lanes; 4],
    /// `alpha~ = compliance / h_s^2` of the deviatoric and hydrostatic constraints.
    pub at: [Lanes; 2],
    /// The constraints' multipliers so far.
    pub lambda: [Lanes; 2],
}

/// The full Gauss-Newton steps of [`LANES`] tets: the corners' moves, the multipliers' changes, and
/// whether the guard accepts it as it is (`None`: the 2x2 system is singular, the scalar update leaves the tet).
pub(super) struct LaneSteps {
    pub dp: [[Lanes; 3]; 4],
    pub dl: [Lanes; 2],
    pub accepted: [Option<bool>; LANES],
    /// What a refused step's halvings are tested against: the local objective, its slope along `dp`, `J`.
    pub phi0: Lanes,
    pub slope: Lanes,
    pub j: Lanes,
}

#[inline(always)]
fn deformation(p: &[[Lanes; 3]; 4], g: &[[Lanes; 3]; 4]) -> [[Lanes; 3]; 3] {
    let mut f = [[[0.0; LANES]; 3]; 3];
    for k in 0..4 {
        for a in 0..3 {
            for b in 0..3 {
                for l in 0..LANES {
                    f[a][b][l] += p[k][a][l] * g[k][b][l];
                }
            }
        }
    }
    f
}

/// `|F|` (0 below 1e-12, as the scalar update) and `J = det F` per lane.
#[inline(always)]
fn norm_and_det(f: &[[Lanes; 3]; 3]) -> (Lanes, Lanes, Lanes) {
    let mut s = [0.0; LANES];
    for i in 0..3 {
        for j in 0..3 {
            for l in 0..LANES {
                s[l] += f[i][j][l] * f[i][j][l];
            }
        }
    }
    let mut raw = [0.0; LANES];
    let mut c_d = [0.0; LANES];
    let mut det = [0.0; LANES];
    for l in 0..LANES {
        let m = |i: usize, j: usize| f[i][j][l];
        raw[l] = s[l].sqrt();
        c_d[l] = if raw[l] > 1e-12 { raw[l] } else { 0.0 };
        det[l] = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1))
            - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0))
            + m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
    }
    (raw, c_d, det)
}

/// The Gauss-Newton step of every lane's tet and the guard's test of its full step (`alpha`: the hydrostatic
/// constraint's rest value), the scalar update's `project_tet` up to its first trial.
#[inline(always)]
pub(super) fn full_steps(t: &TetLanes, alpha: f64) -> LaneSteps {
    let f = deformation(&t.p, &t.g);
    let (norm, c_d, j) = norm_and_det(&f);
    // dC_D/dF = F / |F| (0 for a collapsed tet) and dC_H/dF = cof F.
    let mut q_d = [[[0.0; LANES]; 3]; 3];
    let mut q_h = [[[0.0; LANES]; 3]; 3];
    for l in 0..LANES {
        let m = |i: usize, j: usize| f[i][j][l];
        for a in 0..3 {
            for b in 0..3 {
                q_d[a][b][l] = if norm[l] > 1e-12 {
                    f[a][b][l] / norm[l]
                } else {
                    0.0
                };
            }
        }
        q_h[0][0][l] = m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1);
        q_h[0][1][l] = m(1, 2) * m(2, 0) - m(1, 0) * m(2, 2);
        q_h[0][2][l] = m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0);
        q_h[1][0][l] = m(0, 2) * m(2, 1) - m(0, 1) * m(2, 2);
        q_h[1][1][l] = m(0, 0) * m(2, 2) - m(0, 2) * m(2, 0);
        q_h[1][2][l] = m(0, 1) * m(2, 0) - m(0, 0) * m(2, 1);
        q_h[2][0][l] = m(0, 1) * m(1, 2) - m(0, 2) * m(1, 1);
        q_h[2][1][l] = m(0, 2) * m(1, 0) - m(0, 0) * m(1, 2);
        q_h[2][2][l] = m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0);
    }
    // Corner gradients `grad[c][k] = (dC_c/dF) g_k` and `y = W grad`.
    let mut grad = [[[[0.0; LANES]; 3]; 4]; 2];
    let mut y = [[[[0.0; LANES]; 3]; 4]; 2];
    for k in 0..4 {
        for a in 0..3 {
            for l in 0..LANES {
                let g = |b: usize| t.g[k][b][l];
                grad[0][k][a][l] = q_d[a][0][l] * g(0) + q_d[a][1][l] * g(1) + q_d[a][2][l] * g(2);
                grad[1][k][a][l] = q_h[a][0][l] * g(0) + q_h[a][1][l] * g(1) + q_h[a][2][l] * g(2);
                y[0][k][a][l] = grad[0][k][a][l] * t.w[k][l];
                y[1][k][a][l] = grad[1][k][a][l] * t.w[k][l];
            }
        }
    }
    let dot = |u: &[[Lanes; 3]; 4], v: &[[Lanes; 3]; 4], k: usize, l: usize| {
        u[k][0][l] * v[k][0][l] + u[k][1][l] * v[k][1][l] + u[k][2][l] * v[k][2][l]
    };
    let mut r = [[0.0; LANES]; 2];
    let (mut a11, mut a12, mut a22) = (t.at[0], [0.0; LANES], t.at[1]);
    for l in 0..LANES {
        r[0][l] = c_d[l] + t.at[0][l] * t.lambda[0][l];
        r[1][l] = (j[l] - alpha) + t.at[1][l] * t.lambda[1][l];
        for k in 0..4 {
            a11[l] += dot(&grad[0], &y[0], k, l);
            a12[l] += 0.5 * (dot(&grad[0], &y[1], k, l) + dot(&grad[1], &y[0], k, l));
            a22[l] += dot(&grad[1], &y[1], k, l);
        }
    }
    let mut dl = [[0.0; LANES]; 2];
    let mut singular = [false; LANES];
    for l in 0..LANES {
        let det2 = a11[l] * a22[l] - a12[l] * a12[l];
        singular[l] = !(det2 > 0.0 && det2.is_finite());
        dl[0][l] = (a22[l] * -r[0][l] - a12[l] * -r[1][l]) / det2;
        dl[1][l] = (a11[l] * -r[1][l] - a12[l] * -r[0][l]) / det2;
    }
    // The full step and its trial point.
    let mut dp = [[[0.0; LANES]; 3]; 4];
    let mut p = t.p;
    for k in 0..4 {
        for a in 0..3 {
            for l in 0..LANES {
                dp[k][a][l] = y[0][k][a][l] * dl[0][l] + y[1][k][a][l] * dl[1][l];
                p[k][a][l] += 1.0 * dp[k][a][l];
            }
        }
    }
    // The guard: Armijo on the local objective and, for an upright tet, an upright trial.
    let mut phi0 = [0.0; LANES];
    let mut slope = [0.0; LANES];
    for l in 0..LANES {
        phi0[l] = 0.5 * r[0][l] * r[0][l] / t.at[0][l] + 0.5 * r[1][l] * r[1][l] / t.at[1][l];
        for k in 0..4 {
            slope[l] += r[0][l] / t.at[0][l] * dot(&grad[0], &dp, k, l)
                + r[1][l] / t.at[1][l] * dot(&grad[1], &dp, k, l);
        }
    }
    let f_trial = deformation(&p, &t.g);
    let (_, c_trial, j_trial) = norm_and_det(&f_trial);
    let mut phi = [0.0; LANES];
    for l in 0..LANES {
        let mut kin = 0.0;
        for k in 0..4 {
            if t.w[k][l] > 0.0 {
                let d: Vec3 = [0, 1, 2].map(|a| p[k][a][l] - t.p[k][a][l]);
                kin += (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / t.w[k][l];
            }
        }
        phi[l] = 0.5 * kin;
        let c = [c_trial[l], j_trial[l] - alpha];
        for i in 0..2 {
            let e = c[i] + t.at[i][l] * t.lambda[i][l];
            phi[l] += 0.5 * e * e / t.at[i][l];
        }
    }
    let accepted = std::array::from_fn(|l| {
        let descent = phi[l].is_finite() && phi[l] <= phi0[l] + 1e-4 * 1.0 * slope[l];
        let upright = j[l] <= 0.0 || j_trial[l] > 0.0;
        (!singular[l]).then_some(descent && upright)
    });
    LaneSteps {
        dp,
        dl,
        accepted,
        phi0,
        slope,
        j,
    }
}
