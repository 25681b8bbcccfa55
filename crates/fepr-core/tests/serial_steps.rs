//! `parallel::serial`: steps run on the calling thread alone, without any thread pool, with the bits of a pool's
//! steps. Guards one-thread simulations stepped once per call (Python's `Simulation(threads=1)`): a pool of one
//! thread had to be woken for every call and parked after it, which doubled a small mesh's time per step.
//!
//! A file of its own: the test occupies every thread of the process's global pool while it runs.

mod common;
use common::*;
use fepr_core::exec::{current_threads, serial};
use fepr_core::integrators::{ImplicitEuler, NewtonSettings};
use fepr_core::integrators::{Integrator, SymplecticEuler};
use fepr_core::integrators::{PdSettings, ProjectiveDynamics};
use fepr_core::integrators::{Xpbd, XpbdSettings};
use fepr_core::material::{Arap, ConstraintNeoHookean, Material};
use fepr_core::model::State;
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// Every integrator with FEPR on a stretched, spinning block of 3 x 3 x 3 cubes (162 tets).
fn simulations() -> Vec<Simulation> {
    let cases: Vec<(Material, Box<dyn Integrator>, f64)> = vec![
        (
            neo_hookean(1e3, 0.3),
            Box::new(SymplecticEuler::new()),
            1e-3,
        ),
        (
            neo_hookean(1e3, 0.3),
            Box::new(ImplicitEuler::new(NewtonSettings::default()).unwrap()),
            1.0 / 30.0,
        ),
        (
            Material::Arap(Arap::new(1e3, 0.3).unwrap()),
            Box::new(ProjectiveDynamics::new(PdSettings::default()).unwrap()),
            1.0 / 30.0,
        ),
        (
            Material::ConstraintNeoHookean(ConstraintNeoHookean::new(1e3, 0.3).unwrap()),
            Box::new(Xpbd::new(XpbdSettings::default()).unwrap()),
            1.0 / 60.0,
        ),
    ];
    cases
        .into_iter()
        .map(|(material, integrator, dt)| {
            let model = model(cubes_mesh(&block_cells(3), 0.1), material, 0.05, [0.0; 3]);
            let mut state = State::at_rest(&model);
            scaled(&mut state, 1.05, [0.15; 3]);
            for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
                *v = [0.3 - (x[1] - 0.15), 0.1 + (x[0] - 0.15), 0.0];
            }
            let proj = Projector::new(ProjectionSettings::default()).unwrap();
            Simulation::new(model, state, integrator, dt, Some(proj)).unwrap()
        })
        .collect()
}

/// Three steps of every simulation; their final states' bits.
fn run(mut sims: Vec<Simulation>) -> Vec<Vec<u64>> {
    for sim in &mut sims {
        for _ in 0..3 {
            sim.step().unwrap();
        }
    }
    let bits = |s: &Simulation| {
        s.state
            .x
            .iter()
            .chain(&s.state.v)
            .flat_map(|p| p.map(f64::to_bits))
            .collect()
    };
    sims.iter().map(bits).collect()
}

#[test]
fn serial_steps_use_no_pool_and_keep_the_bits_of_a_pool() {
    let in_a_pool = in_pool(2, || run(simulations()));

    // Hold every thread of the global pool until the serial steps are done: a step that sent any work to the
    // pool would wait for ever (here: fail after a minute).
    let threads = rayon::current_num_threads();
    let (started, release) = (
        Arc::new(AtomicUsize::new(0)),
        Arc::new(AtomicBool::new(false)),
    );
    for _ in 0..threads {
        let (started, release) = (Arc::clone(&started), Arc::clone(&release));
        rayon::spawn(move || {
            started.fetch_add(1, Ordering::SeqCst);
            while !release.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(1));
            }
        });
    }
    while started.load(Ordering::SeqCst) < threads {
        std::thread::sleep(Duration::from_millis(1));
    }
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let bits = serial(|| {
            assert_eq!(current_threads(), 1);
            run(simulations())
        });
        assert_eq!(current_threads(), rayon::current_num_threads(), "restored");
        tx.send(bits).unwrap();
    });
    let serial_bits = rx.recv_timeout(Duration::from_secs(60));
    release.store(true, Ordering::SeqCst);
    let serial_bits = serial_bits.expect("the serial steps finished without the pool's threads");
    assert_eq!(serial_bits.len(), in_a_pool.len());
    for (k, (a, b)) in serial_bits.iter().zip(&in_a_pool).enumerate() {
        assert!(a == b, "simulation {k}: serial steps changed bits");
    }
}
