//! Self contact: a bar whose halves are set turning towards each other, in space, folds until its ends meet.
//! With self contact they do not pass through each other, and since the impulses are internal the body's
//! momentum and angular momentum are those it started with; with restitution 1 and FEPR its energy too.

mod common;
use common::*;
use fepr_core::integrators::{ImplicitEuler, Integrator, NewtonSettings, ProjectiveDynamics};
use fepr_core::material::{Arap, Material, StableNeoHookean};
use fepr_core::math::{add, cross, scale};
use fepr_core::model::State;
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::{BodyCoefficients, Simulation};

const LENGTH: f64 = 1.0;
/// Each half turns at this rate (rad/s) about the bar's centre, its end towards the other's.
const TURN: f64 = 6.0;

/// The bar (1 m x 0.1 m x 0.1 m, 20 x 2 x 2 cubes, centred at the origin), its halves turning towards each other.
/// Projective Dynamics takes its own (ARAP) energy, backward Euler the Stable Neo-Hookean one.
fn folding_bar(integrator: Box<dyn Integrator>, self_contact: bool) -> Simulation {
    let cells: Vec<[i64; 3]> = (0..20)
        .flat_map(|i| (0..2).flat_map(move |j| (0..2).map(move |k| [i, j, k])))
        .collect();
    let material = material_for(integrator.as_ref());
    // 10 kg over the 189 vertices (density 1000 kg/m^3).
    let m = model(cubes_mesh(&cells, 0.05), material, 10.0 / 189.0, [0.0; 3]);
    let mut state = State::at_rest(&m);
    for (x, v) in state.x.iter_mut().zip(state.v.iter_mut()) {
        *x = add(*x, [-0.5 * LENGTH, -0.05, -0.05]);
        *v = [-TURN * x[0].signum() * x[2], 0.0, TURN * x[0].abs()];
    }
    let proj = Projector::new(ProjectionSettings::default()).unwrap();
    let mut sim = Simulation::new(m, state, integrator, 1.0 / 60.0, Some(proj)).unwrap();
    if self_contact {
        sim.set_self_contact(Some(BodyCoefficients::new(1.0, 0.0).unwrap()));
    }
    sim
}

fn material_for(integrator: &dyn Integrator) -> Material {
    if integrator.name() == "projective_dynamics" {
        Material::Arap(Arap::new(2e4, 0.4).unwrap())
    } else {
        Material::StableNeoHookean(StableNeoHookean::new(2e4, 0.4).unwrap())
    }
}

fn momenta(s: &Simulation) -> ([f64; 3], [f64; 3]) {
    let (mut p, mut l) = ([0.0; 3], [0.0; 3]);
    for ((x, v), &m) in s.state.x.iter().zip(&s.state.v).zip(&s.model.masses) {
        p = add(p, scale(*v, m));
        l = add(l, cross(*x, scale(*v, m)));
    }
    (p, l)
}

/// Mean x of the vertices at the bar's right end less that of its left end (m): negative once the ends have
/// passed through each other.
fn ends_apart(s: &Simulation) -> f64 {
    let ends = |right: bool| {
        let xs: Vec<f64> = s
            .model
            .mesh
            .vertices()
            .iter()
            .zip(&s.state.x)
            .filter(|(r, _)| (r[0] > 0.99) == right && (r[0] < 0.01) != right)
            .map(|(_, x)| x[0])
            .collect();
        xs.iter().sum::<f64>() / xs.len() as f64
    };
    ends(true) - ends(false)
}

fn integrators() -> Vec<(&'static str, fn() -> Box<dyn Integrator>)> {
    vec![
        ("projective dynamics", || {
            Box::new(ProjectiveDynamics::default())
        }),
        ("backward Euler", || {
            Box::new(ImplicitEuler::new(NewtonSettings::default()).unwrap())
        }),
    ]
}

#[test]
fn a_folding_bar_does_not_pass_through_itself_and_keeps_its_momenta() {
    for (name, make) in integrators() {
        let mut sim = folding_bar(make(), true);
        let (p0, l0) = momenta(&sim);
        let (p_scale, l_scale) = (norm(p0), norm(l0).max(norm(p0) * LENGTH));
        let mut closest = f64::INFINITY;
        for _ in 0..60 {
            sim.step().unwrap();
            closest = closest.min(ends_apart(&sim));
        }
        let (p, l) = momenta(&sim);
        let dp = norm(add(p, scale(p0, -1.0))) / p_scale;
        let dl = norm(add(l, scale(l0, -1.0))) / l_scale;
        let h = sim.history();
        let h0 = h[0].invariants.total;
        let books = h
            .iter()
            .map(|d| (d.invariants.total - h0 - d.budget_total).abs() / h0.abs())
            .fold(0.0, f64::max);
        let energy = h
            .iter()
            .map(|d| (d.invariants.total - h0).abs() / h0.abs())
            .fold(0.0, f64::max);
        let touched = h.iter().filter(|d| d.contacts > 0).count();
        eprintln!(
            "{name}: ends apart at least {closest:.3} m, contact on {touched} steps, P {dp:.1e}, L {dl:.1e}, \
             H {energy:.1e}, books {books:.1e}"
        );
        assert!(touched > 0, "{name}: the ends never met");
        assert!(closest > 0.0, "{name}: the ends passed through each other");
        assert!(dp <= 1e-12 && dl <= 1e-12, "{name}: P {dp:e}, L {dl:e}");
        // Restitution 1, no friction: self contact takes no energy, and the projection restores what the
        // integrator lost.
        assert!(
            books <= 1e-8 && energy <= 1e-8,
            "{name}: books {books:e}, H {energy:e}"
        );
    }
}

#[test]
fn without_self_contact_the_same_bar_passes_through_itself() {
    // The check above can fail: the same motion without self contact folds the ends through each other.
    let mut sim = folding_bar(Box::new(ProjectiveDynamics::default()), false);
    let mut closest = f64::INFINITY;
    for _ in 0..60 {
        sim.step().unwrap();
        closest = closest.min(ends_apart(&sim));
    }
    assert!(
        closest < 0.0,
        "the ends stayed apart ({closest} m) without self contact"
    );
}

#[test]
fn a_straight_bar_has_no_self_contact() {
    // A body whose surface is nowhere near another part of itself: self contact finds nothing (its own faces
    // beside a vertex are not contacts), so the run is the one without it, bit for bit.
    let run = |self_contact: bool| {
        let material = Material::Arap(Arap::new(2e4, 0.4).unwrap());
        let m = model(
            cubes_mesh(&block_cells(3), 0.1),
            material,
            0.05,
            [0.0, 0.0, -9.81],
        );
        let mut state = State::at_rest(&m);
        scaled(&mut state, 1.1, [0.15; 3]);
        let mut sim = Simulation::new(
            m,
            state,
            Box::new(ProjectiveDynamics::default()),
            1.0 / 60.0,
            None,
        )
        .unwrap();
        if self_contact {
            sim.set_self_contact(Some(BodyCoefficients::new(0.5, 0.5).unwrap()));
        }
        for _ in 0..30 {
            sim.step().unwrap();
        }
        assert!(sim.history().iter().all(|d| d.contacts == 0));
        sim.state.x.clone()
    };
    assert_eq!(run(true), run(false));
}
