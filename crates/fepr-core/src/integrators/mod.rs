//! Base integrators. Each takes `(model, state, dt)`, advances the state, and reports what the step is
//! *supposed* to change physically (the energy budget and the external impulses of fepr-spec section 2),
//! which the projection turns into targets.
//!
//! This file holds the [`Integrator`] trait, the step report, the helpers the integrators share and the
//! names the scene files use; each integrator has its own file, and [`HandOver`] (in `hand_over`) is what a
//! step and the projection around it share.

mod hand_over;
mod implicit_euler;
mod projective_dynamics;
mod symplectic_euler;
mod xpbd;
mod xpbd_lanes;

pub use hand_over::*;
pub use implicit_euler::*;
pub use projective_dynamics::*;
pub use symplectic_euler::*;
pub use xpbd::*;
mod choice;
pub use choice::*;

use crate::math::Vec3;
use crate::model::{Model, State};

/// What a base step reports besides the new state.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepReport {
    /// Physical energy change of the step from non-conservative processes (damping < 0), J.
    pub energy_budget: f64,
    /// External linear impulse over the step (gravity `h m g`, damping), kg m/s.
    pub impulse: Vec3,
    /// External angular impulse about the centre of mass over the step, kg m^2/s.
    pub angular_impulse: Vec3,
    /// True when the step contained an impulsive event (then the projection keeps the base step's centre
    /// of mass instead of the smooth-force target).
    pub impulsive: bool,
    /// Solver iterations of the base step (Newton or local/global iterations; 0 for explicit steps).
    pub iterations: usize,
    /// Final relative residual of the base step's solver (0 for explicit steps).
    pub residual: f64,
    /// Line-search step halvings taken by the base step's solver.
    pub line_search_steps: usize,
    /// Substeps the simulation split the step into for an impact (0: the step was not split).
    pub substeps: usize,
    /// The contacts an implicit step held inside its solve ([`Integrator::set_obstacles`]): their count, work
    /// and impulses, already included in `impulse` and `angular_impulse` (not in `energy_budget`).
    pub contact: crate::world::ContactReport,
}

/// A base time integrator: the physics of a step. What a step and the projection around it can share instead
/// of evaluating twice goes through the [`HandOver`] passed to [`Integrator::step`] (see its module).
pub trait Integrator: Send + Sync {
    /// Short name (as used in scene files).
    fn name(&self) -> &'static str;
    /// Advance `state` by `dt` seconds. `hand_over` is the simulation's (a caller stepping an integrator on its
    /// own passes one it keeps, or a new one: the step's result is the same bits either way).
    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        dt: f64,
        hand_over: &mut HandOver,
    ) -> StepReport;
    /// Check that this integrator can run on `model` (called once when a simulation is built).
    fn check(&self, _model: &Model) -> crate::error::Result<()> {
        Ok(())
    }
    /// True if the step applies the model's per-step damping factor `Model::damping` (the seed's); a
    /// simulation refuses a nonzero factor with an integrator that would ignore it.
    fn applies_step_damping(&self) -> bool {
        false
    }
    /// The static obstacles, for an integrator that keeps its free vertices out of them inside its own solve
    /// (contact inside the solve, [`crate::world::ContactPotential`]). The push-out after the step
    /// ([`crate::world::resolve_contacts`]) runs for every integrator; one that ignores the obstacles (the
    /// default) leaves contact to it.
    fn set_obstacles(&mut self, _obstacles: &[crate::world::Obstacle]) {}
    /// True for implicit (unconditionally stable, dissipative) integrators: the projection then uses the
    /// stiffness metric by default (see [`crate::projection::Metric`]).
    fn is_implicit(&self) -> bool {
        false
    }
    /// The step as iterations that several bodies take together ([`CoupledSolve`]), for an integrator that
    /// can hold contact between bodies inside its solve; `None` (the default): it cannot, and contact between
    /// bodies is answered after its step.
    fn coupled(&mut self) -> Option<&mut dyn CoupledSolve> {
        None
    }
    /// The step as a Newton minimisation that several bodies take together ([`CoupledNewton`]), for an
    /// integrator whose step minimises an objective (backward Euler); `None` (the default): it is not one.
    fn coupled_newton(&mut self) -> Option<&mut dyn CoupledNewton> {
        None
    }
    /// Substeps of the integrator's own in one step (1: it has none). When every body of a scene has more than
    /// one, contact between the bodies is answered after each substep ([`crate::simulation::step_bodies`]).
    fn substeps(&self) -> usize {
        1
    }
    /// The caller takes each step in `parts` calls of [`Integrator::step`] of `dt / parts` seconds (1: whole
    /// steps, the default): an integrator with its own substeps then takes its substeps divided among the
    /// parts (at least one a part), so that the substeps keep their length.
    fn take_in_parts(&mut self, _parts: usize) {}
    /// What the integrator's next steps depend on besides the model and the state, into a checkpoint (entries
    /// named `integrator.*`; the default: nothing).
    fn carry(&self, _c: &mut crate::checkpoint::Carry) {}
    /// Back from [`Integrator::carry`] (for a model of `num_vertices` vertices).
    fn resume(
        &mut self,
        _c: &crate::checkpoint::Carry,
        _num_vertices: usize,
    ) -> crate::error::Result<()> {
        Ok(())
    }
}

