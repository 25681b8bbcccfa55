//! Integrators, the projection and the world keep data built from the model: backward Euler's sparsity
//! pattern and symbolic analysis, the Projective Dynamics factor, the XPBD colouring and compliances, the
//! projection's stiffness metric and its metric rows, the Rayleigh damping pattern and an elastic gradient offered to symplectic
//! Euler. The model's fields are public, so a user of the Rust API can change pins, masses or the material
//! between steps (`sim.model.pinned[i] = true`), or step one integrator with two models. Guard: each cache
//! notices the change and is rebuilt, so an integrator that has stepped before gives the bits a new one gives.

mod common;
use common::*;
use fepr_core::elasticity::{elastic_energy_gradient, ElasticWorkspace};
use fepr_core::integrators::ImplicitEuler;
use fepr_core::integrators::ProjectiveDynamics;
use fepr_core::integrators::Xpbd;
use fepr_core::integrators::{HandOver, Integrator, StepReport, SymplecticEuler};
use fepr_core::invariants::measure;
use fepr_core::material::{Arap, ConstraintNeoHookean, Material};
use fepr_core::model::{Model, State};
use fepr_core::projection::{Metric, ProjectionSettings, Projector, Targets};
use fepr_core::simulation::Simulation;

fn assert_same_bits(a: &State, b: &State, what: &str) {
    for (i, (p, q)) in
        a.x.iter()
            .chain(&a.v)
            .zip(b.x.iter().chain(&b.v))
            .enumerate()
    {
        for k in 0..3 {
            assert_eq!(
                p[k].to_bits(),
                q[k].to_bits(),
                "{what}: row {i} (positions, then velocities), axis {k}: {} vs {}",
                p[k],
                q[k]
            );
        }
    }
}

/// Vertices of the L on the ground plane z = 0.
fn bottom(m: &Model) -> Vec<usize> {
    (0..m.num_vertices())
        .filter(|&i| m.mesh.vertices()[i][2] == 0.0)
        .collect()
}

/// A deformed, moving state.
fn moving_state(m: &Model) -> State {
    let mut s = State::at_rest(m);
    scaled(&mut s, 1.15, [0.5, 0.5, 1.0]);
    for (i, v) in s.v.iter_mut().enumerate() {
        *v = [0.2 * (i % 3) as f64, -0.1, 0.05 * (i % 4) as f64];
    }
    s
}

fn pin(m: &mut Model, s: &mut State, vertices: &[usize], on: bool) {
    for &p in vertices {
        m.pinned[p] = on;
        if on {
            s.v[p] = [0.0; 3];
        }
    }
}

/// A projection's targets: the measured state's momenta and centre of mass, its energy times `factor`.
fn targets_above(inv: &fepr_core::invariants::Invariants, factor: f64) -> Targets {
    Targets {
        energy: factor * inv.total,
        momentum: inv.momentum,
        angular_momentum: inv.angular_momentum,
        center_of_mass: inv.center_of_mass,
        energy_scale: inv.kinetic + inv.elastic.abs(),
        uncertain_impulses: false,
    }
}

/// Step `used` (which has stepped with an earlier model) and a new integrator from `state` on `m`: the same bits.
fn compare_with_new(
    used: &mut dyn Integrator,
    new: &mut dyn Integrator,
    m: &Model,
    state: &State,
    h: f64,
    what: &str,
) {
    let (mut a, mut b) = (state.clone(), state.clone());
    used.step(m, &mut a, h, &mut HandOver::new());
    new.step(m, &mut b, h, &mut HandOver::new());
    assert_same_bits(&a, &b, what);
}

#[test]
fn implicit_euler_rebuilds_its_pattern_after_a_pin_change() {
    let h = 0.02;
    let mut m = model(ell_mesh(), neo_hookean(1e4, 0.3), 1.0, [0.0, 0.0, -9.81]);
    let mut s = moving_state(&m);
    let mut ie = ImplicitEuler::default();
    for _ in 0..3 {
        ie.step(&m, &mut s, h, &mut HandOver::new());
    }
    let base = bottom(&m);
    pin(&mut m, &mut s, &base, true);
    compare_with_new(&mut ie, &mut ImplicitEuler::default(), &m, &s, h, "pinned");
    assert_eq!(ie.symbolic_analyses, 2);
    // A pinned vertex that is released moves again (a stale pattern would keep it frozen forever).
    pin(&mut m, &mut s, &base, false);
    compare_with_new(
        &mut ie,
        &mut ImplicitEuler::default(),
        &m,
        &s,
        h,
        "released",
    );
    assert_eq!(ie.symbolic_analyses, 3);
    // Masses and the material are read at every step: a change keeps the pattern.
    m.masses.iter_mut().for_each(|w| *w *= 2.0);
    m.total_mass *= 2.0;
    m.material = neo_hookean(3e4, 0.3);
    compare_with_new(&mut ie, &mut ImplicitEuler::default(), &m, &s, h, "masses");
    assert_eq!(ie.symbolic_analyses, 3);
}

