//! The velocity warm start (fepr-spec section 3, before the iteration): meet the energy row by scaling the
//! deformational velocities, with the rigid part on the momentum targets.

use super::evaluate::{vertex_chunk, Eval};
use super::problem::Problem;
use crate::exec::{for_each_chunk_mut, reduce_chunks};
use crate::math::{cross, dot, sub, Mat3, Vec3};

/// The rigid part of the free vertices' velocities: `V + omega x (x - c)`, carrying all of their P and L, with
/// `omega = I^-1 L` about their centre of mass `c`. The rest `u = v - rigid` has zero momenta.
pub(super) struct RigidPart {
    /// `V`, m/s.
    pub(super) velocity: Vec3,
    /// `omega`, rad/s.
    pub(super) omega: Vec3,
    /// `c`, m.
    pub(super) center: Vec3,
    /// The free mass, kg.
    pub(super) mass: f64,
    /// `I^-1` about `c`, 1/(kg m^2) (`None` for a degenerate, e.g. collinear, body).
    pub(super) inertia_inv: Option<Mat3>,
}

impl RigidPart {
    /// No rigid motion (every velocity is deformational).
    pub(super) fn none() -> Self {
        Self {
            velocity: [0.0; 3],
            omega: [0.0; 3],
            center: [0.0; 3],
            mass: 0.0,
            inertia_inv: None,
        }
    }

    pub(super) fn at(&self, x: Vec3) -> Vec3 {
        let w = cross(self.omega, sub(x, self.center));
        [
            self.velocity[0] + w[0],
            self.velocity[1] + w[1],
            self.velocity[2] + w[2],
        ]
    }
}

/// The [`RigidPart`] of the free vertices' velocities, from the moments an evaluation `e` summed for `S`.
pub(super) fn rigid_velocity(pb: &Problem, e: &Eval) -> RigidPart {
    // From the free vertices' moments about the target centre of mass C_t that the evaluation summed for S
    // (no serial passes of its own). With
    // r = x - C_t, the centre of mass is c = C_t + d, d = sum m r / M; about c, the inertia is
    // [tr(R) I - R] - M (|d|^2 I - d d^T) (R = sum m r r^T), and the angular momentum of v - V is
    // sum m r x v - d x P.
    debug_assert!(e.s_moments, "the moments for S");
    let mf = e.free_mass;
    if mf <= 0.0 {
        return RigidPart::none();
    }
    let d: Vec3 = std::array::from_fn(|a| e.free_r[a] / mf);
    let vc: Vec3 = std::array::from_fn(|a| e.free_p[a] / mf);
    let (tr, dd) = (e.rr[0][0] + e.rr[1][1] + e.rr[2][2], dot(d, d));
    let inertia: Mat3 = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            let delta = if a == b { 1.0 } else { 0.0 };
            (tr * delta - e.rr[a][b]) - mf * (dd * delta - d[a] * d[b])
        })
    });
    let l = sub(e.free_l, cross(d, e.free_p));
    let inertia_inv = crate::math::inverse(&inertia);
    let omega = inertia_inv.map_or([0.0; 3], |inv| mat_vec(&inv, l));
    let ct = pb.targets.center_of_mass;
    RigidPart {
        velocity: vc,
        omega,
        center: [ct[0] + d[0], ct[1] + d[1], ct[2] + d[2]],
        mass: mf,
        inertia_inv,
    }
}

