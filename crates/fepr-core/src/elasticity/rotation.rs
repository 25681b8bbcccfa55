//! The per-tet passes that need each tet's rotation `R = polar(F)`, over the model's [`TetBlocks`]: the ARAP
//! energy (and gradient) that FEPR evaluates after Projective Dynamics, and the PD local step's corner
//! terms `w R D_m^-T` (fepr-spec section 5). As in the Neo-Hookean kernel, `F` is formed in lanes straight
//! from the blocks and the corner values are written as whole blocks; the rotations come from
//! [`polar_lanes`], [`LANES`] tets at a time, with no transposition of `F` or `R` through per-tet matrices.
//! For the ARAP energy every operation mirrors the per-tet path (`Arap::energy_and_stress_given`,
//! `write_corners`), so the results are the same bits (gated by a test); only the scheduling differs. The PD
//! local step stops the polar iteration at [`PD_LOCAL`] (rotations to about 1e-10).

use crate::exec::for_each_chunk_mut;
use std::ops::Range;

use crate::elasticity::{
    add_corner_rows, block_corner_rows, block_deformation_gradients, chunked_pass, ElasticSummary,
    GradientSink,
};
use crate::material::Arap;
use crate::math::simd::avx2_dispatch;
use crate::math::Vec3;
use crate::math::{polar_lanes, Lanes, EXACT, LANES, PD_LOCAL};
use crate::model::{Block, Model, TetBlock, TetBlocks, BLOCK};

const _: () = assert!(BLOCK.is_multiple_of(LANES));

/// What a pass computes per tet, and where it goes.
enum Sink<'a> {
    /// The ARAP energy summary alone.
    Energy,
    /// The ARAP energy summary and the corner gradients `V 2 mu (F - R) D_m^-T`, added into the chunk's
    /// accumulator (`corner_sums`).
    Gradient(&'a mut [Vec3]),
    /// The PD corner terms `2 mu V R D_m^-T`, per tet in block order (no summary). Per tet and not per block: the PD
    /// right-hand side gathers them 10 times per step, and a vertex's incident tets, close in index, then
    /// share cache lines whichever corner the vertex is (measured 1.9x faster than from blocks).
    PdTerms(&'a mut [[Vec3; 4]]),
}

/// ARAP energy and gradient (to `sink`), summed per chunk of tets ([`Model::tet_chunk`]) in chunk order; as
/// `elasticity`'s per-tet pass for any material, bit for bit.
pub(crate) fn arap_gradient_pass(
    arap: &Arap,
    model: &Model,
    x: &[Vec3],
    sink: GradientSink,
) -> ElasticSummary {
    let (blocks, chunk_blocks) = (&model.tet_blocks, model.tet_chunk() / BLOCK);
    chunked_pass(model, x, sink, |c, xl, acc, len| {
        let first = c * chunk_blocks;
        let range = first..first + len.div_ceil(BLOCK);
        run(arap.mu, blocks, range, xl, Sink::Gradient(acc), len)
    })
}

/// The ARAP energy summary alone.
pub(crate) fn arap_energy(arap: &Arap, model: &Model, x: &[Vec3]) -> ElasticSummary {
    let (blocks, chunk) = (&model.tet_blocks, model.tet_chunk());
    ElasticSummary::over_chunks(model.num_tets(), chunk, |range| {
        let b = range.start / BLOCK..range.end.div_ceil(BLOCK);
        let c = range.start / chunk;
        (model.corner_sums).with_positions(c, x, |xl| {
            run(arap.mu, blocks, b, xl, Sink::Energy, range.len())
        })
    })
}

/// The Projective Dynamics local step for shear modulus `mu`: every tet's closest rotation `R` to `F` and
/// its corner terms `w R g_k` with `w = 2 mu V` and `g_k` the shape-function gradients (corners 1..3: the
/// columns of `w R D_m^-T`; corner 0 minus their sum), into `out[p]` for the tet at block position `p`
/// (`Model::tet_at`; shape (num_tets, 4, 3)). Parallel over fixed chunks; each tet's terms depend on that
/// tet alone.
pub(crate) fn pd_rotation_terms(mu: f64, model: &Model, x: &[Vec3], out: &mut [[Vec3; 4]]) {
    let (blocks, k) = (&model.tet_blocks, model.num_tets());
    assert_eq!(out.len(), k, "one entry per tet");
    let tet_chunk = model.tet_chunk();
    for_each_chunk_mut(out, tet_chunk, |c, chunk| {
        let first = c * (tet_chunk / BLOCK);
        let range = first..first + chunk.len().div_ceil(BLOCK);
        let len = chunk.len();
        (model.corner_sums).with_positions(c, x, |xl| {
            run(mu, blocks, range, xl, Sink::PdTerms(chunk), len);
        });
    });
}

avx2_dispatch! {
    /// [`rotation_blocks`] compiled for AVX2 where the CPU has it (the batched polar decomposition measured
    /// slower with AVX-512 lanes), else portable; no fused multiply-adds either way, so the same bits.
    fn run<'a>(
        mu: f64,
        blocks: &'a TetBlocks,
        range: Range<usize>,
        x: &'a [Vec3],
        out: Sink<'a>,
        len: usize,
    ) -> ElasticSummary => rotation_blocks
}

