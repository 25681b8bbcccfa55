//! Conservation gates (fepr-spec sections 2, 3, 6, 7): every conservation claim is measured here.

mod common;
use common::*;
use fepr_core::integrators::{HandOver, SymplecticEuler};
use fepr_core::model::State;
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;

/// Seed demo 3 analogue on the procedural L: stretched 1.5x about the origin, dt = 1/30, no gravity. At this
/// step size symplectic Euler is unstable in the compressed states the motion reaches (its energy errors reach
/// 1e4 of the energy scale in single steps): without the quality guard FEPR restores every deficit and holds
/// H to 1e-8; with it (the default) the deficits it cannot restore within the guard are booked as unresolved,
/// the books still close, and the worst tet stays better than without it.
#[test]
fn seed_demo3_on_procedural_ell_conserves_energy_and_momenta() {
    let run = |quality_margin: Option<f64>| {
        let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
        let mut state = State::at_rest(&model);
        scaled(&mut state, 1.5, [0.0; 3]);
        let settings = ProjectionSettings {
            quality_margin,
            ..Default::default()
        };
        let proj = Projector::new(settings).unwrap();
        let mut sim = Simulation::new(
            model,
            state,
            Box::new(SymplecticEuler::new()),
            1.0 / 30.0,
            Some(proj),
        )
        .unwrap();
        let h0 = sim.history()[0].invariants.total;
        let (mut max_dh, mut max_books, mut max_p, mut max_l, mut min_j): (
            f64,
            f64,
            f64,
            f64,
            f64,
        ) = (0.0, 0.0, 0.0, 0.0, f64::INFINITY);
        let mut iters = 0;
        for _ in 0..300 {
            let d = *sim.step().unwrap();
            max_dh = max_dh.max(rel(d.invariants.total, h0));
            max_books = max_books.max(((d.invariants.total - h0 - d.budget_total) / h0).abs());
            max_p = max_p.max(norm(d.invariants.momentum));
            max_l = max_l.max(norm(d.invariants.angular_momentum));
            min_j = min_j.min(d.invariants.min_j);
            let p = d.projection.unwrap();
            assert!(p.converged, "step {}: {p:?}", d.step);
            assert_eq!(d.invariants.inverted, 0, "step {}", d.step);
            iters += p.iterations;
        }
        let unresolved = sim.history().iter().map(|d| d.work.unresolved).sum::<f64>() / h0;
        eprintln!(
            "demo3 (procedural L, margin {quality_margin:?}): max |H/H0-1| = {max_dh:.2e}, books {max_books:.2e}, \
             unresolved {unresolved:.2e}, max |P| = {max_p:.2e}, max |L| = {max_l:.2e}, min J {min_j:.3}, \
             mean iterations {:.2}",
            iters as f64 / 300.0
        );
        let m_tot = sim.model.total_mass;
        let r = sim.model.length_scale;
        // P and L are zero initially: compare with the natural scales m r / dt and m r^2 / dt.
        assert!(max_p <= 1e-10 * m_tot * r * 30.0);
        assert!(max_l <= 1e-10 * m_tot * r * r * 30.0);
        assert!(max_books <= 1e-8);
        (max_dh, unresolved, min_j)
    };
    let (dh_full, unresolved_full, min_j_full) = run(None);
    assert!(dh_full <= 1e-8 && unresolved_full == 0.0);
    let (_, unresolved, min_j) = run(Some(fepr_core::projection::DEFAULT_QUALITY_MARGIN));
    assert!(
        unresolved < 0.0,
        "the unstable steps leave energy the guard books"
    );
    assert!(min_j > min_j_full, "{min_j} vs {min_j_full}");
}

