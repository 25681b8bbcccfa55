//! A plain timing loop over the elastic energy + gradient (for `perf stat` / `perf record`):
//! `cargo bench -p fepr-core --bench eg_loop -- CELLS THREADS REPEATS` (a CELLS^3 box, 6 tets per cell).
//! `cargo bench -p fepr-core --bench eg_loop -- eg STEM THREADS REPEATS`: the same on a TetGen mesh
//! `STEM.node`/`STEM.ele`.
//! `cargo bench -p fepr-core --bench eg_loop -- proj STEM THREADS REPEATS`: the FEPR projection alone after
//! one symplectic Euler step (dt = 1 ms) from the same set-up, the same input every call: ms per call (best
//! and median), iterations, and the energy + gradient in the same pool for the ratio.
//! `cargo bench -p fepr-core --bench eg_loop -- sim STEM THREADS STEPS`: symplectic Euler + FEPR steps of a
//! `Simulation`.
//! `cargo bench -p fepr-core --bench eg_loop -- becold STEM [THREADS]`: the projection right after a backward
//! Euler step (caches cold) against the same projection again at once, per elastic evaluation.
//! `cargo bench -p fepr-core --bench eg_loop -- small` times the small dense kernels instead (polar
//! decomposition, 3x3 and 9x9 symmetric eigen-decompositions, PSD projection), one thread, ns per call.
//! `cargo bench -p fepr-core --bench eg_loop -- newton STEM STEPS` runs backward Euler (no projection) on a
//! TetGen mesh `STEM.node`/`STEM.ele` (Neo-Hookean E = 1e5 Pa, nu = 0.3, 1000 kg/m^3, 10% stretch about the
//! centre of mass, dt = 1/30 s; `fepr` after STEPS: with the FEPR projection) and prints every step's
//! Newton decrements (for convergence studies).
//! `cargo bench -p fepr-core --bench eg_loop -- pd STEM STEPS [fepr]`: the same set-up with the ARAP material
//! and Projective Dynamics (10 iterations), ms per step and the local / right-hand side / solve times, after
//! the vertex Cholesky study: its 3-column solve, sequential, parallel inside pools of 1 and 2 threads, and
//! parallel on the global pool (`RAYON_NUM_THREADS`) called from the main thread as PD calls it (`solve STEM
//! [ROUNDS]`: that study alone).

use std::time::Instant;

mod common;
use common::{bench_model, load_tetgen};

use fepr_core::elasticity::{elastic_energy_gradient, ElasticWorkspace};
use fepr_core::material::{Material, NeoHookean};
use fepr_core::mesh::{MassSpec, TetMesh};
use fepr_core::model::ModelBuilder;

/// Times `f` over `samples` (ns per call, best of 5 rounds).
fn time_ns<T, R>(samples: &[T], mut f: impl FnMut(&T) -> R) -> f64 {
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t0 = Instant::now();
        for s in samples {
            std::hint::black_box(f(std::hint::black_box(s)));
        }
        best = best.min(t0.elapsed().as_secs_f64() * 1e9 / samples.len() as f64);
    }
    best
}

