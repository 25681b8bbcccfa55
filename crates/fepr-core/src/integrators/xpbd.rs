//! XPBD (Macklin, Mueller, Chentanez 2016) with the Neo-Hookean constraints of Macklin and Mueller 2021: per
//! tet a deviatoric constraint `C_D = sqrt(I_C)` with compliance `1 / (mu V)` and a hydrostatic constraint
//! `C_H = J - alpha` with compliance `1 / (lambda' V)`. Their energies `C^2 / (2 compliance)` sum to the
//! [`ConstraintNeoHookean`] energy (up to a constant), which is therefore the `U` in FEPR's H (fepr-spec
//! section 5).
//!
//! A step of size `h` runs `substeps` substeps of size `h_s = h / substeps`; each predicts
//! `x = x_n + h_s v + h_s^2 g`, resets the multipliers, runs `iterations` Gauss-Seidel sweeps over the
//! constraints, and sets `v = (x - x_n) / h_s`. The sweeps go colour by colour (a greedy colouring in which the
//! tets of one colour share no vertex): within a colour the tets are solved in parallel, which is exactly the
//! sequential Gauss-Seidel result, so the step is bit-identical for any number of threads.
//!
//! Obstacles ([`Integrator::set_obstacles`]) are contact constraints of zero compliance in the same sweeps:
//! after each sweep, a vertex inside an obstacle is put back on its surface
//! ([`ContactPotential::project_out`]), so the substep's velocity `(x - x_n) / h_s` already holds the contact.

use super::xpbd_lanes::{self, TetLanes, LANES};
use crate::elasticity::shape_gradients;
use crate::error::{invalid, Result};
use crate::integrators::{HandOver, Integrator, StepReport};
use crate::material::{ConstraintNeoHookean, Material};
use crate::math::simd::avx2_dispatch;
use crate::math::{add, det, scale, Mat3, Vec3};
use crate::model::{Model, ModelKey, State};
use crate::world::{ContactPotential, Obstacle};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering::Relaxed};

/// XPBD settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct XpbdSettings {
    /// Substeps per step (default 20).
    pub substeps: usize,
    /// Gauss-Seidel sweeps per substep (default 1).
    pub iterations: usize,
}

impl Default for XpbdSettings {
    fn default() -> Self {
        // "Small steps" (Macklin et al. 2019): substeps with one sweep each. XPBD's local solves drop the
        // constraints' curvature (the deviatoric constraint sqrt(I_C) is pre-stressed at rest), which large
        // substeps on stiff elements turn into a divergent Gauss-Seidel sweep; small substeps keep the mass term
        // dominant.
        Self {
            substeps: 20,
            iterations: 1,
        }
    }
}

/// Per-run data: the colouring and the per-tet constants (rebuilt when [`Model::key`] changes), stored in colour
/// order so that a sweep over a colour streams through contiguous memory.
struct Prepared {
    /// The [`Model::key`] this was prepared for (material, masses, pins, mesh).
    key: ModelKey,
    /// Tets in colour order: colour `c` is `colour_start[c]..colour_start[c + 1]` of the arrays below.
    colour_start: Vec<usize>,
    /// Corner vertices of each tet (colour order), by their rank in [`Model::kernel_rank`] (the order of
    /// the sweep's positions and of `inv_mass`).
    corners: Vec<[usize; 4]>,
    grads: Vec<[Vec3; 4]>,
    /// Compliances `1 / (mu V)` and `1 / (lambda' V)` per tet.
    compliance: Vec<[f64; 2]>,
    inv_mass: Vec<f64>,
}

/// The XPBD integrator.
#[derive(Default)]
pub struct Xpbd {
    pub settings: XpbdSettings,
    pre: Option<Prepared>,
    /// Multipliers per tet, in the colour order of [`Prepared`].
    lambdas: Vec<[f64; 2]>,
    /// The positions while a sweep updates them in place, as `f64` bits: the tets of one colour share no vertex,
    /// so each position has one writer; atomics (plain loads and stores on the usual targets) say so to the
    /// compiler without `unsafe`.
    shared_x: Vec<[AtomicU64; 3]>,
    /// Positions at the start of the substep (reused, no allocation per step).
    x_prev: Vec<Vec3>,
    /// The obstacles as contact constraints (empty: none).
    contact: ContactPotential,
    /// Per vertex, the velocity change the contact constraints gave it over the step, m/s (empty: no obstacle).
    contact_dv: Vec<Vec3>,
    /// The velocities at the start of the step, m/s (kept only with obstacles).
    v_start: Vec<Vec3>,
    /// The parts a caller takes each step in ([`Integrator::take_in_parts`]; 0 or 1: whole steps).
    parts: usize,
}

impl std::fmt::Debug for Xpbd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Xpbd")
            .field("settings", &self.settings)
            .finish()
    }
}

