//! Mesh-level elastic energy `E_el(x) = sum_e V_e Psi(F_e)` and its gradient, parallel over tets and
//! deterministic: per-tet results go to a per-tet buffer, then each vertex gathers its slots in a fixed
//! order (no floating-point atomics), and energies are summed over fixed chunks in chunk order. The
//! result is bit-identical for any number of threads.
//!
//! Per tet: `D_s = [x1-x0, x2-x0, x3-x0]`, `F = D_s D_m^-1`, gradient on vertices 1..3 = the columns of
//! `V P(F) D_m^-T`, vertex 0 gets minus their sum (fepr-spec section 4).

use rayon::prelude::*;

use crate::linalg::{det, matmul, transpose, Mat3, Vec3};
use crate::material::{Hyperelastic, Material, NeoHookean, LANES};
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

/// Scratch memory for gradient evaluations (reused across calls, no allocation in the step loop): the
/// gradients on the 4 corners of every tet.
#[derive(Clone, Debug, Default)]
pub struct ElasticWorkspace {
    element_gradients: Vec<[Vec3; 4]>,
    /// Per-chunk partial summaries, combined in chunk order.
    partials: Vec<ElasticSummary>,
}

impl ElasticWorkspace {
    /// Bytes held by the workspace.
    pub fn bytes(&self) -> usize {
        self.element_gradients.capacity() * std::mem::size_of::<[Vec3; 4]>()
            + self.partials.capacity() * std::mem::size_of::<ElasticSummary>()
    }
}

/// Deformation gradient of tet `e`.
#[inline]
pub fn deformation_gradient(model: &Model, x: &[Vec3], e: usize) -> Mat3 {
    let t = &model.mesh.tets()[e];
    matmul(&edge_matrix(x, t), &model.rest.dm_inv[e])
}

/// Call `$body` with `$m` bound to the concrete material, so that the per-tet loops are compiled once per
/// material (no per-tet dispatch).
macro_rules! with_material {
    ($model:expr, $m:ident => $body:expr) => {
        match &$model.material {
            Material::NeoHookean($m) => $body,
            Material::StableNeoHookean($m) => $body,
            Material::Arap($m) => $body,
            #[allow(unreachable_patterns)]
            $m => $body,
        }
    };
}

/// Elastic energy only (no gradient), J.
pub fn elastic_energy(model: &Model, x: &[Vec3]) -> ElasticSummary {
    match &model.material {
        Material::NeoHookean(nh) => neo_hookean_energy(nh, model, x),
        _ => with_material!(model, mat => energy_impl(mat, model, x)),
    }
}

/// Energy only, with the batched Neo-Hookean kernel (bit-identical to [`energy_impl`]).
fn neo_hookean_energy(nh: &NeoHookean, model: &Model, x: &[Vec3]) -> ElasticSummary {
    #[cfg(target_arch = "x86_64")]
    let avx2 = std::arch::is_x86_feature_detected!("avx2");
    reduce_chunks(
        model.num_tets(),
        TET_CHUNK,
        |range| {
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: the CPU supports AVX2 (checked above); the function is otherwise safe.
                return unsafe {
                    neo_hookean_chunk_avx2::<false>(nh, model, x, range.start, &mut [], range.len())
                };
            }
            neo_hookean_chunk::<false>(nh, model, x, range.start, &mut [], range.len())
        },
        ElasticSummary::combine,
    )
    .unwrap_or_else(ElasticSummary::zero)
}

fn energy_impl<M: Hyperelastic + Sync>(mat: &M, model: &Model, x: &[Vec3]) -> ElasticSummary {
    let k = model.num_tets();
    let (tets, dm_inv, volume) = (model.mesh.tets(), &model.rest.dm_inv, &model.rest.volume);
    reduce_chunks(
        k,
        TET_CHUNK,
        |range| {
            let mut s = ElasticSummary::zero();
            let (mut f, mut psi) = ([[[0.0; 3]; 3]; LANES], [0.0; LANES]);
            for e0 in range.clone().step_by(LANES) {
                // Full groups go through the material's batched call; the last, partial one per tet.
                let n = LANES.min(range.end - e0);
                for l in 0..n {
                    f[l] = matmul(&edge_matrix(x, &tets[e0 + l]), &dm_inv[e0 + l]);
                }
                if n == LANES {
                    mat.energy_density_lanes(&f, &mut psi);
                } else {
                    for l in 0..n {
                        psi[l] = mat.energy_density(&f[l]);
                    }
                }
                for l in 0..n {
                    let j = det(&f[l]);
                    s.energy += volume[e0 + l] * psi[l];
                    s.min_j = s.min_j.min(j);
                    s.inverted += (j <= 0.0) as usize;
                }
            }
            s
        },
        ElasticSummary::combine,
    )
    .unwrap_or_else(ElasticSummary::zero)
}