fn small_kernels() {
    use fepr_core::material::project_psd;
    use fepr_core::material::Hyperelastic;
    use fepr_core::math::{
        matmul, polar_rotation, polar_rotation_svd, symmetric_eigen, symmetric_eigen3,
        symmetric_eigen_fixed, transpose, Mat3,
    };
    // Deterministic deformation gradients: a rotation about a varying axis times a stretch within 10%.
    let fs: Vec<Mat3> = (0..20_000)
        .map(|k| {
            let t = k as f64;
            let (a, b, c) = ((0.37 * t).sin(), (0.11 * t).cos(), (0.23 * t).sin());
            let s = [
                [1.0 + 0.1 * a, 0.03 * b, 0.02 * c],
                [0.03 * b, 1.0 - 0.08 * c, 0.04 * a],
                [0.02 * c, 0.04 * a, 1.0 + 0.09 * b],
            ];
            let (ca, sa) = (t.cos(), t.sin());
            let r = [[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]];
            matmul(&r, &s)
        })
        .collect();
    let ftf: Vec<Mat3> = fs.iter().map(|f| matmul(&transpose(f), f)).collect();
    let nh = NeoHookean::new(1e5, 0.3).unwrap();
    let ds: Vec<_> = fs.iter().map(|f| nh.stress_derivative(f)).collect();
    println!(
        "polar_rotation (Newton)     {:8.1} ns",
        time_ns(&fs, polar_rotation)
    );
    let mut rs = vec![[[0.0; 3]; 3]; fs.len()];
    let batch = time_ns(&[()], |_| fepr_core::math::polar_rotations(&fs, &mut rs));
    println!(
        "polar_rotations (batched)   {:8.1} ns",
        batch / fs.len() as f64
    );
    println!(
        "polar_rotation_svd (Jacobi) {:8.1} ns",
        time_ns(&fs, polar_rotation_svd)
    );
    println!(
        "symmetric_eigen3            {:8.1} ns",
        time_ns(&ftf, symmetric_eigen3)
    );
    println!(
        "symmetric_eigen (general) 3 {:8.1} ns",
        time_ns(&ftf, |a| symmetric_eigen(a.as_flattened(), 3))
    );
    println!(
        "NeoHookean dP/dF            {:8.1} ns",
        time_ns(&fs, |f| nh.stress_derivative(f))
    );
    println!(
        "symmetric_eigen_fixed 9     {:8.1} ns",
        time_ns(&ds, symmetric_eigen_fixed)
    );
    println!(
        "symmetric_eigen (general) 9 {:8.1} ns",
        time_ns(&ds, |a| symmetric_eigen(a.as_flattened(), 9))
    );
    println!(
        "project_psd (NH dP/dF)      {:8.1} ns",
        time_ns(&ds, project_psd)
    );
    println!(
        "NH stress_derivative_psd    {:8.1} ns",
        time_ns(&fs, |f| nh.stress_derivative_psd(f))
    );
}

/// Backward Euler that prints its Newton decrements after every step.
struct Verbose(fepr_core::integrators::ImplicitEuler);

impl fepr_core::integrators::Integrator for Verbose {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn is_implicit(&self) -> bool {
        true
    }
    fn step(
        &mut self,
        model: &fepr_core::model::Model,
        state: &mut fepr_core::model::State,
        dt: f64,
        hand_over: &mut fepr_core::integrators::HandOver,
    ) -> fepr_core::integrators::StepReport {
        let t0 = Instant::now();
        let r = self.0.step(model, state, dt, hand_over);
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        let d0 = self.0.last_decrements.first().copied().unwrap_or(0.0);
        let rel: Vec<String> = self
            .0
            .last_decrements
            .iter()
            .map(|d| format!("{:.1e}", d / d0))
            .collect();
        println!(
            "{ms:.0} ms, {} iterations, {} halvings, decrement0 {d0:.3e}, relative: {}",
            r.iterations,
            r.line_search_steps,
            rel.join(" ")
        );
        r
    }
}

/// The mesh `STEM.node`/`STEM.ele` with `material`, 1000 kg/m^3, stretched 10% about its centre of mass (the
/// integrators issue's bunny set-up).
fn stretched_study_model(
    stem: &str,
    material: Material,
) -> (fepr_core::model::Model, fepr_core::model::State) {
    let model = ModelBuilder::new(
        load_tetgen(std::path::Path::new(stem)).expect("readable TetGen mesh STEM.node/STEM.ele"),
        material,
    )
    .mass(MassSpec::Density(1000.0))
    .build()
    .unwrap();
    let mut state = fepr_core::model::State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
    for p in state.x.iter_mut() {
        *p = [0, 1, 2].map(|a| c[a] + 1.1 * (p[a] - c[a]));
    }
    (model, state)
}