#[test]
fn free_body_thousand_steps_conserves_h_p_l_and_beats_the_unprojected_drift() {
    // A spinning, thrown, stretched L at a stable step size.
    let build = |project: bool| {
        let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
        let mut state = State::at_rest(&model);
        let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
        scaled(&mut state, 1.1, c);
        for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
            // angular velocity (0.3, 0.2, 1.0) rad/s about the centre of mass, plus (1, 0.5, 0) m/s
            let w = [0.3, 0.2, 1.0];
            let r = [x[0] - c[0], x[1] - c[1], x[2] - c[2]];
            *v = [
                1.0 + w[1] * r[2] - w[2] * r[1],
                0.5 + w[2] * r[0] - w[0] * r[2],
                w[0] * r[1] - w[1] * r[0],
            ];
        }
        simulation(model, state, 0.01, project)
    };
    let mut results = Vec::new();
    for project in [true, false] {
        let mut sim = build(project);
        let d0 = sim.history()[0].invariants;
        let (mut dh, mut dp, mut dl) = (0.0f64, 0.0f64, 0.0f64);
        for _ in 0..1000 {
            let d = sim.step().unwrap().invariants;
            dh = dh.max(rel(d.total, d0.total));
            dp = dp.max(
                norm([
                    d.momentum[0] - d0.momentum[0],
                    d.momentum[1] - d0.momentum[1],
                    d.momentum[2] - d0.momentum[2],
                ]) / norm(d0.momentum),
            );
            dl = dl.max(
                norm([
                    d.angular_momentum[0] - d0.angular_momentum[0],
                    d.angular_momentum[1] - d0.angular_momentum[1],
                    d.angular_momentum[2] - d0.angular_momentum[2],
                ]) / norm(d0.angular_momentum),
            );
        }
        eprintln!("free body, projection {project}: max |dH|/H0 = {dh:.3e}, |dP|/P0 = {dp:.3e}, |dL|/L0 = {dl:.3e}");
        results.push((dh, dp, dl));
    }
    let (dh, dp, dl) = results[0];
    assert!(dh <= 1e-8, "projected energy drift {dh}");
    assert!(dp <= 1e-10, "projected momentum drift {dp}");
    assert!(dl <= 1e-10, "projected angular momentum drift {dl}");
    assert!(
        results[1].0 > 100.0 * dh,
        "the unprojected drift {} should be measurably larger than {dh}",
        results[1].0
    );
}

#[test]
fn gravity_centre_of_mass_follows_the_ballistic_path_and_h_is_held() {
    let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0, 0.0, -9.81]);
    let mut state = State::at_rest(&model);
    let c0 = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
    scaled(&mut state, 1.05, c0);
    let v0 = [1.0, 0.0, 2.0];
    for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
        let r = [x[0] - c0[0], x[1] - c0[1]];
        *v = [v0[0] - r[1], v0[1] + r[0], v0[2]]; // 1 rad/s about z
    }
    let dt = 0.01;
    let mut sim = simulation(model, state, dt, true);
    let h0 = sim.history()[0].invariants.total;
    let mut worst_c: f64 = 0.0;
    let mut worst_h: f64 = 0.0;
    for _ in 0..100 {
        let d = *sim.step().unwrap();
        let t = d.time;
        let expected = [
            c0[0] + v0[0] * t,
            c0[1] + v0[1] * t,
            c0[2] + v0[2] * t - 0.5 * 9.81 * t * t,
        ];
        let c = d.invariants.center_of_mass;
        let err =
            norm([c[0] - expected[0], c[1] - expected[1], c[2] - expected[2]]) / norm(expected);
        worst_c = worst_c.max(err);
        worst_h = worst_h.max(rel(d.invariants.total, h0));
        assert!(d.projection.unwrap().converged);
    }
    eprintln!("gravity: centre of mass off the parabola by {worst_c:.2e} (relative), max |H/H0-1| = {worst_h:.2e}");
    assert!(worst_c <= 1e-10);
    assert!(worst_h <= 1e-8);
}

