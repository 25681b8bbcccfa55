//! Bodies in contact with Projective Dynamics take their solves together: contact between them is a set of
//! constraints of their joint global step, so an impact at a large step needs no parts and the scene's momentum
//! is kept exactly (equal and opposite forces in every iteration), with or without the projection. Backward
//! Euler bodies minimise their objectives together with the contact between them: no parts either, and the
//! momentum kept to Newton's tolerance (exactly with the projection).

mod common;
use common::*;
use fepr_core::integrators::{ImplicitEuler, Integrator, ProjectiveDynamics};
use fepr_core::material::{Arap, Material};
use fepr_core::model::State;
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::{step_bodies, BodyCoefficients, Simulation};

fn block_with(
    offset: f64,
    speed: f64,
    project: bool,
    integrator: Box<dyn Integrator>,
) -> Simulation {
    let material = Material::Arap(Arap::new(1e5, 0.4).unwrap());
    let m = model(cubes_mesh(&block_cells(3), 0.1), material, 0.05, [0.0; 3]);
    let mut state = State::at_rest(&m);
    for (x, v) in state.x.iter_mut().zip(state.v.iter_mut()) {
        x[0] += offset;
        // A little off centre, so that the contact also turns the blocks.
        x[1] += 0.05 * offset.signum();
        *v = [speed, 0.0, 0.0];
    }
    let proj = project.then(|| Projector::new(ProjectionSettings::default()).unwrap());
    Simulation::new(m, state, integrator, 1.0 / 60.0, proj).unwrap()
}

fn momentum(sims: &[&mut Simulation]) -> [f64; 3] {
    let mut p = [0.0; 3];
    for s in sims {
        for (v, m) in s.state.v.iter().zip(&s.model.masses) {
            for a in 0..3 {
                p[a] += m * v[a];
            }
        }
    }
    p
}

fn mean_vx(s: &Simulation) -> f64 {
    s.state.v.iter().map(|v| v[0]).sum::<f64>() / s.state.v.len() as f64
}

/// Two blocks thrown at each other (restitution 0.5, frictionless, so that they bounce back apart) with the
/// integrator `make` gives, with and without the projection: they touch, the impact needs no parts, the scene's
/// momentum drifts at most `drift_limit(project)` (relative), they separate, and no tet inverts.
fn collide_blocks(make: fn() -> Box<dyn Integrator>, drift_limit: fn(bool) -> f64) {
    for project in [false, true] {
        let mut a = block_with(-0.16, 2.0, project, make());
        let mut b = block_with(0.16, -2.0, project, make());
        let coefficients = [BodyCoefficients::new(0.5, 0.0).unwrap(); 2];
        let scale = 2.0 * 2.0 * a.model.total_mass;
        let p0 = momentum(&[&mut a, &mut b]);
        for _ in 0..30 {
            step_bodies(&mut [&mut a, &mut b], &coefficients).unwrap();
        }
        let p = momentum(&[&mut a, &mut b]);
        let drift = (0..3).map(|k| (p[k] - p0[k]).abs()).fold(0.0, f64::max) / scale;
        let touched = a.history().iter().any(|d| d.contacts > 0);
        let parts = a.history().iter().map(|d| d.base.substeps).max().unwrap();
        eprintln!("projection {project}: momentum drift {drift:.1e}, impact parts {parts}");
        assert!(touched);
        assert!(drift <= drift_limit(project), "momentum drift {drift:e}");
        assert_eq!(parts, 0, "the impact was redone in parts");
        let (va, vb) = (mean_vx(&a), mean_vx(&b));
        assert!(va < vb, "the blocks separate: {va} {vb}");
        assert!(a
            .history()
            .iter()
            .chain(b.history())
            .all(|d| d.invariants.inverted == 0));
    }
}

#[test]
fn blocks_colliding_with_projective_dynamics_need_no_parts_and_keep_their_momentum() {
    collide_blocks(|| Box::new(ProjectiveDynamics::default()), |_| 1e-12);
}

/// Newton stops at its tolerance, so without the projection the momentum is kept to that; the projection holds
/// it to the targets, whose contact impulses are equal and opposite.
#[test]
fn blocks_colliding_with_backward_euler_need_no_parts_and_keep_their_momentum() {
    collide_blocks(
        || Box::new(ImplicitEuler::default()),
        |project| if project { 1e-12 } else { 1e-10 },
    );
}

/// The joint Newton solve of backward Euler bodies in contact gives the same bits for any thread count.
#[test]
fn backward_euler_bodies_in_contact_are_bit_identical_for_any_thread_count() {
    let run = || {
        let be = || Box::new(ImplicitEuler::default());
        let mut a = block_with(-0.16, 2.0, true, be());
        let mut b = block_with(0.16, -2.0, true, be());
        let coefficients = [BodyCoefficients::new(0.5, 0.3).unwrap(); 2];
        for _ in 0..12 {
            step_bodies(&mut [&mut a, &mut b], &coefficients).unwrap();
        }
        (
            a.state.x.clone(),
            b.state.x.clone(),
            a.state.v.clone(),
            b.state.v.clone(),
        )
    };
    let one = in_pool(1, run);
    let two = in_pool(2, run);
    assert!(one == two, "results differ between 1 and 2 threads");
}

/// Projective Dynamics bodies in contact take their solves, columns and corrections side by side: the same bits
/// for any thread count (three bodies, friction, the projection on).
#[test]
fn projective_dynamics_bodies_in_contact_are_bit_identical_for_any_thread_count() {
    let run = || {
        let pd = || Box::new(ProjectiveDynamics::default());
        let mut a = block_with(-0.16, 2.0, true, pd());
        let mut b = block_with(0.16, -2.0, true, pd());
        let mut c = block_with(0.5, -1.0, true, pd());
        let coefficients = [BodyCoefficients::new(0.5, 0.3).unwrap(); 3];
        for _ in 0..12 {
            step_bodies(&mut [&mut a, &mut b, &mut c], &coefficients).unwrap();
        }
        assert!(a.history().iter().any(|d| d.contacts > 0));
        [a, b, c].map(|s| (s.state.x.clone(), s.state.v.clone()))
    };
    let one = in_pool(1, run);
    for threads in [2, 3] {
        assert!(
            one == in_pool(threads, run),
            "results differ between 1 and {threads} threads"
        );
    }
}

/// A backward Euler body whose swept box meets no other body's takes its own step: its trajectory in the scene
/// is the one it has alone, bit for bit, while the others minimise together.
#[test]
fn a_backward_euler_body_apart_from_the_others_keeps_its_own_trajectory() {
    let be = || Box::new(ImplicitEuler::default());
    let mut alone = block_with(2.0, 0.5, true, be());
    let mut far = block_with(2.0, 0.5, true, be());
    let mut a = block_with(-0.16, 2.0, true, be());
    let mut b = block_with(0.16, -2.0, true, be());
    let coefficients = [BodyCoefficients::new(0.5, 0.0).unwrap(); 3];
    for _ in 0..10 {
        step_bodies(&mut [&mut a, &mut b, &mut far], &coefficients).unwrap();
        alone.step().unwrap();
    }
    assert!(a.history().iter().any(|d| d.contacts > 0));
    assert_eq!(far.state.x, alone.state.x);
    assert_eq!(far.state.v, alone.state.v);
}