/// Greedy colouring of the tets: no two tets that share a vertex get the same colour. Deterministic (tets in
/// index order, smallest free colour).
pub fn colour_tets(model: &Model) -> Vec<Vec<usize>> {
    let tets = model.mesh.tets();
    let mut colour = vec![usize::MAX; tets.len()];
    // forbidden[c] == e + 1: colour c is used by a neighbour of tet e.
    let mut forbidden: Vec<usize> = Vec::new();
    let offsets = &model.incidence_offsets;
    let (slots, tet_at) = (&model.incidence_slots, &model.tet_at);
    let mut colours: Vec<Vec<usize>> = Vec::new();
    for (e, t) in tets.iter().enumerate() {
        for &v in t {
            let r = model.kernel_rank[v] as usize;
            for &slot in &slots[offsets[r]..offsets[r + 1]] {
                // Slots are in block positions: the user tet at that position.
                let f = tet_at[slot as usize / 4] as usize;
                if colour[f] != usize::MAX {
                    forbidden[colour[f]] = e + 1;
                }
            }
        }
        let c = (0..forbidden.len())
            .find(|&c| forbidden[c] != e + 1)
            .unwrap_or(forbidden.len());
        if c == forbidden.len() {
            forbidden.push(0);
            colours.push(Vec::new());
        }
        colour[e] = c;
        colours[c].push(e);
    }
    colours
}

impl Xpbd {
    pub fn new(settings: XpbdSettings) -> Result<Self> {
        if settings.substeps == 0 || settings.substeps > 10_000 {
            return Err(invalid(
                "xpbd_substeps",
                format!("must be in 1..=10000, got {}", settings.substeps),
            ));
        }
        if settings.iterations == 0 || settings.iterations > 10_000 {
            return Err(invalid(
                "xpbd_iterations",
                format!("must be in 1..=10000, got {}", settings.iterations),
            ));
        }
        Ok(Self {
            settings,
            ..Default::default()
        })
    }

    fn material(model: &Model) -> Option<ConstraintNeoHookean> {
        match model.material {
            Material::ConstraintNeoHookean(c) => Some(c),
            _ => None,
        }
    }

    fn prepare(model: &Model, mat: ConstraintNeoHookean) -> Prepared {
        let mut colours = colour_tets(model);
        // Within a colour (whose tets are independent: any order gives the same bits), the tets in the order of
        // their first corner in the kernels' vertex order (`Model::kernel_rank`, which keeps neighbours close in
        // memory): a chunk of a colour then reads and writes vertices near each other, and two threads' chunks
        // rarely share a cache line.
        let rank = |v: usize| model.kernel_rank[v] as usize;
        let tets = model.mesh.tets();
        for c in colours.iter_mut() {
            c.sort_by_key(|&e| tets[e].iter().map(|&v| rank(v)).min());
        }
        let mut colour_start = vec![0];
        let order: Vec<usize> = colours
            .iter()
            .flat_map(|c| {
                colour_start.push(colour_start.last().expect("starts at 0") + c.len());
                c.iter().copied()
            })
            .collect();
        let mut inv_mass = vec![0.0; model.num_vertices()];
        for i in 0..model.num_vertices() {
            if !(model.pinned[i] || model.masses[i] <= 0.0) {
                inv_mass[rank(i)] = 1.0 / model.masses[i];
            }
        }
        Prepared {
            key: model.key(),
            colour_start,
            corners: order.iter().map(|&e| tets[e].map(rank)).collect(),
            grads: order.iter().map(|&e| shape_gradients(model, e)).collect(),
            compliance: order
                .iter()
                .map(|&e| {
                    let v = model.rest_volume[e];
                    [1.0 / (mat.mu * v), 1.0 / (mat.lambda * v)]
                })
                .collect(),
            inv_mass,
        }
    }
}

/// One Gauss-Seidel sweep over the constraints of every tet of `pre`, colour by colour, updating `x` (m) and the
/// multipliers `lambdas` (colour order); `rank` is [`Model::kernel_rank`]; `inv_hs2` = `1 / h_s^2`; `shared` is
/// scratch (the positions by rank). Returns the step halvings
/// of the guarded updates.
///
/// Within a colour the tets share no vertex, so they are solved in parallel, each writing its own corners in
/// place: exactly the sequential sweep over the colour, hence bit-identical for any number of threads.
fn sweep(
    pre: &Prepared,
    rank: &[u32],
    lambdas: &mut [[f64; 2]],
    shared: &mut Vec<[AtomicU64; 3]>,
    x: &mut [Vec3],
    alpha: f64,
    inv_hs2: f64,
) -> usize {
    shared.resize_with(x.len(), Default::default);
    for (p, &r) in x.iter().zip(rank) {
        let s = &mut shared[r as usize];
        for a in 0..3 {
            *s[a].get_mut() = p[a].to_bits();
        }
    }
    let shared_ref = &*shared;
    let halvings = AtomicUsize::new(0);
    // Fixed chunks of a colour (`exec::for_each_chunk_mut`, so that `exec::serial` holds).
    const TETS: usize = 64;
    for c in 0..pre.colour_start.len() - 1 {
        let start = pre.colour_start[c];
        let end = pre.colour_start[c + 1];
        crate::exec::for_each_chunk_mut(&mut lambdas[start..end], TETS, |k, lambdas| {
            let halved = sweep_chunk(pre, start + k * TETS, lambdas, shared_ref, alpha, inv_hs2);
            halvings.fetch_add(halved, Relaxed);
        });
    }
    for (p, &r) in x.iter_mut().zip(rank) {
        let s = &mut shared[r as usize];
        for a in 0..3 {
            p[a] = f64::from_bits(*s[a].get_mut());
        }
    }
    halvings.into_inner()
}