#[test]
fn implicit_euler_in_a_simulation_moves_vertices_released_between_steps() {
    let mut m = model(ell_mesh(), neo_hookean(1e4, 0.3), 1.0, [0.0, 0.0, -9.81]);
    let base = bottom(&m);
    let top: Vec<usize> = (0..m.num_vertices())
        .filter(|&i| !base.contains(&i))
        .collect();
    for &p in &base {
        m.pinned[p] = true;
    }
    let state = State::at_rest(&m);
    let mut sim =
        Simulation::new(m, state, Box::new(ImplicitEuler::default()), 0.02, None).unwrap();
    sim.step().unwrap();
    // Release the base and pin the rest instead.
    for &p in &base {
        sim.model.pinned[p] = false;
    }
    for &p in &top {
        sim.model.pinned[p] = true;
        sim.state.v[p] = [0.0; 3];
    }
    let z0: Vec<f64> = base.iter().map(|&p| sim.state.x[p][2]).collect();
    let x_top: Vec<[f64; 3]> = top.iter().map(|&p| sim.state.x[p]).collect();
    for _ in 0..5 {
        sim.step().unwrap();
    }
    for (k, &p) in base.iter().enumerate() {
        assert!(
            sim.state.x[p][2] < z0[k] - 1e-4,
            "released vertex {p} did not fall: z {} -> {}",
            z0[k],
            sim.state.x[p][2]
        );
    }
    for (k, &p) in top.iter().enumerate() {
        assert_eq!(sim.state.x[p], x_top[k], "pinned vertex {p} moved");
    }
}

#[test]
fn projective_dynamics_refactorises_after_a_material_mass_or_pin_change() {
    let h = 1.0 / 30.0;
    let arap = |e: f64| Material::Arap(Arap::new(e, 0.3).unwrap());
    let mut m = model(ell_mesh(), arap(1e3), 1.0, [0.0, 0.0, -9.81]);
    let mut s = moving_state(&m);
    let mut pd = ProjectiveDynamics::default();
    pd.step(&m, &mut s, h, &mut HandOver::new());
    m.material = arap(4e3);
    compare_with_new(
        &mut pd,
        &mut ProjectiveDynamics::default(),
        &m,
        &s,
        h,
        "material",
    );
    m.masses[3] *= 3.0;
    m.total_mass += 2.0 * m.masses[3] / 3.0;
    compare_with_new(
        &mut pd,
        &mut ProjectiveDynamics::default(),
        &m,
        &s,
        h,
        "masses",
    );
    let base = bottom(&m);
    pin(&mut m, &mut s, &base, true);
    compare_with_new(
        &mut pd,
        &mut ProjectiveDynamics::default(),
        &m,
        &s,
        h,
        "pins",
    );
    assert_eq!(pd.factorizations, 4);
    // No change: no new factorisation.
    compare_with_new(
        &mut pd,
        &mut ProjectiveDynamics::default(),
        &m,
        &s,
        h,
        "same",
    );
    assert_eq!(pd.factorizations, 4);
}

#[test]
fn projective_dynamics_serves_two_models_in_turn() {
    let h = 1.0 / 30.0;
    let a = model(
        ell_mesh(),
        Material::Arap(Arap::new(1e3, 0.3).unwrap()),
        1.0,
        [0.0; 3],
    );
    // The same cells at half the size: the same vertex count, masses, pins and material, another rest shape.
    let b = model(
        cubes_mesh(
            &[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 2]],
            0.5,
        ),
        Material::Arap(Arap::new(1e3, 0.3).unwrap()),
        1.0,
        [0.0; 3],
    );
    let mut pd = ProjectiveDynamics::default();
    let mut sa = moving_state(&a);
    pd.step(&a, &mut sa, h, &mut HandOver::new());
    let sb = moving_state(&b);
    compare_with_new(
        &mut pd,
        &mut ProjectiveDynamics::default(),
        &b,
        &sb,
        h,
        "other mesh",
    );
}

