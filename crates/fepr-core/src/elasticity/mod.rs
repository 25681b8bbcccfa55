//! Mesh-level elastic energy `E_el(x) = sum_e V_e Psi(F_e)` and its gradient, parallel over tets and
//! deterministic: each fixed chunk of tets reads its vertices' positions from a local copy and adds its
//! corner gradients into its vertices in a fixed order (`corner_sums`: no per-tet buffer, no floating-point
//! atomics), and energies are summed over the chunks in chunk order. The result is bit-identical for any
//! number of threads.
//!
//! Per tet: `D_s = [x1-x0, x2-x0, x3-x0]`, `F = D_s D_m^-1`, gradient on vertices 1..3 = the columns of
//! `V P(F) D_m^-T`, vertex 0 gets minus their sum (fepr-spec section 4).
//!
//! Length: about 670 lines of code and 440 of tests (finite-difference gates of every material, every lane width
//! against the per-tet path); the batched kernel and the per-tet pass it must match bit for bit stay together.

mod hessian;
mod rotation;

pub use hessian::*;
pub(crate) use rotation::*;

use std::ops::Range;

use crate::exec::reduce_chunks;
use crate::material::{ln, ln_core, ln_core_applies, Hyperelastic, Material, NeoHookean, LANES};
use crate::math::simd::{self, Kernel};
use crate::math::{det, matmul, transpose, Mat3, Vec3, COFACTOR_PAIRS};
use crate::mesh::edge_matrix;
use crate::model::{Block, Model, TetBlock, TetBlocks, BLOCK};

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

impl Default for ElasticSummary {
    /// The summary of no tets (the identity of combining): energy 0, `min_j` infinite, none inverted.
    fn default() -> Self {
        Self::zero()
    }
}

impl ElasticSummary {
    pub(crate) fn zero() -> Self {
        Self {
            energy: 0.0,
            min_j: f64::INFINITY,
            inverted: 0,
        }
    }
    pub(crate) fn combine(a: Self, b: Self) -> Self {
        Self {
            energy: a.energy + b.energy,
            min_j: a.min_j.min(b.min_j),
            inverted: a.inverted + b.inverted,
        }
    }

    /// The summary of `0..num_tets` from `map` over fixed chunks of `chunk` tets, combined in chunk order
    /// (`parallel::reduce_chunks`; the chunks' summaries in this thread's reused buffer: no allocation once
    /// it has grown, as the energy-only passes run inside the step loop).
    pub(crate) fn over_chunks(
        num_tets: usize,
        chunk: usize,
        map: impl Fn(std::ops::Range<usize>) -> Self + Sync,
    ) -> Self {
        thread_local! {
            static PARTS: std::cell::Cell<Vec<ElasticSummary>> = const { std::cell::Cell::new(Vec::new()) };
        }
        // Taken out of the cell, not borrowed: a nested call (none today) would allocate, not panic.
        let mut parts = PARTS.take();
        let sum = reduce_chunks(num_tets, chunk, &mut parts, map, Self::combine);
        PARTS.set(parts);
        sum.unwrap_or_else(Self::zero)
    }
}

/// Scratch memory for energy and gradient evaluations (reused across calls, no allocation in the step loop):
/// the chunks' gradient accumulators (`corner_sums`) and summaries.
#[derive(Clone, Debug, Default)]
pub struct ElasticWorkspace {
    /// Per-chunk vertex sums of the corner gradients (`CornerSums::run`).
    corner_acc: Vec<Vec3>,
    /// Per-chunk partial summaries, combined in chunk order.
    partials: Vec<ElasticSummary>,
}

impl ElasticWorkspace {
    /// Bytes held by the workspace.
    pub fn bytes(&self) -> usize {
        self.partials.capacity() * std::mem::size_of::<ElasticSummary>()
            + self.corner_acc.capacity() * std::mem::size_of::<Vec3>()
    }
}

/// Deformation gradient of tet `e` (a user tet index).
#[inline]
pub fn deformation_gradient(model: &Model, x: &[Vec3], e: usize) -> Mat3 {
    let t = &model.mesh.tets()[e];
    matmul(&edge_matrix(x, t), &model.dm_inv(e))
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
        Material::Arap(arap) => crate::elasticity::arap_energy(arap, model, x),
        _ => with_material!(model, mat => energy_impl(mat, model, x)),
    }
}