/// Per-block arrays, reused block after block (cache-line aligned for the SIMD loads and stores).
#[repr(C, align(64))]
struct Scratch {
    ds: [[Block; 3]; 3],
    f: [[Block; 3]; 3],
    r: [[Block; 3]; 3],
    p: [[Block; 3]; 3],
    h: [[Block; 3]; 3],
    h0: [Block; 3],
    scale: Block,
}

/// Consecutive blocks holding `len` tets (the last block may be partial), their results into `out`.
#[inline(always)]
fn rotation_blocks(
    mu: f64,
    blocks: &TetBlocks,
    range: Range<usize>,
    x: &[Vec3],
    mut out: Sink,
    len: usize,
) -> ElasticSummary {
    let mut s = ElasticSummary::zero();
    let z = [0.0; BLOCK];
    let mut w = Scratch {
        ds: [[z; 3]; 3],
        f: [[z; 3]; 3],
        r: [[z; 3]; 3],
        p: [[z; 3]; 3],
        h: [[z; 3]; 3],
        h0: [z; 3],
        scale: z,
    };
    for (b, tb) in blocks.blocks[range].iter().enumerate() {
        let valid = (len - b * BLOCK).min(BLOCK);
        block_deformation_gradients(tb, x, &mut w.ds, &mut w.f);
        // The energy the projection conserves needs the exact rotation; the PD local step does not.
        let stop = match out {
            Sink::PdTerms(_) => PD_LOCAL,
            _ => EXACT,
        };
        block_rotations(&w.f, &mut w.r, stop);
        match &mut out {
            Sink::PdTerms(terms) => {
                // w = 2 mu V, as the PD matrix's weights.
                let two_mu = 2.0 * mu;
                for l in 0..BLOCK {
                    w.scale[l] = two_mu * tb.vol[l];
                }
                block_corner_rows(&w.r, &w.scale, &tb.dm, &mut w.h, &mut w.h0);
                let (h, h0) = (&w.h, &w.h0);
                for (l, t) in terms[b * BLOCK..b * BLOCK + valid].iter_mut().enumerate() {
                    *t = [
                        [h0[0][l], h0[1][l], h0[2][l]],
                        [h[0][0][l], h[0][1][l], h[0][2][l]],
                        [h[1][0][l], h[1][1][l], h[1][2][l]],
                        [h[2][0][l], h[2][1][l], h[2][2][l]],
                    ];
                }
            }
            Sink::Energy => arap_block(mu, tb, &mut w, valid, &mut s),
            Sink::Gradient(acc) => {
                arap_block(mu, tb, &mut w, valid, &mut s);
                block_corner_rows(&w.p, &tb.vol, &tb.dm, &mut w.h, &mut w.h0);
                add_corner_rows(&w.h, &w.h0, &tb.loc, valid, acc);
            }
        }
    }
    s
}

