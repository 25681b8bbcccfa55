//! Symplectic (semi-implicit) Euler, the seed's integrator.

use crate::elasticity::{elastic_energy_gradient, ElasticWorkspace};
use crate::exec::row_tasks2;
use crate::integrators::{HandOver, Integrator, StepReport};
use crate::invariants::{angular_momentum, center_of_mass, kinetic_energy, linear_momentum};
use crate::math::{scale, Vec3};
use crate::model::{Model, State};

/// Symplectic (semi-implicit) Euler, the seed's integrator:
/// `v <- (1 - d) (v + h M^-1 f(x))`, `x <- x + h v`, with `f = -grad E_el + m g` and damping factor `d`.
/// Pinned vertices keep their position and zero velocity.
#[derive(Clone, Debug, Default)]
pub struct SymplecticEuler {
    grad: Vec<Vec3>,
    ws: ElasticWorkspace,
    /// Steps that took the gradient from the hand-over instead of evaluating it (for tests and benchmarks).
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

    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        hand_over: &mut HandOver,
    ) -> StepReport {
        let m = model.num_vertices();
        // The projection's last evaluation is usually at exactly these positions (fepr-spec: symplectic Euler
        // + FEPR would otherwise evaluate the gradient at x_{n+1} twice).
        if hand_over.take_start_gradient(model, &state.x, &mut self.grad) {
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elasticity::{elastic_energy_gradient, ElasticWorkspace};
    use crate::material::{Material, NeoHookean};
    use crate::math::same_bits;
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
    fn handed_over_gradient_is_reused_only_at_bit_identical_positions() {
        let model = cube_model();
        let h = 1e-4;
        let start = stretched_state(&model);
        let mut fresh = start.clone();
        SymplecticEuler::new().step(&model, &mut fresh, h, &mut HandOver::new());
        let exact = || {
            let mut g = vec![[0.0; 3]; model.num_vertices()];
            elastic_energy_gradient(&model, &start.x, &mut ElasticWorkspace::default(), &mut g);
            g
        };

        // The exact gradient at the start positions, handed over: reused, and the step is the same bits.
        let mut hand_over = HandOver::new();
        hand_over.put_final_gradient(&model, &start.x, None, &mut exact());
        let mut se = SymplecticEuler::new();
        let mut reused = start.clone();
        se.step(&model, &mut reused, h, &mut hand_over);
        assert_eq!(se.reused_gradients, 1);
        assert!(same_state(&fresh, &reused));

        // A gradient for other positions (one coordinate one ulp away) is ignored: a garbage gradient there
        // changes nothing.
        let mut other = start.x.clone();
        other[5][1] = f64::from_bits(other[5][1].to_bits() + 1);
        let mut garbage = vec![[1e30; 3]; model.num_vertices()];
        let mut hand_over = HandOver::new();
        hand_over.put_final_gradient(&model, &other, None, &mut garbage);
        let mut se = SymplecticEuler::new();
        let mut ignored = start.clone();
        se.step(&model, &mut ignored, h, &mut hand_over);
        assert_eq!(se.reused_gradients, 0);
        assert!(same_state(&fresh, &ignored));

        // An entry is good for one step only.
        let mut twice = start.clone();
        let mut se = SymplecticEuler::new();
        let mut hand_over = HandOver::new();
        hand_over.put_final_gradient(&model, &start.x, None, &mut exact());
        se.step(&model, &mut twice, h, &mut hand_over);
        twice.x.clone_from(&start.x);
        twice.v.clone_from(&start.v);
        se.step(&model, &mut twice, h, &mut hand_over);
        assert_eq!(se.reused_gradients, 1);
        assert!(same_state(&fresh, &twice));
    }
}
