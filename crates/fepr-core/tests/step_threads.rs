//! Where a step runs. Called from a thread outside every rayon pool (a program's main thread; Python's, when a
//! simulation has no pool of its own), a step runs on a thread of the global pool; inside a pool, on the thread
//! that called it. Guards the default Python path: its steps ran on Python's own thread, which sent every
//! parallel region to the pool as a job and slept until it was done (the 1k box's symplectic Euler + FEPR step
//! took 2-2.5x as long as inside a two-thread pool).

mod common;
use common::*;
use fepr_core::integrators::{HandOver, Integrator, StepReport, SymplecticEuler};
use fepr_core::model::{Model, State};
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;
use std::sync::{Arc, Mutex};

/// Symplectic Euler that records the rayon thread index (`None`: outside every pool) of each of its steps.
struct Recording(SymplecticEuler, Arc<Mutex<Vec<Option<usize>>>>);

impl Integrator for Recording {
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
        self.1.lock().unwrap().push(rayon::current_thread_index());
        self.0.step(model, state, dt, hand_over)
    }
}

fn recorded_simulation() -> (Simulation, Arc<Mutex<Vec<Option<usize>>>>) {
    let model = model(
        cubes_mesh(&block_cells(3), 0.1),
        neo_hookean(1e3, 0.3),
        0.05,
        [0.0; 3],
    );
    let mut state = State::at_rest(&model);
    scaled(&mut state, 1.05, [0.15; 3]);
    let seen = Arc::new(Mutex::new(Vec::new()));
    let integrator = Box::new(Recording(SymplecticEuler::new(), Arc::clone(&seen)));
    let proj = Projector::new(ProjectionSettings::default()).unwrap();
    let sim = Simulation::new(model, state, integrator, 1e-3, Some(proj)).unwrap();
    (sim, seen)
}

#[test]
fn a_step_called_outside_every_pool_runs_on_a_pool_thread() {
    // The test harness runs each test on a thread of its own, outside every rayon pool.
    assert_eq!(rayon::current_thread_index(), None);
    let (mut outside, seen) = recorded_simulation();
    for _ in 0..4 {
        outside.step().unwrap();
    }
    let threads = seen.lock().unwrap().clone();
    assert_eq!(threads.len(), 4);
    assert!(
        threads.iter().all(Option::is_some),
        "every step ran on a pool thread: {threads:?}"
    );

    // Inside a pool, the step stays on the calling thread.
    let (inside, seen) = in_pool(2, || {
        let (mut sim, seen) = recorded_simulation();
        let caller = rayon::current_thread_index();
        for _ in 0..4 {
            sim.step().unwrap();
        }
        assert!(seen.lock().unwrap().iter().all(|&t| t == caller));
        (sim, seen)
    });
    assert_eq!(seen.lock().unwrap().len(), 4);

    // Where the step ran changes no bit of it.
    for (a, b) in outside
        .state
        .x
        .iter()
        .chain(&outside.state.v)
        .zip(inside.state.x.iter().chain(&inside.state.v))
    {
        assert_eq!(a.map(f64::to_bits), b.map(f64::to_bits));
    }
}