#[test]
fn dropped_from_rest_converges_in_one_iteration_without_singular_failure() {
    let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0, 0.0, -9.81]);
    let state = State::at_rest(&model);
    let c0 = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
    let mut sim = simulation(model, state, 1.0 / 60.0, true);
    let h0 = sim.history()[0].invariants.total;
    for _ in 0..60 {
        let d = *sim.step().unwrap();
        let p = d.projection.unwrap();
        assert!(p.converged && p.iterations <= 1, "step {}: {p:?}", d.step);
        assert!(!p.fallback);
        let t = d.time;
        let c = d.invariants.center_of_mass;
        assert!(
            (c[2] - (c0[2] - 0.5 * 9.81 * t * t)).abs() <= 1e-10,
            "step {}: {c:?}",
            d.step
        );
        assert!(rel(d.invariants.total, h0) <= 1e-12);
    }
}

#[test]
fn rest_state_and_rigid_translation_take_zero_iterations() {
    let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
    let state = State::at_rest(&model);
    let mut sim = simulation(model.clone(), state, 1.0 / 30.0, true);
    for _ in 0..10 {
        let d = *sim.step().unwrap();
        let p = d.projection.unwrap();
        assert_eq!(p.iterations, 0, "{p:?}");
        assert!(p.converged && d.state_is_finite());
    }
    let mut state = State::at_rest(&model);
    // Far from the origin, moving rigidly.
    for (x, v) in state.x.iter_mut().zip(state.v.iter_mut()) {
        x[0] += 1e3;
        *v = [2.0, -1.0, 0.5];
    }
    let mut sim = simulation(model, state, 1.0 / 30.0, true);
    for _ in 0..10 {
        let d = *sim.step().unwrap();
        let p = d.projection.unwrap();
        assert_eq!(p.iterations, 0, "{p:?}");
        assert!(p.converged);
    }
}

#[test]
fn a_body_at_rest_without_gravity_is_no_runaway_with_any_integrator() {
    // Its energy is zero: the step's energy scale is the elastic energy of a small strain, so the rounding of the
    // implicit integrators' solves is neither a runaway nor a failed projection.
    use fepr_core::integrators::{ImplicitEuler, Integrator, NewtonSettings, ProjectiveDynamics};
    use fepr_core::material::{Arap, Material};
    let runs: Vec<(Material, Box<dyn Integrator>)> = vec![
        (
            neo_hookean(1e3, 0.3),
            Box::new(ImplicitEuler::new(NewtonSettings::default()).unwrap()),
        ),
        (
            Material::Arap(Arap::new(1e3, 0.3).unwrap()),
            Box::new(ProjectiveDynamics::default()),
        ),
    ];
    for (material, integrator) in runs {
        let name = integrator.name();
        let model = model(ell_mesh(), material, 5.0, [0.0; 3]);
        let state = State::at_rest(&model);
        let proj = Projector::new(ProjectionSettings::default()).unwrap();
        let mut sim = Simulation::new(model, state, integrator, 1.0 / 60.0, Some(proj)).unwrap();
        for _ in 0..5 {
            let d = *sim.step().unwrap();
            assert!(!d.runaway, "{name}: {d:?}");
            assert!(d.projection.unwrap().converged, "{name}: {d:?}");
        }
    }
}

trait FiniteCheck {
    fn state_is_finite(&self) -> bool;
}
impl FiniteCheck for fepr_core::simulation::StepDiagnostics {
    fn state_is_finite(&self) -> bool {
        self.invariants.total.is_finite() && self.invariants.min_j.is_finite()
    }
}

#[test]
fn damping_budget_is_honoured_by_the_projection() {
    // With damping d the projection must follow the budget (energy removed), not restore H0.
    let mut m = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
    m.damping = 0.01;
    let mut state = State::at_rest(&m);
    scaled(&mut state, 1.2, [0.0; 3]);
    let mut sim = simulation(m, state, 1.0 / 60.0, true);
    let h0 = sim.history()[0].invariants.total;
    let mut expected = h0;
    for _ in 0..200 {
        let d = *sim.step().unwrap();
        expected += d.energy_budget;
        assert!(d.projection.unwrap().converged);
        assert!(
            rel(d.invariants.total, expected) <= 1e-8,
            "step {}: H {} vs expected {expected}",
            d.step,
            d.invariants.total
        );
    }
    let last = sim.history().last().unwrap().invariants.total;
    assert!(
        last < 0.9 * h0,
        "damping must remove energy: {last} vs {h0}"
    );
}