/// Energy only, with the batched Neo-Hookean kernel (bit-identical to [`energy_impl`]).
fn neo_hookean_energy(nh: &NeoHookean, model: &Model, x: &[Vec3]) -> ElasticSummary {
    let (blocks, lanes, chunk) = (&model.tet_blocks, Lanes::detect(), model.tet_chunk());
    ElasticSummary::over_chunks(model.num_tets(), chunk, |range| {
        let b = range.start / BLOCK..range.end.div_ceil(BLOCK);
        let c = range.start / chunk;
        (model.corner_sums).with_positions(c, x, |xl| {
            lanes.run::<false>(nh, blocks, b, xl, &mut [], range.len())
        })
    })
}

/// Energy only, per tet through the material interface, summed in the blocks' tet order (as the kernels).
fn energy_impl<M: Hyperelastic + Sync>(mat: &M, model: &Model, x: &[Vec3]) -> ElasticSummary {
    let k = model.num_tets();
    let (tets, volume, tet_at) = (model.mesh.tets(), &model.rest_volume, &model.tet_at);
    ElasticSummary::over_chunks(k, model.tet_chunk(), |range| {
        let mut s = ElasticSummary::zero();
        let (mut f, mut psi) = ([[[0.0; 3]; 3]; LANES], [0.0; LANES]);
        for p0 in range.clone().step_by(LANES) {
            // Full groups go through the material's batched call; the last, partial one per tet.
            let n = LANES.min(range.end - p0);
            for l in 0..n {
                let (p, e) = (p0 + l, tet_at[p0 + l] as usize);
                f[l] = matmul(&edge_matrix(x, &tets[e]), &model.tet_blocks.dm_inv_at(p));
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
                s.energy += volume[tet_at[p0 + l] as usize] * psi[l];
                s.min_j = s.min_j.min(j);
                s.inverted += (j <= 0.0) as usize;
            }
        }
        s
    })
}

/// Elastic energy and its gradient `dE_el/dx` (written to `grad`, shape (m, 3), J/m).
///
/// One parallel pass over fixed chunks of the blocks (energy density, stress, corner gradients added into
/// the chunk's vertices in ascending block position), then the vertices on the chunks' borders are summed
/// in chunk order (`corner_sums`). Neither order depends on the thread count, so the result is
/// bit-identical for any thread count.
pub fn elastic_energy_gradient(
    model: &Model,
    x: &[Vec3],
    ws: &mut ElasticWorkspace,
    grad: &mut [Vec3],
) -> ElasticSummary {
    let summary = elastic_gradient_chunks(model, x, ws);
    ws.gradient_into(model, grad);
    summary
}

/// The per-tet half of [`elastic_energy_gradient`] at `x`: the energy summary, and the chunks' partial
/// gradient sums in `ws` (a caller with its own pass over the vertices sums them there). Vertex `v`'s gradient is then
/// [`ElasticWorkspace::gradient_at`].
pub(crate) fn elastic_gradient_chunks(
    model: &Model,
    x: &[Vec3],
    ws: &mut ElasticWorkspace,
) -> ElasticSummary {
    let sink = GradientSink {
        acc: &mut ws.corner_acc,
        parts: &mut ws.partials,
    };
    match &model.material {
        Material::NeoHookean(nh) => neo_hookean_pass(Lanes::detect(), nh, model, x, sink),
        Material::Arap(arap) => crate::elasticity::arap_gradient_pass(arap, model, x, sink),
        _ => with_material!(model, mat => element_pass(mat, model, x, sink)),
    }
}

impl ElasticWorkspace {
    /// The elastic gradient on every vertex (J/m, into `out`, shape (m, 3)) from the last
    /// [`elastic_gradient_chunks`] of `model`: the vertex pass of [`elastic_energy_gradient`].
    pub(crate) fn gradient_into(&self, model: &Model, out: &mut [Vec3]) {
        model.corner_sums.sums_into(&self.corner_acc, out);
    }

    /// The elastic gradient on user vertex `v` (J/m) from the last [`elastic_gradient_chunks`] of `model`.
    #[inline(always)]
    pub(crate) fn gradient_at(&self, model: &Model, v: usize) -> Vec3 {
        model.corner_sums.vertex_sum(&self.corner_acc, v)
    }
}

/// Where a gradient pass puts its results: the chunks' partial gradient sums and summaries.
pub(crate) struct GradientSink<'a> {
    pub(crate) acc: &'a mut Vec<Vec3>,
    pub(crate) parts: &'a mut Vec<ElasticSummary>,
}