/// Elastic energy and its gradient `dE_el/dx` (written to `grad`, shape (m, 3), J/m).
///
/// Two passes: a per-tet pass over fixed chunks (energy density, stress, the corner gradients into the
/// workspace) and a per-vertex gather in the fixed incidence order (ascending tet index). Both are
/// parallel; neither depends on the thread count, so the result is bit-identical for any thread count.
pub fn elastic_energy_gradient(
    model: &Model,
    x: &[Vec3],
    ws: &mut ElasticWorkspace,
    grad: &mut [Vec3],
) -> ElasticSummary {
    let k = model.num_tets();
    if ws.element_gradients.len() != k {
        ws.element_gradients.resize(k, [[0.0; 3]; 4]);
    }
    let (out, parts) = (&mut ws.element_gradients, &mut ws.partials);
    let summary = match &model.material {
        Material::NeoHookean(nh) => neo_hookean_pass(nh, model, x, out, parts),
        _ => with_material!(model, mat => element_pass(mat, model, x, out, parts)),
    };
    gather(model, &ws.element_gradients, grad);
    summary
}

/// Partial summaries of fixed chunks, written in place (no allocation once `parts` has grown), then
/// combined in chunk order.
fn chunked_pass<F>(
    out: &mut [[Vec3; 4]],
    parts: &mut Vec<ElasticSummary>,
    chunk_fn: F,
) -> ElasticSummary
where
    F: Fn(usize, &mut [[Vec3; 4]]) -> ElasticSummary + Sync,
{
    parts.clear();
    parts.resize(out.len().div_ceil(TET_CHUNK), ElasticSummary::zero());
    out.par_chunks_mut(TET_CHUNK)
        .zip(parts.par_iter_mut())
        .enumerate()
        .for_each(|(c, (chunk, part))| *part = chunk_fn(c, chunk));
    parts.iter().fold(ElasticSummary::zero(), |a, b| {
        ElasticSummary::combine(a, *b)
    })
}

fn element_pass<M: Hyperelastic + Sync>(
    mat: &M,
    model: &Model,
    x: &[Vec3],
    out: &mut [[Vec3; 4]],
    parts: &mut Vec<ElasticSummary>,
) -> ElasticSummary {
    let (tets, dm_inv, volume) = (model.mesh.tets(), &model.rest.dm_inv, &model.rest.volume);
    chunked_pass(out, parts, |c, chunk| {
        let base = c * TET_CHUNK;
        let mut s = ElasticSummary::zero();
        let (mut f, mut psi, mut p) =
            ([[[0.0; 3]; 3]; LANES], [0.0; LANES], [[[0.0; 3]; 3]; LANES]);
        for k0 in (0..chunk.len()).step_by(LANES) {
            // Full groups go through the material's batched call; the last, partial one per tet.
            let n = LANES.min(chunk.len() - k0);
            for l in 0..n {
                let e = base + k0 + l;
                f[l] = matmul(&edge_matrix(x, &tets[e]), &dm_inv[e]);
            }
            if n == LANES {
                mat.energy_and_stress_lanes(&f, &mut psi, &mut p);
            } else {
                for l in 0..n {
                    (psi[l], p[l]) = mat.energy_and_stress(&f[l]);
                }
            }
            for l in 0..n {
                let e = base + k0 + l;
                let (vol, j) = (volume[e], det(&f[l]));
                s.energy += vol * psi[l];
                s.min_j = s.min_j.min(j);
                s.inverted += (j <= 0.0) as usize;
                // H = V P D_m^-T; its columns are the gradients on vertices 1..3.
                let h = matmul(&p[l], &transpose(&dm_inv[e]));
                write_corners(&h, vol, &mut chunk[k0 + l]);
            }
        }
        s
    })
}

/// The Neo-Hookean element pass, in blocks of [`BLOCK`] tets. The arithmetic mirrors
/// [`NeoHookean::energy_and_stress`] operation by operation (no fused multiply-adds), so every lane gives
/// bit-for-bit the scalar result (gated by a test); only the scheduling differs.
fn neo_hookean_pass(
    nh: &NeoHookean,
    model: &Model,
    x: &[Vec3],
    out: &mut [[Vec3; 4]],
    parts: &mut Vec<ElasticSummary>,
) -> ElasticSummary {
    #[cfg(target_arch = "x86_64")]
    let avx2 = std::arch::is_x86_feature_detected!("avx2");
    chunked_pass(out, parts, |c, chunk| {
        #[cfg(target_arch = "x86_64")]
        if avx2 {
            // SAFETY: the CPU supports AVX2 (checked above); the function is otherwise safe.
            let n = chunk.len();
            return unsafe {
                neo_hookean_chunk_avx2::<true>(nh, model, x, c * TET_CHUNK, chunk, n)
            };
        }
        let n = chunk.len();
        neo_hookean_chunk::<true>(nh, model, x, c * TET_CHUNK, chunk, n)
    })
}