#[test]
fn xpbd_prepares_again_after_a_material_mass_or_pin_change() {
    let h = 1.0 / 60.0;
    let cnh = |e: f64| Material::ConstraintNeoHookean(ConstraintNeoHookean::new(e, 0.3).unwrap());
    let mut m = model(ell_mesh(), cnh(1e3), 1.0, [0.0, 0.0, -9.81]);
    let mut s = moving_state(&m);
    let mut xpbd = Xpbd::default();
    xpbd.step(&m, &mut s, h, &mut HandOver::new());
    m.material = cnh(5e3);
    compare_with_new(&mut xpbd, &mut Xpbd::default(), &m, &s, h, "material");
    m.masses[2] *= 4.0;
    m.total_mass += 3.0 * m.masses[2] / 4.0;
    compare_with_new(&mut xpbd, &mut Xpbd::default(), &m, &s, h, "masses");
    let base = bottom(&m);
    pin(&mut m, &mut s, &base, true);
    compare_with_new(&mut xpbd, &mut Xpbd::default(), &m, &s, h, "pins");
}

#[test]
fn stiffness_metric_is_recomputed_after_a_material_change() {
    let h = 1.0 / 30.0;
    let settings = ProjectionSettings {
        metric: Metric::Stiffness,
        ..Default::default()
    };
    let soft = model(ell_mesh(), neo_hookean(1e3, 0.3), 1.0, [0.0; 3]);
    let mut stiff = soft.clone();
    stiff.material = neo_hookean(2e4, 0.45);
    // A base step's state and targets 10% above its energy, momenta as they are.
    let state = moving_state(&stiff);
    let inv = measure(&stiff, &state);
    let targets = targets_above(&inv, 1.1);
    let mut used = Projector::new(settings).unwrap();
    let mut first = moving_state(&soft);
    let inv_soft = measure(&soft, &first);
    let soft_targets = Targets {
        energy: 1.1 * inv_soft.total,
        ..targets
    };
    used.project(&soft, &mut first, h, &soft_targets);
    let (mut a, mut b) = (state.clone(), state.clone());
    let (ra, _) = used.project(&stiff, &mut a, h, &targets);
    let (rb, _) = Projector::new(settings)
        .unwrap()
        .project(&stiff, &mut b, h, &targets);
    assert!(ra.stiffness_metric && rb.stiffness_metric);
    assert_same_bits(&a, &b, "stiffness metric");
}

/// The projection keeps its metric's per-vertex rows from one step to the next; a change of the masses, of
/// the pins or (for the stiffness metric) of the step size between two projections must give the bits of a
/// new projector, for either metric.
#[test]
fn projection_metric_rows_follow_a_mass_pin_or_step_size_change() {
    for metric in [Metric::Mass, Metric::Stiffness] {
        let settings = ProjectionSettings {
            metric,
            ..Default::default()
        };
        let m0 = model(ell_mesh(), neo_hookean(1e4, 0.3), 1.0, [0.0, 0.0, -9.81]);
        let project = |p: &mut Projector, m: &Model, h: f64| {
            let mut s = moving_state(m);
            let inv = measure(m, &s);
            let targets = targets_above(&inv, 1.05);
            let (report, _) = p.project(m, &mut s, h, &targets);
            assert!(report.converged, "{metric:?}: {report:?}");
            s
        };
        let mut heavier = m0.clone();
        for (i, mass) in heavier.masses.iter_mut().enumerate() {
            *mass *= 1.0 + 0.1 * (i % 3) as f64;
        }
        heavier.total_mass = heavier.masses.iter().sum();
        let mut pinned = heavier.clone();
        let mut unused = State::at_rest(&pinned);
        pin(&mut pinned, &mut unused, &bottom(&m0)[..2], true);
        let mut used = Projector::new(settings).unwrap();
        // The same model twice (the rows kept), then each change after the one before.
        for (what, m, h) in [
            ("same model", &m0, 0.01),
            ("same model again", &m0, 0.01),
            ("masses", &heavier, 0.01),
            ("pins", &pinned, 0.01),
            ("step size", &pinned, 0.02),
        ] {
            let a = project(&mut used, m, h);
            let b = project(&mut Projector::new(settings).unwrap(), m, h);
            assert_same_bits(&a, &b, &format!("{metric:?}: {what}"));
        }
    }
}

