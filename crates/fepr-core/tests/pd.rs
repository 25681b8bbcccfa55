//! Projective Dynamics: prefactored once, dissipative alone, conserving with FEPR (the PD energy).

mod common;
use common::*;
use fepr_core::material::{Arap, Material};
use fepr_core::model::State;
use fepr_core::pd::ProjectiveDynamics;
use fepr_core::simulation::Simulation;

fn arap() -> Material {
    Material::Arap(Arap::new(1e3, 0.3).unwrap())
}

#[test]
fn pd_alone_dissipates_and_with_fepr_conserves_the_pd_energy_and_momenta() {
    let (d0, plain) = spinning_ell_run(arap(), Box::new(ProjectiveDynamics::default()), false, 150);
    let kept = plain.last().unwrap().invariants.total / d0.total;
    eprintln!("PD alone keeps {:.1}% of H after 5 s", 100.0 * kept);
    assert!(kept < 0.5);
    let (d0, projected) =
        spinning_ell_run(arap(), Box::new(ProjectiveDynamics::default()), true, 300);
    let (dh, dp, dl) = max_drifts(&d0, &projected);
    eprintln!("PD + FEPR 10 s: max |H/H0-1| {dh:.2e}, |dP|/P0 {dp:.2e}, |dL|/L0 {dl:.2e}");
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
