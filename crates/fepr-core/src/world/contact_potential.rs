//! Contact inside an implicit step: the obstacles as a penalty energy in the step's optimisation.
//!
//! An implicit step (backward Euler's Newton solve, Projective Dynamics' local/global iterations) that ignores
//! the obstacles ends a fast vertex deep inside one at a large step (2.4 m/s at dt = 1/60: 4 cm), and pushing it
//! out afterwards strains the elements around it (and makes the simulation redo the step in impact substeps).
//! With the obstacles inside the solve, the elastic response to the contact is part of the same solve, and the
//! push-out after the step ([`super::resolve_contacts`]) only has the penalty's residual depth left to repair.
//!
//! Why a penalty on the active set (rather than constraints or a barrier): it keeps the solve an unconstrained
//! minimisation of a C1 objective with a positive semi-definite Hessian term, so backward Euler's Newton solve
//! with its Armijo line search and Projective Dynamics' prefactored global matrix need no new machinery, and
//! no step needs a feasible start (a barrier does: a start inside an obstacle is infinite energy). The residual
//! depth is small and bounded: the penalty's stiffness is tied to the vertex's inertia term,
//!
//! ```text
//! E_c(x) = sum over free vertices i and obstacles o with phi_o(x_i) < d of  k_i / 2 (phi_o(x_i) - d)^2,
//! k_i = STIFFNESS_RATIO m_i / h^2,   d = ACTIVATION_MARGIN times the body's size,
//! ```
//!
//! so a lone vertex arriving at speed v stops within `v h / (1 + STIFFNESS_RATIO)` of the layer `phi = d` (4 um
//! for the example above); a vertex carrying the load of the body above it sinks in proportion to that load (the
//! feet of a 1 m armadillo standing on a plane at dt = 1/60 stay inside the impact limit, so that its resting
//! steps take no impact substeps; the push-out after the step repairs that depth). Backward Euler stiffens the
//! penalty of the vertices its solve leaves deeper than a contact test allows ([`ContactPotential::stiffen_deep`]),
//! and keeps it while they stay in reach ([`ContactPotential::relax_stiffening`]).
//! The solve only stops a vertex; restitution and friction are applied after it to each vertex the solve held
//! ([`ContactPotential::apply_impacts`]): the impact's energy loss and friction are booked as contact work, and the
//! contact force's impulse goes to the momentum targets, so that the projection neither undoes the contact's
//! momentum change nor restores the energy an inelastic contact removed.
//!
//! The Hessian term is the Gauss-Newton part `k n n^T` (exact for planes and box faces); the curvature part of
//! curved surfaces (`k phi dn/dx`, negative inside a sphere or capsule) is left out so that the term stays
//! positive semi-definite.

use super::{ContactReport, Obstacle, Shape};
use crate::math::{add, cross, dot, norm, scale, sub, Mat3, Vec3};
use crate::model::{Model, State};

/// Penalty stiffness per vertex in units of the vertex's inertia term `m_i / h^2` (see the module comment).
/// Why 1e4: the vertices a resting body stands on carry the load of many vertices, and sink by that load over
/// the stiffness. At 1e3 the feet of the 4,406-tet armadillo standing on a plane at dt = 1/60 sink deeper than
/// the impact limit (a tenth of a mean edge) on every resting step, which is then redone in substeps; at 1e4 they
/// do not. 1e5 costs Newton iterations and line-search steps on the same drop and gains nothing.
pub const STIFFNESS_RATIO: f64 = 1e4;

/// Approach speeds below this many steps of gravity (`RESTING_SPEED_STEPS |g| h`) are resting contact: no
/// restitution (see [`ContactPotential::apply_impacts`]).
pub const RESTING_SPEED_STEPS: f64 = 2.0;

/// The penalty acts from this fraction of the body's size outside an obstacle (`Model::length_scale`): a vertex
/// touching the surface is then in the penalty's reach, so that Newton's Hessian holds it, and a body at rest
/// stands on a layer this thin (0.1 mm for a 1 m body).
pub const ACTIVATION_MARGIN: f64 = 1e-4;