/// 343 vertices (the step's row passes on the calling thread) and 1,728 (in vertex tasks: above
/// `parallel::SERIAL_ROWS`).
#[test]
fn projected_run_is_bit_identical_for_any_thread_count() {
    for cells in [6, 11] {
        projected_run_is_bit_identical_for_any_thread_count_on(cells);
    }
}

fn projected_run_is_bit_identical_for_any_thread_count_on(cells: i64) {
    let run = |threads: usize| {
        in_pool(threads, || {
            let big = cubes_mesh(&block_cells(cells), 0.1);
            assert!(
                cells < 10 || big.num_vertices() > fepr_core::exec::SERIAL_ROWS,
                "{} vertices",
                big.num_vertices()
            );
            let model = model(big, neo_hookean(1e4, 0.3), 0.01, [0.0, 0.0, -9.81]);
            let mut state = State::at_rest(&model);
            scaled(&mut state, 1.1, [0.3, 0.3, 0.3]);
            let mut sim = simulation(model, state, 2e-3, true);
            for _ in 0..20 {
                sim.step().unwrap();
            }
            sim.state
                .x
                .iter()
                .chain(&sim.state.v)
                .flatten()
                .map(|c| c.to_bits())
                .collect::<Vec<u64>>()
        })
    };
    let one = run(1);
    assert_eq!(one, run(2));
    assert_eq!(one, run(3));
}

#[test]
fn warm_start_restores_a_large_energy_deficit_and_keeps_the_momenta() {
    use fepr_core::invariants::measure;
    use fepr_core::projection::{ProjectionSettings, Projector, Targets};
    let model = model(ell_mesh(), neo_hookean(1e4, 0.3), 5.0, [0.0; 3]);
    let mut state = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
    scaled(&mut state, 1.02, c);
    for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
        // spin + drift + a breathing (deformational) part 0.2 (x - c), which carries no momentum
        *v = [0, 1, 2].map(|a| 0.2 * (x[a] - c[a]));
        v[0] += 0.3 - (x[1] - c[1]);
        v[1] += 0.1 + (x[0] - c[0]);
        v[2] += 0.05;
    }
    let inv = measure(&model, &state);
    // Ask for three times the energy (a base step that lost two thirds of H), same momenta.
    let targets = Targets {
        energy: 3.0 * inv.total,
        momentum: inv.momentum,
        angular_momentum: inv.angular_momentum,
        center_of_mass: inv.center_of_mass,
        energy_scale: 3.0 * inv.total,
        uncertain_impulses: false,
    };
    // The warm start itself, without the quality guard (which would book most of a threefold deficit).
    let settings = ProjectionSettings {
        warm_start_threshold: 0.05,
        quality_margin: None,
        ..Default::default()
    };
    let mut proj = Projector::new(settings).unwrap();
    let (report, out) = proj.project(&model, &mut state, 1.0 / 30.0, &targets);
    eprintln!("warm start: {report:?}");
    assert!(report.warm_start && report.converged, "{report:?}");
    assert!(rel(out.total, targets.energy) <= 1e-9);
    for a in 0..3 {
        assert!((out.momentum[a] - inv.momentum[a]).abs() <= 1e-9 * norm(inv.momentum));
        assert!(
            (out.angular_momentum[a] - inv.angular_momentum[a]).abs()
                <= 1e-8 * norm(inv.angular_momentum)
        );
    }
}

