//! A simulation resumed from its carry (a checkpoint's core part) takes the same steps as the one that kept
//! running, bit for bit: every integrator, with the projection, contact, damping and bodies touching each other.

mod common;
use common::*;
use fepr_core::checkpoint::Carry;
use fepr_core::integrators::{
    ImplicitEuler, Integrator, NewtonSettings, PdSettings, ProjectiveDynamics, SymplecticEuler,
    Xpbd, XpbdSettings,
};
use fepr_core::model::State;
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::{material_for_integrator, step_bodies, BodyCoefficients, Simulation};
use fepr_core::world::{Obstacle, Shape};

fn integrator(name: &str) -> Box<dyn Integrator> {
    match name {
        "symplectic_euler" => Box::new(SymplecticEuler::new()),
        "implicit_euler" => Box::new(ImplicitEuler::new(NewtonSettings::default()).unwrap()),
        "projective_dynamics" => Box::new(ProjectiveDynamics::new(PdSettings::default()).unwrap()),
        _ => Box::new(Xpbd::new(XpbdSettings::default()).unwrap()),
    }
}

/// A 2x2x2 block of 5 cm cubes, E = 1e5, 1 cm above a plane (restitution 0.5, friction 0.4), falling and
/// spinning, with Rayleigh damping; `dt` small enough for symplectic Euler.
fn falling_block(name: &str, offset: [f64; 3]) -> Simulation {
    let material = material_for_integrator(name, "neo_hookean", 1e5, 0.4, 1.0).unwrap();
    let m = model(
        cubes_mesh(&block_cells(2), 0.05),
        material,
        0.02,
        [0.0, 0.0, -9.81],
    );
    let mut state = State::at_rest(&m);
    for (x, v) in state.x.iter_mut().zip(state.v.iter_mut()) {
        *v = [0.3 * -(x[1] - 0.05), 0.3 * (x[0] - 0.05), -0.5];
        for a in 0..3 {
            x[a] += offset[a];
        }
        x[2] += 0.01;
    }
    let dt = if name == "symplectic_euler" {
        2e-4
    } else {
        1.0 / 60.0
    };
    let proj = Projector::new(ProjectionSettings::default()).unwrap();
    let mut sim = Simulation::new(m, state, integrator(name), dt, Some(proj)).unwrap();
    let plane = Shape::Plane {
        point: [0.0; 3],
        normal: [0.0, 0.0, 1.0],
    };
    sim.set_obstacles(vec![Obstacle::new(plane, 0.5, 0.4).unwrap()]);
    sim.set_damping(0.1, 1e-3).unwrap();
    sim
}

fn bits(s: &Simulation) -> Vec<u64> {
    s.state
        .x
        .iter()
        .chain(&s.state.v)
        .flatten()
        .map(|a| a.to_bits())
        .chain([s.state.time.to_bits()])
        .collect()
}

#[test]
fn a_resumed_body_takes_the_same_steps_bit_for_bit_with_every_integrator() {
    for name in [
        "symplectic_euler",
        "implicit_euler",
        "projective_dynamics",
        "xpbd",
    ] {
        let (before, after) = if name == "symplectic_euler" {
            (50, 300)
        } else {
            (20, 25)
        };
        let mut a = falling_block(name, [0.0; 3]);
        for _ in 0..before {
            a.step().unwrap();
        }
        let carry: Carry = a.carry();
        let mut b = falling_block(name, [0.0; 3]);
        b.resume(&carry).unwrap();
        assert_eq!(b.num_steps(), a.num_steps());
        for _ in 0..after {
            a.step().unwrap();
            b.step().unwrap();
            assert!(bits(&a) == bits(&b), "{name}: step {}", a.num_steps());
        }
        let (ha, hb) = (a.history().last().unwrap(), b.history().last().unwrap());
        assert_eq!(
            ha.budget_total.to_bits(),
            hb.budget_total.to_bits(),
            "{name}"
        );
        assert_eq!(ha.references, hb.references, "{name}");
        assert!(
            a.history().iter().any(|d| d.contacts > 0),
            "{name}: the block must reach the plane"
        );
    }
}

#[test]
fn bodies_resumed_in_contact_take_the_same_steps_bit_for_bit() {
    for name in ["projective_dynamics", "implicit_euler", "xpbd"] {
        let make = || {
            (
                falling_block(name, [0.0; 3]),
                falling_block(name, [0.02, 0.01, 0.105]),
            )
        };
        let coefficients = [BodyCoefficients::new(0.3, 0.5).unwrap(); 2];
        let (mut a0, mut a1) = make();
        for _ in 0..15 {
            step_bodies(&mut [&mut a0, &mut a1], &coefficients).unwrap();
        }
        let (c0, c1) = (a0.carry(), a1.carry());
        let (mut b0, mut b1) = make();
        b0.resume(&c0).unwrap();
        b1.resume(&c1).unwrap();
        for _ in 0..20 {
            step_bodies(&mut [&mut a0, &mut a1], &coefficients).unwrap();
            step_bodies(&mut [&mut b0, &mut b1], &coefficients).unwrap();
            assert!(bits(&a0) == bits(&b0), "{name}");
            assert!(bits(&a1) == bits(&b1), "{name}");
        }
    }
}

