//! The projection hands its final elastic gradient to the next symplectic Euler step (which then skips that
//! evaluation), and backward Euler hands the gradient at its last Newton iterate to the projection (which
//! then skips its first evaluation). Guard: the trajectories are bit for bit the ones computed without the
//! hand-offs.

mod common;
use common::*;
use fepr_core::integrators::{HandOver, Integrator, StepReport, SymplecticEuler};
use fepr_core::integrators::{ImplicitEuler, NewtonSettings};
use fepr_core::mesh::TetMesh;
use fepr_core::model::{Model, State};
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

/// Symplectic Euler stepped with a hand-over of its own, new at every step: it finds no gradient there and
/// always evaluates.
struct WithoutHandoff(SymplecticEuler);

impl Integrator for WithoutHandoff {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        dt: f64,
        _hand_over: &mut HandOver,
    ) -> StepReport {
        self.0.step(model, state, dt, &mut HandOver::new())
    }
}

/// Symplectic Euler with the simulation's hand-over, publishing how many steps reused its gradient.
struct Counting(SymplecticEuler, Arc<AtomicUsize>);

impl Integrator for Counting {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        dt: f64,
        hand_over: &mut HandOver,
    ) -> StepReport {
        let r = self.0.step(model, state, dt, hand_over);
        self.1.store(self.0.reused_gradients, Ordering::Relaxed);
        r
    }
}

/// Backward Euler stepped with a hand-over of its own: its last gradient does not reach the projection, which
/// evaluates it again.
struct BackwardWithoutHandoff(ImplicitEuler);

impl Integrator for BackwardWithoutHandoff {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        dt: f64,
        _hand_over: &mut HandOver,
    ) -> StepReport {
        self.0.step(model, state, dt, &mut HandOver::new())
    }
    fn is_implicit(&self) -> bool {
        true
    }
}

fn run(integrator: Box<dyn Integrator>, steps: usize) -> Vec<State> {
    run_with_evaluations(integrator, steps).0
}

/// The states after each step, and the projection's elastic evaluations in each.
fn run_with_evaluations(integrator: Box<dyn Integrator>, steps: usize) -> (Vec<State>, Vec<usize>) {
    run_on(ell_mesh(), integrator, steps)
}

/// [`run_with_evaluations`] on `mesh`.
fn run_on(
    mesh: TetMesh,
    integrator: Box<dyn Integrator>,
    steps: usize,
) -> (Vec<State>, Vec<usize>) {
    run_counting_copies(mesh, integrator, steps).0
}

/// [`run_on`], and the hand-over's entries whose positions were the projection's own copy.
fn run_counting_copies(
    mesh: TetMesh,
    integrator: Box<dyn Integrator>,
    steps: usize,
) -> ((Vec<State>, Vec<usize>), usize) {
    let model = model(mesh, neo_hookean(1e3, 0.3), 5.0, [0.0, 0.0, -9.81]);
    let mut state = State::at_rest(&model);
    scaled(&mut state, 1.3, [0.0; 3]);
    for (i, v) in state.v.iter_mut().enumerate() {
        *v = [0.1 * (i % 3) as f64, -0.2, 0.05 * (i % 5) as f64];
    }
    let proj = Projector::new(ProjectionSettings::default()).unwrap();
    let mut sim = Simulation::new(model, state, integrator, 1.0 / 60.0, Some(proj)).unwrap();
    let run = (0..steps)
        .map(|_| {
            let evaluations = sim.step().unwrap().projection.unwrap().evaluations;
            (sim.state.clone(), evaluations)
        })
        .unzip();
    (run, sim.hand_over().positions_swapped())
}

fn assert_same_bits(a: &[State], b: &[State]) {
    for (n, (a, b)) in a.iter().zip(b).enumerate() {
        for (p, q) in a.x.iter().chain(&a.v).zip(b.x.iter().chain(&b.v)) {
            for k in 0..3 {
                assert_eq!(p[k].to_bits(), q[k].to_bits(), "step {}", n + 1);
            }
        }
    }
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
    assert_same_bits(&with, &without);
}

/// The projection's trial pass writes a copy of the positions it returns, which the hand-over takes by a swap
/// instead of copying them after every projection (from `exec::SERIAL_ROWS` vertices: a 10^3 block of cubes,
/// 1,331): every entry but the first comes with it, every step after the first still reuses the gradient, and
/// the trajectory keeps its bits. On a mesh below that size no entry comes with a copy.
#[test]
fn projected_positions_copy_is_handed_over_and_leaves_the_trajectory_bit_identical() {
    let cells: Vec<[i64; 3]> = (0..1000).map(|c| [c % 10, c / 10 % 10, c / 100]).collect();
    let block = || cubes_mesh(&cells, 0.1);
    assert!(block().num_vertices() >= fepr_core::exec::SERIAL_ROWS);
    let steps = 12;
    let reused = Arc::new(AtomicUsize::new(0));
    let counting = Counting(SymplecticEuler::new(), reused.clone());
    let ((with, _), swapped) = run_counting_copies(block(), Box::new(counting), steps);
    assert_eq!(reused.load(Ordering::Relaxed), steps - 1);
    // The first projection has no copy (nobody had asked for one yet); the later ones return their accepted
    // trial point here.
    assert_eq!(swapped, steps - 1);
    let (without, _) = run_on(
        block(),
        Box::new(WithoutHandoff(SymplecticEuler::new())),
        steps,
    );
    assert_same_bits(&with, &without);

    let small = Arc::new(AtomicUsize::new(0));
    let ((_, _), swapped) = run_counting_copies(
        ell_mesh(),
        Box::new(Counting(SymplecticEuler::new(), small.clone())),
        10,
    );
    assert_eq!(small.load(Ordering::Relaxed), 9);
    assert_eq!(swapped, 0);
}

#[test]
fn backward_euler_gradient_handoff_leaves_the_projected_trajectory_bit_identical() {
    let newton = || ImplicitEuler::new(NewtonSettings::default()).unwrap();
    let (with, evals_with) = run_with_evaluations(Box::new(newton()), 25);
    let (without, evals_without) =
        run_with_evaluations(Box::new(BackwardWithoutHandoff(newton())), 25);
    assert_same_bits(&with, &without);
    // The same iterations, one elastic evaluation fewer wherever Newton converged (most steps here).
    let handed = (evals_with.iter().zip(&evals_without))
        .filter(|(w, wo)| **w + 1 == **wo)
        .count();
    assert!(
        evals_with
            .iter()
            .zip(&evals_without)
            .all(|(w, wo)| w == wo || w + 1 == *wo),
        "{evals_with:?} vs {evals_without:?}"
    );
    assert!(handed >= 20, "hand-offs in {handed} of 25 steps");
}
