//! Base integrators. Each takes `(model, state, dt)`, advances the state, and reports what the step is
//! *supposed* to change physically (the energy budget and the external impulses of fepr-spec section 2),
//! which the projection turns into targets.

use crate::elasticity::{elastic_energy_gradient, ElasticWorkspace};
use crate::invariants::{angular_momentum, center_of_mass, kinetic_energy, linear_momentum};
use crate::linalg::{scale, Vec3};
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
    /// True for implicit (unconditionally stable, dissipative) integrators: the projection then uses the
    /// stiffness metric by default (see [`crate::projection::Metric`]).
    fn is_implicit(&self) -> bool {
        false
    }
}

/// Symplectic (semi-implicit) Euler, the seed's integrator:
/// `v <- (1 - d) (v + h M^-1 f(x))`, `x <- x + h v`, with `f = -grad E_el + m g` and damping factor `d`.
/// Pinned vertices keep their position and zero velocity.
#[derive(Clone, Debug, Default)]
pub struct SymplecticEuler {
    grad: Vec<Vec3>,
    ws: ElasticWorkspace,
}

impl SymplecticEuler {
    pub fn new() -> Self {
        Self::default()
    }
}

impl Integrator for SymplecticEuler {
    fn name(&self) -> &'static str {
        "symplectic_euler"
    }

    fn step(&mut self, model: &Model, state: &mut State, h: f64) -> StepReport {
        let m = model.num_vertices();
        self.grad.resize(m, [0.0; 3]);
        elastic_energy_gradient(model, &state.x, &mut self.ws, &mut self.grad);
        let g = model.gravity;
        for i in 0..m {
            if model.pinned[i] {
                state.v[i] = [0.0; 3];
                continue;
            }
            let inv_m = 1.0 / model.masses[i];
            for a in 0..3 {
                state.v[i][a] += h * (g[a] - self.grad[i][a] * inv_m);
            }
        }
        let mut report = StepReport {
            impulse: scale(g, h * model.free_mass()),
            ..Default::default()
        };
        if model.damping > 0.0 {
            // The damping impulse and dissipated energy, measured on the undamped velocities at the
            // positions the step ends at (uniform scaling of v scales P and L by the same factor).
            let d = model.damping;
            let kin = kinetic_energy(&model.masses, &state.v);
            let p = linear_momentum(&model.masses, &state.v);
            // At the end positions x + h (1 - d) v, (x_i + h(1-d) v_i - c) x v_i = (x_i - c) x v_i: L about
            // the end centre of mass needs no new positions.
            let c0 = center_of_mass(&model.masses, model.total_mass, &state.x);
            let c = [0, 1, 2].map(|a| c0[a] + h * (1.0 - d) * p[a] / model.total_mass);
            let l = angular_momentum(&model.masses, &state.x, &state.v, c);
            for vi in state.v.iter_mut() {
                *vi = scale(*vi, 1.0 - d);
            }
            report.energy_budget = -kin * (1.0 - (1.0 - d) * (1.0 - d));
            report.impulse = [
                report.impulse[0] - d * p[0],
                report.impulse[1] - d * p[1],
                report.impulse[2] - d * p[2],
            ];
            report.angular_impulse = scale(l, -d);
        }
        for i in 0..m {
            for a in 0..3 {
                state.x[i][a] += h * state.v[i][a];
            }
        }
        state.time += h;
        report
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
        "implicit_euler" => Some(Box::new(crate::implicit::ImplicitEuler::default())),
        "projective_dynamics" => Some(Box::new(crate::pd::ProjectiveDynamics::default())),
        "xpbd" => Some(Box::new(crate::xpbd::Xpbd::default())),
        _ => None,
    }
}