pub(super) fn mat_vec(m: &Mat3, v: Vec3) -> Vec3 {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

/// The rigid part whose momenta are the targets: `P = P_target` and `L_Ct = L_target` (the slack-free targets
/// of fepr-spec section 2), for the free centre of mass `c` of `now`: `V = P_target / m` and
/// `omega = I^-1 (L_target - m (c - C_t) x V)` (u adds nothing to either: it has zero momenta about `c`).
/// `None` where the momentum rows do not all hold the whole body (pins, rows off, slack free) or `I` is singular.
pub(super) fn rigid_part_on_target(pb: &Problem, now: &RigidPart) -> Option<RigidPart> {
    let momenta_rows = pb.active[1..7].iter().all(|&a| a);
    let slack_free = pb.dp_star != [0.0; 3] || pb.dl_star != [0.0; 3];
    if pb.model.num_pinned() > 0 || !momenta_rows || slack_free || now.mass <= 0.0 {
        return None;
    }
    let inv = now.inertia_inv?;
    let (velocity, l_spin) = pb.targets.rigid_motion_at(now.mass, now.center);
    Some(RigidPart {
        velocity,
        omega: mat_vec(&inv, l_spin),
        center: now.center,
        mass: now.mass,
        inertia_inv: now.inertia_inv,
    })
}

/// Warm start (fepr-spec section 3, before the iteration): split the free velocities into a rigid part and a
/// deformational rest `u` (see [`rigid_velocity`]); put the rigid part on the momentum targets where the
/// momentum rows cover the whole body (see [`rigid_part_on_target`]), and scale `u` by the factor that then
/// meets the energy row. The kinetic energy splits into rigid + deformational parts (u carries no momenta), so
/// the result meets the energy row and, on the whole body, the momentum rows; otherwise P and L stay what they
/// were. With no momentum row active, nothing is rigid: every free velocity is scaled. The iteration starts
/// from there and only fixes what is left (the centre of mass, round-off): a dissipative base step that lost
/// most of H is then 0-2 iterations from the manifold instead of a stiff position correction away. False if
/// that energy cannot be reached.
pub(super) fn warm_start_velocities(
    pb: &Problem,
    e: &Eval,
    x: &[Vec3],
    v: &mut [Vec3],
    parts: &mut Vec<[f64; 3]>,
) -> bool {
    let c_h = e.c[0];
    // Without momentum rows (the default with pins) nothing holds P or L, so no rigid part is kept: every free
    // velocity is scaled. A pinned body's swing is mostly a best-fit rigid rotation; scaling only the small
    // rest amplifies it many times per step (a Projective Dynamics cantilever's energy error then grows).
    let momenta_rows = pb.active[1..7].iter().any(|&a| a);
    let now = if momenta_rows {
        rigid_velocity(pb, e)
    } else {
        RigidPart::none()
    };
    let target = rigid_part_on_target(pb, &now);
    let next = target.as_ref().unwrap_or(&now);
    // The kinetic energies of u, of the rigid part now and of the next one, over fixed vertex tasks added in
    // task order (the same bits for any thread count).
    let (model, chunk) = (pb.model, vertex_chunk(v.len()));
    let vr: &[Vec3] = v;
    let map = |r: std::ops::Range<usize>| {
        let mut k = [0.0; 3];
        for i in r.filter(|&i| !model.pinned[i]) {
            let m = model.masses[i];
            let (r_now, r_next) = (now.at(x[i]), next.at(x[i]));
            let u = sub(vr[i], r_now);
            k[0] += 0.5 * m * dot(u, u);
            k[1] += 0.5 * m * dot(r_now, r_now);
            k[2] += 0.5 * m * dot(r_next, r_next);
        }
        k
    };
    let add3 = |a: [f64; 3], b: [f64; 3]| [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
    let [k_u, k_now, k_next] = reduce_chunks(vr.len(), chunk, parts, map, add3).unwrap_or([0.0; 3]);
    let k_target = k_u - c_h - (k_next - k_now);
    // A (nearly) rigid motion has no deformational energy to scale: a huge factor would only amplify round-off.
    // The rigid part still goes onto its momentum targets (a spinning body after Projective Dynamics lost
    // angular momentum and rotational energy together: putting its spin back restores both, and leaves the
    // iteration a small energy residual where the angular momentum rows, linearised about a fast rotation,
    // converged a few percent per iteration).
    let scalable = k_target > 0.0 && k_target.is_finite() && k_u > 1e-6 * k_target;
    if !scalable && target.is_none() {
        return false;
    }
    let beta = if scalable {
        (k_target / k_u).sqrt()
    } else {
        1.0
    };
    for_each_chunk_mut(v, chunk, |c, vs| {
        for (k, vi) in vs.iter_mut().enumerate() {
            let i = c * chunk + k;
            if !model.pinned[i] {
                let (r_now, r_next) = (now.at(x[i]), next.at(x[i]));
                *vi = [0, 1, 2].map(|a| r_next[a] + beta * (vi[a] - r_now[a]));
            }
        }
    });
    true
}