avx2_dispatch! {
    /// [`update_chunk`] compiled for AVX2 where the CPU has it, else portable; no fused multiply-adds either way,
    /// so the same bits.
    fn sweep_chunk<'a>(
        pre: &'a Prepared,
        first: usize,
        lambdas: &'a mut [[f64; 2]],
        shared: &'a [[AtomicU64; 3]],
        alpha: f64,
        inv_hs2: f64,
    ) -> usize => update_chunk
}

/// The updates of the tets `first..first + lambdas.len()` (colour order, one colour: no two share a vertex) on the
/// positions in `shared`, [`LANES`] side by side ([`xpbd_lanes::full_steps`]); a lane whose full step the guard
/// refuses is redone by [`project_tet`], which halves it. Returns the halvings.
#[inline(always)]
fn update_chunk(
    pre: &Prepared,
    first: usize,
    lambdas: &mut [[f64; 2]],
    shared: &[[AtomicU64; 3]],
    alpha: f64,
    inv_hs2: f64,
) -> usize {
    let load = |v: usize| [0, 1, 2].map(|a| f64::from_bits(shared[v][a].load(Relaxed)));
    let mut halvings = 0;
    let len = lambdas.len();
    let mut lanes = TetLanes::default();
    for j0 in (0..len).step_by(LANES) {
        let n = LANES.min(len - j0);
        // Unused lanes repeat lane 0 (computed, never written).
        for l in 0..LANES {
            let e = first + j0 + l.min(n - 1);
            let t = pre.corners[e];
            for k in 0..4 {
                let p = load(t[k]);
                for a in 0..3 {
                    lanes.p[k][a][l] = p[a];
                    lanes.g[k][a][l] = pre.grads[e][k][a];
                }
                lanes.w[k][l] = pre.inv_mass[t[k]];
            }
            for c in 0..2 {
                lanes.at[c][l] = pre.compliance[e][c] * inv_hs2;
                lanes.lambda[c][l] = lambdas[j0 + l.min(n - 1)][c];
            }
        }
        let steps = xpbd_lanes::full_steps(&lanes, alpha);
        for l in 0..n {
            let e = first + j0 + l;
            let (p0, p, k) = finish_lane(
                &lanes,
                &steps,
                l,
                &pre.grads[e],
                alpha,
                &mut lambdas[j0 + l],
            );
            halvings += k;
            for (i, &v) in pre.corners[e].iter().enumerate() {
                for a in 0..3 {
                    // `x + (p - x)`, not `p`: the bits of the update as applied before.
                    let moved = p0[i][a] + (p[i][a] - p0[i][a]);
                    shared[v][a].store(moved.to_bits(), Relaxed);
                }
            }
        }
    }
    halvings
}

/// Lane `l`'s update from its full step ([`xpbd_lanes::full_steps`]), as the scalar update [`project_tet`] makes
/// it: the full step where the guard accepts it, else the guard's search from its first halving, none for a
/// singular system. Updates the tet's multipliers `lambda`; returns its corners before and after and the halvings.
#[inline(always)]
fn finish_lane(
    lanes: &TetLanes,
    steps: &xpbd_lanes::LaneSteps,
    l: usize,
    g: &[Vec3; 4],
    alpha: f64,
    lambda: &mut [f64; 2],
) -> ([Vec3; 4], [Vec3; 4], usize) {
    let p0: [Vec3; 4] = std::array::from_fn(|k| [0, 1, 2].map(|a| lanes.p[k][a][l]));
    let (t, halvings) = match steps.accepted[l] {
        Some(true) => (1.0, 0),
        Some(false) => {
            let w = [0, 1, 2, 3].map(|k| lanes.w[k][l]);
            let dp: [Vec3; 4] = std::array::from_fn(|k| [0, 1, 2].map(|a| steps.dp[k][a][l]));
            let local = LocalStep {
                p0: &p0,
                dp: &dp,
                w: &w,
                g,
                alpha_tilde: [lanes.at[0][l], lanes.at[1][l]],
                lambda,
                phi0: steps.phi0[l],
                slope: steps.slope[l],
                j0: steps.j[l],
            };
            match local.guarded_fraction(alpha, 1) {
                Ok(found) => found,
                Err(k) => return (p0, p0, k),
            }
        }
        None => return (p0, p0, 0),
    };
    let p = std::array::from_fn(|k| [0, 1, 2].map(|a| p0[k][a] + t * steps.dp[k][a][l]));
    for c in 0..2 {
        lambda[c] += t * steps.dl[c][l];
    }
    (p0, p, halvings)
}