/// The deformational part `u = v - V - omega x (x - c)` of a velocity field (rigid part fitted by mass:
/// `V = P / m`, `omega = I_c^-1 L_c`).
fn deformational_part(masses: &[f64], x: &[[f64; 3]], v: &[[f64; 3]]) -> Vec<[f64; 3]> {
    use fepr_core::math::{cross, inverse, sub};
    let m: f64 = masses.iter().sum();
    let (mut p, mut mx) = ([0.0; 3], [0.0; 3]);
    for ((mi, xi), vi) in masses.iter().zip(x).zip(v) {
        for a in 0..3 {
            p[a] += mi * vi[a];
            mx[a] += mi * xi[a];
        }
    }
    let vc = p.map(|pa| pa / m);
    let c = mx.map(|ma| ma / m);
    let (mut inertia, mut l) = ([[0.0; 3]; 3], [0.0; 3]);
    for ((mi, xi), vi) in masses.iter().zip(x).zip(v) {
        let r = sub(*xi, c);
        let rr: f64 = r.iter().map(|q| q * q).sum();
        for a in 0..3 {
            for b in 0..3 {
                inertia[a][b] += mi * (if a == b { rr } else { 0.0 } - r[a] * r[b]);
            }
        }
        let lv = cross(r, *vi);
        for a in 0..3 {
            l[a] += mi * lv[a];
        }
    }
    let inv = inverse(&inertia).unwrap();
    let omega = [0, 1, 2].map(|a| (0..3).map(|b| inv[a][b] * l[b]).sum::<f64>());
    x.iter()
        .zip(v)
        .map(|(xi, vi)| {
            let w = cross(omega, sub(*xi, c));
            [0, 1, 2].map(|a| vi[a] - vc[a] - w[a])
        })
        .collect()
}

/// Project `state` (dt = 1/30 s) with the warm start above `threshold`, and check that the warm start alone
/// ended the projection: converged without iterations, the positions held, the energy on its target.
fn warm_start_alone(
    model: &fepr_core::model::Model,
    state: &mut State,
    targets: &fepr_core::projection::Targets,
    threshold: f64,
) -> fepr_core::invariants::Invariants {
    use fepr_core::projection::{ProjectionSettings, Projector};
    let x0 = state.x.clone();
    // The warm start itself, without the quality guard.
    let settings = ProjectionSettings {
        warm_start_threshold: threshold,
        quality_margin: None,
        ..Default::default()
    };
    let mut proj = Projector::new(settings).unwrap();
    let (report, out) = proj.project(model, state, 1.0 / 30.0, targets);
    assert!(report.warm_start && report.converged, "{report:?}");
    assert_eq!(report.iterations, 0, "{report:?}");
    assert_eq!(state.x, x0, "the warm start holds the positions");
    assert!(rel(out.total, targets.energy) <= 1e-12, "{out:?}");
    out
}

#[test]
fn warm_start_puts_the_momenta_on_their_targets_with_positions_held_and_leaves_no_iteration() {
    use fepr_core::invariants::measure;
    use fepr_core::projection::Targets;
    let model = model(ell_mesh(), neo_hookean(1e4, 0.3), 5.0, [0.0; 3]);
    let mut state = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
    scaled(&mut state, 1.03, c);
    for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
        *v = [0, 1, 2].map(|a| 0.2 * (x[a] - c[a]) + 0.05 * (3.0 * x[(a + 1) % 3]).sin());
        v[0] += 0.3 - 0.5 * (x[1] - c[1]);
        v[1] += 0.5 * (x[0] - c[0]);
    }
    let inv = measure(&model, &state);
    // A dissipative base step: it lost half of H and some of P and L (targets: the start-of-step values).
    let targets = Targets {
        energy: 2.0 * inv.total,
        momentum: [
            inv.momentum[0] * 1.1,
            inv.momentum[1] + 0.2,
            inv.momentum[2],
        ],
        angular_momentum: inv.angular_momentum.map(|l| 1.2 * l + 0.1),
        center_of_mass: inv.center_of_mass,
        energy_scale: 2.0 * inv.total,
        uncertain_impulses: false,
    };
    let base = state.clone();
    let out = warm_start_alone(&model, &mut state, &targets, 0.05);
    for a in 0..3 {
        assert!((out.momentum[a] - targets.momentum[a]).abs() <= 1e-12 * norm(targets.momentum));
        assert!(
            (out.angular_momentum[a] - targets.angular_momentum[a]).abs()
                <= 1e-12 * norm(targets.angular_momentum)
        );
    }
    // Closest point with the positions held (the KKT condition): the deformational part is only scaled.
    let u0 = deformational_part(&model.masses, &base.x, &base.v);
    let u1 = deformational_part(&model.masses, &state.x, &state.v);
    let size = |u: &[[f64; 3]]| u.iter().flatten().map(|q| q * q).sum::<f64>().sqrt();
    let beta = size(&u1) / size(&u0);
    assert!(beta > 1.2, "the energy deficit went into u (beta {beta})");
    let off: Vec<[f64; 3]> = u1
        .iter()
        .zip(&u0)
        .map(|(a, b)| [0, 1, 2].map(|k| a[k] - beta * b[k]))
        .collect();
    assert!(
        size(&off) <= 1e-12 * size(&u1),
        "u not parallel: {}",
        size(&off) / size(&u1)
    );
}