/// The rotations of a block's tets, [`LANES`] at a time, to the accuracy `stop` of [`polar_lanes`].
#[inline(always)]
fn block_rotations(f: &[[Block; 3]; 3], r: &mut [[Block; 3]; 3], stop: f64) {
    for half in 0..BLOCK / LANES {
        let lanes = half * LANES..(half + 1) * LANES;
        let mut fl: [[Lanes; 3]; 3] = [[[0.0; LANES]; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                fl[i][j].copy_from_slice(&f[i][j][lanes.clone()]);
            }
        }
        let mut rl = [[[0.0; LANES]; 3]; 3];
        polar_lanes(&fl, &mut rl, stop);
        for i in 0..3 {
            for j in 0..3 {
                r[i][j][lanes.clone()].copy_from_slice(&rl[i][j]);
            }
        }
    }
}

/// ARAP energy density `mu |F - R|^2` and stress `P = 2 mu (F - R)` of a block (into `w.p`), and the
/// summary over its first `valid` tets (`J = det F` as `linalg::det`), operation by operation as
/// `Arap::energy_and_stress_given` and the per-tet pass.
#[inline(always)]
fn arap_block(mu: f64, tb: &TetBlock, w: &mut Scratch, valid: usize, s: &mut ElasticSummary) {
    let (f, r, p) = (&w.f, &w.r, &mut w.p);
    let mut psi = [0.0; BLOCK];
    for i in 0..3 {
        for j in 0..3 {
            for l in 0..BLOCK {
                let d = f[i][j][l] - r[i][j][l];
                psi[l] += d * d;
                p[i][j][l] = 2.0 * mu * d;
            }
        }
    }
    for l in 0..valid {
        let j = f[0][0][l] * (f[1][1][l] * f[2][2][l] - f[1][2][l] * f[2][1][l])
            - f[0][1][l] * (f[1][0][l] * f[2][2][l] - f[1][2][l] * f[2][0][l])
            + f[0][2][l] * (f[1][0][l] * f[2][1][l] - f[1][1][l] * f[2][0][l]);
        s.energy += tb.vol[l] * (mu * psi[l]);
        s.min_j = s.min_j.min(j);
        s.inverted += (j <= 0.0) as usize;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elasticity::tests::{deformed, grid_model};
    use crate::material::Material;

    #[test]
    fn pd_terms_are_two_mu_v_times_the_rotation_times_the_shape_gradients() {
        // 162 tets: 10 blocks, the last one partial; a deformation with rotation and stretch.
        let model = grid_model(3, Material::Arap(Arap::new(1e5, 0.3).unwrap()));
        let x = deformed(&model, 3);
        let mu = 123.0;
        let mut out = vec![[[0.0; 3]; 4]; model.num_tets()];
        pd_rotation_terms(mu, &model, &x, &mut out);
        for e in 0..model.num_tets() {
            let pos = model.tet_position[e] as usize;
            let f = crate::elasticity::deformation_gradient(&model, &x, e);
            let r = crate::math::polar_rotation(&f).0;
            let g = crate::elasticity::shape_gradients(&model, e);
            let w = 2.0 * mu * model.rest_volume[e];
            for (k, gk) in g.iter().enumerate() {
                let got = out[pos][k];
                for a in 0..3 {
                    let want = w * (r[a][0] * gk[0] + r[a][1] * gk[1] + r[a][2] * gk[2]);
                    // The PD local step's rotations are accurate to about 1e-10 (`math::PD_LOCAL`).
                    assert!(
                        (got[a] - want).abs() <= 1e-9 * w,
                        "tet {e} corner {k}: {got:?} vs {want}"
                    );
                }
            }
        }
    }
}