/// A gradient pass at `x` over the model's fixed chunks of tets ([`Model::tet_chunk`]):
/// `chunk_fn(c, xl, acc, len)` reads chunk `c`'s vertex positions from `xl` and adds its corner gradients
/// into its accumulator `acc` (both indexed by local vertex: [`TetBlock::loc`]), and returns its summary;
/// the partial sums stay in `sink.acc` (`CornerSums::chunks`), and the summaries, written in place (no
/// allocation once `parts` has grown), are combined in chunk order.
pub(crate) fn chunked_pass<F>(
    model: &Model,
    x: &[Vec3],
    sink: GradientSink,
    chunk_fn: F,
) -> ElasticSummary
where
    F: Fn(usize, &[Vec3], &mut [Vec3], usize) -> ElasticSummary + Sync,
{
    let (num_tets, chunk) = (model.num_tets(), model.tet_chunk());
    let parts = sink.parts;
    parts.clear();
    parts.resize(num_tets.div_ceil(chunk), ElasticSummary::zero());
    model.corner_sums.chunks(x, sink.acc, parts, |c, xl, acc| {
        chunk_fn(c, xl, acc, (num_tets - c * chunk).min(chunk))
    });
    parts.iter().fold(ElasticSummary::zero(), |a, b| {
        ElasticSummary::combine(a, *b)
    })
}

fn element_pass<M: Hyperelastic + Sync>(
    mat: &M,
    model: &Model,
    x: &[Vec3],
    sink: GradientSink,
) -> ElasticSummary {
    // Tets in block order (position p holds tet tet_at[p]): the chunks and local indices of `corner_sums`.
    let (volume, tet_at, blocks) = (&model.rest_volume, &model.tet_at, &model.tet_blocks);
    let corners = |pos: usize| {
        let loc = &blocks.blocks[pos / BLOCK].loc;
        [0, 1, 2, 3].map(|c| loc[c][pos % BLOCK] as usize)
    };
    let chunk = model.tet_chunk();
    chunked_pass(model, x, sink, |c, xl, acc, len| {
        let first = c * chunk;
        let mut s = ElasticSummary::zero();
        let (mut f, mut psi, mut p) =
            ([[[0.0; 3]; 3]; LANES], [0.0; LANES], [[[0.0; 3]; 3]; LANES]);
        for k0 in (0..len).step_by(LANES) {
            // Full groups go through the material's batched call; the last, partial one per tet.
            let n = LANES.min(len - k0);
            for l in 0..n {
                let pos = first + k0 + l;
                f[l] = matmul(&edge_matrix(xl, &corners(pos)), &blocks.dm_inv_at(pos));
            }
            if n == LANES {
                mat.energy_and_stress_lanes(&f, &mut psi, &mut p);
            } else {
                for l in 0..n {
                    (psi[l], p[l]) = mat.energy_and_stress(&f[l]);
                }
            }
            for l in 0..n {
                let pos = first + k0 + l;
                let (vol, j) = (volume[tet_at[pos] as usize], det(&f[l]));
                s.energy += vol * psi[l];
                s.min_j = s.min_j.min(j);
                s.inverted += (j <= 0.0) as usize;
                // H = V P D_m^-T; its columns are the gradients on vertices 1..3.
                let h = matmul(&p[l], &transpose(&blocks.dm_inv_at(pos)));
                add_corners(&h, vol, corners(pos), acc);
            }
        }
        s
    })
}

/// The Neo-Hookean element pass over the model's [`TetBlocks`]. The arithmetic mirrors
/// [`NeoHookean::energy_and_stress`] operation by operation (no fused multiply-adds), so every lane gives
/// bit-for-bit the scalar result (gated by a test); only the scheduling differs.
fn neo_hookean_pass(
    lanes: Lanes,
    nh: &NeoHookean,
    model: &Model,
    x: &[Vec3],
    sink: GradientSink,
) -> ElasticSummary {
    let (blocks, chunk_blocks) = (&model.tet_blocks, model.tet_chunk() / BLOCK);
    chunked_pass(model, x, sink, |c, xl, acc, len| {
        let first = c * chunk_blocks;
        lanes.run::<true>(nh, blocks, first..first + len.div_ceil(BLOCK), xl, acc, len)
    })
}

/// The SIMD width the batched kernel is compiled for, picked at run time. Every variant runs the same
/// operations in the same order (no fused multiply-adds), so all give the same bits.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Lanes {
    Avx512,
    Avx2,
    Plain,
}

impl Lanes {
    fn detect() -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Lanes::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                return Lanes::Avx2;
            }
        }
        Lanes::Plain
    }

    /// [`neo_hookean_blocks`] at this width (`self` must be supported by the CPU: from [`Lanes::detect`]; a
    /// width the CPU lacks runs the portable build).
    fn run<const GRAD: bool>(
        self,
        nh: &NeoHookean,
        blocks: &TetBlocks,
        range: Range<usize>,
        x: &[Vec3],
        acc: &mut [Vec3],
        len: usize,
    ) -> ElasticSummary {
        let k = BlocksKernel::<GRAD> {
            nh,
            blocks,
            range,
            x,
            acc,
            len,
        };
        match self {
            Lanes::Avx512 => simd::run_avx512(k).unwrap_or_else(Kernel::call),
            Lanes::Avx2 => simd::run_avx2(k),
            Lanes::Plain => k.call(),
        }
    }
}