/// `F = sum_k x_k g_k^T` of a tet from its four corner positions.
fn deformation(p: &[Vec3; 4], g: &[Vec3; 4]) -> Mat3 {
    let mut f = [[0.0; 3]; 3];
    for k in 0..4 {
        for a in 0..3 {
            for b in 0..3 {
                f[a][b] += p[k][a] * g[k][b];
            }
        }
    }
    f
}

/// The constraint values and corner gradients of a tet at corner positions `p`.
#[cfg(test)]
struct TetConstraints {
    /// `C_D = |F|` and `C_H = J - alpha`.
    c: [f64; 2],
    /// `J = det F`.
    j: f64,
    /// `grad[c][k]`: gradient of constraint `c` with respect to corner `k`, `(dC_c/dF) g_k`.
    grad: [[Vec3; 4]; 2],
}

/// `(C_D, C_H, J)` of a tet at corner positions `p`: [`tet_constraints`] without the gradients (same bits), for
/// the guarded update's trial points.
fn constraint_values(p: &[Vec3; 4], g: &[Vec3; 4], alpha: f64) -> ([f64; 2], f64) {
    let f = deformation(p, g);
    let norm = crate::math::ddot(&f, &f).sqrt();
    let j = det(&f);
    ([if norm > 1e-12 { norm } else { 0.0 }, j - alpha], j)
}

#[cfg(test)]
fn tet_constraints(p: &[Vec3; 4], g: &[Vec3; 4], alpha: f64) -> TetConstraints {
    let f = deformation(p, g);
    let norm = crate::math::ddot(&f, &f).sqrt();
    // C_D = |F|, dC_D/dF = F / |F| (undefined at F = 0: a collapsed tet is left to the hydrostatic term).
    let (c_d, q_d) = if norm > 1e-12 {
        (norm, f.map(|row| row.map(|v| v / norm)))
    } else {
        (0.0, [[0.0; 3]; 3])
    };
    // C_H = J - alpha, dC_H/dF = cof F.
    let j = det(&f);
    let q_h = crate::math::cofactor(&f);
    let mut grad = [[[0.0; 3]; 4]; 2];
    for k in 0..4 {
        for a in 0..3 {
            grad[0][k][a] = q_d[a][0] * g[k][0] + q_d[a][1] * g[k][1] + q_d[a][2] * g[k][2];
            grad[1][k][a] = q_h[a][0] * g[k][0] + q_h[a][1] * g[k][1] + q_h[a][2] * g[k][2];
        }
    }
    TetConstraints {
        c: [c_d, j - alpha],
        j,
        grad,
    }
}

/// The local objective of a tet's XPBD update,
/// `Phi(p) = 1/2 sum_k |p_k - p0_k|^2 / w_k + sum_c (C_c(p) + alpha~_c lambda_c)^2 / (2 alpha~_c)` (pinned corners,
/// `w_k = 0`, do not move and are left out), and `J` at `p`.
fn local_objective(
    p: &[Vec3; 4],
    p0: &[Vec3; 4],
    w: &[f64; 4],
    g: &[Vec3; 4],
    alpha: f64,
    alpha_tilde: [f64; 2],
    lambda: &[f64; 2],
) -> (f64, f64) {
    let (c, j) = constraint_values(p, g, alpha);
    let mut kin = 0.0;
    for k in 0..4 {
        if w[k] > 0.0 {
            let d = crate::math::sub(p[k], p0[k]);
            kin += crate::math::dot(d, d) / w[k];
        }
    }
    let mut phi = 0.5 * kin;
    for i in 0..2 {
        let e = c[i] + alpha_tilde[i] * lambda[i];
        phi += 0.5 * e * e / alpha_tilde[i];
    }
    (phi, j)
}

/// Step halvings after which a tet's update is skipped for this sweep (its step would be below 2^-30).
const MAX_HALVINGS: usize = 30;