/// The obstacles an implicit step keeps its free vertices out of (see the module comment).
#[derive(Debug, Default)]
pub struct ContactPotential {
    obstacles: Vec<Obstacle>,
    /// For each closed-mesh obstacle and vertex, a position and the exact signed distance there (`(obstacle *
    /// m + vertex)`; empty until the first query). A closed surface's signed distance is 1-Lipschitz, so
    /// `phi(x) >= phi_ref - |x - x_ref|`: a vertex that cannot have come within reach since needs no BVH query.
    /// The solve evaluates the potential many times per step with each vertex moving little in between, so
    /// most mesh queries are skipped; the answers are exact either way.
    clear: std::sync::Mutex<Vec<(Vec3, f64)>>,
    /// Per-vertex multipliers of the stiffness (empty: all 1): raised by [`ContactPotential::stiffen_deep`], kept
    /// while the vertex stays in reach ([`ContactPotential::relax_stiffening`]).
    stiffening: Vec<f64>,
}

impl Clone for ContactPotential {
    fn clone(&self) -> Self {
        Self::new(&self.obstacles)
    }
}

impl PartialEq for ContactPotential {
    fn eq(&self, other: &Self) -> bool {
        self.obstacles == other.obstacles
    }
}

impl ContactPotential {
    pub fn new(obstacles: &[Obstacle]) -> Self {
        Self {
            obstacles: obstacles.to_vec(),
            clear: Default::default(),
            stiffening: Vec::new(),
        }
    }

