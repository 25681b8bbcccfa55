//! Mesh-level elastic energy `E_el(x) = sum_e V_e Psi(F_e)` and its gradient, parallel over tets and
//! deterministic: per-tet results go to a per-tet buffer, then each vertex gathers its slots in a fixed
//! order (no floating-point atomics), and energies are summed over fixed chunks in chunk order. The
//! result is bit-identical for any number of threads.
//!
//! Per tet: `D_s = [x1-x0, x2-x0, x3-x0]`, `F = D_s D_m^-1`, gradient on vertices 1..3 = the columns of
//! `V P(F) D_m^-T`, vertex 0 gets minus their sum (fepr-spec section 4).

use rayon::prelude::*;

use crate::linalg::{det, matmul, transpose, Mat3, Vec3};
use crate::material::Hyperelastic;
use crate::mesh::edge_matrix;
use crate::model::Model;
use crate::parallel::{reduce_chunks, TET_CHUNK};

/// Energy and element-health summary of one evaluation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ElasticSummary {
    /// Elastic energy, J.
    pub energy: f64,
    /// Smallest `J = det F` over all tets.
    pub min_j: f64,
    /// Number of tets with `J <= 0` (inverted or flat).
    pub inverted: usize,
}

impl ElasticSummary {
    fn zero() -> Self {
        Self {
            energy: 0.0,
            min_j: f64::INFINITY,
            inverted: 0,
        }
    }
    fn combine(a: Self, b: Self) -> Self {
        Self {
            energy: a.energy + b.energy,
            min_j: a.min_j.min(b.min_j),
            inverted: a.inverted + b.inverted,
        }
    }
}

/// Scratch memory for gradient evaluations (reused across calls, no allocation in the step loop).
#[derive(Clone, Debug, Default)]
pub struct ElasticWorkspace {
    element_gradients: Vec<[Vec3; 4]>,
}

/// Deformation gradient of tet `e`.
#[inline]
pub fn deformation_gradient(model: &Model, x: &[Vec3], e: usize) -> Mat3 {
    let t = &model.mesh.tets()[e];
    matmul(&edge_matrix(x, t), &model.rest.dm_inv[e])
}

/// Elastic energy only (no gradient), J.
pub fn elastic_energy(model: &Model, x: &[Vec3]) -> ElasticSummary {
    let k = model.num_tets();
    reduce_chunks(
        k,
        TET_CHUNK,
        |range| {
            let mut s = ElasticSummary::zero();
            for e in range {
                let f = deformation_gradient(model, x, e);
                let j = det(&f);
                s.energy += model.rest.volume[e] * model.material.energy_density(&f);
                s.min_j = s.min_j.min(j);
                s.inverted += (j <= 0.0) as usize;
            }
            s
        },
        ElasticSummary::combine,
    )
    .unwrap_or_else(ElasticSummary::zero)
}

/// Elastic energy and its gradient `dE_el/dx` (written to `grad`, shape (m, 3), J/m).
pub fn elastic_energy_gradient(
    model: &Model,
    x: &[Vec3],
    ws: &mut ElasticWorkspace,
    grad: &mut [Vec3],
) -> ElasticSummary {
    let k = model.num_tets();
    ws.element_gradients.resize(k, [[0.0; 3]; 4]);
    let parts: Vec<ElasticSummary> = ws
        .element_gradients
        .par_chunks_mut(TET_CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let mut s = ElasticSummary::zero();
            for (i, out) in chunk.iter_mut().enumerate() {
                let e = c * TET_CHUNK + i;
                let f = deformation_gradient(model, x, e);
                let j = det(&f);
                let vol = model.rest.volume[e];
                let (psi, p) = model.material.energy_and_stress(&f);
                s.energy += vol * psi;
                s.min_j = s.min_j.min(j);
                s.inverted += (j <= 0.0) as usize;
                // H = V P D_m^-T; its columns are the gradients on vertices 1..3.
                let h = matmul(&p, &transpose(&model.rest.dm_inv[e]));
                let mut g0 = [0.0; 3];
                for a in 0..3 {
                    for b in 0..3 {
                        let gab = vol * h[b][a];
                        out[a + 1][b] = gab;
                        g0[b] -= gab;
                    }
                }
                out[0] = g0;
            }
            s
        })
        .collect();
    let summary = parts
        .into_iter()
        .fold(ElasticSummary::zero(), ElasticSummary::combine);
    gather(model, &ws.element_gradients, grad);
    summary
}