/// One XPBD update of a tet's two constraints, `p` its corner positions, `w` their inverse masses.
///
/// The update is a step on the tet's local objective `Phi` ([`local_objective`], with `p0` the positions
/// before the update and `lambda` the multipliers so far), whose minimiser satisfies XPBD's conditions
/// `M (p - p0) = grad C dl`, `C(p) + alpha~ (lambda + dl) = 0`. The classic XPBD update is its Gauss-Newton
/// step: a 2x2 block solve of the linearised conditions `C_c + alpha~_c lambda_c + grad C_c . dx = 0`,
/// `dx = W (grad C_D dl_D + grad C_H dl_H)`. Solving the two constraints together matters: at rest their
/// gradients are parallel (both a pure dilation) and their forces cancel, which a sequential update misses.
///
/// `guarded` (what [`Xpbd`] uses): the full Gauss-Newton step is taken when it lowers `Phi` (Armijo,
/// `Phi(t) <= Phi(0) + 1e-4 t Phi'(0)`) and, for a tet that is upright before the update, keeps it upright
/// (`J > 0`); otherwise the step `t (dx, dl)` is halved until it does. The Gauss-Newton step ignores the
/// constraints' curvature, which on sliver tets (huge shape gradients) makes it overshoot: the tet inverts
/// itself or its objective grows, and the excess becomes velocity jitter. A tet that is already inverted is
/// updated like any other (the hydrostatic constraint pushes `J` back towards `alpha`) under the same descent
/// test. Neither test changes the constraints or their compliance (the energy FEPR conserves); they only
/// shorten a step. After [`MAX_HALVINGS`] the tet is left as it is for this sweep. Returns the halvings.
///
/// The sweeps make this update four tets at a time ([`xpbd_lanes::full_steps`], [`finish_lane`]), with the same
/// operations in the same order; this one-tet form is the reference a test holds them to, bit for bit.
#[cfg(test)]
fn project_tet(
    p: &mut [Vec3; 4],
    w: &[f64; 4],
    g: &[Vec3; 4],
    alpha: f64,
    alpha_tilde: [f64; 2],
    lambda: &mut [f64; 2],
    guarded: bool,
) -> usize {
    let tc = tet_constraints(p, g, alpha);
    let r = [
        tc.c[0] + alpha_tilde[0] * lambda[0],
        tc.c[1] + alpha_tilde[1] * lambda[1],
    ];
    // y_c = W grad C_c.
    let mut y = tc.grad;
    for yc in y.iter_mut() {
        for k in 0..4 {
            yc[k] = scale(yc[k], w[k]);
        }
    }
    let (mut a11, mut a12, mut a22) = (alpha_tilde[0], 0.0, alpha_tilde[1]);
    for k in 0..4 {
        a11 += crate::math::dot(tc.grad[0][k], y[0][k]);
        a12 += 0.5
            * (crate::math::dot(tc.grad[0][k], y[1][k]) + crate::math::dot(tc.grad[1][k], y[0][k]));
        a22 += crate::math::dot(tc.grad[1][k], y[1][k]);
    }
    let det2 = a11 * a22 - a12 * a12;
    if !(det2 > 0.0 && det2.is_finite()) {
        return 0;
    }
    let dl_d = (a22 * -r[0] - a12 * -r[1]) / det2;
    let dl_h = (a11 * -r[1] - a12 * -r[0]) / det2;
    let mut dp = [[0.0; 3]; 4];
    for k in 0..4 {
        for a in 0..3 {
            dp[k][a] = y[0][k][a] * dl_d + y[1][k][a] * dl_h;
        }
    }
    let p0 = *p;
    let (t, halvings) = if guarded {
        let phi0 = 0.5 * r[0] * r[0] / alpha_tilde[0] + 0.5 * r[1] * r[1] / alpha_tilde[1];
        // Phi'(0) along dp: sum_c (r_c / alpha~_c) grad C_c . dp (negative: the Gauss-Newton matrix is SPD).
        let mut slope = 0.0;
        for k in 0..4 {
            slope += r[0] / alpha_tilde[0] * crate::math::dot(tc.grad[0][k], dp[k])
                + r[1] / alpha_tilde[1] * crate::math::dot(tc.grad[1][k], dp[k]);
        }
        let local = LocalStep {
            p0: &p0,
            dp: &dp,
            w,
            g,
            alpha_tilde,
            lambda,
            phi0,
            slope,
            j0: tc.j,
        };
        match local.guarded_fraction(alpha, 0) {
            Ok(found) => found,
            Err(halvings) => return halvings,
        }
    } else {
        (1.0, 0)
    };
    let trial = step_to(&p0, &dp, t);
    lambda[0] += t * dl_d;
    lambda[1] += t * dl_h;
    *p = trial;
    halvings
}

/// `p0 + t dp`.
pub(super) fn step_to(p0: &[Vec3; 4], dp: &[Vec3; 4], t: f64) -> [Vec3; 4] {
    let mut q = *p0;
    for k in 0..4 {
        for a in 0..3 {
            q[k][a] += t * dp[k][a];
        }
    }
    q
}

/// A tet's Gauss-Newton step `dp` from `p0` ([`project_tet`]), with what the guard tests it against: the local
/// objective `phi0` and its slope along `dp` at `p0`, and `J` at `p0`.
pub(super) struct LocalStep<'a> {
    pub p0: &'a [Vec3; 4],
    pub dp: &'a [Vec3; 4],
    pub w: &'a [f64; 4],
    pub g: &'a [Vec3; 4],
    pub alpha_tilde: [f64; 2],
    pub lambda: &'a [f64; 2],
    pub phi0: f64,
    pub slope: f64,
    pub j0: f64,
}

