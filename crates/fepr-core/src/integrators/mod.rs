//! Base integrators. Each takes `(model, state, dt)`, advances the state, and reports what the step is
//! *supposed* to change physically (the energy budget and the external impulses of fepr-spec section 2),
//! which the projection turns into targets.

mod implicit_euler;
mod projective_dynamics;
mod xpbd;

pub use implicit_euler::*;
pub use projective_dynamics::*;
pub use xpbd::*;
mod choice;
pub use choice::*;

use crate::elasticity::{elastic_energy_gradient, ElasticSummary, ElasticWorkspace};
use crate::exec::row_tasks2;
use crate::invariants::{angular_momentum, center_of_mass, kinetic_energy, linear_momentum};
use crate::math::{same_bits, scale, Vec3};
use crate::model::{Model, ModelKey, State};

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

/// Symplectic (semi-implicit) Euler, the seed's integrator:
/// `v <- (1 - d) (v + h M^-1 f(x))`, `x <- x + h v`, with `f = -grad E_el + m g` and damping factor `d`.
/// Pinned vertices keep their position and zero velocity.
#[derive(Clone, Debug, Default)]
pub struct SymplecticEuler {
    grad: Vec<Vec3>,
    ws: ElasticWorkspace,
    /// Positions of a gradient offered by the projection (see [`Integrator::offer_elastic_gradient`]), valid
    /// while `offered_key` is set (the buffer keeps its length between offers: no fill before each copy). The
    /// gradient itself is then in `grad`.
    offered_x: Vec<Vec3>,
    /// [`Model::elastic_key`] of the model the offered gradient belongs to; `None` when there is no offer.
    offered_key: Option<ModelKey>,
    /// Steps that reused an offered gradient instead of evaluating it (for tests and benchmarks).
    pub reused_gradients: usize,
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

    fn applies_step_damping(&self) -> bool {
        true
    }

    fn step(&mut self, model: &Model, state: &mut State, h: f64) -> StepReport {
        let m = model.num_vertices();
        // The projection's last evaluation is usually at exactly these positions (fepr-spec: symplectic Euler
        // + FEPR would otherwise evaluate the gradient at x_{n+1} twice); reuse it only when every bit agrees.
        let offered_key = self.offered_key.take();
        if offered_key == Some(model.elastic_key())
            && self.offered_x.len() == m
            && self.grad.len() == m
            && same_bits(&self.offered_x, &state.x)
        {
            self.reused_gradients += 1;
        } else {
            self.grad.resize(m, [0.0; 3]);
            elastic_energy_gradient(model, &state.x, &mut self.ws, &mut self.grad);
        }
        let g = model.gravity;
        let mut report = StepReport {
            impulse: scale(g, h * model.free_mass()),
            ..Default::default()
        };
        // The kick and the drift run in the vertex tasks of every vertex pass (`row_tasks2`): each thread
        // writes the rows that it reads next, in the projection's passes (on a serial update, the other
        // thread read its half of the state from this one's cache). Each row's update is its own: the same
        // bits for any thread count.
        let kick = |first: usize, v: &mut [Vec3]| {
            for (k, vi) in v.iter_mut().enumerate() {
                let i = first + k;
                if model.pinned[i] {
                    *vi = [0.0; 3];
                    continue;
                }
                let (inv_m, gr) = (1.0 / model.masses[i], self.grad[i]);
                for a in 0..3 {
                    vi[a] += h * (g[a] - gr[a] * inv_m);
                }
            }
        };
        let drift = |x: &mut [Vec3], v: &[Vec3]| {
            for (xi, vi) in x.iter_mut().zip(v) {
                for a in 0..3 {
                    xi[a] += h * vi[a];
                }
            }
        };
        let (x, v) = (&mut state.x, &mut state.v);
        if model.damping == 0.0 {
            row_tasks2(x, v, |first, x, v| {
                kick(first, v);
                drift(x, v);
            });
            state.time += h;
            return report;
        }
        row_tasks2(&mut state.x, &mut state.v, |first, _, v| kick(first, v));
        // The damping impulse and dissipated energy, measured on the undamped velocities at the positions the
        // step ends at (uniform scaling of v scales P and L by the same factor).
        let d = model.damping;
        let kin = kinetic_energy(&model.masses, &state.v);
        let p = linear_momentum(&model.masses, &state.v);
        // At the end positions x + h (1 - d) v, (x_i + h(1-d) v_i - c) x v_i = (x_i - c) x v_i: L about the end
        // centre of mass needs no new positions.
        let c0 = center_of_mass(&model.masses, model.total_mass, &state.x);
        let c = [0, 1, 2].map(|a| c0[a] + h * (1.0 - d) * p[a] / model.total_mass);
        let l = angular_momentum(&model.masses, &state.x, &state.v, c);
        report.energy_budget = -kin * (1.0 - (1.0 - d) * (1.0 - d));
        report.impulse = [
            report.impulse[0] - d * p[0],
            report.impulse[1] - d * p[1],
            report.impulse[2] - d * p[2],
        ];
        report.angular_impulse = scale(l, -d);
        let (x, v) = (&mut state.x, &mut state.v);
        row_tasks2(x, v, |_, x, v| {
            for vi in v.iter_mut() {
                *vi = scale(*vi, 1.0 - d);
            }
            drift(x, v);
        });
        state.time += h;
        report
    }