/// Sum per-tet corner values into vertices, in the fixed incidence order.
fn gather(model: &Model, element_values: &[[Vec3; 4]], out: &mut [Vec3]) {
    let offsets = &model.incidence_offsets;
    let slots = &model.incidence_slots;
    out.par_iter_mut().enumerate().for_each(|(i, g)| {
        let mut acc = [0.0; 3];
        for &slot in &slots[offsets[i]..offsets[i + 1]] {
            let s = slot as usize;
            let v = element_values[s / 4][s % 4];
            acc[0] += v[0];
            acc[1] += v[1];
            acc[2] += v[2];
        }
        *g = acc;
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::{Material, NeoHookean, StableNeoHookean};
    use crate::mesh::{tests::cube, MassSpec, TetMesh};
    use crate::model::ModelBuilder;

    pub(crate) fn grid_model(n: usize, material: Material) -> Model {
        // An n x n x n grid of cubes, each cut into 6 tets around its main diagonal (conforming).
        let idx = |i: usize, j: usize, k: usize| (i + (n + 1) * (j + (n + 1) * k)) as i64;
        let mut v = Vec::new();
        for k in 0..=n {
            for j in 0..=n {
                for i in 0..=n {
                    v.push([
                        i as f64 / n as f64,
                        j as f64 / n as f64,
                        k as f64 / n as f64,
                    ]);
                }
            }
        }
        let (_, cube_tets) = cube();
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
                    for ct in &cube_tets {
                        t.push([corner(ct[0]), corner(ct[1]), corner(ct[2]), corner(ct[3])]);
                    }
                }
            }
        }
        let (mesh, _) = TetMesh::new(v, &t).unwrap();
        ModelBuilder::new(mesh, material)
            .mass(MassSpec::Density(1000.0))
            .build()
            .unwrap()
    }

    fn deformed(model: &Model, seed: u64) -> Vec<Vec3> {
        let mut s = seed;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        model
            .mesh
            .vertices()
            .iter()
            .map(|p| {
                [
                    1.1 * p[0] + 0.05 * rnd(),
                    0.95 * p[1] + 0.05 * rnd() + 0.1 * p[0],
                    p[2] + 0.05 * rnd(),
                ]
            })
            .collect()
    }

    fn materials() -> Vec<Material> {
        vec![
            Material::NeoHookean(NeoHookean::new(1e4, 0.3).unwrap()),
            Material::StableNeoHookean(StableNeoHookean::new(1e4, 0.4).unwrap()),
        ]
    }

    #[test]
    fn mesh_gradient_matches_finite_differences() {
        for mat in materials() {
            let model = grid_model(3, mat);
            let x = deformed(&model, 7);
            let mut grad = vec![[0.0; 3]; x.len()];
            let mut ws = ElasticWorkspace::default();
            elastic_energy_gradient(&model, &x, &mut ws, &mut grad);
            let h = 1e-6;
            let gmax = grad.iter().flatten().fold(0.0f64, |a, b| a.max(b.abs()));
            for i in 0..x.len() {
                for a in 0..3 {
                    let mut xp = x.clone();
                    xp[i][a] += h;
                    let mut xm = x.clone();
                    xm[i][a] -= h;
                    let fd = (elastic_energy(&model, &xp).energy
                        - elastic_energy(&model, &xm).energy)
                        / (2.0 * h);
                    assert!(
                        (fd - grad[i][a]).abs() <= 1e-6 * gmax,
                        "vertex {i} axis {a}: fd {fd} vs {}",
                        grad[i][a]
                    );
                }
            }
        }
    }

    #[test]
    fn energy_is_invariant_under_rigid_motion() {
        for mat in materials() {
            let model = grid_model(3, mat);
            let x = deformed(&model, 3);
            let e0 = elastic_energy(&model, &x).energy;
            let (c, s) = (0.6f64.cos(), 0.6f64.sin());
            // rotation about an oblique axis: Rz(0.6) * Rx(0.6), then a far translation
            let rot = |p: Vec3| {
                let q = [p[0], c * p[1] - s * p[2], s * p[1] + c * p[2]];
                [
                    c * q[0] - s * q[1] + 100.0,
                    s * q[0] + c * q[1] - 50.0,
                    q[2] + 25.0,
                ]
            };
            let xr: Vec<Vec3> = x.iter().map(|p| rot(*p)).collect();
            let e1 = elastic_energy(&model, &xr).energy;
            assert!((e1 - e0).abs() <= 1e-9 * e0.abs(), "{e0} vs {e1}");
            assert!(e0 > 0.0);
        }
    }

    #[test]
    fn energy_and_gradient_are_bit_identical_for_any_thread_count() {
        let model = grid_model(12, materials()[0]);
        let x = deformed(&model, 11);
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    let mut grad = vec![[0.0; 3]; x.len()];
                    let mut ws = ElasticWorkspace::default();
                    let s = elastic_energy_gradient(&model, &x, &mut ws, &mut grad);
                    (
                        s.energy.to_bits(),
                        elastic_energy(&model, &x).energy.to_bits(),
                        grad.iter()
                            .flatten()
                            .map(|g| g.to_bits())
                            .collect::<Vec<_>>(),
                    )
                })
        };
        let one = run(1);
        assert_eq!(one, run(2));
        assert_eq!(one, run(4));
    }

    #[test]
    fn rest_state_has_zero_energy_and_gradient() {
        let model = grid_model(2, materials()[0]);
        let x = model.mesh.vertices().to_vec();
        let mut grad = vec![[0.0; 3]; x.len()];
        let s = elastic_energy_gradient(&model, &x, &mut ElasticWorkspace::default(), &mut grad);
        assert!(s.energy.abs() < 1e-10);
        assert!((s.min_j - 1.0).abs() < 1e-12);
        assert!(grad.iter().flatten().all(|g| g.abs() < 1e-9));
    }
}