impl LocalStep<'_> {
    /// The guard's search: the step `t = 2^-k` for the first `k` from `done` (halvings already refused) whose
    /// trial point lowers the objective (Armijo) and keeps an upright tet upright, with `k`
    /// (`Err(MAX_HALVINGS)`: none before the limit, the tet is left as it is).
    pub(super) fn guarded_fraction(
        &self,
        alpha: f64,
        done: usize,
    ) -> std::result::Result<(f64, usize), usize> {
        let mut t = 1.0;
        for _ in 0..done {
            t *= 0.5;
        }
        let mut halvings = done;
        loop {
            let trial = step_to(self.p0, self.dp, t);
            let (phi, j) = local_objective(
                &trial,
                self.p0,
                self.w,
                self.g,
                alpha,
                self.alpha_tilde,
                self.lambda,
            );
            let descent = phi.is_finite() && phi <= self.phi0 + 1e-4 * t * self.slope;
            let upright = self.j0 <= 0.0 || j > 0.0;
            if descent && upright {
                return Ok((t, halvings));
            }
            halvings += 1;
            t *= 0.5;
            if halvings >= MAX_HALVINGS {
                return Err(halvings);
            }
        }
    }
}

impl Integrator for Xpbd {
    fn name(&self) -> &'static str {
        "xpbd"
    }

    fn is_implicit(&self) -> bool {
        true
    }

    fn set_obstacles(&mut self, obstacles: &[Obstacle]) {
        self.contact = ContactPotential::new(obstacles);
    }

    fn substeps(&self) -> usize {
        self.settings.substeps
    }

    fn take_in_parts(&mut self, parts: usize) {
        self.parts = parts;
    }

    fn check(&self, model: &Model) -> Result<()> {
        match Self::material(model) {
            Some(_) => Ok(()),
            None => Err(invalid(
                "material",
                "xpbd solves the Neo-Hookean constraints of Macklin and Mueller 2021; give the ConstraintNeoHookean \
                 material so that FEPR conserves the energy its compliance encodes",
            )),
        }
    }

    // Long (about 140 lines): one XPBD step as the paper states it (substeps: predict, Gauss-Seidel sweeps colour
    // by colour with the contact constraints after each, velocities), kept in one place to be read against it.
    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        _hand_over: &mut HandOver,
    ) -> StepReport {
        let Some(mat) = Self::material(model) else {
            // Only reachable without `check`: poison the state so that the simulation reports it.
            state.x.iter_mut().for_each(|p| *p = [f64::NAN; 3]);
            return StepReport::default();
        };
        // The compliances, inverse masses and colouring come from the model: prepare them again when it changed
        // since (public fields changed between steps, or another model).
        if self.pre.as_ref().is_some_and(|p| p.key != model.key()) {
            self.pre = None;
        }
        if self.pre.is_none() {
            self.pre = Some(Self::prepare(model, mat));
        }
        let pre = self.pre.as_ref().expect("prepared");
        let m = model.num_vertices();
        // A step taken in parts (bodies in contact, answered after each substep): this call's share of the
        // substeps, each of the step's substep length.
        let substeps = (self.settings.substeps / self.parts.max(1)).max(1);
        let hs = h / substeps as f64;
        self.contact_dv.clear();
        if !self.contact.is_empty() {
            self.contact_dv.resize(model.num_vertices(), [0.0; 3]);
            self.v_start.clone_from(&state.v);
        }
        let inv_hs2 = 1.0 / (hs * hs);
        let g = model.gravity;
        self.lambdas.resize(model.num_tets(), [0.0; 2]);
        let mut halvings = 0usize;
        let mut x_prev = std::mem::take(&mut self.x_prev);
        x_prev.resize(m, [0.0; 3]);
        let t0 = state.time;
        for k in 0..substeps {
            x_prev.copy_from_slice(&state.x);
            // Moving obstacles advance substep by substep (placed once for the whole step, a vertex pushed out
            // in the first substep would leave with the step's whole displacement of the obstacle as velocity).
            self.contact.place(t0 + k as f64 * hs, hs);
            for i in 0..m {
                if model.pinned[i] {
                    state.v[i] = [0.0; 3];
                    continue;
                }
                for a in 0..3 {
                    state.v[i][a] += hs * g[a];
                    state.x[i][a] += hs * state.v[i][a];
                }
            }
            self.lambdas.iter_mut().for_each(|l| *l = [0.0; 2]);
            for _ in 0..self.settings.iterations {
                halvings += sweep(
                    pre,
                    &model.kernel_rank,
                    &mut self.lambdas,
                    &mut self.shared_x,
                    &mut state.x,
                    mat.alpha,
                    inv_hs2,
                );
                self.contact.project_out_recording(
                    model,
                    &mut state.x,
                    1.0 / hs,
                    &mut self.contact_dv,
                );
            }
            let inv_hs = 1.0 / hs;
            for i in 0..m {
                if model.pinned[i] {
                    state.x[i] = x_prev[i];
                    state.v[i] = [0.0; 3];
                    continue;
                }
                for a in 0..3 {
                    state.v[i][a] = (state.x[i][a] - x_prev[i][a]) * inv_hs;
                }
            }
        }
        self.x_prev = x_prev;
        state.time += h;
        // The impacts are answered against the obstacles' surface velocity over the whole step.
        self.contact.place(t0, h);
        let dv = &self.contact_dv;
        let v_start = &self.v_start;
        let contact = self.contact.apply_impacts(
            model,
            state,
            h,
            |i| v_start[i],
            |i, _| {
                let d = dv[i];
                (d != [0.0; 3]).then_some(d)
            },
        );
        StepReport {
            impulse: add(scale(g, h * model.free_mass()), contact.impulse),
            angular_impulse: contact.angular_impulse,
            iterations: self.settings.iterations * substeps,
            line_search_steps: halvings,
            contact,
            ..Default::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (no dependency): uniform in [-1, 1).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        }
    }

    /// Shape gradients `g_k` of a rest tet (`F = sum_k x_k g_k^T`) and its volume.
    fn rest_tet(x: &[Vec3; 4]) -> ([Vec3; 4], f64) {
        let dm = [0, 1, 2].map(|a| [0, 1, 2].map(|k| x[k + 1][a] - x[0][a]));
        let inv = crate::math::inverse(&dm).expect("non-degenerate rest tet");
        let g1 = inv[0];
        let g2 = inv[1];
        let g3 = inv[2];
        let g0 = [0, 1, 2].map(|b| -(g1[b] + g2[b] + g3[b]));
        ([g0, g1, g2, g3], det(&dm).abs() / 6.0)
    }

    /// A sliver: nearly flat (height 2% of its edge), 1 cm across.
    fn sliver() -> [Vec3; 4] {
        [
            [0.0, 0.0, 0.0],
            [0.01, 0.0, 0.0],
            [0.0, 0.01, 0.0],
            [0.004, 0.004, 0.0002],
        ]
    }

    /// The sweeps' four-at-a-time update against the one-tet reference, bit for bit: positions, multipliers and
    /// halvings, on tets upright and inverted, slivers, pinned corners, and steps the guard refuses.
    #[test]
    fn updates_side_by_side_are_the_one_tet_update_bit_for_bit() {
        let mut rng = Lcg(5);
        let mat = ConstraintNeoHookean::new(1e5, 0.3).unwrap();
        let (mut refused, mut singular, mut n) = (0, 0, 0);
        for round in 0..300 {
            let mut lanes = TetLanes::default();
            let mut cases = Vec::new();
            for l in 0..LANES {
                let rest = if (round + l) % 3 == 0 {
                    sliver()
                } else {
                    [
                        [0.0, 0.0, 0.0],
                        [0.02, 0.0, 0.0],
                        [0.0, 0.02, 0.0],
                        [0.0, 0.0, 0.02],
                    ]
                };
                let (g, vol) = rest_tet(&rest);
                let spread = [0.0005, 0.003, 0.02][(round / 3 + l) % 3];
                let mut p0 = rest.map(|v| v.map(|c| 1.1 * c + spread * rng.next()));
                if (round + l) % 7 == 0 {
                    p0[3][2] = -p0[3][2]; // inverted
                }
                let hs = [1.0 / 600.0, 1.0 / 19200.0][round % 2];
                let at = [
                    1.0 / (mat.mu * vol * hs * hs),
                    1.0 / (mat.lambda * vol * hs * hs),
                ];
                let mut w = [1.0 / (1000.0 * 20.0 * vol); 4];
                if (round + l) % 5 == 0 {
                    w[1] = 0.0; // pinned corner
                }
                let lambda = [rng.next() * 1e-4, rng.next() * 1e-4];
                for k in 0..4 {
                    for a in 0..3 {
                        lanes.p[k][a][l] = p0[k][a];
                        lanes.g[k][a][l] = g[k][a];
                    }
                    lanes.w[k][l] = w[k];
                }
                for c in 0..2 {
                    lanes.at[c][l] = at[c];
                    lanes.lambda[c][l] = lambda[c];
                }
                cases.push((p0, g, w, at, lambda));
            }
            let steps = xpbd_lanes::full_steps(&lanes, mat.alpha);
            for (l, &(p0, g, w, at, lambda)) in cases.iter().enumerate() {
                let (mut p, mut lam) = (p0, lambda);
                let k_ref = project_tet(&mut p, &w, &g, mat.alpha, at, &mut lam, true);
                let mut lam_lane = lambda;
                let (_, p_lane, k_lane) =
                    finish_lane(&lanes, &steps, l, &g, mat.alpha, &mut lam_lane);
                let bits = |q: &[Vec3; 4]| q.map(|v| v.map(f64::to_bits));
                assert_eq!(bits(&p_lane), bits(&p), "round {round} lane {l}: positions");
                assert_eq!(
                    lam_lane.map(f64::to_bits),
                    lam.map(f64::to_bits),
                    "round {round} lane {l}"
                );
                assert_eq!(k_lane, k_ref, "round {round} lane {l}: halvings");
                refused += usize::from(steps.accepted[l] == Some(false));
                singular += usize::from(steps.accepted[l].is_none());
                n += 1;
            }
        }
        eprintln!("{n} updates: {refused} full steps refused, {singular} singular");
        assert!(
            refused > 20 && n - refused - singular > 20,
            "full steps taken and refused ({refused} of {n} refused)"
        );
    }

    /// Random deformations of a sliver with a substep's compliance: the plain XPBD update (Gauss-Newton, full
    /// step) overshoots on about a third of them (its local objective grows); the guarded update always lowers
    /// it and keeps the upright sliver upright.
    #[test]
    fn guarded_local_solve_decreases_its_objective_and_keeps_upright_slivers_upright() {
        let mut rng = Lcg(11);
        let rest = sliver();
        let (g, vol) = rest_tet(&rest);
        let mat = ConstraintNeoHookean::new(1e5, 0.3).unwrap();
        let hs = 1.0 / 600.0;
        let at = [
            1.0 / (mat.mu * vol * hs * hs),
            1.0 / (mat.lambda * vol * hs * hs),
        ];
        // Corner masses of a 1000 kg/m^3 body whose vertices each carry about 20 such tets' worth of mass.
        let w = [1.0 / (1000.0 * 20.0 * vol); 4];
        let (mut plain_worse, mut plain_inverted, mut tried) = (0, 0, 0);
        for _ in 0..400 {
            let mut p0 = rest.map(|v| v.map(|c| 1.1 * c + 0.0005 * rng.next()));
            // Squash the apex towards the base (0.05 to 1 of its height): the states that invert slivers.
            p0[3][2] = rest[3][2] * (0.525 + 0.475 * rng.next());
            if det(&deformation(&p0, &g)) <= 0.0 {
                continue;
            }
            tried += 1;
            let lambda0 = [0.0; 2];
            let (phi0, _) = local_objective(&p0, &p0, &w, &g, mat.alpha, at, &lambda0);
            let mut p = p0;
            let mut lam = lambda0;
            project_tet(&mut p, &w, &g, mat.alpha, at, &mut lam, false);
            let (phi, j) = local_objective(&p, &p0, &w, &g, mat.alpha, at, &lambda0);
            plain_worse += usize::from(phi > phi0);
            plain_inverted += usize::from(j <= 0.0);
            let mut p = p0;
            let mut lam = lambda0;
            project_tet(&mut p, &w, &g, mat.alpha, at, &mut lam, true);
            let (phi, j) = local_objective(&p, &p0, &w, &g, mat.alpha, at, &lambda0);
            assert!(
                phi <= phi0 && j > 0.0,
                "guarded update: Phi {phi0:.3e} -> {phi:.3e}, J {j:.3e}"
            );
            assert!(p.iter().flatten().all(|c| c.is_finite()));
        }
        eprintln!(
            "plain XPBD update: Phi grew in {plain_worse}, inverted {plain_inverted} of {tried}"
        );
        assert!(tried > 100 && plain_worse + plain_inverted > 0);
    }

    /// An inverted tet: the guarded update moves it towards upright (J grows), lowers its objective and stays
    /// finite.
    #[test]
    fn guarded_local_solve_of_an_inverted_tet_is_finite_and_decreases_its_objective() {
        let rest = [
            [0.0, 0.0, 0.0],
            [0.02, 0.0, 0.0],
            [0.0, 0.02, 0.0],
            [0.0, 0.0, 0.02],
        ];
        let (g, vol) = rest_tet(&rest);
        let mat = ConstraintNeoHookean::new(1e5, 0.3).unwrap();
        let hs = 1.0 / 600.0;
        let at = [
            1.0 / (mat.mu * vol * hs * hs),
            1.0 / (mat.lambda * vol * hs * hs),
        ];
        let w = [1.0 / (1000.0 * vol); 4];
        for depth in [0.001, 0.01, 0.05] {
            let mut p0 = rest;
            p0[3][2] = -depth;
            let lambda0 = [0.0; 2];
            let (phi0, j0) = local_objective(&p0, &p0, &w, &g, mat.alpha, at, &lambda0);
            let mut p = p0;
            let mut lam = lambda0;
            project_tet(&mut p, &w, &g, mat.alpha, at, &mut lam, true);
            let (phi, j) = local_objective(&p, &p0, &w, &g, mat.alpha, at, &lambda0);
            assert!(
                j0 < 0.0 && j > j0 && phi < phi0,
                "depth {depth}: J {j0} -> {j}, Phi {phi0} -> {phi}"
            );
            assert!(lam.iter().all(|l| l.is_finite()));
        }
    }
}