    /// The cache of [`ContactPotential::clear`], locked and sized for `m` vertices.
    fn clear_cache(&self, m: usize) -> std::sync::MutexGuard<'_, Vec<(Vec3, f64)>> {
        let mut clear = self.clear.lock().unwrap_or_else(|e| e.into_inner());
        if clear.len() != self.obstacles.len() * m {
            // Unknown: a reference infinitely far below reach.
            *clear = vec![([0.0; 3], f64::NEG_INFINITY); self.obstacles.len() * m];
        }
        clear
    }

    /// `(phi, n)` of obstacle `k` at `x`, the position of vertex `i` of `m`, when `phi < below` (m); `None`
    /// otherwise, without a query when a closed mesh's cached bound already proves it.
    fn near(
        &self,
        clear: &mut [(Vec3, f64)],
        m: usize,
        k: usize,
        i: usize,
        x: Vec3,
        below: f64,
    ) -> Option<(f64, Vec3)> {
        let ob = &self.obstacles[k];
        // A moving mesh's distances change without the vertex moving: no bound carries over.
        let cached =
            ob.motion().is_none() && matches!(&ob.shape, Shape::Mesh(mesh) if mesh.is_closed());
        if cached {
            let (x_ref, phi_ref) = clear[k * m + i];
            if phi_ref - norm(sub(x, x_ref)) >= below {
                return None;
            }
        }
        let near = ob.signed_distance_below(x, below);
        if cached {
            // Exact where found; otherwise `below` is a lower bound of the distance, as good for the next query.
            clear[k * m + i] = (x, near.map_or(below, |(phi, _)| phi));
        }
        near
    }

    /// Place the moving obstacles for a step (or an XPBD substep) from `t` over `h` seconds
    /// ([`Obstacle::place`]); the potential is then the one of where they are at its end.
    pub fn place(&mut self, t: f64, h: f64) {
        for ob in self.obstacles.iter_mut() {
            ob.place(t, h);
        }
    }

    /// True when an obstacle moves (its placement must follow the steps: [`ContactPotential::place`]).
    pub fn has_motion(&self) -> bool {
        self.obstacles.iter().any(|ob| ob.motion().is_some())
    }

    /// True when there is no obstacle (the potential is 0 everywhere).
    pub fn is_empty(&self) -> bool {
        self.obstacles.is_empty()
    }

    /// The penalty stiffness `k_i` of vertex `i` at step size `h`, N/m.
    fn stiffness(&self, model: &Model, i: usize, h: f64) -> f64 {
        STIFFNESS_RATIO * self.multiplier(i) * model.masses[i] / (h * h)
    }

    /// Vertex `i`'s stiffness multiplier.
    fn multiplier(&self, i: usize) -> f64 {
        self.stiffening.get(i).copied().unwrap_or(1.0)
    }

    /// The start of a step from positions `x` (m): a vertex out of every obstacle's reach
    /// ([`ContactPotential::in_reach`]) is back to the plain stiffness; one still in reach keeps its multiplier.
    /// Why keep it: a vertex that an impact pushed deep keeps carrying load once the body stands on it, and at the
    /// plain stiffness it would sink as deep again, so that every standing step would take a second Newton round
    /// after stiffening it again (the armadillo dropped 0.3 m onto a plane, backward Euler at 1/60 without FEPR:
    /// 2.8-3.4 Newton iterations per standing step, 4.2-5.5 with the multipliers reset each step).
    pub fn relax_stiffening(&mut self, model: &Model, x: &[Vec3]) {
        if self.stiffening.len() != x.len() {
            self.stiffening.clear();
            return;
        }
        let mut any = false;
        for i in 0..x.len() {
            if self.stiffening[i] != 1.0 && !self.in_reach(model, x[i]) {
                self.stiffening[i] = 1.0;
            }
            any |= self.stiffening[i] != 1.0;
        }
        if !any {
            self.stiffening.clear();
        }
    }

    /// The stiffness multipliers per vertex (empty: all 1), for a checkpoint.
    pub fn stiffening(&self) -> &[f64] {
        &self.stiffening
    }

    /// Put back multipliers from [`ContactPotential::stiffening`] (empty: all 1).
    pub fn set_stiffening(&mut self, multipliers: Vec<f64>) {
        self.stiffening = multipliers;
    }

    /// Multiplies by `factor` the stiffness of every free vertex of `x` (m) that lies deeper than `limit` (m)
    /// inside an obstacle, up to `most` times the plain stiffness; returns how many. Why: a vertex carrying a body's
    /// momentum into the ground sinks by its force over the stiffness, and the push-out after the step then moves
    /// it (and, for a sliver wholly inside, all four vertices, flattening the tet) without the elastic response;
    /// stiffened, the same solve carries the stop into the body.
    pub fn stiffen_deep(
        &mut self,
        model: &Model,
        x: &[Vec3],
        limit: f64,
        factor: f64,
        most: f64,
    ) -> usize {
        let mut count = 0;
        for (i, xi) in x.iter().enumerate() {
            if model.pinned[i]
                || self.multiplier(i) * factor > most
                || !self
                    .obstacles
                    .iter()
                    .any(|ob| ob.signed_distance_below(*xi, -limit).is_some())
            {
                continue;
            }
            if self.stiffening.len() != x.len() {
                // Empty while no vertex is stiffened: refilled in place (the capacity stays), no allocation once
                // the step loop runs.
                self.stiffening.clear();
                self.stiffening.resize(x.len(), 1.0);
            }
            self.stiffening[i] *= factor;
            count += 1;
        }
        count
    }

    /// The obstacles whose penalty reaches the point `x` (m): `(phi - d, n)` for each (the signed distance less
    /// the activation distance `margin`, negative, m; the obstacle's outward normal).
    fn reaching(&self, margin: f64, x: Vec3) -> impl Iterator<Item = (f64, Vec3)> + '_ {
        self.obstacles.iter().filter_map(move |ob| {
            ob.signed_distance_below(x, margin)
                .map(|(phi, n)| (phi - margin, n))
        })
    }

    /// Each penalty term on the free vertices at `x` (m, (m, 3)): `f(i, k_i, phi - d, n)` with the vertex, its
    /// stiffness (N/m), its depth in the layer (m, negative) and the obstacle's outward normal.
    fn each_penetration(
        &self,
        model: &Model,
        x: &[Vec3],
        h: f64,
        mut f: impl FnMut(usize, f64, f64, Vec3),
    ) {
        if self.obstacles.is_empty() {
            return;
        }
        let margin = Self::margin(model);
        let m = x.len();
        let mut clear = self.clear_cache(m);
        for (i, xi) in x.iter().enumerate() {
            if !model.pinned[i] {
                let stiffness = self.stiffness(model, i, h);
                for k in 0..self.obstacles.len() {
                    if let Some((phi, n)) = self.near(&mut clear, m, k, i, *xi, margin) {
                        f(i, stiffness, phi - margin, n);
                    }
                }
            }
        }
    }

    /// `E_c(x)`, J.
    pub fn energy(&self, model: &Model, x: &[Vec3], h: f64) -> f64 {
        let mut e = 0.0;
        self.each_penetration(model, x, h, |_, k, phi, _| e += 0.5 * k * phi * phi);
        e
    }

    /// `E_c(x)` (J), adding its gradient `k_i phi n` to `grad` (J/m, (m, 3)).
    pub fn add_gradient(&self, model: &Model, x: &[Vec3], h: f64, grad: &mut [Vec3]) -> f64 {
        let mut e = 0.0;
        self.each_penetration(model, x, h, |i, k, phi, n| {
            e += 0.5 * k * phi * phi;
            for a in 0..3 {
                grad[i][a] += k * phi * n[a];
            }
        });
        e
    }

    /// `f(i, k_i n n^T)` for every penetration: the Gauss-Newton Hessian block of vertex `i` (N/m).
    pub fn hessian_blocks(
        &self,
        model: &Model,
        x: &[Vec3],
        h: f64,
        mut f: impl FnMut(usize, Mat3),
    ) {
        self.each_penetration(model, x, h, |i, k, _, n| {
            f(
                i,
                [scale(n, k * n[0]), scale(n, k * n[1]), scale(n, k * n[2])],
            );
        });
    }

    /// The velocity change (m/s) that the penalty's force at `x` (m) gives vertex `i` over a step of `h`: the
    /// impulse `-h k_i (phi - d) n` over the vertex's mass, summed over the obstacles that reach `x`; `None` when
    /// none does. Backward Euler's contact impulse at its final iterate.
    pub fn penalty_velocity_change(
        &self,
        model: &Model,
        i: usize,
        x: Vec3,
        h: f64,
    ) -> Option<Vec3> {
        let k_over_m = STIFFNESS_RATIO * self.multiplier(i) / (h * h);
        self.reaching(Self::margin(model), x)
            .map(|(gap, n)| scale(n, -h * k_over_m * gap))
            .reduce(add)
    }

    /// The penalty's activation distance, m: [`ACTIVATION_MARGIN`] times the body's size.
    pub fn margin(model: &Model) -> f64 {
        ACTIVATION_MARGIN * model.length_scale
    }

    /// The contacts an implicit step held inside its solve, after it: `dv(i, x_i)` is the velocity change the
    /// solve's contact force gave free vertex `i` over the step (m/s; None: no contact) and `v_start(i)` its
    /// velocity at the start of the step (m/s). For each such vertex, against the nearest obstacle (normal `n`):
    /// - the impact's loss: a vertex that approached at `u = (v_start + h g) . n` faster than the resting speed
    ///   [`RESTING_SPEED_STEPS`] `|g| h` loses `(1 - restitution^2) m u^2 / 2` (what a restitution law takes of
    ///   the normal kinetic energy). The solve itself stops the vertex (the integrator's dissipation), and the
    ///   projection puts back what the loss does not claim, as far as its quality guard allows (the rest is
    ///   booked as unresolved energy): the bounce is the projection's. Why not set the vertex's normal velocity
    ///   to `-restitution u`: only the layer in contact would bounce, against a body the solve had already
    ///   stopped, and the strain puts that energy into vibration and squeezes the layer's tets. Slower approaches
    ///   are resting contact: no loss;
    /// - Coulomb friction: the tangential velocity loses at most `friction` times the normal velocity change
    ///   `dv . n` (it stops below that); its kinetic energy change is booked too.
    ///
    /// Returns the contacts' work (J, <= 0 against static obstacles), their impulse `sum m (dv + friction's change)`
    /// (kg m/s) and its moment about the centre of mass (kg m^2/s).
    pub fn apply_impacts(
        &self,
        model: &Model,
        state: &mut State,
        h: f64,
        v_start: impl Fn(usize) -> Vec3,
        dv: impl Fn(usize, Vec3) -> Option<Vec3>,
    ) -> ContactReport {
        let mut report = ContactReport::default();
        if self.obstacles.is_empty() {
            return report;
        }
        let c = crate::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
        let resting_speed = RESTING_SPEED_STEPS * norm(model.gravity) * h;
        for i in 0..model.num_vertices() {
            if model.pinned[i] {
                continue;
            }
            let Some(dv_i) = dv(i, state.x[i]) else {
                continue;
            };
            let (ob, n, surface) = self
                .obstacles
                .iter()
                .map(|ob| {
                    let (phi, n) = ob.signed_distance(state.x[i]);
                    (phi, ob, n, sub(state.x[i], scale(n, phi)))
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .map(|(_, ob, n, surface)| (ob, n, surface))
                .expect("an obstacle");
            let m = model.masses[i];
            // Velocities relative to the obstacle's surface: a moving obstacle's contact is a static one's in its
            // frame, plus the obstacle's work on the vertex (its impulse times the surface's velocity).
            let v_surface = ob.velocity_at(surface);
            let u = dot(sub(add(v_start(i), scale(model.gravity, h)), v_surface), n);
            let impact = -u > resting_speed;
            if impact {
                report.work -= 0.5 * m * (1.0 - ob.restitution * ob.restitution) * u * u;
            }
            let v = sub(state.v[i], v_surface);
            let vn = dot(v, n);
            let vt = sub(v, scale(n, vn));
            let vt_len = norm(vt);
            let cut = ob.friction * dot(dv_i, n).max(0.0);
            let vt_out = if vt_len <= cut || vt_len == 0.0 {
                [0.0; 3]
            } else {
                scale(vt, 1.0 - cut / vt_len)
            };
            let v_out = add(scale(n, vn), vt_out);
            let d = add(dv_i, sub(v_out, v));
            report.contacts += 1;
            report.work += 0.5 * m * (dot(vt_out, vt_out) - dot(vt, vt)) + m * dot(d, v_surface);
            report.impulse = add(report.impulse, scale(d, m));
            report.angular_impulse = add(
                report.angular_impulse,
                scale(cross(sub(state.x[i], c), d), m),
            );
            state.v[i] = add(v_surface, v_out);
        }
        report
    }

    /// Whether `x` (m) lies within the penalty's reach of an obstacle ([`ContactPotential::margin`]).
    pub fn in_reach(&self, model: &Model, x: Vec3) -> bool {
        self.reaching(Self::margin(model), x).next().is_some()
    }

    /// `x` (m) moved out of every obstacle it lies in onto that obstacle's surface, in obstacle order (`x` itself
    /// when it is outside all of them): the target of a projective contact constraint.
    pub fn nearest_outside(&self, model: &Model, mut x: Vec3) -> Vec3 {
        let margin = Self::margin(model);
        for ob in &self.obstacles {
            if let Some((phi, n)) = ob.signed_distance_below(x, margin) {
                for a in 0..3 {
                    x[a] -= (phi - margin) * n[a];
                }
            }
        }
        x
    }

    /// The target of a projective contact constraint for a vertex at `x` (m) that the unconstrained equations
    /// would move by `step` (m; one Jacobi step): `x + step` moved out of the obstacles
    /// ([`ContactPotential::nearest_outside`]), with Coulomb friction on the move along the surface. The normal
    /// correction `c` is what the obstacle's force undoes of the step, so the move along the surface `s_t` is
    /// held (static friction) while `|s_t| <= mu |c|` and shortened by `mu |c|` otherwise (both measured with the
    /// same diagonal of the system, which cancels), `mu` the friction of the obstacle the vertex lies deepest in.
    /// A vertex whose step keeps it out of every obstacle moves freely.
    pub fn friction_target(&self, model: &Model, x: Vec3, step: Vec3) -> Vec3 {
        let margin = Self::margin(model);
        let free = add(x, step);
        let mut p = free;
        let (mut deepest, mut mu) = (0.0f64, 0.0);
        for ob in &self.obstacles {
            if let Some((phi, n)) = ob.signed_distance_below(p, margin) {
                let depth = margin - phi;
                if depth > deepest {
                    (deepest, mu) = (depth, ob.friction);
                }
                p = sub(p, scale(n, phi - margin));
            }
        }
        let correction = sub(p, free);
        let c = norm(correction);
        if c == 0.0 || mu == 0.0 {
            return p;
        }
        let n = scale(correction, 1.0 / c);
        let along = sub(step, scale(n, dot(step, n)));
        let slide = norm(along);
        let kept = if slide <= mu * c {
            0.0
        } else {
            1.0 - mu * c / slide
        };
        sub(p, scale(along, 1.0 - kept))
    }

    /// Pushes every free vertex of `x` that lies inside an obstacle onto its surface (m); returns how many.
    /// XPBD's contact constraints after each sweep.
    pub fn project_out(&self, model: &Model, x: &mut [Vec3]) -> usize {
        self.project_out_recording(model, x, 0.0, &mut [])
    }

    /// [`ContactPotential::project_out`], adding each move times `rate` (1/s) to the vertex's row of `record`
    /// (m/s; empty: nothing recorded): XPBD's substep velocity changes by contact.
    pub fn project_out_recording(
        &self,
        model: &Model,
        x: &mut [Vec3],
        rate: f64,
        record: &mut [Vec3],
    ) -> usize {
        let mut moved = 0;
        if self.obstacles.is_empty() {
            return 0;
        }
        let m = x.len();
        let mut clear = self.clear_cache(m);
        for (i, xi) in x.iter_mut().enumerate() {
            if model.pinned[i] {
                continue;
            }
            for k in 0..self.obstacles.len() {
                if let Some((phi, n)) = self.near(&mut clear, m, k, i, *xi, 0.0) {
                    for a in 0..3 {
                        xi[a] -= phi * n[a];
                    }
                    if let Some(r) = record.get_mut(i) {
                        *r = add(*r, scale(n, -phi * rate));
                    }
                    moved += 1;
                }
            }
        }
        moved
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elasticity::tests::grid_model;
    use crate::material::{Material, NeoHookean};

    fn model_and_potential() -> (Model, ContactPotential) {
        let model = grid_model(2, Material::NeoHookean(NeoHookean::new(1e4, 0.3).unwrap()));
        let obstacles = [
            Obstacle::new(
                Shape::Plane {
                    point: [0.0, 0.0, 0.3],
                    normal: [0.1, 0.0, 1.0],
                },
                0.5,
                0.2,
            )
            .unwrap(),
            Obstacle::new(
                Shape::Box {
                    center: [1.0, 1.0, 0.5],
                    half_extents: [0.3, 0.2, 0.4],
                    axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                },
                0.0,
                0.0,
            )
            .unwrap(),
        ];
        (model, ContactPotential::new(&obstacles))
    }

    fn positions(model: &Model) -> Vec<Vec3> {
        // Shifted and sheared so that some vertices are inside each obstacle, none on a kink.
        model
            .mesh
            .vertices()
            .iter()
            .map(|p| [p[0] + 0.013 + 0.05 * p[2], p[1] + 0.007, p[2] - 0.011])
            .collect()
    }

    #[test]
    fn stiffening_stays_while_a_vertex_is_in_reach_up_to_its_cap_and_ends_when_it_leaves() {
        let (model, mut pot) = model_and_potential();
        let mut x = positions(&model);
        let margin = ContactPotential::margin(&model);
        let depth = |pot: &ContactPotential, xi: Vec3| {
            pot.obstacles
                .iter()
                .map(|ob| ob.signed_distance(xi).0)
                .fold(f64::INFINITY, f64::min)
        };
        let limit = 0.25;
        let deep: Vec<usize> = (0..x.len())
            .filter(|&i| depth(&pot, x[i]) < -limit)
            .collect();
        assert!(deep.len() >= 2, "the sample needs two deep vertices");
        // Stiffened twice, capped at 100 times: the third stiffening changes nothing.
        assert_eq!(pot.stiffen_deep(&model, &x, limit, 10.0, 100.0), deep.len());
        assert_eq!(pot.stiffen_deep(&model, &x, limit, 10.0, 100.0), deep.len());
        assert_eq!(pot.stiffen_deep(&model, &x, limit, 10.0, 100.0), 0);
        // A new step with the vertices where they are: the multipliers stay.
        pot.relax_stiffening(&model, &x);
        for &i in &deep {
            assert_eq!(pot.multiplier(i), 100.0, "vertex {i}");
        }
        // One deep vertex moved far out of every obstacle's reach: back to the plain stiffness, the others not.
        let (gone, kept) = (deep[0], &deep[1..]);
        x[gone] = [50.0, 50.0, 50.0];
        assert!(depth(&pot, x[gone]) > margin);
        pot.relax_stiffening(&model, &x);
        assert_eq!(pot.multiplier(gone), 1.0);
        for &i in kept {
            assert_eq!(pot.multiplier(i), 100.0, "vertex {i}");
        }
        // All out of reach: every multiplier 1 (and nothing kept).
        let far = vec![[50.0, 50.0, 50.0]; x.len()];
        pot.relax_stiffening(&model, &far);
        assert!(pot.stiffening().is_empty());
    }

    #[test]
    fn stiffening_multiplies_only_the_deep_vertices_penalty_and_keeps_the_gradient_exact() {
        let (model, mut pot) = model_and_potential();
        let h = 0.01;
        let x = positions(&model);
        let margin = ContactPotential::margin(&model);
        let depth = |xi: Vec3| {
            pot.obstacles
                .iter()
                .map(|ob| ob.signed_distance(xi).0)
                .fold(f64::INFINITY, f64::min)
        };
        let limit = 0.25;
        let deep: Vec<bool> = x.iter().map(|&xi| depth(xi) < -limit).collect();
        let shallow = (0..x.len()).any(|i| !deep[i] && depth(x[i]) < margin);
        assert!(
            deep.iter().any(|&d| d) && shallow,
            "the sample needs deep and shallow contacts"
        );
        let per_vertex = |pot: &ContactPotential| {
            let mut e = vec![0.0; x.len()];
            pot.each_penetration(&model, &x, h, |i, k, phi, _| e[i] += 0.5 * k * phi * phi);
            e
        };
        let before = per_vertex(&pot);
        let count = pot.stiffen_deep(&model, &x, limit, 10.0, 1e3);
        assert_eq!(count, deep.iter().filter(|&&d| d).count());
        let after = per_vertex(&pot);
        for i in 0..x.len() {
            let expected = if deep[i] { 10.0 * before[i] } else { before[i] };
            assert!(
                (after[i] - expected).abs() <= 1e-12 * expected.abs(),
                "vertex {i}"
            );
        }
        // Gradient against finite differences with the multipliers in place.
        let mut g = vec![[0.0; 3]; x.len()];
        pot.add_gradient(&model, &x, h, &mut g);
        assert_gradient_is_the_energy_derivative(&pot, &model, &x, h, &g);
        pot.set_stiffening(Vec::new());
        assert_eq!(per_vertex(&pot), before);
    }

    #[test]
    fn gradient_matches_finite_differences_of_the_energy() {
        let (model, pot) = model_and_potential();
        let h = 0.01;
        let x = positions(&model);
        let mut g = vec![[0.0; 3]; x.len()];
        let e = pot.add_gradient(&model, &x, h, &mut g);
        assert!(e > 0.0, "some vertices penetrate");
        assert_eq!(e, pot.energy(&model, &x, h));
        assert_gradient_is_the_energy_derivative(&pot, &model, &x, h, &g);
    }

    /// `g` against central differences of `pot`'s energy at `x`, every vertex and axis.
    fn assert_gradient_is_the_energy_derivative(
        pot: &ContactPotential,
        model: &Model,
        x: &[Vec3],
        h: f64,
        g: &[Vec3],
    ) {
        let eps = 1e-7;
        for i in 0..x.len() {
            for a in 0..3 {
                let (mut xp, mut xm) = (x.to_vec(), x.to_vec());
                xp[i][a] += eps;
                xm[i][a] -= eps;
                let fd = (pot.energy(model, &xp, h) - pot.energy(model, &xm, h)) / (2.0 * eps);
                assert!(
                    (fd - g[i][a]).abs() <= 1e-5 * (1.0 + g[i][a].abs()),
                    "vertex {i} axis {a}: fd {fd} analytic {}",
                    g[i][a]
                );
            }
        }
    }

    #[test]
    fn hessian_blocks_match_finite_differences_of_the_gradient_on_flat_faces() {
        let (model, pot) = model_and_potential();
        let h = 0.01;
        let x = positions(&model);
        let mut blocks = vec![[[0.0; 3]; 3]; x.len()];
        pot.hessian_blocks(&model, &x, h, |i, b| {
            for r in 0..3 {
                for c in 0..3 {
                    blocks[i][r][c] += b[r][c];
                }
            }
        });
        assert!(blocks.iter().any(|b| b[2][2] > 0.0));
        let eps = 1e-7;
        for i in 0..x.len() {
            for c in 0..3 {
                let (mut xp, mut xm) = (x.clone(), x.clone());
                xp[i][c] += eps;
                xm[i][c] -= eps;
                let (mut gp, mut gm) = (vec![[0.0; 3]; x.len()], vec![[0.0; 3]; x.len()]);
                pot.add_gradient(&model, &xp, h, &mut gp);
                pot.add_gradient(&model, &xm, h, &mut gm);
                for r in 0..3 {
                    let fd = (gp[i][r] - gm[i][r]) / (2.0 * eps);
                    assert!(
                        (fd - blocks[i][r][c]).abs() <= 1e-5 * (1.0 + blocks[i][r][c].abs()),
                        "vertex {i} ({r}, {c}): fd {fd} analytic {}",
                        blocks[i][r][c]
                    );
                }
            }
        }
    }

    #[test]
    fn project_out_leaves_no_vertex_inside_and_moves_only_those_inside() {
        let (model, both) = model_and_potential();
        // One obstacle: out of one, a vertex may be pushed into another.
        let pot = ContactPotential::new(&both.obstacles[..1]);
        let mut x = positions(&model);
        let before = x.clone();
        let moved = pot.project_out(&model, &mut x);
        assert!(moved > 0);
        let plane = &pot.obstacles[0];
        assert!(x.iter().all(|p| plane.signed_distance(*p).0 >= -1e-12));
        let unchanged = x.iter().zip(&before).filter(|(a, b)| a == b).count();
        assert!(unchanged > 0 && unchanged < x.len());
    }

    #[test]
    fn friction_target_holds_a_short_slide_shortens_a_long_one_and_frees_a_vertex_outside() {
        let (model, _) = model_and_potential();
        let floor = |mu: f64| {
            ContactPotential::new(&[Obstacle::new(
                Shape::Plane {
                    point: [0.0; 3],
                    normal: [0.0, 0.0, 1.0],
                },
                0.0,
                mu,
            )
            .unwrap()])
        };
        let d = ContactPotential::margin(&model);
        let x = [0.2, 0.3, d];
        // Pressed 1 mm into the floor while pulled 0.5 mm along it: static friction (mu 0.8) holds it.
        let t = floor(0.8).friction_target(&model, x, [5e-4, 0.0, -1e-3]);
        assert!(
            (t[0] - x[0]).abs() < 1e-15 && (t[2] - d).abs() < 1e-15,
            "{t:?}"
        );
        // Pulled 3 mm: it slides 3 - 0.8 mm.
        let t = floor(0.8).friction_target(&model, x, [3e-3, 0.0, -1e-3]);
        assert!(
            (t[0] - x[0] - 2.2e-3).abs() < 1e-12 && (t[2] - d).abs() < 1e-15,
            "{t:?}"
        );
        // Without friction the slide is whole; lifted off the floor the step is free.
        let t = floor(0.0).friction_target(&model, x, [3e-3, 0.0, -1e-3]);
        assert!((t[0] - x[0] - 3e-3).abs() < 1e-15);
        let t = floor(0.8).friction_target(&model, x, [3e-3, 0.0, 1e-3]);
        assert_eq!(t, add(x, [3e-3, 0.0, 1e-3]));
    }

    #[test]
    fn a_moving_obstacle_answers_where_it_is_and_books_its_work() {
        use crate::world::{ObstacleMotion, PinMotion};
        // A floor rising at 1 m/s over the step from t = 0.5 s.
        let motion = ObstacleMotion {
            translation: PinMotion::Keyframes {
                times: vec![0.0, 1.0],
                offsets: vec![[0.0; 3], [0.0, 0.0, 1.0]],
            },
            angular_velocity: [0.0; 3],
            pivot: [0.0; 3],
            orientations: (Vec::new(), Vec::new()),
        };
        let mut ob = Obstacle::new(
            Shape::Plane {
                point: [0.0; 3],
                normal: [0.0, 0.0, 1.0],
            },
            0.0,
            0.0,
        )
        .unwrap()
        .with_motion(motion)
        .unwrap();
        ob.place(0.5, 0.1);
        let (phi, n) = ob.signed_distance([0.3, 0.0, 0.55]);
        assert!((phi + 0.05).abs() < 1e-12 && n == [0.0, 0.0, 1.0], "{phi}");
        let (phi0, _) = ob.signed_distance_at_start([0.3, 0.0, 0.55]);
        assert!((phi0 - 0.05).abs() < 1e-12);
        assert!(crate::math::norm(sub(ob.velocity_at([0.3, 0.0, 0.6]), [0.0, 0.0, 1.0])) < 1e-12);
        // A vertex at rest at z = 0.55 is crossed by the floor within the step: the crossing is found.
        let (t, point, normal) = ob
            .first_crossing([0.3, 0.0, 0.55], [0.3, 0.0, 0.55])
            .unwrap();
        assert!(
            (t - 0.5).abs() < 1e-9 && (point[2] - 0.6).abs() < 1e-9 && normal[2] == 1.0,
            "{t} {point:?}"
        );
        // A vertex at rest, hit by the floor and carried at its velocity (the solve's contact velocity change
        // 1 m/s): an inelastic impact at 1 m/s relative (loss m/2) and the floor's work m (its impulse m times its
        // velocity), so the books hold the kinetic energy the vertex gained, m/2.
        let (model, _) = model_and_potential();
        let pot = {
            let mut p = ContactPotential::new(&[ob.clone()]);
            p.place(0.5, 0.1);
            p
        };
        let mut state = State::at_rest(&model);
        let i = (0..model.num_vertices())
            .find(|&i| !model.pinned[i])
            .unwrap();
        state.x[i] = [0.3, 0.0, 0.6];
        state.v[i] = [0.0, 0.0, 1.0];
        let report = pot.apply_impacts(
            &model,
            &mut state,
            0.1,
            |_| [0.0; 3],
            |k, _| (k == i).then_some([0.0, 0.0, 1.0]),
        );
        let m = model.masses[i];
        assert!(
            (report.work - 0.5 * m).abs() < 1e-12 * m.max(1.0),
            "{} {m}",
            report.work
        );
        assert!((report.impulse[2] - m).abs() < 1e-12);
    }
}