/// Regression: with pins the momentum rows are off, and the warm start kept the velocities' best-fit rigid part
/// (a pinned body's swing is mostly that) while scaling only the small rest: 17x on the PD cantilever demo.
/// With nothing holding P or L, the closest point with the positions held scales every free velocity alike.
#[test]
fn warm_start_on_a_pinned_body_scales_every_free_velocity_alike() {
    use fepr_core::invariants::measure;
    use fepr_core::projection::Targets;
    let mut model = model(ell_mesh(), neo_hookean(1e4, 0.3), 5.0, [0.0, 0.0, -9.81]);
    for i in 0..model.num_vertices() {
        model.pinned[i] = model.mesh.vertices()[i][2] == 0.0;
    }
    let mut state = State::at_rest(&model);
    for (i, (x, v)) in state.x.iter().zip(state.v.iter_mut()).enumerate() {
        if !model.pinned[i] {
            // A swing about the pinned base (nearly rigid) plus a little bending.
            *v = [0.4 * x[2] + 0.02 * x[2] * x[2], -0.1 * x[2], 0.0];
        }
    }
    let inv = measure(&model, &state);
    // A dissipative base step that lost 10 J (the kinetic energy is about 32 J).
    let targets = Targets {
        energy: inv.total + 10.0,
        momentum: inv.momentum,
        angular_momentum: inv.angular_momentum,
        center_of_mass: inv.center_of_mass,
        energy_scale: inv.total.abs() + inv.kinetic,
        uncertain_impulses: false,
    };
    let base = state.clone();
    warm_start_alone(&model, &mut state, &targets, 0.0);
    let beta = ((inv.kinetic + 10.0) / inv.kinetic).sqrt();
    for (i, (v1, v0)) in state.v.iter().zip(&base.v).enumerate() {
        for a in 0..3 {
            let want = beta * v0[a];
            assert!(
                (v1[a] - want).abs() <= 1e-12 * (1.0 + want.abs()),
                "vertex {i}: {v1:?} against {beta} x {v0:?}"
            );
        }
    }
}

