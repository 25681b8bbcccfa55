//! Fill and factorisation time of the sparse Cholesky with AMD vs METIS nested dissection, on the vertex
//! graph of tet meshes at Projective Dynamics size (m x m) and Newton size (3m x 3m):
//! `cargo bench -p fepr-core --bench ordering [-- STEM ...]` (prints a table; meshes as in `kernels`, plus any
//! TetGen `STEM.node`/`STEM.ele` given as arguments).

use std::path::PathBuf;
use std::time::Instant;

mod common;
use common::load_tetgen;

use fepr_core::math::{FillOrdering, LowerPattern, SparseCholesky};
use fepr_core::mesh::TetMesh;

fn box_mesh(n: usize) -> TetMesh {
    let idx = |i: usize, j: usize, k: usize| (i + (n + 1) * (j + (n + 1) * k)) as i64;
    let mut v = Vec::new();
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
    let mut t = Vec::new();
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

/// Vertex-graph pattern with `b` dofs per vertex, and SPD values (Laplacian + identity).
fn pattern(mesh: &TetMesh, b: usize) -> (LowerPattern, Vec<f64>) {
    let n = b * mesh.num_vertices();
    let mut cols = vec![Vec::new(); n];
    for t in mesh.tets() {
        for &p in t {
            for &q in t {
                for a in 0..b {
                    for c in 0..b {
                        let (i, j) = (b * p + a, b * q + c);
                        if j > i {
                            cols[i].push(j);
                        }
                    }
                }
            }
        }
    }
    let pat = LowerPattern::from_columns(n, cols);
    let mut values = vec![0.0; pat.nnz()];
    let mut diag = vec![1.0; n];
    for c in 0..n {
        for k in pat.col_ptr[c] + 1..pat.col_ptr[c + 1] {
            values[k] = -0.1;
            diag[c] += 0.1;
            diag[pat.row_idx[k]] += 0.1;
        }
    }
    for c in 0..n {
        values[pat.col_ptr[c]] = diag[c];
    }
    (pat, values)
}

fn main() {
    let mut meshes = vec![
        ("box_10k".to_string(), box_mesh(12)),
        ("box_100k".to_string(), box_mesh(26)),
    ];
    let root =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/meshes/seed/bunny2.1");
    if let Some(m) = load_tetgen(&root) {
        meshes.insert(1, ("bunny2".to_string(), m));
    }
    // Extra TetGen meshes given as arguments (path stems without .node/.ele).
    for stem in std::env::args().skip(1).filter(|a| !a.starts_with('-')) {
        if let Some(m) = load_tetgen(std::path::Path::new(&stem)) {
            let name = std::path::Path::new(&stem)
                .file_name()
                .map_or(stem.clone(), |n| n.to_string_lossy().into_owned());
            meshes.push((name, m));
        }
    }
    println!(
        "{:<10} {:>3} {:>8} {:>7} {:>12} {:>10} {:>11} {:>10} {:>7}",
        "mesh", "b", "n", "order", "nnz(L)", "analyse ms", "factor ms", "solve ms", "fill x"
    );
    for (name, mesh) in &meshes {
        for b in [1, 3] {
            let (pat, values) = pattern(mesh, b);
            let mut amd_nnz = 0;
            for ord in [FillOrdering::Amd, FillOrdering::NestedDissection] {
                let t0 = Instant::now();
                let mut chol = SparseCholesky::analyse_with(&pat, 3, ord).unwrap();
                let analyse = t0.elapsed().as_secs_f64() * 1e3;
                let reps = 3;
                let mut factor = f64::INFINITY;
                for _ in 0..reps {
                    let t0 = Instant::now();
                    chol.factorize(&values).unwrap();
                    factor = factor.min(t0.elapsed().as_secs_f64() * 1e3);
                }
                let mut rhs = vec![1.0; 3 * pat.n];
                let t0 = Instant::now();
                chol.solve_in_place(&mut rhs, 3);
                let solve = t0.elapsed().as_secs_f64() * 1e3;
                if ord == FillOrdering::Amd {
                    amd_nnz = chol.factor_nnz();
                }
                println!(
                    "{name:<10} {b:>3} {:>8} {:>7} {:>12} {analyse:>10.1} {factor:>11.1} {solve:>10.2} {:>7.2}",
                    pat.n,
                    if ord == FillOrdering::Amd { "amd" } else { "nd" },
                    chol.factor_nnz(),
                    chol.factor_nnz() as f64 / amd_nnz as f64
                );
            }
        }
    }
}