/// An implicit step whose iterations bodies in contact take together, each a linear solve that the caller
/// may correct between the solve and its acceptance (contact between bodies as constraints of the bodies'
/// joint global step, [`crate::simulation::step_bodies`]). `begin`, then for `it` in `0..iterations()`:
/// `solve`, any correction of `solution_mut`, `accept` (true: converged); then `finish`. Without corrections
/// this is [`Integrator::step`], bit for bit.
pub trait CoupledSolve {
    /// Start a step of `h` seconds from `state`.
    fn begin(&mut self, model: &Model, state: &State, h: f64, hand_over: &mut HandOver);
    /// Iterations the step takes at most (0 after a failed start).
    fn iterations(&self) -> usize;
    /// The current iterate, m (all vertices).
    fn positions(&self) -> &[Vec3];
    /// The iteration's local step and linear solve; its solution is then in [`CoupledSolve::solution_mut`].
    fn solve(&mut self, model: &Model);
    /// The free vertices, in the order of the solution's rows.
    fn free_vertices(&self) -> Vec<usize>;
    /// The last solve's solution, one row (m) per free vertex, to correct before `accept`.
    fn solution_mut(&mut self) -> &mut [Vec3];
    /// Solve the step's current matrix (a scalar matrix, the same for x, y and z) for `count` right-hand sides
    /// at once, in place: column-major, one value per free vertex in each column.
    fn solve_columns(&mut self, columns: &mut [f64], count: usize);
    /// Changes whenever the matrix [`CoupledSolve::solve_columns`] solves with changes.
    fn matrix_version(&self) -> usize;
    /// The solution becomes the iterate (iteration `it`). Returns true when the step converged.
    fn accept(&mut self, model: &Model, it: usize) -> bool;
    /// Whether the last `accept` added vertices to the obstacles' contact constraints (the next solve differs).
    fn contacts_grew(&self) -> bool;
    /// End the step: the state at its end and the report (without contact between bodies, which the caller
    /// books).
    fn finish(&mut self, model: &Model, state: &mut State, h: f64) -> StepReport;
}

/// A step that minimises an objective `Phi(x)` by Newton's method, which bodies in contact take together:
/// their objectives plus the contact between them are one minimisation whose Hessian is the bodies' own, block
/// diagonal, plus a low-rank coupling ([`crate::simulation::step_bodies`]). `begin`, then per iteration
/// `linearise` (the objective's gradient and factorised Hessian at the iterate), `solve` for the direction,
/// `objective` along it for the line search, `set_positions` for the accepted iterate; then `finish`.
pub trait CoupledNewton {
    /// Start a step of `h` seconds from `state`: the first iterate (as [`Integrator::step`] starts).
    fn begin(&mut self, model: &Model, state: &State, h: f64);
    /// Newton iterations the step takes at most, and its relative decrement tolerance.
    fn limits(&self) -> (usize, f64);
    /// The current iterate, m (all vertices).
    fn positions(&self) -> &[Vec3];
    /// Make `x` the iterate (m, all vertices; pinned ones as they are).
    fn set_positions(&mut self, x: &[Vec3]);
    /// At the iterate: the objective (J), its magnitude (the sum of its terms' absolute values, which bounds
    /// its round-off), the gradient ([`CoupledNewton::gradient`]) and the factorised Hessian. `None`: the
    /// Hessian could not be factorised, the step stops at the iterate.
    fn linearise(&mut self, model: &Model) -> Option<(f64, f64)>;
    /// The gradient of the objective at the last linearised iterate, N (all vertices; zero on pinned ones).
    fn gradient(&self) -> &[Vec3];
    /// Solve the last factorised Hessian in place for `ncols` right-hand sides: `rhs` is `ncols` blocks of
    /// one vector per vertex (pinned ones left zero).
    fn solve(&mut self, rhs: &mut [Vec3], ncols: usize);
    /// The objective at `x` (J), for the line search.
    fn objective(&self, model: &Model, x: &[Vec3]) -> f64;
    /// End the step on the iterate after `iterations` (relative decrement `residual`): the state and the
    /// report (without contact between bodies, which the caller books; `held_impulse`, N s, is what that
    /// contact gave the body, so that the obstacles' impulse, measured as the step's momentum change less
    /// gravity's, leaves it out).
    fn finish(
        &mut self,
        model: &Model,
        state: &mut State,
        iterations: usize,
        residual: f64,
        held_impulse: Vec3,
    ) -> StepReport;
}

/// End a step of a position-based integrator (backward Euler, Projective Dynamics): the new positions
/// `x`, velocities `(x - x_n) / h`; pinned vertices keep their position and zero velocity; time advances.
pub fn finish_positional_step(model: &Model, state: &mut State, x: &[Vec3], x_n: &[Vec3], h: f64) {
    let inv_h = 1.0 / h;
    for i in 0..model.num_vertices() {
        if model.pinned[i] {
            state.v[i] = [0.0; 3];
            continue;
        }
        for a in 0..3 {
            state.v[i][a] = (x[i][a] - x_n[i][a]) * inv_h;
        }
        state.x[i] = x[i];
    }
    state.time += h;
}

/// Integrator names known to [`integrator_by_name`].
pub const INTEGRATOR_NAMES: &[&str] = &[
    "symplectic_euler",
    "implicit_euler",
    "projective_dynamics",
    "xpbd",
];

/// Make an integrator from its scene-file name, with default settings ([`IntegratorChoice::from_name`]).
pub fn integrator_by_name(name: &str) -> Option<Box<dyn Integrator>> {
    IntegratorChoice::from_name(name)?.build().ok()
}