fn newton_study(stem: &str, steps: usize, project: bool) {
    use fepr_core::integrators::{ImplicitEuler, NewtonSettings};
    let (model, state) = stretched_study_model(
        stem,
        Material::NeoHookean(NeoHookean::new(1e5, 0.3).unwrap()),
    );
    let ie = Verbose(ImplicitEuler::new(NewtonSettings::default()).unwrap());
    let projector = project.then(|| {
        fepr_core::projection::Projector::new(Default::default()).expect("default projection")
    });
    let mut sim =
        fepr_core::simulation::Simulation::new(model, state, Box::new(ie), 1.0 / 30.0, projector)
            .unwrap();
    for step in 0..steps {
        print!("step {step}: ");
        let d = sim.step().unwrap();
        if let Some(p) = &d.projection {
            println!("    projection: {} iterations", p.iterations);
        }
    }
}

/// The projection's targets that keep the invariants `inv` (no impulses).
fn targets_at(inv: &fepr_core::invariants::Invariants) -> fepr_core::projection::Targets {
    fepr_core::projection::Targets {
        energy: inv.total,
        momentum: inv.momentum,
        angular_momentum: inv.angular_momentum,
        center_of_mass: inv.center_of_mass,
        energy_scale: inv.total.abs(),
        uncertain_impulses: false,
    }
}

/// The projection right after a backward Euler step (its caches cold from the Newton solve) against the same
/// projection again at once (warm): microseconds per elastic evaluation of each, over steps 10-59 of the
/// set-up of `newton_study` on `threads` threads.
fn cold_projection_study(stem: &str, threads: usize) {
    use fepr_core::integrators::Integrator;
    use fepr_core::integrators::{ImplicitEuler, NewtonSettings};
    use fepr_core::invariants::measure;
    use fepr_core::projection::Projector;
    let material = Material::NeoHookean(NeoHookean::new(1e5, 0.3).unwrap());
    let (model, mut state) = stretched_study_model(stem, material);
    let inv = measure(&model, &state);
    let targets = targets_at(&inv);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let mut ie = ImplicitEuler::new(NewtonSettings::default()).unwrap();
        let mut proj = Projector::new(Default::default()).unwrap();
        proj.set_implicit_base(true);
        let h = 1.0 / 30.0;
        // (seconds, evaluations) of the cold and of the warm projections.
        let mut totals = [(0.0, 0); 2];
        for step in 0..60 {
            let mut base = state.clone();
            ie.step(
                &model,
                &mut base,
                h,
                &mut fepr_core::integrators::HandOver::new(),
            );
            let mut results = Vec::with_capacity(2);
            for total in totals.iter_mut() {
                let mut s = base.clone();
                let t0 = Instant::now();
                let (report, _) = proj.project(&model, &mut s, h, &targets);
                if step >= 10 {
                    total.0 += t0.elapsed().as_secs_f64();
                    total.1 += report.evaluations;
                }
                results.push(s);
            }
            state = results.swap_remove(0);
        }
        let per = |(t, n): (f64, usize)| t * 1e6 / n.max(1) as f64;
        println!(
            "threads {threads}: cold {:.1} us per evaluation, warm {:.1} ({} and {} evaluations)",
            per(totals[0]),
            per(totals[1]),
            totals[0].1,
            totals[1].1
        );
    });
}

/// Projective Dynamics (10 iterations) on a TetGen mesh as in `newton_study`, but with the
/// ARAP material; prints ms per step and the phase times (`fepr` after STEPS: with the FEPR projection).
struct TimedPd(fepr_core::integrators::ProjectiveDynamics);

impl fepr_core::integrators::Integrator for TimedPd {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn check(&self, model: &fepr_core::model::Model) -> fepr_core::error::Result<()> {
        self.0.check(model)
    }
    fn is_implicit(&self) -> bool {
        true
    }
    fn step(
        &mut self,
        model: &fepr_core::model::Model,
        state: &mut fepr_core::model::State,
        dt: f64,
        hand_over: &mut fepr_core::integrators::HandOver,
    ) -> fepr_core::integrators::StepReport {
        let r = self.0.step(model, state, dt, hand_over);
        let t = self.0.timing;
        print!(
            "local {:.2} ms, rhs {:.2} ms, solve {:.2} ms; ",
            t.local * 1e3,
            t.rhs * 1e3,
            t.solve * 1e3
        );
        r
    }
}

