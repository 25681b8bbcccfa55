//! Criterion benchmarks of the kernels: elastic energy + gradient (1 thread and all threads), one symplectic
//! Euler step, one FEPR projection, and the sparse Cholesky factorisations (fill-reducing ordering).
//!
//! `cargo bench -p fepr-core --bench kernels` (add `-- energy` to run a subset). Meshes: built-in boxes
//! (6 tets per cell) and, when present, `../shared/meshes/seed/bunny2.1.{node,ele}` beside the repository.

use std::hint::black_box;
use std::path::PathBuf;

mod common;
use common::{bench_model as model, load_tetgen, vertex_pattern};

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use fepr_core::elasticity::{elastic_energy_gradient, ElasticWorkspace};
use fepr_core::integrators::{Integrator, SymplecticEuler};
use fepr_core::math::Vec3;
use fepr_core::math::{LowerPattern, SparseCholesky};
use fepr_core::mesh::TetMesh;
use fepr_core::model::{Model, State};
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;

/// An `n x n x n` box of unit size, 6 tets per cell (the layout of `fepr.meshes.box`).
fn box_mesh(n: usize) -> TetMesh {
    let idx = |i: usize, j: usize, k: usize| (i + (n + 1) * (j + (n + 1) * k)) as i64;
    let mut v = Vec::with_capacity((n + 1).pow(3));
    for k in 0..=n {
        for j in 0..=n {
            for i in 0..=n {
                v.push([i as f64, j as f64, k as f64].map(|c| c / n as f64));
            }
        }
    }
    const CUBE: [[i64; 4]; 6] = [
        [0, 1, 3, 7],
        [0, 3, 2, 7],
        [0, 2, 6, 7],
        [0, 6, 4, 7],
        [0, 4, 5, 7],
        [0, 5, 1, 7],
    ];
    let mut t = Vec::with_capacity(6 * n * n * n);
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let corner = |c: i64| {
                    idx(
                        i + (c & 1) as usize,
                        j + ((c >> 1) & 1) as usize,
                        k + ((c >> 2) & 1) as usize,
                    )
                };
                for ct in &CUBE {
                    t.push(ct.map(corner));
                }
            }
        }
    }
    TetMesh::new(v, &t).unwrap().0
}

fn bunny2() -> Option<TetMesh> {
    let root =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/meshes/seed/bunny2.1");
    load_tetgen(&root)
}

/// Stretched by 5% about the centroid (the bench scenes' initial state).
fn stretched(model: &Model) -> Vec<Vec3> {
    let x = model.mesh.vertices();
    let n = x.len() as f64;
    let c = [0, 1, 2].map(|a| x.iter().map(|p| p[a]).sum::<f64>() / n);
    x.iter()
        .map(|p| [0, 1, 2].map(|a| c[a] + 1.05 * (p[a] - c[a])))
        .collect()
}

fn scenes() -> Vec<(String, Model)> {
    let mut s = vec![
        ("box_10k".to_string(), model(box_mesh(12))),
        ("box_100k".to_string(), model(box_mesh(26))),
    ];
    if let Some(b) = bunny2() {
        s.push(("bunny2".to_string(), model(b)));
    }
    s
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

fn energy_gradient(c: &mut Criterion) {
    let mut g = c.benchmark_group("energy_gradient");
    let all = std::thread::available_parallelism().map_or(1, |n| n.get());
    for (name, model) in scenes() {
        let x = stretched(&model);
        let mut grad = vec![[0.0; 3]; x.len()];
        let mut ws = ElasticWorkspace::default();
        g.throughput(Throughput::Elements(model.num_tets() as u64));
        for threads in [1, all] {
            let p = pool(threads);
            g.bench_function(BenchmarkId::new(format!("{name}/threads"), threads), |b| {
                p.install(|| {
                    b.iter(|| elastic_energy_gradient(&model, black_box(&x), &mut ws, &mut grad))
                })
            });
        }
    }
    g.finish();
}

fn steps(c: &mut Criterion) {
    let mut g = c.benchmark_group("step");
    g.sample_size(20);
    for (name, model) in scenes() {
        let x = stretched(&model);
        g.throughput(Throughput::Elements(model.num_tets() as u64));
        let mut state = State::at_rest(&model);
        state.x.clone_from(&x);
        let mut se = SymplecticEuler::new();
        g.bench_function(BenchmarkId::new("symplectic_euler", &name), |b| {
            b.iter(|| {
                se.step(
                    &model,
                    &mut state,
                    1e-3,
                    &mut fepr_core::integrators::HandOver::new(),
                );
            })
        });
        let mut state = State::at_rest(&model);
        state.x.clone_from(&x);
        let proj = Projector::new(ProjectionSettings::default()).unwrap();
        let mut sim = Simulation::new(
            model.clone(),
            state,
            Box::new(SymplecticEuler::new()),
            1e-3,
            Some(proj),
        )
        .unwrap();
        g.bench_function(BenchmarkId::new("symplectic_euler_fepr", &name), |b| {
            b.iter(|| {
                sim.step().unwrap();
            })
        });
    }
    g.finish();
}

/// A graph Laplacian plus a mass-like diagonal on the pattern: SPD.
fn laplacian_values(p: &LowerPattern) -> Vec<f64> {
    let mut values = vec![0.0; p.nnz()];
    let mut diag = vec![1.0; p.n];
    for c in 0..p.n {
        for k in p.col_ptr[c] + 1..p.col_ptr[c + 1] {
            values[k] = -1.0;
            diag[c] += 1.0;
            diag[p.row_idx[k]] += 1.0;
        }
    }
    for c in 0..p.n {
        values[p.col_ptr[c]] = diag[c];
    }
    values
}

fn cholesky(c: &mut Criterion) {
    let mut g = c.benchmark_group("cholesky");
    g.sample_size(10);
    for (name, model) in scenes() {
        let p = vertex_pattern(&model);
        let values = laplacian_values(&p);
        let mut chol = SparseCholesky::analyse(&p, 3).unwrap();
        g.bench_function(BenchmarkId::new("factorize_m", &name), |b| {
            b.iter(|| chol.factorize(&values).unwrap())
        });
        // Factorised here too, so that the solve bench also runs when filtered on its own.
        chol.factorize(&values).unwrap();
        let mut rhs = vec![1.0; 3 * p.n];
        g.bench_function(BenchmarkId::new("solve_m_3rhs", &name), |b| {
            b.iter(|| chol.solve_in_place(&mut rhs, 3))
        });
    }
    g.finish();
}

criterion_group!(benches, energy_gradient, steps, cholesky);
criterion_main!(benches);