#[test]
fn warm_start_computes_the_elastic_gradient_only_when_an_iteration_needs_it() {
    use fepr_core::invariants::measure;
    use fepr_core::projection::{ProjectionSettings, Projector, Targets};
    let model = model(ell_mesh(), neo_hookean(1e4, 0.3), 5.0, [0.0; 3]);
    let mut base = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &base.x);
    scaled(&mut base, 1.03, c);
    for (x, v) in base.x.iter().zip(base.v.iter_mut()) {
        *v = [0, 1, 2].map(|a| 0.2 * (x[a] - c[a]));
        v[0] += 0.3 - 0.5 * (x[1] - c[1]);
    }
    let inv = measure(&model, &base);
    let settings = ProjectionSettings {
        warm_start_threshold: 0.0,
        quality_margin: None,
        ..Default::default()
    };
    for (shift, iterates) in [(0.0, false), (1e-4, true)] {
        // A centre-of-mass target off by `shift` m: only the iteration can move the positions there.
        let targets = Targets {
            energy: 1.5 * inv.total,
            momentum: inv.momentum,
            angular_momentum: inv.angular_momentum,
            center_of_mass: [
                inv.center_of_mass[0] + shift,
                inv.center_of_mass[1],
                inv.center_of_mass[2],
            ],
            energy_scale: 1.5 * inv.total,
            uncertain_impulses: false,
        };
        let mut state = base.clone();
        let mut proj = Projector::new(settings).unwrap();
        // Vertex 0 held (as in contact): the body cannot be translated onto the centre-of-mass target, so only
        // the iteration can move the positions there.
        proj.set_frozen_positions(&[0]);
        let (report, out) = proj.project(&model, &mut state, 1.0 / 30.0, &targets);
        assert!(report.warm_start && report.converged, "{report:?}");
        assert_eq!(report.iterations > 0, iterates, "{report:?}");
        assert!(rel(out.total, targets.energy) <= 1e-10);
        assert!((out.center_of_mass[0] - targets.center_of_mass[0]).abs() <= 1e-12);
        // The gradient handed to the next step exists only if it was computed, and is the one at the result.
        match proj.take_final_gradient() {
            Some(g) => {
                assert!(iterates);
                let mut ws = fepr_core::elasticity::ElasticWorkspace::default();
                let mut want = vec![[0.0; 3]; model.num_vertices()];
                fepr_core::elasticity::elastic_energy_gradient(
                    &model, &state.x, &mut ws, &mut want,
                );
                assert_eq!(*g, want);
            }
            None => assert!(!iterates, "a converged iteration leaves its gradient"),
        }
    }
}

/// The L stretched by 4% about its centre of mass, spinning with a ripple on top (a base step's state whose
/// projection has work to do).
fn stretched_spinning_ell() -> (fepr_core::model::Model, State) {
    let model = model(ell_mesh(), neo_hookean(1e4, 0.3), 5.0, [0.0; 3]);
    let mut base = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &base.x);
    scaled(&mut base, 1.04, c);
    for (x, v) in base.x.iter().zip(base.v.iter_mut()) {
        *v = [0, 1, 2].map(|a| 0.3 * (x[(a + 1) % 3] - c[(a + 1) % 3]) + 0.02 * (4.0 * x[a]).cos());
    }
    (model, base)
}

#[test]
fn unconverged_projection_returns_its_best_iterate_with_matching_invariants() {
    // A tolerance no iterate meets: every run ends in the fallback and must return the best iterate it saw
    // (kept by buffer swaps, not copies), with the invariants of that very state. Up to 12 iterations and no
    // step halving: the later iterates jitter at round-off, so worse iterates follow the best one (the swap
    // path).
    use fepr_core::invariants::measure;
    use fepr_core::projection::{ProjectionSettings, Projector, Targets};
    let (model, base) = stretched_spinning_ell();
    let inv = measure(&model, &base);
    let targets = Targets {
        energy: 0.97 * inv.total,
        momentum: inv.momentum,
        angular_momentum: inv.angular_momentum,
        center_of_mass: inv.center_of_mass,
        energy_scale: inv.total,
        uncertain_impulses: false,
    };
    let mut previous = f64::INFINITY;
    for iterations in 1..=12 {
        let settings = ProjectionSettings {
            tolerance: 1e-300,
            max_iterations: iterations,
            max_halvings: 0,
            ..Default::default()
        };
        let mut proj = Projector::new(settings).unwrap();
        let mut state = base.clone();
        let (report, out) = proj.project(&model, &mut state, 1.0 / 30.0, &targets);
        assert!(!report.converged && report.fallback, "{report:?}");
        assert!(
            report.final_residual < report.initial_residual,
            "{report:?}"
        );
        assert!(
            report.final_residual <= previous,
            "{iterations} iterations: {} after {previous}",
            report.final_residual
        );
        previous = report.final_residual;
        let again = measure(&model, &state);
        assert!(rel(again.total, out.total) <= 1e-12, "{again:?} vs {out:?}");
        for a in 0..3 {
            assert!(
                (again.momentum[a] - out.momentum[a]).abs() <= 1e-12 * norm(inv.momentum).max(1e-9)
            );
        }
    }
    assert!(
        previous < 1e-12,
        "the iterations reach round-off: {previous}"
    );
}