/// The vertex-graph Cholesky of `model` (a Laplacian-like SPD matrix): size, fill, solve time with 3
/// right-hand sides.
fn solve_study(model: &fepr_core::model::Model, rounds: usize) {
    use fepr_core::math::SparseCholesky;
    let n = model.num_vertices();
    let pattern = common::vertex_pattern(model);
    let mut values = vec![-1e-3; pattern.nnz()];
    for c in 0..n {
        values[pattern.position(c, c).unwrap()] = 100.0;
    }
    let mut chol = SparseCholesky::analyse(&pattern, 3).unwrap();
    chol.factorize(&values).unwrap();
    let mut rhs = vec![1.0; 3 * n];
    let t0 = Instant::now();
    for _ in 0..50 {
        chol.solve_in_place(&mut rhs, 3);
    }
    let faer_ms = t0.elapsed().as_secs_f64() * 1e3 / 50.0;
    // The 3-column solve: the sequential walk, the parallel one inside pools of 1 and 2 threads and from
    // the main thread (outside the pools, as PD calls it); rounds alternate (a noisy machine), best of each.
    let mut rhs3 = vec![[1.0; 3]; n];
    let pools = [1, 2].map(|k| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(k)
            .build()
            .unwrap()
    });
    let mut best = [f64::INFINITY; 4];
    for _ in 0..rounds {
        for (v, b) in best.iter_mut().enumerate() {
            let mut run = || {
                // x is about b / 100: restart from b = 1 so that no round reaches subnormal numbers.
                rhs3.fill([1.0; 3]);
                let t0 = Instant::now();
                for _ in 0..20 {
                    match v {
                        0 => chol.solve3_in_place_sequential(&mut rhs3),
                        _ => chol.solve3_in_place(&mut rhs3),
                    }
                }
                t0.elapsed().as_secs_f64() * 1e3 / 20.0
            };
            let ms = match v {
                0 | 3 => run(),
                _ => pools[v - 1].install(run),
            };
            *b = b.min(ms);
        }
    }
    let (tasks, rest) = chol.solve3_plan_work();
    let total = tasks.iter().sum::<usize>() + rest;
    let pct = |w: usize| format!("{:.1}", 100.0 * w as f64 / total as f64);
    println!(
        "vertex Cholesky: n {n}, nnz(A lower) {}, nnz(L) {}, solve with 3 rhs: faer {faer_ms:.3} ms, \
         interleaved sequential {:.3} ms, parallel 1 thread {:.3} ms, 2 threads {:.3} ms, \
         {} threads from the main thread {:.3} ms",
        pattern.nnz(),
        chol.factor_nnz(),
        best[0],
        best[1],
        best[2],
        rayon::current_num_threads(),
        best[3],
    );
    println!(
        "  solve plan: {} tasks, work % of nnz(L): rest {}, tasks [{}]",
        tasks.len(),
        pct(rest),
        tasks.iter().map(|&w| pct(w)).collect::<Vec<_>>().join(" ")
    );
}

