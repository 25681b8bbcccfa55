//! Base integrators. Each takes `(model, state, dt)`, advances the state, and reports what the step is
//! *supposed* to change physically (the energy budget and the external impulses of fepr-spec section 2),
//! which the projection turns into targets.

mod implicit_euler;
mod projective_dynamics;
mod symplectic_euler;
mod xpbd;

pub use implicit_euler::*;
pub use projective_dynamics::*;
pub use symplectic_euler::*;
pub use xpbd::*;

use crate::elasticity::ElasticSummary;
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
}

/// A base time integrator.
pub trait Integrator: Send + Sync {
    /// Short name (as used in scene files).
    fn name(&self) -> &'static str;
    /// Advance `state` by `dt` seconds.
    fn step(&mut self, model: &Model, state: &mut State, dt: f64) -> StepReport;
    /// Check that this integrator can run on `model` (called once when a simulation is built).
    fn check(&self, _model: &Model) -> crate::error::Result<()> {
        Ok(())
    }
    /// True if the step applies the model's per-step damping factor `Model::damping` (the seed's); a
    /// simulation refuses a nonzero factor with an integrator that would ignore it.
    fn applies_step_damping(&self) -> bool {
        false
    }
    /// True for implicit (unconditionally stable, dissipative) integrators: the projection then uses the
    /// stiffness metric by default (see [`crate::projection::Metric`]).
    fn is_implicit(&self) -> bool {
        false
    }
    /// Offer the elastic gradient `grad` (J/m, shape (m, 3)) of `model` at positions `x`, computed by the
    /// projection at the end of a step, for the **next** call of [`Integrator::step`] only. An integrator that
    /// starts its step with the gradient at the current positions may take the buffer (swap it) and skip that
    /// evaluation when the positions it then sees are still bit-identical to `x` and the model's
    /// [`Model::elastic_key`] (mesh and material) is still the one of `model` (so the result is the same bits
    /// either way). Default: ignore the offer.
    fn offer_elastic_gradient(&mut self, _model: &Model, _x: &[Vec3], _grad: &mut Vec<Vec3>) {}
    /// [`Integrator::offer_elastic_gradient`] with `x_copy`, a buffer that holds `x` bit for bit (shape (m, 3)):
    /// an integrator that keeps the offer's positions may take it by a swap instead of copying `x`. Default:
    /// the offer without it.
    fn offer_elastic_gradient_with_positions(
        &mut self,
        model: &Model,
        x: &[Vec3],
        _x_copy: &mut Vec<Vec3>,
        grad: &mut Vec<Vec3>,
    ) {
        self.offer_elastic_gradient(model, x, grad);
    }
    /// The elastic energy summary and gradient (J/m, shape (m, 3)) that the last [`Integrator::step`]
    /// evaluated at the positions it ended on, with those positions, if it did (backward Euler's converged
    /// Newton iterate): the projection that follows may take the buffer (swap it) and skip its first elastic
    /// evaluation when the state's positions are still bit-identical to them (so the result is the same
    /// bits either way). Valid until the next step. Default: none.
    fn result_elastic_gradient(&mut self) -> Option<(ElasticSummary, &[Vec3], &mut Vec<Vec3>)> {
        None
    }
    /// The position metric this integrator has factorised for the projection that follows its step, if any
    /// (Projective Dynamics: its global matrix; see [`crate::projection::SystemMetric`]). Default: none.
    fn system_metric(&mut self) -> Option<&mut dyn crate::projection::SystemMetric> {
        None
    }
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

/// Make an integrator from its scene-file name, with default settings.
pub fn integrator_by_name(name: &str) -> Option<Box<dyn Integrator>> {
    match name {
        "symplectic_euler" => Some(Box::new(SymplecticEuler::new())),
        "implicit_euler" => Some(Box::new(crate::integrators::ImplicitEuler::default())),
        "projective_dynamics" => Some(Box::new(crate::integrators::ProjectiveDynamics::default())),
        "xpbd" => Some(Box::new(crate::integrators::Xpbd::default())),
        _ => None,
    }
}