#[test]
fn a_carry_of_another_model_or_time_step_is_refused() {
    let a = falling_block("implicit_euler", [0.0; 3]);
    let carry = a.carry();
    let material = material_for_integrator("implicit_euler", "neo_hookean", 2e5, 0.4, 1.0).unwrap();
    let m = model(
        cubes_mesh(&block_cells(2), 0.05),
        material,
        0.02,
        [0.0, 0.0, -9.81],
    );
    let state = State::at_rest(&m);
    let mut other =
        Simulation::new(m, state, integrator("implicit_euler"), 1.0 / 60.0, None).unwrap();
    let err = other.resume(&carry).unwrap_err().to_string();
    assert!(err.contains("another model"), "{err}");
    let mut slower = falling_block("symplectic_euler", [0.0; 3]);
    let err = slower.resume(&carry).unwrap_err().to_string();
    assert!(err.contains("dt ="), "{err}");
    let mut bigger = Simulation::new(
        model(
            cubes_mesh(&block_cells(3), 0.05),
            neo_hookean(1e5, 0.4),
            0.02,
            [0.0; 3],
        ),
        State::at_rest(&model(
            cubes_mesh(&block_cells(3), 0.05),
            neo_hookean(1e5, 0.4),
            0.02,
            [0.0; 3],
        )),
        integrator("implicit_euler"),
        1.0 / 60.0,
        None,
    )
    .unwrap();
    let err = bigger.resume(&carry).unwrap_err().to_string();
    assert!(err.contains("vertices"), "{err}");
}

/// A stretched block released at a game step with Projective Dynamics: the quality guard limits what the
/// projection restores, so the carry holds the search's last accepted fraction, which the resumed run's next
/// search starts from.
#[test]
fn a_resumed_run_whose_projection_is_guard_limited_takes_the_same_steps() {
    let make = || {
        let material =
            material_for_integrator("projective_dynamics", "neo_hookean", 1e5, 0.4, 1.0).unwrap();
        let m = model(cubes_mesh(&block_cells(3), 0.1), material, 0.05, [0.0; 3]);
        let mut state = State::at_rest(&m);
        scaled(&mut state, 1.4, [0.15; 3]);
        let proj = Projector::new(ProjectionSettings::default()).unwrap();
        Simulation::new(
            m,
            state,
            integrator("projective_dynamics"),
            1.0 / 30.0,
            Some(proj),
        )
        .unwrap()
    };
    let mut a = make();
    let mut carried = None;
    for _ in 0..40 {
        a.step().unwrap();
        let c = a.carry();
        if !c.get("projection.last_fraction").unwrap().is_empty() {
            carried = Some(c);
            break;
        }
    }
    let carry = carried.expect("a guard-limited step within 40 steps");
    let mut b = make();
    b.resume(&carry).unwrap();
    for _ in 0..20 {
        a.step().unwrap();
        b.step().unwrap();
        assert!(bits(&a) == bits(&b), "step {}", a.num_steps());
    }
}

/// Symplectic Euler in free flight takes its force from the projection's last gradient (the hand-over), which
/// can differ in its last bits from one evaluated afresh: the carry holds it, so the resumed run takes it too.
#[test]
fn a_resumed_symplectic_euler_run_takes_the_handed_over_gradient_as_the_original_does() {
    let make = || {
        let material =
            material_for_integrator("symplectic_euler", "stable_neo_hookean", 2e4, 0.3, 1.0)
                .unwrap();
        let m = model(
            cubes_mesh(&block_cells(3), 1.0 / 6.0),
            material,
            0.05,
            [0.0, 0.0, -9.81],
        );
        let mut state = State::at_rest(&m);
        for x in state.x.iter_mut() {
            x[2] += 1.0;
        }
        for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
            *v = [0.3 * -(x[1] - 0.25), 0.3 * (x[0] - 0.25), 0.0];
        }
        let proj = Projector::new(ProjectionSettings::default()).unwrap();
        Simulation::new(m, state, integrator("symplectic_euler"), 2e-3, Some(proj)).unwrap()
    };
    let mut a = make();
    for _ in 0..30 {
        a.step().unwrap();
    }
    let carry = a.carry();
    assert!(!carry.get("hand_over.start_gradient").unwrap().is_empty());
    let mut b = make();
    b.resume(&carry).unwrap();
    for _ in 0..30 {
        a.step().unwrap();
        b.step().unwrap();
        assert!(bits(&a) == bits(&b), "step {}", a.num_steps());
    }
}