/// Guards the D-norm of the correction with held positions (contact vertices, or a restart's frozen ones:
/// `a_i = 0`): their term is 0, where it was 0/0 and made `correction` NaN.
#[test]
fn correction_is_finite_with_frozen_positions() {
    use fepr_core::integrators::{Integrator, SymplecticEuler};
    use fepr_core::projection::{ProjectionSettings, Projector, Targets};
    let model = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
    let mut start = State::at_rest(&model);
    scaled(&mut start, 1.2, [0.0; 3]);
    let inv = fepr_core::invariants::measure(&model, &start);
    let targets = Targets {
        energy: inv.total,
        momentum: inv.momentum,
        angular_momentum: inv.angular_momentum,
        center_of_mass: inv.center_of_mass,
        energy_scale: inv.total.abs(),
        uncertain_impulses: false,
    };
    let h = 1.0 / 30.0;
    let mut state = start.clone();
    SymplecticEuler::new().step(&model, &mut state, h, &mut HandOver::new());
    let mut proj = Projector::new(ProjectionSettings::default()).unwrap();
    proj.set_frozen_positions(&[0, 1]);
    let (x0, x1) = (state.x[0], state.x[1]);
    let (report, _) = proj.project(&model, &mut state, h, &targets);
    assert!(report.iterations >= 1, "{report:?}");
    assert!(
        report.correction.is_finite() && report.correction > 0.0,
        "{report:?}"
    );
    assert_eq!((state.x[0], state.x[1]), (x0, x1), "held positions moved");
}

#[test]
fn a_projection_that_falls_back_still_puts_the_momenta_on_their_targets() {
    // No iterate meets the tolerance and a quality margin of 1e-9 lets no fraction of the energy gap through,
    // so the projection falls back to the base step's state; its momenta are still put on the targets the
    // processes set (an impulse exchanged with another body), so a scene's P and L do not drift through the
    // steps its projections fail (two armadillos colliding with Projective Dynamics drifted 12% in L).
    use fepr_core::invariants::measure;
    use fepr_core::projection::{ProjectionSettings, Projector, Targets};
    let (model, base) = stretched_spinning_ell();
    let inv = measure(&model, &base);
    let kick = [0.4, -0.2, 0.1];
    let twist = [0.05, 0.1, -0.08];
    let targets = Targets {
        energy: 0.3 * inv.total,
        momentum: [0, 1, 2].map(|a| inv.momentum[a] + kick[a]),
        angular_momentum: [0, 1, 2].map(|a| inv.angular_momentum[a] + twist[a]),
        center_of_mass: inv.center_of_mass,
        energy_scale: inv.total,
        uncertain_impulses: false,
    };
    for iterations in [1, 3] {
        let settings = ProjectionSettings {
            tolerance: 1e-300,
            max_iterations: iterations,
            quality_margin: Some(1e-9),
            ..Default::default()
        };
        let mut proj = Projector::new(settings).unwrap();
        let mut state = base.clone();
        let (report, out) = proj.project(&model, &mut state, 1.0 / 30.0, &targets);
        assert!(!report.converged && report.fallback, "{report:?}");
        let now = measure(&model, &state);
        assert!(rel(now.total, out.total) <= 1e-12, "{now:?} vs {out:?}");
        // The angular momentum target is about the target centre of mass (fepr-spec section 2).
        let ct = targets.center_of_mass;
        let l_ct = fepr_core::invariants::angular_momentum(&model.masses, &state.x, &state.v, ct);
        for a in 0..3 {
            assert!(
                (now.momentum[a] - targets.momentum[a]).abs() <= 1e-12,
                "{iterations} iterations: P {:?} against {:?}",
                now.momentum,
                targets.momentum
            );
            assert!(
                (l_ct[a] - targets.angular_momentum[a]).abs() <= 1e-12,
                "{iterations} iterations: L {:?} against {:?}",
                l_ct,
                targets.angular_momentum
            );
        }
        let min_j = now.min_j;
        assert!(
            min_j > 0.5,
            "a rigid change of velocities leaves the positions: min J {min_j}"
        );
    }
}