    fn offer_elastic_gradient(&mut self, model: &Model, x: &[Vec3], grad: &mut Vec<Vec3>) {
        if x.len() != grad.len() {
            return;
        }
        std::mem::swap(&mut self.grad, grad);
        crate::exec::copy_rows(x, &mut self.offered_x);
        self.offered_key = Some(model.elastic_key());
    }

    fn offer_elastic_gradient_with_positions(
        &mut self,
        model: &Model,
        x: &[Vec3],
        x_copy: &mut Vec<Vec3>,
        grad: &mut Vec<Vec3>,
    ) {
        if x_copy.len() != x.len() || grad.len() != x.len() {
            return self.offer_elastic_gradient(model, x, grad);
        }
        debug_assert!(same_bits(x, x_copy), "the offered copy holds x bit for bit");
        std::mem::swap(&mut self.grad, grad);
        std::mem::swap(&mut self.offered_x, x_copy);
        self.offered_key = Some(model.elastic_key());
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::{Material, NeoHookean};
    use crate::mesh::{tests::cube, MassSpec, TetMesh};
    use crate::model::ModelBuilder;

    fn cube_model() -> Model {
        let (v, t) = cube();
        let (mesh, _) = TetMesh::new(v, &t).unwrap();
        ModelBuilder::new(
            mesh,
            Material::NeoHookean(NeoHookean::new(1e5, 0.3).unwrap()),
        )
        .mass(MassSpec::Density(1000.0))
        .build()
        .unwrap()
    }

    fn stretched_state(model: &Model) -> State {
        let mut s = State::at_rest(model);
        for (i, p) in s.x.iter_mut().enumerate() {
            *p = [1.07 * p[0], 0.96 * p[1] + 0.01 * (i % 3) as f64, p[2]];
        }
        s
    }

    fn same_state(a: &State, b: &State) -> bool {
        same_bits(&a.x, &b.x) && same_bits(&a.v, &b.v)
    }

    #[test]
    fn offered_gradient_is_reused_only_at_bit_identical_positions() {
        let model = cube_model();
        let h = 1e-4;
        let start = stretched_state(&model);
        let mut fresh = start.clone();
        SymplecticEuler::new().step(&model, &mut fresh, h);

        // The exact gradient at the start positions, offered: reused, and the step is the same bits.
        let mut exact = vec![[0.0; 3]; model.num_vertices()];
        elastic_energy_gradient(
            &model,
            &start.x,
            &mut ElasticWorkspace::default(),
            &mut exact,
        );
        let mut se = SymplecticEuler::new();
        se.offer_elastic_gradient(&model, &start.x, &mut exact);
        let mut reused = start.clone();
        se.step(&model, &mut reused, h);
        assert_eq!(se.reused_gradients, 1);
        assert!(same_state(&fresh, &reused));

        // An offer for other positions (one coordinate one ulp away) is ignored: a garbage gradient there
        // changes nothing.
        let mut other = start.x.clone();
        other[5][1] = f64::from_bits(other[5][1].to_bits() + 1);
        let mut garbage = vec![[1e30; 3]; model.num_vertices()];
        let mut se = SymplecticEuler::new();
        se.offer_elastic_gradient(&model, &other, &mut garbage);
        let mut ignored = start.clone();
        se.step(&model, &mut ignored, h);
        assert_eq!(se.reused_gradients, 0);
        assert!(same_state(&fresh, &ignored));

        // An offer is good for one step only.
        let mut twice = start.clone();
        let mut se = SymplecticEuler::new();
        let mut exact2 = vec![[0.0; 3]; model.num_vertices()];
        elastic_energy_gradient(
            &model,
            &start.x,
            &mut ElasticWorkspace::default(),
            &mut exact2,
        );
        se.offer_elastic_gradient(&model, &start.x, &mut exact2);
        se.step(&model, &mut twice, h);
        twice.x.clone_from(&start.x);
        twice.v.clone_from(&start.v);
        se.step(&model, &mut twice, h);
        assert_eq!(se.reused_gradients, 1);
        assert!(same_state(&fresh, &twice));
    }
}