fn pd_study(stem: &str, steps: usize, project: bool) {
    use fepr_core::material::Arap;
    let (model, state) = stretched_study_model(stem, Material::Arap(Arap::new(1e5, 0.3).unwrap()));
    solve_study(&model, 5);
    let pd = TimedPd(fepr_core::integrators::ProjectiveDynamics::default());
    // The Python layer's default after PD: warm start always (`Projection(warm_start="auto")`).
    let settings = fepr_core::projection::ProjectionSettings {
        warm_start_threshold: 0.0,
        ..Default::default()
    };
    let projector = project
        .then(|| fepr_core::projection::Projector::new(settings).expect("default projection"));
    let mut sim =
        fepr_core::simulation::Simulation::new(model, state, Box::new(pd), 1.0 / 30.0, projector)
            .unwrap();
    let mut total = 0.0;
    for step in 0..steps {
        let t0 = Instant::now();
        let d = *sim.step().unwrap();
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        if step > 0 {
            total += ms;
        }
        let its = d.projection.map_or(0, |p| p.iterations);
        println!("step {step}: {ms:.1} ms (projection {its} iterations)");
    }
    println!(
        "mean after the first: {:.1} ms/step",
        total / (steps - 1).max(1) as f64
    );
    // The polar decompositions of the final state, batched and one by one.
    let fs: Vec<fepr_core::math::Mat3> = (0..sim.model.num_tets())
        .map(|e| fepr_core::elasticity::deformation_gradient(&sim.model, &sim.state.x, e))
        .collect();
    let inverted = fs.iter().filter(|f| fepr_core::math::det(f) <= 0.0).count();
    let mut rs = vec![[[0.0; 3]; 3]; fs.len()];
    let batched = time_ns(&[()], |_| fepr_core::math::polar_rotations(&fs, &mut rs));
    let scalar = time_ns(&fs, fepr_core::math::polar_rotation);
    println!(
        "final state: {} tets ({inverted} inverted): polar batched {:.1} ns/tet, scalar {:.1} ns/tet",
        fs.len(),
        batched / fs.len() as f64,
        scalar
    );
}

/// The vertex Cholesky study of `pd_study` alone, `rounds` rounds.
fn solve_only_study(stem: &str, rounds: usize, _: bool) {
    use fepr_core::material::Arap;
    let (model, _) = stretched_study_model(stem, Material::Arap(Arap::new(1e5, 0.3).unwrap()));
    solve_study(&model, rounds);
}

/// A study on a TetGen mesh: `(stem, steps, with FEPR)`.
type Study = fn(&str, usize, bool);

fn main() {
    let raw: Vec<String> = std::env::args().skip(1).collect();
    if raw.first().map(String::as_str) == Some("becold") {
        let threads = raw.get(2).and_then(|s| s.parse().ok()).unwrap_or(2);
        cold_projection_study(&raw[1], threads);
        return;
    }
    if raw.first().map(String::as_str) == Some("small") {
        small_kernels();
        return;
    }
    // `pd STEM STEPS [fepr]` and `newton STEM STEPS [fepr]`: the studies on a TetGen mesh.
    let study: Option<(Study, usize)> = match raw.first().map(String::as_str) {
        Some("pd") => Some((pd_study, 10)),
        Some("newton") => Some((newton_study, 3)),
        Some("solve") => Some((solve_only_study, 20)),
        _ => None,
    };
    if let Some((run, default_steps)) = study {
        let steps = raw
            .get(2)
            .and_then(|s| s.parse().ok())
            .unwrap_or(default_steps);
        run(
            &raw[1],
            steps,
            raw.get(3).map(String::as_str) == Some("fepr"),
        );
        return;
    }
    if raw.first().map(String::as_str) == Some("proj") {
        let num =
            |i: usize, default: usize| raw.get(i).and_then(|s| s.parse().ok()).unwrap_or(default);
        let mesh = load_tetgen(std::path::Path::new(&raw[1])).expect("a TetGen mesh");
        time_projection(mesh, num(2, 1), num(3, 200));
        return;
    }
    if raw.first().map(String::as_str) == Some("sim") {
        let num =
            |i: usize, default: usize| raw.get(i).and_then(|s| s.parse().ok()).unwrap_or(default);
        let mesh = load_tetgen(std::path::Path::new(&raw[1])).expect("a TetGen mesh");
        time_simulation(mesh, num(2, 1), num(3, 2000));
        return;
    }
    if raw.first().map(String::as_str) == Some("eg") {
        let num =
            |i: usize, default: usize| raw.get(i).and_then(|s| s.parse().ok()).unwrap_or(default);
        let mesh = load_tetgen(std::path::Path::new(&raw[1])).expect("a TetGen mesh");
        time_energy_gradient(mesh, num(2, 1), num(3, 200));
        return;
    }
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let n = args.first().copied().unwrap_or(26);
    let threads = args.get(1).copied().unwrap_or(1);
    let repeats = args.get(2).copied().unwrap_or(200);
    let idx = |i: usize, j: usize, k: usize| (i + (n + 1) * (j + (n + 1) * k)) as i64;
    let mut v = Vec::new();
    for k in 0..=n {
        for j in 0..=n {
            for i in 0..=n {
                v.push([i as f64, j as f64, k as f64].map(|c| c / n as f64));
            }
        }
    }
    let cube: [[i64; 4]; 6] = [
        [0, 1, 3, 7],
        [0, 3, 2, 7],
        [0, 2, 6, 7],
        [0, 6, 4, 7],
        [0, 4, 5, 7],
        [0, 5, 1, 7],
    ];
    let mut t = Vec::new();
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let c = |c: i64| {
                    idx(
                        i + (c & 1) as usize,
                        j + ((c >> 1) & 1) as usize,
                        k + ((c >> 2) & 1) as usize,
                    )
                };
                for ct in &cube {
                    t.push(ct.map(c));
                }
            }
        }
    }
    time_energy_gradient(TetMesh::new(v, &t).unwrap().0, threads, repeats);
}

