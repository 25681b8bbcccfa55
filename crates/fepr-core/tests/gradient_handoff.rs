//! The projection hands its final elastic gradient to the next symplectic Euler step (which then skips that
//! evaluation). Guard: the trajectory is bit for bit the one computed without the hand-off.

mod common;
use common::*;
use fepr_core::integrators::{Integrator, StepReport, SymplecticEuler};
use fepr_core::model::{Model, State};
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

/// Symplectic Euler that declines every offered gradient (the trait's default), i.e. always evaluates.
struct WithoutHandoff(SymplecticEuler);

impl Integrator for WithoutHandoff {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn step(&mut self, model: &Model, state: &mut State, dt: f64) -> StepReport {
        self.0.step(model, state, dt)
    }
}

/// Symplectic Euler that takes offers, and publishes how many steps reused one.
struct Counting(SymplecticEuler, Arc<AtomicUsize>);

impl Integrator for Counting {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn step(&mut self, model: &Model, state: &mut State, dt: f64) -> StepReport {
        let r = self.0.step(model, state, dt);
        self.1.store(self.0.reused_gradients, Ordering::Relaxed);
        r
    }
    fn offer_elastic_gradient(&mut self, model: &Model, x: &[[f64; 3]], grad: &mut Vec<[f64; 3]>) {
        self.0.offer_elastic_gradient(model, x, grad);
    }
}

fn run(integrator: Box<dyn Integrator>, steps: usize) -> Vec<State> {
    let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0, 0.0, -9.81]);
    let mut state = State::at_rest(&model);
    scaled(&mut state, 1.3, [0.0; 3]);
    for (i, v) in state.v.iter_mut().enumerate() {
        *v = [0.1 * (i % 3) as f64, -0.2, 0.05 * (i % 5) as f64];
    }
    let proj = Projector::new(ProjectionSettings::default()).unwrap();
    let mut sim = Simulation::new(model, state, integrator, 1.0 / 60.0, Some(proj)).unwrap();
    (0..steps)
        .map(|_| {
            sim.step().unwrap();
            sim.state.clone()
        })
        .collect()
}

#[test]
fn gradient_handoff_leaves_the_projected_trajectory_bit_identical() {
    let reused = Arc::new(AtomicUsize::new(0));
    let with = run(
        Box::new(Counting(SymplecticEuler::new(), reused.clone())),
        40,
    );
    // Every step after the first starts where the previous projection ended.
    assert_eq!(reused.load(Ordering::Relaxed), 39);
    let without = run(Box::new(WithoutHandoff(SymplecticEuler::new())), 40);
    for (n, (a, b)) in with.iter().zip(&without).enumerate() {
        for (p, q) in a.x.iter().chain(&a.v).zip(b.x.iter().chain(&b.v)) {
            for k in 0..3 {
                assert_eq!(p[k].to_bits(), q[k].to_bits(), "step {}", n + 1);
            }
        }
    }
}
