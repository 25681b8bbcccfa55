//! The world around the body: kinematic pins, external forces (constant fields and the user's drag spring),
//! mass- and stiffness-proportional damping, and obstacles. None of these conserve energy; each reports the
//! work it does (the step's energy budget W) and its impulses, so that the projection enforces
//! `H_n = H_0 + sum W` instead of undoing them (fepr-spec section 2).
//!
//! Every process is applied by [`crate::simulation::Simulation`] around the base step, so every integrator
//! gets them without knowing about them:
//! - external forces: a velocity kick `h f / m` before the base step (for symplectic Euler, backward Euler
//!   and Projective Dynamics this is exactly the force term in their equations); work `sum f . (x* - x_n)`,
//!   exact for a force constant over the step;
//! - kinematic pins: moved to their end-of-step path before the base step (every integrator then holds them
//!   there), their velocity set after it; the work is the change of H caused by moving them with the free
//!   vertices held at the start of the step. This splitting matches what the integrators do (the free
//!   vertices then move with the pins fixed at their new place), so the energy balance has no drift from
//!   the bookkeeping itself; it is exactly 0 for static pins;
//! - damping: an operator on the velocities after the base step; its work is the kinetic energy it removes;
//! - contact ([`crate::world`]): after damping.

mod body_contact;
mod contact_potential;
mod mesh_collider;
mod obstacle_motion;
mod obstacles;
mod self_contact;

pub use body_contact::*;
pub use contact_potential::*;

pub use mesh_collider::MeshCollider;
pub(crate) use obstacle_motion::Moving;
pub use obstacle_motion::{ObstacleMotion, Placement};
pub use obstacles::*;
pub use self_contact::SelfContact;

use crate::elasticity::deformation_gradient;
use crate::elasticity::{element_hessian, HessianAssembler};
use crate::error::{invalid, Result};
use crate::material::Hyperelastic;
use crate::math::SparseCholesky;
use crate::math::{add, cross, dot, scale, sub, Vec3};
use crate::model::{Model, ModelKey, State};

/// A prescribed displacement `d(t)` of a group of pinned vertices, m (with `d` relative to `d(0)`).
#[derive(Clone, Debug, PartialEq)]
pub enum PinMotion {
    /// `d(t) = amplitude (sin(2 pi f t + phase) - sin(phase))`.
    Sinusoid {
        amplitude: Vec3,
        frequency: f64,
        phase: f64,
    },
    /// Piecewise-linear through `(times[k], offsets[k])`, held constant before the first and after the last.
    Keyframes { times: Vec<f64>, offsets: Vec<Vec3> },
}