/// Times the energy + gradient of `mesh` (Neo-Hookean E = 1e3 Pa, nu = 0.3, 0.05 kg per node) at a 5% stretch,
/// inside a pool of `threads` threads (ns per tet).
fn time_energy_gradient(mesh: TetMesh, threads: usize, repeats: usize) {
    let model = &bench_model(mesh);
    let x: Vec<_> = model
        .mesh
        .vertices()
        .iter()
        .map(|p| p.map(|c| 1.05 * c))
        .collect();
    let mut grad = vec![[0.0; 3]; x.len()];
    let mut ws = ElasticWorkspace::default();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        elastic_energy_gradient(model, &x, &mut ws, &mut grad);
        let t0 = Instant::now();
        for _ in 0..repeats {
            elastic_energy_gradient(model, &x, &mut ws, &mut grad);
        }
        let dt = t0.elapsed().as_secs_f64() / repeats as f64;
        println!(
            "tets {} threads {threads}: {:.1} ns/tet",
            model.num_tets(),
            dt * 1e9 / model.num_tets() as f64
        );
    });
}

/// Times `Projector::project` on the state after one symplectic Euler step from the set-up of
/// [`time_energy_gradient`] (targets: the invariants of the initial state), the same input every call.
/// Steps a `Simulation` as `fepr bench` does (symplectic Euler + FEPR, dt = 1 ms, released from a 5% stretch
/// about the centroid; bench_model) for `steps` steps in a pool of `threads` threads, and prints the base
/// step's and the projection's time per step (mean and the best of ten batches, as `fepr bench` takes
/// `it/EG`), the iterations, and the energy + gradient in the same pool for the ratio.
fn time_simulation(mesh: TetMesh, threads: usize, steps: usize) {
    use fepr_core::integrators::SymplecticEuler;
    use fepr_core::model::State;
    use fepr_core::projection::{ProjectionSettings, Projector};
    use fepr_core::simulation::Simulation;
    let model = bench_model(mesh);
    let mut start = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &start.x);
    for p in start.x.iter_mut() {
        *p = [0, 1, 2].map(|a| c[a] + 1.05 * (p[a] - c[a]));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let x = start.x.clone();
        let proj = Projector::new(ProjectionSettings::default()).unwrap();
        let integ = Box::new(SymplecticEuler::new());
        let mut sim = Simulation::new(model, start, integ, 1e-3, Some(proj)).unwrap();
        for _ in 0..20 {
            sim.step().unwrap();
        }
        let n0 = sim.num_steps();
        for _ in 0..steps {
            sim.step().unwrap();
        }
        let h = &sim.history()[n0 + 1..];
        let mean = |f: &dyn Fn(&fepr_core::simulation::StepDiagnostics) -> f64| {
            h.iter().map(f).sum::<f64>() / h.len() as f64
        };
        let iters = |d: &fepr_core::simulation::StepDiagnostics| {
            d.projection.map_or(0.0, |p| p.iterations as f64)
        };
        let best_batch = h
            .chunks(h.len().div_ceil(10))
            .map(|b| {
                let t: f64 = b.iter().map(|d| d.proj_ms).sum();
                let u: f64 = b.iter().map(|d| 1.0 + iters(d)).sum();
                t / u
            })
            .fold(f64::INFINITY, f64::min);
        let (mut grad, mut ws) = (vec![[0.0; 3]; x.len()], ElasticWorkspace::default());
        let mut eg = f64::INFINITY;
        for _ in 0..10 {
            let t0 = Instant::now();
            for _ in 0..50 {
                std::hint::black_box(elastic_energy_gradient(&sim.model, &x, &mut ws, &mut grad));
            }
            eg = eg.min(t0.elapsed().as_secs_f64() * 1e3 / 50.0);
        }
        println!(
            "tets {} threads {threads}: base {:.4} ms, projection {:.4} ms per step, {:.2} iterations; \
             E+G {eg:.4} ms; it/EG (best batch) {:.3}, (mean) {:.3}",
            sim.model.num_tets(),
            mean(&|d| d.base_ms),
            mean(&|d| d.proj_ms),
            mean(&iters),
            best_batch / eg,
            mean(&|d| d.proj_ms) / (1.0 + mean(&iters)) / eg,
        );
    });
}