/// [`neo_hookean_chunk`] compiled for AVX2 (wider lanes; no FMA, so the results are the same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn neo_hookean_chunk_avx2<const GRAD: bool>(
    nh: &NeoHookean,
    model: &Model,
    x: &[Vec3],
    base: usize,
    chunk: &mut [[Vec3; 4]],
    len: usize,
) -> ElasticSummary {
    neo_hookean_chunk::<GRAD>(nh, model, x, base, chunk, len)
}

/// One chunk of tets `base..base + len`, in blocks of [`BLOCK`], the remainder one by one. With `GRAD`
/// the corner gradients go to `chunk` (length `len`); without, only the summary is computed.
#[inline(always)]
fn neo_hookean_chunk<const GRAD: bool>(
    nh: &NeoHookean,
    model: &Model,
    x: &[Vec3],
    base: usize,
    chunk: &mut [[Vec3; 4]],
    len: usize,
) -> ElasticSummary {
    let (tets, dm_inv, volume) = (model.mesh.tets(), &model.rest.dm_inv, &model.rest.volume);
    let mut s = ElasticSummary::zero();
    let full = len - len % BLOCK;
    let mut scratch = [[[0.0; 3]; 4]; BLOCK];
    let mut w = BlockScratch::new();
    for e0 in (base..base + full).step_by(BLOCK) {
        let out: &mut [[Vec3; 4]; BLOCK] = if GRAD {
            (&mut chunk[e0 - base..e0 - base + BLOCK])
                .try_into()
                .expect("exact block")
        } else {
            &mut scratch
        };
        neo_hookean_block::<GRAD>(
            nh,
            tets[e0..e0 + BLOCK].try_into().expect("in range"),
            dm_inv[e0..e0 + BLOCK].try_into().expect("in range"),
            volume[e0..e0 + BLOCK].try_into().expect("in range"),
            x,
            out,
            &mut s,
            &mut w,
        );
    }
    for e in base + full..base + len {
        if GRAD {
            element_scalar(
                nh,
                &tets[e],
                &dm_inv[e],
                volume[e],
                x,
                &mut chunk[e - base],
                &mut s,
            );
        } else {
            let f = matmul(&edge_matrix(x, &tets[e]), &dm_inv[e]);
            let j = det(&f);
            s.energy += volume[e] * nh.energy_density(&f);
            s.min_j = s.min_j.min(j);
            s.inverted += (j <= 0.0) as usize;
        }
    }
    s
}

/// One tet through the generic material interface (the reference the batched kernel must match).
#[inline(always)]
fn element_scalar<M: Hyperelastic>(
    mat: &M,
    t: &[usize; 4],
    dmi: &Mat3,
    vol: f64,
    x: &[Vec3],
    out: &mut [Vec3; 4],
    s: &mut ElasticSummary,
) {
    let f = matmul(&edge_matrix(x, t), dmi);
    let j = det(&f);
    let (psi, p) = mat.energy_and_stress(&f);
    s.energy += vol * psi;
    s.min_j = s.min_j.min(j);
    s.inverted += (j <= 0.0) as usize;
    let h = matmul(&p, &transpose(dmi));
    write_corners(&h, vol, out);
}

/// Tets per block of the Neo-Hookean kernel: the block's data lives in structure-of-arrays form in a
/// scratch struct (in L1), so each pass is a plain loop over the block that the compiler turns into SIMD lanes.
const BLOCK: usize = 16;
type Block = [f64; BLOCK];

/// Per-block arrays, allocated once per chunk (every field is overwritten by each block before it is read).
struct BlockScratch {
    ds: [[Block; 3]; 3],
    dm: [[Block; 3]; 3],
    f: [[Block; 3]; 3],
    p: [[Block; 3]; 3],
    h: [[Block; 3]; 3],
    jd: Block,
    lg: Block,
    dl: Block,
    ic: Block,
    psi: Block,
    dg: Block,
}