impl PinMotion {
    pub fn validate(&self) -> Result<()> {
        match self {
            PinMotion::Sinusoid {
                amplitude,
                frequency,
                phase,
            } => {
                if !amplitude.iter().all(|a| a.is_finite()) {
                    return Err(invalid(
                        "amplitude",
                        format!("must be finite, got {amplitude:?}"),
                    ));
                }
                if !(frequency.is_finite() && *frequency >= 0.0) {
                    return Err(invalid(
                        "frequency",
                        format!("must be a finite frequency >= 0 in Hz, got {frequency}"),
                    ));
                }
                if !phase.is_finite() {
                    return Err(invalid("phase", format!("must be finite, got {phase}")));
                }
            }
            PinMotion::Keyframes { times, offsets } => {
                if times.is_empty() || times.len() != offsets.len() {
                    return Err(invalid(
                        "keyframes",
                        format!(
                            "need at least one keyframe and as many offsets as times, got {} times and {} offsets",
                            times.len(),
                            offsets.len()
                        ),
                    ));
                }
                check_key_times(times, "keyframes")?;
                if let Some(k) = offsets
                    .iter()
                    .position(|o| !o.iter().all(|c| c.is_finite()))
                {
                    return Err(invalid(
                        "keyframes",
                        format!("offset {k} is not finite: {:?}", offsets[k]),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Displacement at time `t`, m.
    pub fn displacement(&self, t: f64) -> Vec3 {
        match self {
            PinMotion::Sinusoid {
                amplitude,
                frequency,
                phase,
            } => {
                let w = 2.0 * std::f64::consts::PI * frequency;
                scale(*amplitude, (w * t + phase).sin() - phase.sin())
            }
            PinMotion::Keyframes { times, offsets } => {
                let n = times.len();
                if t <= times[0] {
                    return offsets[0];
                }
                if t >= times[n - 1] {
                    return offsets[n - 1];
                }
                let k = times.partition_point(|tk| *tk <= t) - 1;
                let s = (t - times[k]) / (times[k + 1] - times[k]);
                add(offsets[k], scale(sub(offsets[k + 1], offsets[k]), s))
            }
        }
    }

    /// Velocity at time `t`, m/s (for keyframes: the slope of the segment that starts at or before `t`).
    pub fn velocity(&self, t: f64) -> Vec3 {
        match self {
            PinMotion::Sinusoid {
                amplitude,
                frequency,
                phase,
            } => {
                let w = 2.0 * std::f64::consts::PI * frequency;
                scale(*amplitude, w * (w * t + phase).cos())
            }
            PinMotion::Keyframes { times, offsets } => {
                let n = times.len();
                if t < times[0] || t >= times[n - 1] {
                    return [0.0; 3];
                }
                let k = times.partition_point(|tk| *tk <= t) - 1;
                scale(
                    sub(offsets[k + 1], offsets[k]),
                    1.0 / (times[k + 1] - times[k]),
                )
            }
        }
    }
}

/// Check that keyframe `times` (s) are finite and strictly increasing; the error names `key` and the time.
pub(crate) fn check_key_times(times: &[f64], key: &'static str) -> Result<()> {
    for (k, t) in times.iter().enumerate() {
        if !t.is_finite() || (k > 0 && *t <= times[k - 1]) {
            return Err(invalid(
                key,
                format!("times must be finite and strictly increasing; time {k} is {t}"),
            ));
        }
    }
    Ok(())
}

/// A group of pinned vertices that follow `anchor + d(t)`.
#[derive(Clone, Debug, PartialEq)]
pub struct KinematicPins {
    pub vertices: Vec<usize>,
    pub motion: PinMotion,
}

/// The user's drag spring: a force `stiffness (target - x_vertex)` on one vertex, N.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Drag {
    pub vertex: usize,
    /// Target point, m.
    pub target: Vec3,
    /// Spring stiffness, N/m.
    pub stiffness: f64,
}

/// Energy budget of one step by source, J (the budget W is their sum).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Work {
    /// Contact (restitution < 1 and friction remove energy).
    pub contact: f64,
    /// Damping (air, Rayleigh, and the per-step damping factor).
    pub damping: f64,
    /// Kinematic pins.
    pub pins: f64,
    /// External forces and the drag spring.
    pub forces: f64,
    /// Energy the projection did not restore (0 or negative; see
    /// [`crate::projection::ProjectionReport::unresolved`]): what the time step could not carry within the
    /// projection's quality guard.
    pub unresolved: f64,
    /// Change of the energy a failed projection left off its target (the state's energy minus
    /// the target; positive: the state has more). Booked so that the books close while the projection is off
    /// target, reversed by the step that reaches it; the targets never include it.
    pub deferred: f64,
}

impl Work {
    /// The work of the processes that set the step's energy target (everything but `deferred`).
    pub fn total(&self) -> f64 {
        self.contact + self.damping + self.pins + self.forces + self.unresolved
    }
}

/// The processes around the body, with their workspaces. Set them through
/// [`crate::simulation::Simulation`]'s setters, which validate them against the model.
#[derive(Default)]
pub struct World {
    pub(crate) obstacles: Vec<Obstacle>,
    pub(crate) pins: Vec<KinematicPins>,
    /// `anchor_i = x_i - d(t)` for each kinematic vertex (parallel to `pins[k].vertices`).
    pub(crate) anchors: Vec<Vec<Vec3>>,
    /// Tets with a kinematic vertex (their elastic energy changes when the pins move).
    pub(crate) pin_tets: Vec<usize>,
    /// Mass-proportional damping rate, 1/s.
    pub(crate) air_damping: f64,
    /// Stiffness-proportional (Rayleigh) damping coefficient, s.
    pub(crate) rayleigh_damping: f64,
    /// Constant external force per vertex, N (empty: none).
    pub(crate) forces: Vec<Vec3>,
    pub(crate) drag: Option<Drag>,
    /// Pattern and symbolic analysis of the Rayleigh damping solve, with the [`Model::structure_key`] (mesh and
    /// pin set) they were built for.
    rayleigh: Option<(HessianAssembler, SparseCholesky, ModelKey)>,
    /// The step (its start time's and part length's bits) whose damping matrix is factorised in `rayleigh`: the
    /// parts of one step (bodies meeting after each XPBD substep, impact parts) share the first part's
    /// factorisation instead of assembling and factorising the stiffness again in each (20 times per step for
    /// XPBD bodies in contact: 26 against 1.9 ms per step on two boxes resting on each other).
    rayleigh_step: Option<(u64, u64)>,
    values: Vec<f64>,
    rhs: Vec<f64>,
    step_forces: Vec<Vec3>,
    pub(crate) scratch_x: Vec<Vec3>,
    pub(crate) scratch_v: Vec<Vec3>,
}

impl World {
    pub fn obstacles(&self) -> &[Obstacle] {
        &self.obstacles
    }
    pub fn has_pins(&self) -> bool {
        !self.pins.is_empty()
    }

    /// Validate kinematic pins against the model: vertices in range and pinned in the model.
    pub(crate) fn set_pins(
        &mut self,
        model: &Model,
        state: &State,
        pins: Vec<KinematicPins>,
    ) -> Result<()> {
        let m = model.num_vertices();
        let mut is_kinematic = vec![false; m];
        for (k, p) in pins.iter().enumerate() {
            p.motion.validate()?;
            if p.vertices.is_empty() {
                return Err(invalid(
                    "kinematic_pins",
                    format!("group {k} has no vertices"),
                ));
            }
            for &v in &p.vertices {
                if v >= m {
                    return Err(invalid(
                        "kinematic_pins",
                        format!("group {k}: vertex {v} is out of range: the mesh has {m} vertices"),
                    ));
                }
                if !model.pinned[v] {
                    return Err(invalid(
                        "kinematic_pins",
                        format!("group {k}: vertex {v} is not pinned in the model (pin it too)"),
                    ));
                }
                if is_kinematic[v] {
                    return Err(invalid(
                        "kinematic_pins",
                        format!("vertex {v} is in more than one group"),
                    ));
                }
                is_kinematic[v] = true;
            }
        }
        self.pin_tets = model
            .mesh
            .tets()
            .iter()
            .enumerate()
            .filter(|(_, t)| t.iter().any(|&v| is_kinematic[v]))
            .map(|(e, _)| e)
            .collect();
        self.pins = pins;
        self.anchor_pins(state);
        Ok(())
    }

    /// Anchor the kinematic pins at the state's positions (`anchor = x - d(t)`).
    pub(crate) fn anchor_pins(&mut self, state: &State) {
        self.anchors = self
            .pins
            .iter()
            .map(|p| {
                let d = p.motion.displacement(state.time);
                p.vertices.iter().map(|&v| sub(state.x[v], d)).collect()
            })
            .collect();
    }

    pub(crate) fn set_damping(&mut self, air: f64, rayleigh: f64) -> Result<()> {
        if !(air.is_finite() && air >= 0.0) {
            return Err(invalid(
                "air_damping",
                format!("must be a finite rate >= 0 in 1/s, got {air}"),
            ));
        }
        if !(rayleigh.is_finite() && rayleigh >= 0.0) {
            return Err(invalid(
                "rayleigh_damping",
                format!("must be a finite coefficient >= 0 in s, got {rayleigh}"),
            ));
        }
        self.air_damping = air;
        self.rayleigh_damping = rayleigh;
        Ok(())
    }

    pub(crate) fn set_forces(&mut self, model: &Model, forces: Vec<Vec3>) -> Result<()> {
        let m = model.num_vertices();
        if !forces.is_empty() && forces.len() != m {
            return Err(invalid(
                "external_forces",
                format!("needs one force per vertex ({m}), got {}", forces.len()),
            ));
        }
        if let Some(i) = forces.iter().position(|f| !f.iter().all(|c| c.is_finite())) {
            return Err(invalid(
                "external_forces",
                format!("force on vertex {i} is not finite: {:?}", forces[i]),
            ));
        }
        self.forces = if forces.iter().all(|f| *f == [0.0; 3]) {
            Vec::new()
        } else {
            forces
        };
        Ok(())
    }

    pub(crate) fn set_drag(&mut self, model: &Model, drag: Option<Drag>) -> Result<()> {
        if let Some(d) = &drag {
            let m = model.num_vertices();
            if d.vertex >= m {
                return Err(invalid(
                    "drag",
                    format!(
                        "vertex {} is out of range: the mesh has {m} vertices",
                        d.vertex
                    ),
                ));
            }
            if !d.target.iter().all(|c| c.is_finite()) {
                return Err(invalid(
                    "drag",
                    format!("target must be finite, got {:?}", d.target),
                ));
            }
            if !(d.stiffness.is_finite() && d.stiffness >= 0.0) {
                return Err(invalid(
                    "drag",
                    format!("stiffness must be finite and >= 0 N/m, got {}", d.stiffness),
                ));
            }
        }
        self.drag = drag;
        Ok(())
    }

    /// Energy of the part of H that moving the kinematic pins changes: the elastic energy of the tets that
    /// touch them, their kinetic and their gravitational energy, at positions `x` and velocities `v`.
    fn pin_energy(&self, model: &Model, x: &[Vec3], v: &[Vec3]) -> f64 {
        let mut e = 0.0;
        for &t in &self.pin_tets {
            let f = deformation_gradient(model, x, t);
            e += model.rest_volume[t] * model.material.energy_density(&f);
        }
        for p in &self.pins {
            for &i in &p.vertices {
                let mi = model.masses[i];
                e += 0.5 * mi * dot(v[i], v[i]) - mi * dot(model.gravity, x[i]);
            }
        }
        e
    }

    /// The pins' work: the change of H when the pins move from where `state` has them to their positions
    /// and velocities at time `t`, with the free vertices held at `state`.
    pub(crate) fn pin_work(&mut self, model: &Model, state: &State, t: f64) -> f64 {
        if self.pins.is_empty() {
            return 0.0;
        }
        let before = self.pin_energy(model, &state.x, &state.v);
        let mut x = std::mem::take(&mut self.scratch_x);
        let mut v = std::mem::take(&mut self.scratch_v);
        x.clone_from(&state.x);
        v.clone_from(&state.v);
        self.place_pins(&mut x, &mut v, t);
        let after = self.pin_energy(model, &x, &v);
        self.scratch_x = x;
        self.scratch_v = v;
        after - before
    }

    /// Put the kinematic vertices at their path's position and velocity at time `t`.
    pub(crate) fn place_pins(&self, x: &mut [Vec3], v: &mut [Vec3], t: f64) {
        for (p, anchors) in self.pins.iter().zip(&self.anchors) {
            let d = p.motion.displacement(t);
            let w = p.motion.velocity(t);
            for (&i, a) in p.vertices.iter().zip(anchors) {
                x[i] = add(*a, d);
                v[i] = w;
            }
        }
    }

    /// Whether [`World::step_forces`] has forces to give (external forces or a drag).
    pub(crate) fn has_forces(&self) -> bool {
        !self.forces.is_empty() || self.drag.is_some()
    }

    /// This step's external force per vertex (constant field plus the drag spring at the start positions),
    /// or None when there is none.
    pub(crate) fn step_forces(&mut self, model: &Model, x: &[Vec3]) -> Option<&[Vec3]> {
        if !self.has_forces() {
            return None;
        }
        let m = model.num_vertices();
        self.step_forces.clear();
        if self.forces.is_empty() {
            self.step_forces.resize(m, [0.0; 3]);
        } else {
            self.step_forces.extend_from_slice(&self.forces);
        }
        if let Some(d) = self.drag {
            let f = scale(sub(d.target, x[d.vertex]), d.stiffness);
            self.step_forces[d.vertex] = add(self.step_forces[d.vertex], f);
        }
        for (i, f) in self.step_forces.iter_mut().enumerate() {
            if model.pinned[i] {
                *f = [0.0; 3]; // a pinned vertex does not move: no work, and the support takes the force
            }
        }
        Some(&self.step_forces)
    }

    /// Damp the free velocities of `state`: `v <- exp(-a h) v` (air), then `(M + h b K) v' = M v - h b K_fp
    /// v_p` (Rayleigh, with the PSD-projected stiffness at the positions of the step's first part: `step_start`,
    /// s, is the time the step started at). Returns the kinetic energy change (J), the linear and the angular
    /// impulse about the centre of mass.
    pub(crate) fn damp(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        step_start: f64,
    ) -> Result<(f64, Vec3, Vec3)> {
        if self.air_damping == 0.0 && self.rayleigh_damping == 0.0 {
            return Ok((0.0, [0.0; 3], [0.0; 3]));
        }
        let m = model.num_vertices();
        let mut v_old = std::mem::take(&mut self.scratch_v);
        v_old.clone_from(&state.v);
        if self.air_damping > 0.0 {
            let f = (-self.air_damping * h).exp();
            for i in 0..m {
                if !model.pinned[i] {
                    state.v[i] = scale(state.v[i], f);
                }
            }
        }
        if self.rayleigh_damping > 0.0 {
            self.rayleigh(model, state, h, step_start)?;
        }
        let c = crate::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
        let (mut work, mut imp, mut ang) = (0.0, [0.0; 3], [0.0; 3]);
        for i in 0..m {
            let mi = model.masses[i];
            let d = sub(state.v[i], v_old[i]);
            work += 0.5 * mi * (dot(state.v[i], state.v[i]) - dot(v_old[i], v_old[i]));
            imp = add(imp, scale(d, mi));
            ang = add(ang, scale(cross(sub(state.x[i], c), d), mi));
        }
        self.scratch_v = v_old;
        Ok((work, imp, ang))
    }

    fn rayleigh(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        step_start: f64,
    ) -> Result<()> {
        // Built again when the pin set changed since (a user of the Rust API may change `Model::pinned`).
        let key = model.structure_key();
        if self.rayleigh.as_ref().is_none_or(|r| r.2 != key) {
            let asm = HessianAssembler::new(model);
            let chol = SparseCholesky::analyse(&asm.pattern, 1)?;
            self.rayleigh = Some((asm, chol, key));
            self.rayleigh_step = None;
        }
        let (asm, chol, _) = self.rayleigh.as_mut().expect("set above");
        let hb = h * self.rayleigh_damping;
        // (M / (h b) + K) v' = M v / (h b) - K_fp v_p, factorised once per step (and part length).
        let step = (step_start.to_bits(), h.to_bits());
        if self.rayleigh_step != Some(step) {
            self.rayleigh_step = None;
            asm.assemble(model, &state.x, 1.0 / hb, true, &mut self.values);
            chol.factorize(&self.values)?;
            self.rayleigh_step = Some(step);
        }
        let n = asm.ndof();
        self.rhs.clear();
        self.rhs.resize(n, 0.0);
        for (i, &fi) in asm.free_index.iter().enumerate() {
            if fi != usize::MAX {
                for a in 0..3 {
                    self.rhs[3 * fi + a] = model.masses[i] * state.v[i][a] / hb;
                }
            }
        }
        if model.num_pinned() > 0 {
            for (e, t) in model.mesh.tets().iter().enumerate() {
                if !t.iter().any(|&v| model.pinned[v] && state.v[v] != [0.0; 3])
                    || t.iter().all(|&v| model.pinned[v])
                {
                    continue;
                }
                let he = element_hessian(model, &state.x, e, true);
                for (a, &p) in t.iter().enumerate() {
                    let fp = asm.free_index[p];
                    if fp == usize::MAX {
                        continue;
                    }
                    for (b, &q) in t.iter().enumerate() {
                        if !model.pinned[q] {
                            continue;
                        }
                        for i in 0..3 {
                            for k in 0..3 {
                                self.rhs[3 * fp + i] -=
                                    he[(3 * a + i) * 12 + 3 * b + k] * state.v[q][k];
                            }
                        }
                    }
                }
            }
        }
        chol.solve_in_place(&mut self.rhs, 1);
        for (i, &fi) in asm.free_index.iter().enumerate() {
            if fi != usize::MAX {
                state.v[i] = [self.rhs[3 * fi], self.rhs[3 * fi + 1], self.rhs[3 * fi + 2]];
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The parts of one step share the Rayleigh factorisation of its first part (the stiffness at the positions
    /// there); the next step factorises again at its own positions.
    #[test]
    fn the_parts_of_a_step_share_one_damping_factorisation() {
        use crate::material::{Material, NeoHookean};
        use crate::mesh::{tests::cube, TetMesh};
        use crate::model::{ModelBuilder, State};
        let (v, t) = cube();
        let (mesh, _) = TetMesh::new(v, &t).unwrap();
        let material = Material::NeoHookean(NeoHookean::new(1e3, 0.3).unwrap());
        let model = ModelBuilder::new(mesh, material).build().unwrap();
        let mut moving = State::at_rest(&model);
        for (i, v) in moving.v.iter_mut().enumerate() {
            *v = [0.1 * i as f64, -0.05 * i as f64, 0.3 - 0.04 * i as f64];
        }
        // The same velocities with the body squashed: another stiffness.
        let mut squashed = moving.clone();
        squashed.x[0] = [0.2, 0.3, 0.4];
        let fresh = || {
            let mut w = World::default();
            w.set_damping(0.0, 0.05).unwrap();
            w
        };
        let damped = |w: &mut World, s: &State, step_start: f64| {
            let mut s = s.clone();
            w.damp(&model, &mut s, 0.01, step_start).unwrap();
            s.v
        };
        let mut world = fresh();
        let first = damped(&mut world, &moving, 0.0);
        assert_ne!(first, moving.v);
        // A later part of the same step: the first part's stiffness, so the same velocities.
        assert_eq!(damped(&mut world, &squashed, 0.0), first);
        // The next step: its own stiffness, as a new world's.
        let next = damped(&mut world, &squashed, 0.01);
        assert_eq!(next, damped(&mut fresh(), &squashed, 0.01));
        assert_ne!(next, first);
    }

    #[test]
    fn sinusoid_velocity_is_the_derivative_of_its_displacement() {
        let m = PinMotion::Sinusoid {
            amplitude: [0.1, 0.0, -0.2],
            frequency: 1.5,
            phase: 0.3,
        };
        assert_eq!(m.displacement(0.0), [0.0; 3]);
        for t in [0.0, 0.17, 0.9] {
            let e = 1e-6;
            let fd = scale(sub(m.displacement(t + e), m.displacement(t - e)), 0.5 / e);
            let v = m.velocity(t);
            for a in 0..3 {
                assert!((fd[a] - v[a]).abs() < 1e-7, "{t}: {fd:?} vs {v:?}");
            }
        }
    }

    #[test]
    fn keyframes_interpolate_linearly_and_hold_outside() {
        let m = PinMotion::Keyframes {
            times: vec![0.0, 1.0, 3.0],
            offsets: vec![[0.0; 3], [1.0, 0.0, 0.0], [1.0, 2.0, 0.0]],
        };
        m.validate().unwrap();
        assert_eq!(m.displacement(-1.0), [0.0; 3]);
        assert_eq!(m.displacement(0.5), [0.5, 0.0, 0.0]);
        assert_eq!(m.displacement(2.0), [1.0, 1.0, 0.0]);
        assert_eq!(m.displacement(5.0), [1.0, 2.0, 0.0]);
        assert_eq!(m.velocity(0.5), [1.0, 0.0, 0.0]);
        assert_eq!(m.velocity(2.0), [0.0, 1.0, 0.0]);
        assert_eq!(m.velocity(4.0), [0.0; 3]);
        let bad = PinMotion::Keyframes {
            times: vec![0.0, 0.0],
            offsets: vec![[0.0; 3]; 2],
        };
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("increasing"));
    }
}