fn time_projection(mesh: TetMesh, threads: usize, repeats: usize) {
    use fepr_core::integrators::{Integrator, SymplecticEuler};
    use fepr_core::invariants::measure;
    use fepr_core::model::State;
    use fepr_core::projection::{ProjectionSettings, Projector};
    let model = bench_model(mesh);
    let mut start = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &start.x);
    for p in start.x.iter_mut() {
        *p = [0, 1, 2].map(|a| c[a] + 1.05 * (p[a] - c[a]));
    }
    let inv = measure(&model, &start);
    let targets = targets_at(&inv);
    let h = 1e-3;
    let mut base = start.clone();
    SymplecticEuler::new().step(
        &model,
        &mut base,
        h,
        &mut fepr_core::integrators::HandOver::new(),
    );
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let mut proj = Projector::new(ProjectionSettings::default()).unwrap();
        let mut state = base.clone();
        let (report, _) = proj.project(&model, &mut state, h, &targets);
        let mut times = Vec::with_capacity(repeats);
        for _ in 0..repeats {
            state.x.copy_from_slice(&base.x);
            state.v.copy_from_slice(&base.v);
            let t0 = Instant::now();
            std::hint::black_box(proj.project(&model, &mut state, h, &targets));
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        let (mut grad, mut ws) = (vec![[0.0; 3]; start.x.len()], ElasticWorkspace::default());
        let mut eg = Vec::with_capacity(repeats);
        for _ in 0..repeats {
            let t0 = Instant::now();
            std::hint::black_box(elastic_energy_gradient(&model, &base.x, &mut ws, &mut grad));
            eg.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        for t in [&mut times, &mut eg] {
            t.sort_by(f64::total_cmp);
        }
        let (best, median) = (times[0], times[repeats / 2]);
        println!(
            "tets {} threads {threads}: projection {best:.3} / {median:.3} ms (best / median), {} iterations, {} evaluations; \
             E+G {:.3} / {:.3} ms; per evaluation / E+G (best) {:.2}",
            model.num_tets(),
            report.iterations,
            report.evaluations,
            eg[0],
            eg[repeats / 2],
            best / report.evaluations as f64 / eg[0]
        );
    });
}