impl BlockScratch {
    fn new() -> Self {
        let z = [0.0; BLOCK];
        let m = [[z; 3]; 3];
        Self {
            ds: m,
            dm: m,
            f: m,
            p: m,
            h: m,
            jd: z,
            lg: z,
            dl: z,
            ic: z,
            psi: z,
            dg: z,
        }
    }
}

/// One block of [`BLOCK`] tets. Three passes: geometry (`F`, `J`), the logarithms (scalar calls with nothing
/// else live), then energy, stress and corner gradients. Every operation mirrors
/// [`NeoHookean::energy_and_stress`] (and `linalg::{matmul, det, cofactor, ddot}`) in order, without fused
/// multiply-adds, so the results are bit-for-bit those of the scalar path (gated by a test).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn neo_hookean_block<const GRAD: bool>(
    nh: &NeoHookean,
    t: &[[usize; 4]; BLOCK],
    dmi: &[Mat3; BLOCK],
    vol: &[f64; BLOCK],
    x: &[Vec3],
    out: &mut [[Vec3; 4]; BLOCK],
    s: &mut ElasticSummary,
    w: &mut BlockScratch,
) {
    let BlockScratch {
        ds,
        dm,
        f,
        p,
        h,
        jd,
        lg,
        dl,
        ic,
        psi,
        dg,
    } = w;
    // Pass 1: D_s[i][c] = x_{c+1}[i] - x_0[i] and D_m^-1, block-last; F = D_s D_m^-1; J = det F.
    for l in 0..BLOCK {
        let x0 = x[t[l][0]];
        for c in 0..3 {
            let xc = x[t[l][c + 1]];
            for i in 0..3 {
                ds[i][c][l] = xc[i] - x0[i];
                dm[i][c][l] = dmi[l][i][c];
            }
        }
    }
    for i in 0..3 {
        for j in 0..3 {
            for l in 0..BLOCK {
                f[i][j][l] = ds[i][0][l] * dm[0][j][l]
                    + ds[i][1][l] * dm[1][j][l]
                    + ds[i][2][l] * dm[2][j][l];
            }
        }
    }
    for l in 0..BLOCK {
        jd[l] = f[0][0][l] * (f[1][1][l] * f[2][2][l] - f[1][2][l] * f[2][1][l])
            - f[0][1][l] * (f[1][0][l] * f[2][2][l] - f[1][2][l] * f[2][0][l])
            + f[0][2][l] * (f[1][0][l] * f[2][1][l] - f[1][1][l] * f[2][0][l]);
    }
    // Pass 2: the extended logarithm l(J) and l'(J) (NeoHookean::extended_log).
    let (mu, lambda, j0) = (nh.mu, nh.lambda, nh.j0);
    for l in 0..BLOCK {
        let j = jd[l];
        (lg[l], dl[l]) = if j >= j0 {
            (j.ln(), 1.0 / j)
        } else {
            let d = j - j0;
            (
                j0.ln() + d / j0 - d * d / (2.0 * j0 * j0),
                1.0 / j0 - d / (j0 * j0),
            )
        };
    }
    // Pass 3: energy density (I_C as linalg::ddot), summary in tet order.
    for l in 0..BLOCK {
        ic[l] = 0.0;
    }
    for i in 0..3 {
        for j in 0..3 {
            for l in 0..BLOCK {
                ic[l] += f[i][j][l] * f[i][j][l];
            }
        }
    }
    for l in 0..BLOCK {
        let g = -mu * lg[l] + 0.5 * lambda * lg[l] * lg[l];
        dg[l] = (-mu + lambda * lg[l]) * dl[l];
        psi[l] = 0.5 * mu * (ic[l] - 3.0) + g;
    }
    for l in 0..BLOCK {
        s.energy += vol[l] * psi[l];
        s.min_j = s.min_j.min(jd[l]);
        s.inverted += (jd[l] <= 0.0) as usize;
    }
    if !GRAD {
        return;
    }
    // P = mu F + g'(J) cof(F), with cof[i][k] = f[a][b] f[c][d] - f[a][d] f[c][b] for the index pairs of
    // linalg::cofactor.
    const PAIRS: [[(usize, usize, usize, usize); 3]; 3] = [
        [(1, 1, 2, 2), (1, 2, 2, 0), (1, 0, 2, 1)],
        [(0, 2, 2, 1), (0, 0, 2, 2), (0, 1, 2, 0)],
        [(0, 1, 1, 2), (0, 2, 1, 0), (0, 0, 1, 1)],
    ];
    for i in 0..3 {
        for k in 0..3 {
            let (a, b, c, d) = PAIRS[i][k];
            for l in 0..BLOCK {
                let cof = f[a][b][l] * f[c][d][l] - f[a][d][l] * f[c][b][l];
                p[i][k][l] = mu * f[i][k][l] + dg[l] * cof;
            }
        }
    }
    // H = V P D_m^-T; its columns are the gradients on corners 1..3: h[b][a] = sum_k p[b][k] dm_inv[a][k].
    for a in 0..3 {
        for b in 0..3 {
            for l in 0..BLOCK {
                h[a][b][l] = vol[l]
                    * (p[b][0][l] * dm[a][0][l]
                        + p[b][1][l] * dm[a][1][l]
                        + p[b][2][l] * dm[a][2][l]);
            }
        }
    }
    // Corner 0 gets minus the sum of corners 1..3 (in that order, as the scalar path).
    for b in 0..3 {
        for l in 0..BLOCK {
            p[0][b][l] = 0.0 - h[0][b][l] - h[1][b][l] - h[2][b][l];
        }
    }
    for l in 0..BLOCK {
        out[l][0] = [p[0][0][l], p[0][1][l], p[0][2][l]];
        for a in 0..3 {
            for b in 0..3 {
                out[l][a + 1][b] = h[a][b][l];
            }
        }
    }
}