/// The arguments of [`neo_hookean_blocks`], to be run compiled for a SIMD width (see [`crate::math::simd`]).
struct BlocksKernel<'a, const GRAD: bool> {
    nh: &'a NeoHookean,
    blocks: &'a TetBlocks,
    range: Range<usize>,
    x: &'a [Vec3],
    acc: &'a mut [Vec3],
    len: usize,
}

impl<const GRAD: bool> Kernel for BlocksKernel<'_, GRAD> {
    type Output = ElasticSummary;
    #[inline(always)]
    fn call(self) -> ElasticSummary {
        let BlocksKernel {
            nh,
            blocks,
            range,
            x,
            acc,
            len,
        } = self;
        neo_hookean_blocks::<GRAD>(nh, blocks, range, x, acc, len)
    }
}

/// Consecutive blocks holding `len` tets (the last block may be partial). With `GRAD` the corner gradients
/// are added into `acc` (their chunk's accumulator); without, only the summary is computed.
#[inline(always)]
fn neo_hookean_blocks<const GRAD: bool>(
    nh: &NeoHookean,
    blocks: &TetBlocks,
    range: Range<usize>,
    x: &[Vec3],
    acc: &mut [Vec3],
    len: usize,
) -> ElasticSummary {
    let ln_j0 = ln(nh.j0);
    let mut s = ElasticSummary::zero();
    let mut w = BlockScratch::new();
    for (b, tb) in blocks.blocks[range].iter().enumerate() {
        let valid = (len - b * BLOCK).min(BLOCK);
        neo_hookean_block::<GRAD>(nh, ln_j0, tb, x, acc, valid, &mut s, &mut w);
    }
    s
}

/// Per-block arrays, allocated once per chunk (every field is overwritten by each block before it is read).
/// Cache-line aligned: SIMD loads and stores that straddle lines measured up to 25% slower overall.
#[repr(C, align(64))]
struct BlockScratch {
    ds: [[Block; 3]; 3],
    f: [[Block; 3]; 3],
    p: [[Block; 3]; 3],
    h: [[Block; 3]; 3],
    h0: [Block; 3],
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
            f: m,
            p: m,
            h: m,
            h0: [z; 3],
            jd: z,
            lg: z,
            dl: z,
            ic: z,
            psi: z,
            dg: z,
        }
    }
}

