//! XPBD: a valid colouring, rest stays at rest, dissipative alone, conserving with FEPR (the constraint
//! Neo-Hookean energy), bit-identical for any thread count.

mod common;
use common::*;
use fepr_core::integrators::{colour_tets, Xpbd, XpbdSettings};
use fepr_core::integrators::{HandOver, Integrator};
use fepr_core::material::{ConstraintNeoHookean, Material};
use fepr_core::model::State;
use fepr_core::simulation::Simulation;

fn constraint_nh() -> Material {
    Material::ConstraintNeoHookean(ConstraintNeoHookean::new(1e3, 0.3).unwrap())
}

fn block() -> fepr_core::mesh::TetMesh {
    let mut cells = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..2 {
                cells.push([i, j, k]);
            }
        }
    }
    cubes_mesh(&cells, 0.1)
}

#[test]
fn colouring_separates_tets_that_share_a_vertex() {
    let m = model(block(), constraint_nh(), 1.0, [0.0; 3]);
    let colours = colour_tets(&m);
    let mut seen = vec![0usize; m.num_tets()];
    for colour in &colours {
        let mut used = vec![false; m.num_vertices()];
        for &e in colour {
            seen[e] += 1;
            for &v in &m.mesh.tets()[e] {
                assert!(!used[v], "vertex {v} appears twice in one colour");
                used[v] = true;
            }
        }
    }
    assert!(
        seen.iter().all(|&n| n == 1),
        "every tet in exactly one colour"
    );
    assert!(colours.len() < m.num_tets());
}

#[test]
fn rest_state_stays_at_rest_at_a_large_step() {
    let m = model(block(), constraint_nh(), 1.0, [0.0; 3]);
    let mut state = State::at_rest(&m);
    let x0 = state.x.clone();
    let mut xpbd = Xpbd::default();
    for _ in 0..10 {
        xpbd.step(&m, &mut state, 1.0 / 30.0, &mut HandOver::new());
    }
    let moved = state
        .x
        .iter()
        .zip(&x0)
        .flat_map(|(a, b)| (0..3).map(move |k| (a[k] - b[k]).abs()))
        .fold(0.0, f64::max);
    assert!(moved < 1e-12, "rest state moved by {moved} m");
}

#[test]
fn xpbd_alone_dissipates_and_with_fepr_conserves_its_energy_and_momenta() {
    let (d0, plain) = spinning_ell_run(constraint_nh(), Box::new(Xpbd::default()), false, 150);
    let kept = plain.last().unwrap().invariants.total / d0.total;
    eprintln!("XPBD alone keeps {:.1}% of H after 5 s", 100.0 * kept);
    assert!(kept < 0.5);
    let (d0, projected) = spinning_ell_run(constraint_nh(), Box::new(Xpbd::default()), true, 300);
    let (dh, dp, dl) = max_drifts(&d0, &projected);
    eprintln!("XPBD + FEPR 10 s: max |H/H0-1| {dh:.2e}, |dP|/P0 {dp:.2e}, |dL|/L0 {dl:.2e}");
    assert!(dh <= 1e-8 && dp <= 1e-10 && dl <= 1e-10);
}

#[test]
fn xpbd_requires_its_constraint_energy() {
    let m = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
    let state = State::at_rest(&m);
    let err = Simulation::new(m, state, Box::new(Xpbd::default()), 0.01, None)
        .err()
        .unwrap();
    assert!(err.to_string().contains("ConstraintNeoHookean"), "{err}");
}

#[test]
fn xpbd_pins_hold_under_gravity() {
    let mut m = model(ell_mesh(), constraint_nh(), 1.0, [0.0, 0.0, -9.81]);
    let pinned: Vec<usize> = (0..m.num_vertices())
        .filter(|&i| m.mesh.vertices()[i][2] == 0.0)
        .collect();
    for &p in &pinned {
        m.pinned[p] = true;
    }
    let mut state = State::at_rest(&m);
    let x0 = state.x.clone();
    let mut xpbd = Xpbd::new(XpbdSettings {
        substeps: 5,
        iterations: 2,
    })
    .unwrap();
    for _ in 0..20 {
        xpbd.step(&m, &mut state, 0.02, &mut HandOver::new());
    }
    for &p in &pinned {
        assert_eq!(state.x[p], x0[p]);
    }
    let top = (0..m.num_vertices()).find(|&i| x0[i][2] == 3.0).unwrap();
    assert!(state.x[top][2] < 3.0 && state.x.iter().flatten().all(|c| c.is_finite()));
}

#[test]
fn xpbd_is_bit_identical_for_any_thread_count() {
    let run = |threads: usize| {
        in_pool(threads, || {
            spinning_ell_run(constraint_nh(), Box::new(Xpbd::default()), true, 20).1
        })
    };
    let one = run(1);
    for threads in [2, 3] {
        let other = run(threads);
        for (a, b) in one.iter().zip(&other) {
            assert_eq!(a.invariants.total.to_bits(), b.invariants.total.to_bits());
            assert_eq!(a.invariants.momentum, b.invariants.momentum);
        }
    }
}

#[test]
fn invalid_settings_are_rejected_with_their_names() {
    for (s, name) in [
        (
            XpbdSettings {
                substeps: 0,
                iterations: 1,
            },
            "xpbd_substeps",
        ),
        (
            XpbdSettings {
                substeps: 1,
                iterations: 0,
            },
            "xpbd_iterations",
        ),
    ] {
        let err = Xpbd::new(s).err().unwrap();
        assert!(err.to_string().contains(name), "{err}");
    }
}

/// A step taken in parts (bodies in contact answer it after each substep): `parts` calls of `dt / parts`
/// run the same substeps as one call of `dt`, so the positions and velocities are the same bits.
#[test]
fn a_step_taken_in_parts_runs_the_same_substeps() {
    let m = model(block(), constraint_nh(), 1.0, [0.0, 0.0, -9.81]);
    let mut start = State::at_rest(&m);
    scaled(&mut start, 1.2, [0.15, 0.15, 0.1]);
    let dt = 1.0 / 60.0;
    let mut whole = start.clone();
    let mut xpbd = Xpbd::default();
    let mut parted = start.clone();
    let mut in_parts = Xpbd::default();
    let parts = in_parts.substeps();
    in_parts.take_in_parts(parts);
    for _ in 0..3 {
        xpbd.step(&m, &mut whole, dt, &mut HandOver::new());
        for _ in 0..parts {
            in_parts.step(&m, &mut parted, dt / parts as f64, &mut HandOver::new());
        }
    }
    assert_eq!(parts, 20);
    assert_eq!(whole.x, parted.x);
    assert_eq!(whole.v, parted.v);
}
