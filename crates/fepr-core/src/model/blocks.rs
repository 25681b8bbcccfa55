//! The model's rest data in blocks of [`BLOCK`] tets, structure-of-arrays, in the model's internal tet order:
//! what the batched elastic kernels read.

use crate::exec::MIN_TET_CHUNK;
use crate::math::Mat3;
use crate::mesh::RestShape;

/// Tets per block of the rest data and of the batched kernels. A multiple of 8 (the f64
/// lanes of AVX-512) that divides every chunk length (a power of two, at least
/// [`MIN_TET_CHUNK`]), so every chunk but the last is made of whole blocks.
pub const BLOCK: usize = 16;
const _: () = assert!(MIN_TET_CHUNK.is_multiple_of(BLOCK) && BLOCK.is_multiple_of(8));
pub(crate) type Block = [f64; BLOCK];

/// The rest data of [`BLOCK`] consecutive tets in structure-of-arrays form: the Neo-Hookean kernel reads
/// it with SIMD loads instead of transposing `Model::rest` for every evaluation. Lanes past the last tet
/// are padding (vertex 0, zero `D_m^-1` and volume); the kernel ignores their results.
#[derive(Clone, Debug)]
#[repr(C, align(64))]
pub struct TetBlock {
    /// `D_m^-1[i][j]` at `dm[i][j]`.
    pub(crate) dm: [[Block; 3]; 3],
    /// Rest volumes, m^3.
    pub(crate) vol: Block,
    /// Local vertex index of every corner in its chunk (`corner_sums`: the chunk's positions and
    /// accumulator), by corner.
    pub(crate) loc: [[u16; BLOCK]; 4],
}

/// [`TetBlock`]s of a whole mesh (88 bytes per tet), built once with the model, in the model's internal tet
/// order (`Model::tet_at`).
#[derive(Clone, Debug, Default)]
pub struct TetBlocks {
    pub(crate) blocks: Vec<TetBlock>,
}

impl TetBlocks {
    /// Blocks of the rest data: position `p` holds tet `tet_at[p]` (`rest`'s index), with its corners'
    /// local indices `local[p]`.
    pub(crate) fn new(rest: &RestShape, tet_at: &[u32], local: &[[u16; 4]]) -> Self {
        assert_eq!(tet_at.len(), rest.volume.len(), "one position per tet");
        assert_eq!(local.len(), tet_at.len(), "local indices per position");
        let blocks = tet_at
            .chunks(BLOCK)
            .zip(local.chunks(BLOCK))
            .map(|(ts, locs)| {
                let mut tb = TetBlock {
                    dm: [[[0.0; BLOCK]; 3]; 3],
                    vol: [0.0; BLOCK],
                    loc: [[0; BLOCK]; 4],
                };
                for (l, (&e, lc)) in ts.iter().zip(locs).enumerate() {
                    let e = e as usize;
                    for c in 0..4 {
                        tb.loc[c][l] = lc[c];
                    }
                    for i in 0..3 {
                        for j in 0..3 {
                            tb.dm[i][j][l] = rest.dm_inv[e][i][j];
                        }
                    }
                    tb.vol[l] = rest.volume[e];
                }
                tb
            })
            .collect();
        Self { blocks }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.blocks.capacity() * std::mem::size_of::<TetBlock>()
    }

    /// `D_m^-1` of the tet at block position `p` (of user tet `e`: `Model::dm_inv(e)`).
    #[inline]
    pub fn dm_inv_at(&self, p: usize) -> Mat3 {
        let (b, l) = (&self.blocks[p / BLOCK], p % BLOCK);
        // Plain loops: nested `array::map` closures were not inlined here (measured: 13% of a PD step).
        let mut m = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = b.dm[i][j][l];
            }
        }
        m
    }
}