/// One block of [`BLOCK`] tets, of which the first `valid` are real. Three passes: geometry (`F`, `J`),
/// the extended logarithm, then energy, stress and corner gradients. Every operation mirrors
/// [`NeoHookean::energy_and_stress`] (and `linalg::{matmul, det, cofactor, ddot}`) in order, without fused
/// multiply-adds, so the results are bit-for-bit those of the scalar path (gated by a test).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn neo_hookean_block<const GRAD: bool>(
    nh: &NeoHookean,
    ln_j0: f64,
    tb: &TetBlock,
    x: &[Vec3],
    acc: &mut [Vec3],
    valid: usize,
    s: &mut ElasticSummary,
    w: &mut BlockScratch,
) {
    let BlockScratch {
        ds,
        f,
        p,
        h,
        h0,
        jd,
        lg,
        dl,
        ic,
        psi,
        dg,
    } = w;
    let vol = &tb.vol;
    // Pass 1: F = D_s D_m^-1; J = det F.
    block_deformation_gradients(tb, x, ds, f);
    for l in 0..BLOCK {
        jd[l] = f[0][0][l] * (f[1][1][l] * f[2][2][l] - f[1][2][l] * f[2][1][l])
            - f[0][1][l] * (f[1][0][l] * f[2][2][l] - f[1][2][l] * f[2][0][l])
            + f[0][2][l] * (f[1][0][l] * f[2][1][l] - f[1][1][l] * f[2][0][l]);
    }
    // Pass 2: the extended logarithm l(J) and l'(J) (NeoHookean::extended_log with material::ln): the
    // branch-free logarithm in every lane, then the rare lanes below j0 (or with J not a positive normal
    // number) one by one.
    let (mu, lambda, j0) = (nh.mu, nh.lambda, nh.j0);
    let mut rare = false;
    for l in 0..BLOCK {
        let j = jd[l];
        lg[l] = ln_core(j);
        dl[l] = 1.0 / j;
        rare |= !(j >= j0 && ln_core_applies(j));
    }
    if rare {
        extended_log_fixup(j0, ln_j0, jd, lg, dl);
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
    for l in 0..valid {
        s.energy += vol[l] * psi[l];
        s.min_j = s.min_j.min(jd[l]);
        s.inverted += (jd[l] <= 0.0) as usize;
    }
    if !GRAD {
        return;
    }
    // P = mu F + g'(J) cof(F), with cof[i][k] = f[a][b] f[c][d] - f[a][d] f[c][b] for the index pairs of
    // linalg::cofactor.
    for i in 0..3 {
        for k in 0..3 {
            let (a, b, c, d) = COFACTOR_PAIRS[i][k];
            for l in 0..BLOCK {
                let cof = f[a][b][l] * f[c][d][l] - f[a][d][l] * f[c][b][l];
                p[i][k][l] = mu * f[i][k][l] + dg[l] * cof;
            }
        }
    }
    block_corner_rows(p, vol, &tb.dm, h, h0);
    add_corner_rows(h, h0, &tb.loc, valid, acc);
}

/// `F = D_s D_m^-1` of the tets of a block in lanes, with `D_s[i][c] = x_{c+1}[i] - x_0[i]` (as
/// `linalg::matmul(mesh::edge_matrix, dm_inv)`: the same operations, the same bits). `x`: the positions of
/// the block's chunk in local order (`CornerSums::with_positions`), as [`TetBlock::loc`] indexes them.
#[inline(always)]
pub(crate) fn block_deformation_gradients(
    tb: &TetBlock,
    x: &[Vec3],
    ds: &mut [[Block; 3]; 3],
    f: &mut [[Block; 3]; 3],
) {
    let dm = &tb.dm;
    // Bounds-checked loads on purpose: without the checks LLVM turns this loop into AVX-512 gathers, which
    // are far slower here than scalar loads (microcode-mitigated gathers; measured 30% slower overall).
    for l in 0..BLOCK {
        let x0 = x[tb.loc[0][l] as usize];
        for c in 0..3 {
            let xc = x[tb.loc[c + 1][l] as usize];
            for i in 0..3 {
                ds[i][c][l] = xc[i] - x0[i];
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
}

/// The corner values of a block from a per-tet matrix `p`, by component: corner `a + 1`, component `b` of
/// lane `l` at `h[a][b][l]` (the columns of `scale P D_m^-T`: `scale * sum_k p[b][k] dm_inv[a][k]`, as
/// `write_corners(matmul(p, transpose(dm_inv)), scale)`), corner 0 at `h0[b][l]`, minus their sum in that
/// order.
#[inline(always)]
pub(crate) fn block_corner_rows(
    p: &[[Block; 3]; 3],
    scale: &Block,
    dm: &[[Block; 3]; 3],
    h: &mut [[Block; 3]; 3],
    h0: &mut [Block; 3],
) {
    for a in 0..3 {
        for b in 0..3 {
            for l in 0..BLOCK {
                h[a][b][l] = scale[l]
                    * (p[b][0][l] * dm[a][0][l]
                        + p[b][1][l] * dm[a][1][l]
                        + p[b][2][l] * dm[a][2][l]);
            }
        }
    }
    for b in 0..3 {
        for l in 0..BLOCK {
            h0[b][l] = 0.0 - h[0][b][l] - h[1][b][l] - h[2][b][l];
        }
    }
}

/// Adds the corner values of a block's first `valid` tets (`h`, `h0` as from [`block_corner_rows`]) into
/// their chunk's accumulator at the corners' local indices `loc`, tet after tet (ascending block position).
#[inline(always)]
pub(crate) fn add_corner_rows(
    h: &[[Block; 3]; 3],
    h0: &[Block; 3],
    loc: &[[u16; BLOCK]; 4],
    valid: usize,
    acc: &mut [Vec3],
) {
    for l in 0..valid {
        let a = &mut acc[loc[0][l] as usize];
        for i in 0..3 {
            a[i] += h0[i][l];
        }
        for c in 0..3 {
            let a = &mut acc[loc[c + 1][l] as usize];
            for i in 0..3 {
                a[i] += h[c][i][l];
            }
        }
    }
}

/// The lanes of a block where the branch-free logarithm does not apply: below `j0` the C2 extension (as
/// `NeoHookean::extended_log`), and `f64::ln` where `J >= j0` is not a positive normal number.
#[cold]
#[inline(never)]
fn extended_log_fixup(j0: f64, ln_j0: f64, jd: &Block, lg: &mut Block, dl: &mut Block) {
    for l in 0..BLOCK {
        let j = jd[l];
        if j >= j0 {
            if !ln_core_applies(j) {
                lg[l] = j.ln();
            }
        } else {
            let d = j - j0;
            lg[l] = ln_j0 + d / j0 - d * d / (2.0 * j0 * j0);
            dl[l] = 1.0 / j0 - d / (j0 * j0);
        }
    }
}

/// Corner gradients from `H = P D_m^-T` of one tet added into its chunk's accumulator at the corners'
/// local indices `loc`: corners 1..3 are the columns of `V H`, corner 0 minus their sum (the values of
/// [`block_corner_rows`], bit for bit).
#[inline(always)]
fn add_corners(h: &Mat3, vol: f64, loc: [usize; 4], acc: &mut [Vec3]) {
    let mut corners = [[0.0; 3]; 4];
    for a in 0..3 {
        for b in 0..3 {
            corners[a + 1][b] = vol * h[b][a];
        }
    }
    for b in 0..3 {
        corners[0][b] = 0.0 - corners[1][b] - corners[2][b] - corners[3][b];
    }
    for (c, value) in corners.iter().enumerate() {
        let a = &mut acc[loc[c]];
        for i in 0..3 {
            a[i] += value[i];
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::material::{Arap, Material, NeoHookean, StableNeoHookean};
    use crate::mesh::{tests::cube, MassSpec, TetMesh};
    use crate::model::ModelBuilder;

    pub(crate) fn grid_model(n: usize, material: Material) -> Model {
        let (v, t) = grid_mesh(n);
        let (mesh, _) = TetMesh::new(v, &t).unwrap();
        ModelBuilder::new(mesh, material)
            .mass(MassSpec::Density(1000.0))
            .build()
            .unwrap()
    }

    /// An n x n x n grid of cubes, each cut into 6 tets around its main diagonal (conforming).
    fn grid_mesh(n: usize) -> (Vec<Vec3>, Vec<[i64; 4]>) {
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
        (v, t)
    }

    pub(crate) fn deformed(model: &Model, seed: u64) -> Vec<Vec3> {
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

    /// [`deformed`] with vertices squashed along z by varying factors: flattened and inverted tets.
    fn squashed(model: &Model, seed: u64) -> Vec<Vec3> {
        let mut x = deformed(model, seed);
        for (i, p) in x.iter_mut().enumerate() {
            let w = (i as f64 * 1.7).sin();
            p[2] *= 0.05 + 0.9 * w * w;
        }
        x
    }

    #[test]
    fn batched_neo_hookean_matches_the_material_interface_bit_for_bit() {
        // Large random perturbations: many tets below j0 = 0.1 and some inverted, so both branches of the
        // extended logarithm run; 3^3 * 6 = 162 tets is not a multiple of the batch (remainder path too).
        let mat = NeoHookean::new(1e4, 0.3).unwrap();
        let model = grid_model(3, Material::NeoHookean(mat));
        for seed in [1, 5, 9] {
            let x = squashed(&model, seed);
            let k = model.num_tets();
            let (sa, a) = gradient_bits(&model, |sink| {
                neo_hookean_pass(Lanes::detect(), &mat, &model, &x, sink)
            });
            let (sb, b) = gradient_bits(&model, |sink| element_pass(&mat, &model, &x, sink));
            assert!(
                !k.is_multiple_of(BLOCK) && sa.inverted > 0 && sa.min_j < mat.j0,
                "{sa:?}"
            );
            assert_eq!(sa.energy.to_bits(), sb.energy.to_bits());
            assert_eq!(sa.min_j.to_bits(), sb.min_j.to_bits());
            assert_eq!(sa.inverted, sb.inverted);
            assert_eq!(a, b);
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
    fn arap_block_pass_matches_the_material_interface_bit_for_bit() {
        // As the Neo-Hookean test: flattened and inverted tets (the polar decomposition's SVD fallback),
        // 162 tets (a partial last block).
        let arap = Arap::new(1e4, 0.3).unwrap();
        let model = grid_model(3, Material::Arap(arap));
        for seed in [1, 5, 9] {
            let x = squashed(&model, seed);
            let (sa, a) = gradient_bits(&model, |sink| {
                crate::elasticity::arap_gradient_pass(&arap, &model, &x, sink)
            });
            let (sb, b) = gradient_bits(&model, |sink| element_pass(&arap, &model, &x, sink));
            assert!(sa.inverted > 0, "{sa:?}");
            assert_eq!(sa.energy.to_bits(), sb.energy.to_bits());
            assert_eq!(
                (sa.min_j.to_bits(), sa.inverted),
                (sb.min_j.to_bits(), sb.inverted)
            );
            assert_eq!(a, b);
            let ea = crate::elasticity::arap_energy(&arap, &model, &x);
            let eb = energy_impl(&arap, &model, &x);
            assert_eq!(ea.energy.to_bits(), eb.energy.to_bits());
            assert_eq!(
                (ea.min_j.to_bits(), ea.inverted),
                (eb.min_j.to_bits(), eb.inverted)
            );
        }
    }

    /// The summary and the gradient's bits from a gradient pass.
    fn gradient_bits(
        model: &Model,
        pass: impl FnOnce(GradientSink) -> ElasticSummary,
    ) -> (ElasticSummary, Vec<u64>) {
        let mut grad = vec![[f64::NAN; 3]; model.num_vertices()];
        let (mut acc, mut parts) = (Vec::new(), Vec::new());
        let s = pass(GradientSink {
            acc: &mut acc,
            parts: &mut parts,
        });
        model.corner_sums.sums_into(&acc, &mut grad);
        (s, grad.iter().flatten().map(|g| g.to_bits()).collect())
    }

    #[test]
    fn every_lane_width_gives_the_same_bits() {
        // AVX-512, AVX2 and plain code (whichever this CPU has) on a deformation with inverted tets and
        // a partial last block (4^3 * 6 = 384 tets, then 5^3 * 6 = 750).
        let mat = NeoHookean::new(1e4, 0.3).unwrap();
        for n in [4, 5] {
            let model = grid_model(n, Material::NeoHookean(mat));
            let mut x = deformed(&model, 3);
            for (i, p) in x.iter_mut().enumerate() {
                p[2] *= (i as f64 * 0.9).cos();
            }
            let (k, chunk, blocks) = (model.num_tets(), model.tet_chunk(), &model.tet_blocks);
            assert!(k > 2 * chunk, "several chunks");
            let pass = |lanes| {
                gradient_bits(&model, |sink| {
                    neo_hookean_pass(lanes, &mat, &model, &x, sink)
                })
            };
            let (sw, want) = pass(Lanes::Plain);
            assert!(sw.inverted > 0);
            let mut widths = vec![Lanes::Plain];
            #[cfg(target_arch = "x86_64")]
            {
                if std::arch::is_x86_feature_detected!("avx2") {
                    widths.push(Lanes::Avx2);
                }
                if std::arch::is_x86_feature_detected!("avx512f") {
                    widths.push(Lanes::Avx512);
                }
            }
            for lanes in widths {
                let (sg, got) = pass(lanes);
                // The energy-only kernel, chunk by chunk (each chunk's local positions serve its blocks).
                let se = (0..k.div_ceil(chunk))
                    .map(|c| {
                        let r = c * chunk..((c + 1) * chunk).min(k);
                        let b = r.start / BLOCK..r.end.div_ceil(BLOCK);
                        (model.corner_sums).with_positions(c, &x, |xl| {
                            lanes.run::<false>(&mat, blocks, b, xl, &mut [], r.len())
                        })
                    })
                    .fold(ElasticSummary::zero(), ElasticSummary::combine);
                assert_eq!(got, want, "{lanes:?}");
                for t in [sg, se] {
                    assert_eq!(t.energy.to_bits(), sw.energy.to_bits(), "{lanes:?}");
                    assert_eq!(
                        (t.min_j.to_bits(), t.inverted),
                        (sw.min_j.to_bits(), sw.inverted)
                    );
                }
            }
        }
    }

    #[test]
    fn user_numbering_does_not_change_results_and_tet_ids_stay_the_users() {
        // The same grid with its vertices and tets renumbered by pseudo-random permutations: the model's
        // internal order must hide the numbering (energy and per-vertex gradient to round-off), and
        // dm_inv / deformation_gradient must take user tet ids.
        let n = 5;
        let (v, t) = grid_mesh(n);
        let mut s = 12345u64;
        let mut shuffle = |len: usize| {
            let mut p: Vec<usize> = (0..len).collect();
            for i in (1..len).rev() {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                p.swap(i, (s >> 33) as usize % (i + 1));
            }
            p
        };
        // new vertex i is old vertex vp[i]; new tet e is old tet tp[e].
        let (vp, tp) = (shuffle(v.len()), shuffle(t.len()));
        let mut new_of_old = vec![0; v.len()];
        for (i, &o) in vp.iter().enumerate() {
            new_of_old[o] = i as i64;
        }
        let v2: Vec<Vec3> = vp.iter().map(|&o| v[o]).collect();
        let t2: Vec<[i64; 4]> = tp
            .iter()
            .map(|&o| t[o].map(|c| new_of_old[c as usize]))
            .collect();
        let mut all = materials();
        all.push(Material::Arap(Arap::new(1e4, 0.3).unwrap()));
        for mat in all {
            let build = |v: Vec<Vec3>, t: &[[i64; 4]]| {
                let (mesh, _) = TetMesh::new(v, t).unwrap();
                ModelBuilder::new(mesh, mat)
                    .mass(MassSpec::Density(1000.0))
                    .build()
                    .unwrap()
            };
            let (a, b) = (build(v.clone(), &t), build(v2.clone(), &t2));
            // The internal orders differ from the user's (else the test would not test them).
            assert_ne!(b.kernel_rank, (0..v.len() as u32).collect::<Vec<_>>());
            assert_ne!(b.tet_at, (0..t.len() as u32).collect::<Vec<_>>());
            let xa = deformed(&a, 5);
            let xb: Vec<Vec3> = vp.iter().map(|&o| xa[o]).collect();
            let (mut ga, mut gb) = (vec![[0.0; 3]; xa.len()], vec![[0.0; 3]; xb.len()]);
            let mut ws = ElasticWorkspace::default();
            let sa = elastic_energy_gradient(&a, &xa, &mut ws, &mut ga);
            let sb = elastic_energy_gradient(&b, &xb, &mut ElasticWorkspace::default(), &mut gb);
            let eb = elastic_energy(&b, &xb);
            assert!(sa.energy > 0.0);
            for e in [sb.energy, eb.energy] {
                assert!(
                    (e - sa.energy).abs() <= 1e-12 * sa.energy,
                    "{mat:?}: {e} vs {}",
                    sa.energy
                );
            }
            assert_eq!(sa.min_j, sb.min_j);
            assert_eq!(sa.inverted, sb.inverted);
            let gmax = ga.iter().flatten().fold(0.0f64, |m, g| m.max(g.abs()));
            for (i, &o) in vp.iter().enumerate() {
                for c in 0..3 {
                    assert!(
                        (gb[i][c] - ga[o][c]).abs() <= 1e-12 * gmax,
                        "{mat:?}: vertex {i} (old {o}): {:?} vs {:?}",
                        gb[i],
                        ga[o]
                    );
                }
            }
            // User tet ids: D_m^-1 and F of tet e are those of the user's tet e, bit for bit.
            let rest = b.mesh.rest_shape();
            for (e, &o) in tp.iter().enumerate() {
                assert_eq!(b.dm_inv(e), rest.dm_inv[e], "tet {e}");
                assert_eq!(b.dm_inv(e), a.dm_inv(o), "tet {e}");
                let f = matmul(&edge_matrix(&xb, &b.mesh.tets()[e]), &rest.dm_inv[e]);
                assert_eq!(deformation_gradient(&b, &xb, e), f, "tet {e}");
                assert_eq!(deformation_gradient(&a, &xa, o), f, "tet {e}");
            }
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

    #[test]
    fn vertices_no_tet_references_get_a_zero_gradient() {
        // A 12^3 grid (10,368 tets: 21 chunks, so border vertices exist) plus two vertices that no tet
        // references (allowed with node masses): their gradient must be exactly zero,
        // whatever the scratch held, and the others must match the same grid without them.
        let (mut v, t) = grid_mesh(12);
        let plain = {
            let (mesh, _) = TetMesh::new(v.clone(), &t).unwrap();
            ModelBuilder::new(mesh, materials()[0])
                .mass(MassSpec::NodeMass(0.1))
                .build()
                .unwrap()
        };
        v.push([5.0, 5.0, 5.0]);
        v.insert(0, [-5.0, 0.0, 0.0]);
        let t: Vec<[i64; 4]> = t.iter().map(|tet| tet.map(|i| i + 1)).collect();
        let (mesh, report) = TetMesh::new(v, &t).unwrap();
        assert_eq!(report.unreferenced, 2);
        let model = ModelBuilder::new(mesh, materials()[0])
            .mass(MassSpec::NodeMass(0.1))
            .build()
            .unwrap();
        assert!(model.num_tets() > 4 * model.tet_chunk());
        let x = deformed(&model, 4);
        let mut grad = vec![[f64::NAN; 3]; x.len()];
        let mut ws = ElasticWorkspace::default();
        for _ in 0..2 {
            elastic_energy_gradient(&model, &x, &mut ws, &mut grad);
            let m = x.len();
            assert_eq!((grad[0], grad[m - 1]), ([0.0; 3], [0.0; 3]));
        }
        let mut want = vec![[0.0; 3]; x.len() - 2];
        elastic_energy_gradient(
            &plain,
            &x[1..x.len() - 1],
            &mut ElasticWorkspace::default(),
            &mut want,
        );
        let scale = want.iter().flatten().fold(0.0f64, |a, g| a.max(g.abs()));
        for (g, w) in grad[1..x.len() - 1].iter().zip(&want) {
            for a in 0..3 {
                assert!((g[a] - w[a]).abs() <= 1e-12 * scale, "{g:?} vs {w:?}");
            }
        }
    }
}
