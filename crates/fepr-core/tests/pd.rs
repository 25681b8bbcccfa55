//! Projective Dynamics: prefactored once, dissipative alone, conserving with FEPR (the PD energy).

mod common;
use common::*;
use fepr_core::material::{Arap, Material};
use fepr_core::model::State;
use fepr_core::pd::ProjectiveDynamics;
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;

fn arap() -> Material {
    Material::Arap(Arap::new(1e3, 0.3).unwrap())
}

fn run(
    project: bool,
    steps: usize,
) -> (
    fepr_core::invariants::Invariants,
    Vec<fepr_core::simulation::StepDiagnostics>,
) {
    let model = model(ell_mesh(), arap(), 5.0, [0.0; 3]);
    let mut state = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
    scaled(&mut state, 1.3, c);
    for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
        *v = [0.5 - (x[1] - c[1]), 0.2 + (x[0] - c[0]), 0.1];
    }
    let proj = project.then(|| Projector::new(ProjectionSettings::default()).unwrap());
    let mut sim = Simulation::new(
        model,
        state,
        Box::new(ProjectiveDynamics::default()),
        1.0 / 30.0,
        proj,
    )
    .unwrap();
    let d0 = sim.history()[0].invariants;
    for _ in 0..steps {
        sim.step().unwrap();
    }
    (d0, sim.history().to_vec())
}

#[test]
fn pd_alone_dissipates_and_with_fepr_conserves_the_pd_energy_and_momenta() {
    let (d0, plain) = run(false, 150);
    let kept = plain.last().unwrap().invariants.total / d0.total;
    eprintln!("PD alone keeps {:.1}% of H after 5 s", 100.0 * kept);
    assert!(kept < 0.5);
    let (d0, projected) = run(true, 300);
    let (mut dh, mut dp, mut dl): (f64, f64, f64) = (0.0, 0.0, 0.0);
    let mut iters = 0;
    for d in &projected[1..] {
        let p = d.projection.unwrap();
        assert!(p.converged, "step {}: {p:?}", d.step);
        iters += p.iterations;
        dh = dh.max(rel(d.invariants.total, d0.total));
        dp = dp.max(
            norm([0, 1, 2].map(|a| d.invariants.momentum[a] - d0.momentum[a])) / norm(d0.momentum),
        );
        dl = dl.max(
            norm([0, 1, 2].map(|a| d.invariants.angular_momentum[a] - d0.angular_momentum[a]))
                / norm(d0.angular_momentum),
        );
    }
    eprintln!("PD + FEPR 10 s: max |H/H0-1| {dh:.2e}, |dP|/P0 {dp:.2e}, |dL|/L0 {dl:.2e}, mean iterations {:.2}", iters as f64 / 300.0);
    assert!(dh <= 1e-8 && dp <= 1e-10 && dl <= 1e-10);
}

#[test]
fn pd_requires_the_pd_energy() {
    let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
    let state = State::at_rest(&model);
    let err = Simulation::new(
        model,
        state,
        Box::new(ProjectiveDynamics::default()),
        0.01,
        None,
    )
    .err()
    .unwrap();
    assert!(err.to_string().contains("ARAP"), "{err}");
}

#[test]
fn pd_factorises_once_and_pins_hold() {
    let mut m = model(ell_mesh(), arap(), 1.0, [0.0, 0.0, -9.81]);
    let pinned: Vec<usize> = (0..m.num_vertices())
        .filter(|&i| m.mesh.vertices()[i][2] == 0.0)
        .collect();
    for &p in &pinned {
        m.pinned[p] = true;
    }
    let mut state = State::at_rest(&m);
    let x0 = state.x.clone();
    let mut pd = ProjectiveDynamics::default();
    use fepr_core::integrators::Integrator;
    for _ in 0..20 {
        pd.step(&m, &mut state, 0.02);
    }
    assert_eq!(pd.factorizations, 1);
    for &p in &pinned {
        assert_eq!(state.x[p], x0[p]);
    }
    let top = (0..m.num_vertices()).find(|&i| x0[i][2] == 3.0).unwrap();
    assert!(state.x[top][2] < 3.0 && state.x.iter().flatten().all(|c| c.is_finite()));
}
