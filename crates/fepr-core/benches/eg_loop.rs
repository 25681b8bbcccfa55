//! A plain timing loop over the elastic energy + gradient (for `perf stat` / `perf record`):
//! `cargo bench -p fepr-core --bench eg_loop -- CELLS THREADS REPEATS` (a CELLS^3 box, 6 tets per cell).

use std::time::Instant;

use fepr_core::elasticity::{elastic_energy_gradient, ElasticWorkspace};
use fepr_core::material::{Material, NeoHookean};
use fepr_core::mesh::{MassSpec, TetMesh};
use fepr_core::model::ModelBuilder;

fn main() {
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
    let mesh = TetMesh::new(v, &t).unwrap().0;
    let model = ModelBuilder::new(
        mesh,
        Material::NeoHookean(NeoHookean::new(1e3, 0.3).unwrap()),
    )
    .mass(MassSpec::NodeMass(0.05))
    .build()
    .unwrap();
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
        elastic_energy_gradient(&model, &x, &mut ws, &mut grad);
        let t0 = Instant::now();
        for _ in 0..repeats {
            elastic_energy_gradient(&model, &x, &mut ws, &mut grad);
        }
        let dt = t0.elapsed().as_secs_f64() / repeats as f64;
        println!(
            "tets {} threads {threads}: {:.1} ns/tet",
            model.num_tets(),
            dt * 1e9 / model.num_tets() as f64
        );
    });
}