#[test]
fn rayleigh_damping_rebuilds_its_pattern_after_a_pin_change() {
    let build = |m: Model, s: State| {
        let mut sim = Simulation::new(m, s, Box::new(SymplecticEuler::new()), 1e-3, None).unwrap();
        sim.set_damping(0.0, 0.01).unwrap();
        sim
    };
    let mut m = model(ell_mesh(), neo_hookean(1e3, 0.3), 1.0, [0.0; 3]);
    let base = bottom(&m);
    for &p in &base {
        m.pinned[p] = true;
    }
    let mut s = moving_state(&m);
    for &p in &base {
        s.v[p] = [0.0; 3];
    }
    let mut used = build(m, s);
    used.step().unwrap();
    for &p in &base {
        used.model.pinned[p] = false;
    }
    let mut new = build(used.model.clone(), used.state.clone());
    used.step().unwrap();
    new.step().unwrap();
    assert_same_bits(&used.state, &new.state, "Rayleigh damping");
}

/// Symplectic Euler stepped with a hand-over of its own, new at every step: it always evaluates.
struct Declining(SymplecticEuler);

impl Integrator for Declining {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn applies_step_damping(&self) -> bool {
        true
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

#[test]
fn offered_gradient_is_not_reused_after_a_material_change() {
    let run = |integrator: Box<dyn Integrator>| {
        let m = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0, 0.0, -9.81]);
        let s = moving_state(&m);
        let proj = Projector::new(ProjectionSettings::default()).unwrap();
        let mut sim = Simulation::new(m, s, integrator, 1.0 / 120.0, Some(proj)).unwrap();
        sim.step().unwrap();
        // The projection has just offered its gradient for the soft material.
        sim.model.material = neo_hookean(3e3, 0.3);
        sim.step().unwrap();
        sim.state.clone()
    };
    let with_offers = run(Box::new(SymplecticEuler::new()));
    let without = run(Box::new(Declining(SymplecticEuler::new())));
    assert_same_bits(&with_offers, &without, "offered gradient");
}

#[test]
fn offered_gradient_is_reused_by_the_same_model_only() {
    let soft = model(ell_mesh(), neo_hookean(1e3, 0.3), 5.0, [0.0; 3]);
    let mut stiff = soft.clone();
    stiff.material = neo_hookean(3e3, 0.3);
    let start = moving_state(&soft);
    let mut grad = vec![[0.0; 3]; soft.num_vertices()];
    elastic_energy_gradient(&soft, &start.x, &mut ElasticWorkspace::default(), &mut grad);
    let mut hand_over = HandOver::new();
    hand_over.put_final_gradient(&soft, &start.x, None, &mut grad);
    let mut se = SymplecticEuler::new();
    let (mut a, mut b) = (start.clone(), start.clone());
    se.step(&stiff, &mut a, 1e-3, &mut hand_over);
    SymplecticEuler::new().step(&stiff, &mut b, 1e-3, &mut HandOver::new());
    assert_same_bits(&a, &b, "handed-over gradient");
    assert_eq!(se.reused_gradients, 0);
}

#[test]
fn model_keys_follow_the_parts_they_cover() {
    let m = model(ell_mesh(), neo_hookean(1e3, 0.3), 1.0, [0.0; 3]);
    let keys = |m: &Model| (m.elastic_key(), m.structure_key(), m.key());
    let (e, s, k) = keys(&m);
    assert_eq!(keys(&m.clone()), (e, s, k), "a clone has the same keys");
    // Gravity and damping are read at every step and are in no key.
    let mut g = m.clone();
    g.gravity = [0.0, 0.0, -9.81];
    g.damping = 0.01;
    assert_eq!(keys(&g), (e, s, k));
    let mut mat = m.clone();
    mat.material = neo_hookean(1e3, 0.31);
    assert_eq!(mat.structure_key(), s);
    assert!(mat.elastic_key() != e && mat.key() != k);
    let mut pins = m.clone();
    pins.pinned[7] = true;
    assert_eq!(pins.elastic_key(), e);
    assert!(pins.structure_key() != s && pins.key() != k);
    let mut mass = m.clone();
    mass.masses[5] = f64::from_bits(mass.masses[5].to_bits() + 1);
    assert_eq!((mass.elastic_key(), mass.structure_key()), (e, s));
    assert!(mass.key() != k);
    // The same cells at another size: another rest mesh.
    let other = model(
        cubes_mesh(
            &[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 2]],
            0.5,
        ),
        neo_hookean(1e3, 0.3),
        1.0,
        [0.0; 3],
    );
    let (oe, os, ok) = keys(&other);
    assert!(oe != e && os != s && ok != k);
}