/// Corner gradients from `H = P D_m^-T`: corners 1..3 are the columns of `V H`, corner 0 minus their sum.
#[inline(always)]
fn write_corners(h: &Mat3, vol: f64, out: &mut [Vec3; 4]) {
    for a in 0..3 {
        for b in 0..3 {
            out[a + 1][b] = vol * h[b][a];
        }
    }
    for b in 0..3 {
        out[0][b] = 0.0 - out[1][b] - out[2][b] - out[3][b];
    }
}

/// Vertices per parallel task in the gather.
const VERTEX_CHUNK: usize = 512;

/// Sum per-tet corner values into vertices, in the fixed incidence order (ascending tet index).
fn gather(model: &Model, element_values: &[[Vec3; 4]], out: &mut [Vec3]) {
    let offsets = &model.incidence_offsets;
    let slots = &model.incidence_slots;
    let flat = element_values.as_flattened();
    out.par_chunks_mut(VERTEX_CHUNK)
        .enumerate()
        .for_each(|(c, chunk)| {
            let first = c * VERTEX_CHUNK;
            for (i, g) in chunk.iter_mut().enumerate() {
                let v = first + i;
                let mut acc = [0.0; 3];
                for &slot in &slots[offsets[v]..offsets[v + 1]] {
                    let val = flat[slot as usize];
                    acc[0] += val[0];
                    acc[1] += val[1];
                    acc[2] += val[2];
                }
                *g = acc;
            }
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
    fn batched_neo_hookean_matches_the_material_interface_bit_for_bit() {
        // Large random perturbations: many tets below j0 = 0.1 and some inverted, so both branches of the
        // extended logarithm run; 3^3 * 6 = 162 tets is not a multiple of the batch (remainder path too).
        let mat = NeoHookean::new(1e4, 0.3).unwrap();
        let model = grid_model(3, Material::NeoHookean(mat));
        for seed in [1, 5, 9] {
            let mut x = deformed(&model, seed);
            for (i, p) in x.iter_mut().enumerate() {
                let w = (i as f64 * 1.7).sin();
                p[2] *= 0.05 + 0.9 * w * w;
            }
            let k = model.num_tets();
            let mut a = vec![[[0.0; 3]; 4]; k];
            let mut b = vec![[[0.0; 3]; 4]; k];
            let sa = neo_hookean_pass(&mat, &model, &x, &mut a, &mut Vec::new());
            let sb = element_pass(&mat, &model, &x, &mut b, &mut Vec::new());
            assert!(sa.inverted > 0 && sa.min_j < mat.j0, "{sa:?}");
            assert_eq!(sa.energy.to_bits(), sb.energy.to_bits());
            assert_eq!(sa.min_j.to_bits(), sb.min_j.to_bits());
            assert_eq!(sa.inverted, sb.inverted);
            let bits = |v: &Vec<[Vec3; 4]>| -> Vec<u64> {
                v.iter().flatten().flatten().map(|g| g.to_bits()).collect()
            };
            assert_eq!(bits(&a), bits(&b));
            let ea = neo_hookean_energy(&mat, &model, &x);
            let eb = energy_impl(&mat, &model, &x);
            assert_eq!(ea.energy.to_bits(), eb.energy.to_bits());
            assert_eq!(
                (ea.min_j.to_bits(), ea.inverted),
                (eb.min_j.to_bits(), eb.inverted)
            );
            assert_eq!(ea.energy.to_bits(), sa.energy.to_bits());
        }
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
