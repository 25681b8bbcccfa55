//! Deterministic sums of per-tet corner values into vertices, fused into the per-tet passes (the elastic
//! gradient: each vertex gets the sum of its corners' gradients).
//!
//! The passes run over fixed chunks of [`TET_CHUNK`] tets in block order. Each chunk adds its corner values
//! into a small accumulator over the vertices it touches (the blocks hold every corner's local index), in
//! ascending block position, while the values are still in registers: no per-tet buffer is written to
//! memory and read back by a second pass. A vertex that only one chunk touches (most of them: the chunks are
//! spatially compact) gets its sum written to the output, in user order, by that chunk. The others (on the
//! chunks' borders, and vertices that no tet references) are summed afterwards from the chunks' partial
//! sums, in chunk order. Neither order depends on the number of threads, so the sums are bit-identical for
//! any thread count.

use rayon::prelude::*;

use crate::linalg::Vec3;
use crate::parallel::TET_CHUNK;

/// Marks a [`CornerSums::dest`] entry whose vertex is summed after the chunks (the low bits: its index in
/// [`CornerSums::shared_vertex`]).
const SHARED: u32 = 1 << 31;

// Local indices are u16: a chunk touches at most 4 TET_CHUNK vertices.
const _: () = assert!(4 * TET_CHUNK <= u16::MAX as usize + 1);

/// Shared vertices per parallel task in the second pass (fewer than twice this run inline, without waking
/// another thread).
const SHARED_TASK: usize = 2048;

/// The chunk-local vertex numbering of a mesh's tets and how the chunks' sums reach the vertices. Built once
/// with the model (about 5 bytes per tet; the accumulators, in the workspace, about 9).
#[derive(Clone, Debug, Default)]
pub(crate) struct CornerSums {
    /// Accumulator entries per chunk (the largest local vertex count): chunk `c`'s entries are
    /// `c * stride .. c * stride + count[c]`.
    stride: usize,
    /// Local vertex count of every chunk.
    count: Vec<u32>,
    /// Per entry (`c * stride + j`, `j < count[c]`): the user vertex whose sum chunk `c` completes, or
    /// `SHARED | s` for shared vertex `s`.
    dest: Vec<u32>,
    /// User vertex of every shared vertex (ascending).
    shared_vertex: Vec<u32>,
    /// The entries holding shared vertex `s`'s partial sums, in chunk order:
    /// `shared_entries[shared_offsets[s]..shared_offsets[s + 1]]` (none for a vertex no tet references).
    shared_offsets: Vec<usize>,
    shared_entries: Vec<u32>,
}

impl CornerSums {
    /// The numbering of `tets` placed in blocks by `tet_at` (position -> user tet; chunk `c` holds positions
    /// `c TET_CHUNK ..`), and every position's local corner indices (`local[p][corner]`).
    pub(crate) fn new(
        tets: &[[usize; 4]],
        tet_at: &[u32],
        num_vertices: usize,
    ) -> (Self, Vec<[u16; 4]>) {
        assert!(
            num_vertices < SHARED as usize,
            "vertex indices fit in 31 bits"
        );
        let num_chunks = tet_at.len().div_ceil(TET_CHUNK);
        let mut local = vec![[0u16; 4]; tet_at.len()];
        // Every chunk's vertices in first-seen order, and how many chunks touch each vertex.
        let (mut chunk_offsets, mut chunk_vertices) = (vec![0usize], Vec::new());
        let (mut local_of, mut chunks_at) =
            (vec![u16::MAX; num_vertices], vec![0u32; num_vertices]);
        for (c, positions) in tet_at.chunks(TET_CHUNK).enumerate() {
            let first = chunk_vertices.len();
            for (k, &e) in positions.iter().enumerate() {
                for (corner, &v) in tets[e as usize].iter().enumerate() {
                    if local_of[v] == u16::MAX {
                        local_of[v] = (chunk_vertices.len() - first) as u16;
                        chunk_vertices.push(v as u32);
                        chunks_at[v] += 1;
                    }
                    local[c * TET_CHUNK + k][corner] = local_of[v];
                }
            }
            for &v in &chunk_vertices[first..] {
                local_of[v as usize] = u16::MAX;
            }
            chunk_offsets.push(chunk_vertices.len());
        }
        let count: Vec<u32> = chunk_offsets
            .windows(2)
            .map(|w| (w[1] - w[0]) as u32)
            .collect();
        let stride = count.iter().copied().max().unwrap_or(0) as usize;
        u32::try_from(num_chunks * stride).expect("accumulator entries fit in u32");
        // Shared vertices (touched by several chunks, or by none) in ascending order, with room for one
        // partial sum per chunk that touches them.
        let mut shared_index = vec![u32::MAX; num_vertices];
        let (mut shared_vertex, mut shared_offsets) = (Vec::new(), vec![0usize]);
        for (v, &n) in chunks_at.iter().enumerate() {
            if n != 1 {
                shared_index[v] = shared_vertex.len() as u32;
                shared_vertex.push(v as u32);
                shared_offsets.push(shared_offsets.last().copied().unwrap_or(0) + n as usize);
            }
        }
        let mut fill = shared_offsets.clone();
        let mut shared_entries = vec![0u32; fill.last().copied().unwrap_or(0)];
        let mut dest = vec![0u32; num_chunks * stride];
        for c in 0..num_chunks {
            let vertices = &chunk_vertices[chunk_offsets[c]..chunk_offsets[c + 1]];
            for (j, &v) in vertices.iter().enumerate() {
                let entry = c * stride + j;
                let s = shared_index[v as usize];
                dest[entry] = if s == u32::MAX {
                    v
                } else {
                    // Chunks in ascending order: each shared vertex's entries end up in chunk order.
                    shared_entries[fill[s as usize]] = entry as u32;
                    fill[s as usize] += 1;
                    SHARED | s
                };
            }
        }
        let sums = Self {
            stride,
            count,
            dest,
            shared_vertex,
            shared_offsets,
            shared_entries,
        };
        (sums, local)
    }

    /// Runs `chunk_fn(c, acc)` for every chunk `c` in parallel, where `acc` is chunk `c`'s accumulator
    /// (zeroed, indexed by local vertex) into which it adds its corner values in ascending block position,
    /// and writes every vertex's sum to `out` (user order, shape (num_vertices, 3)); `parts[c]` gets the
    /// chunk's return value. `acc` is scratch memory, grown on the first call.
    pub(crate) fn run<S, F>(
        &self,
        acc: &mut Vec<Vec3>,
        parts: &mut [S],
        out: &mut [Vec3],
        chunk_fn: F,
    ) where
        S: Send,
        F: Fn(usize, &mut [Vec3]) -> S + Sync,
    {
        let num_chunks = self.count.len();
        assert_eq!(parts.len(), num_chunks, "one result per chunk");
        acc.resize(num_chunks * self.stride, [0.0; 3]);
        // Every write is checked against the output's length (`VertexWriter::write`).
        let m = out.len();
        let out_ptr = VertexWriter(out.as_mut_ptr(), m);
        let (dest, count) = (&self.dest, &self.count);
        acc.par_chunks_mut(self.stride.max(1))
            .zip(parts.par_iter_mut())
            .enumerate()
            .for_each(|(c, (acc, part))| {
                let acc = &mut acc[..count[c] as usize];
                acc.fill([0.0; 3]);
                *part = chunk_fn(c, acc);
                let dest = &dest[c * self.stride..c * self.stride + acc.len()];
                for (&d, sum) in dest.iter().zip(acc.iter()) {
                    if d & SHARED == 0 {
                        // SAFETY: `d` is a user vertex whose sum only this entry holds (the construction
                        // gives each vertex touched by one chunk exactly one entry), so no other task
                        // writes it, and `out` outlives the parallel loop.
                        unsafe { out_ptr.write(d as usize, *sum) };
                    }
                }
            });
        let acc = &acc[..];
        let (offsets, entries) = (&self.shared_offsets, &self.shared_entries);
        self.shared_vertex
            .par_iter()
            .enumerate()
            .with_min_len(SHARED_TASK)
            .for_each(|(s, &v)| {
                let mut sum = [0.0; 3];
                if let Some((&first, rest)) = entries[offsets[s]..offsets[s + 1]].split_first() {
                    sum = acc[first as usize];
                    for &e in rest {
                        let p = acc[e as usize];
                        sum = [sum[0] + p[0], sum[1] + p[1], sum[2] + p[2]];
                    }
                }
                // SAFETY: shared vertices are distinct, and the chunks wrote none of them.
                unsafe { out_ptr.write(v as usize, sum) };
            });
    }
}

/// Writes to distinct elements of one output slice from several tasks.
#[derive(Clone, Copy)]
struct VertexWriter(*mut Vec3, usize);

// SAFETY: the callers write disjoint elements only (see the SAFETY comments at the writes).
unsafe impl Send for VertexWriter {}
unsafe impl Sync for VertexWriter {}

impl VertexWriter {
    /// # Safety
    /// No other thread may access element `i` during the write.
    #[inline(always)]
    unsafe fn write(self, i: usize, value: Vec3) {
        assert!(i < self.1, "vertex {i} out of range");
        // SAFETY: in range (checked); exclusive by the caller's contract.
        unsafe { self.0.add(i).write(value) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Corner values that identify their slot: tet position p, corner c gets (p, c, 1).
    fn sums_by_reference(tets: &[[usize; 4]], tet_at: &[u32], m: usize) -> Vec<Vec3> {
        // The documented order: per chunk, ascending position; the chunks' partials in chunk order.
        let mut out = vec![[0.0; 3]; m];
        for v in 0..m {
            let mut total: Option<Vec3> = None;
            for positions in tet_at
                .chunks(TET_CHUNK)
                .enumerate()
                .map(|(c, ps)| (c, ps.len()))
            {
                let (c, len) = positions;
                let mut partial = [0.0; 3];
                let mut touched = false;
                for p in c * TET_CHUNK..c * TET_CHUNK + len {
                    for (corner, &w) in tets[tet_at[p] as usize].iter().enumerate() {
                        if w == v {
                            touched = true;
                            let val = value(p, corner);
                            for i in 0..3 {
                                partial[i] += val[i];
                            }
                        }
                    }
                }
                if touched {
                    total = Some(match total {
                        None => partial,
                        Some(t) => [t[0] + partial[0], t[1] + partial[1], t[2] + partial[2]],
                    });
                }
            }
            out[v] = total.unwrap_or([0.0; 3]);
        }
        out
    }

    fn value(p: usize, corner: usize) -> Vec3 {
        let x = (p as f64 * 0.37 + corner as f64 * 1.3).sin();
        [x, 1.0 / (1.0 + p as f64), (corner as f64) * 1e-3 + x * x]
    }

    /// A strip of tets over vertices 0..m (tet i uses i, i+1, i+2, i+3 shifted by a stride), long enough
    /// for several chunks, plus a vertex no tet references.
    fn strip(k: usize) -> (Vec<[usize; 4]>, usize) {
        let tets: Vec<[usize; 4]> = (0..k)
            .map(|i| [i, i + 1, i + 2, (i * 7919) % (k + 3)])
            .collect();
        (tets, k + 4)
    }

    #[test]
    fn sums_follow_the_documented_order_for_any_thread_count() {
        let k = 3 * TET_CHUNK + 77;
        let (tets, m) = strip(k);
        // A scrambled placement: position p holds tet (p * 5) mod k.
        let tet_at: Vec<u32> = (0..k).map(|p| ((p * 5) % k) as u32).collect();
        let (sums, local) = CornerSums::new(&tets, &tet_at, m);
        let want = sums_by_reference(&tets, &tet_at, m);
        assert_eq!(want[m - 1], [0.0; 3], "the unreferenced vertex");
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let got = pool.install(|| {
                let (mut acc, mut parts) = (Vec::new(), vec![0usize; k.div_ceil(TET_CHUNK)]);
                let mut out = vec![[f64::NAN; 3]; m];
                sums.run(&mut acc, &mut parts, &mut out, |c, acc| {
                    let end = ((c + 1) * TET_CHUNK).min(k);
                    for p in c * TET_CHUNK..end {
                        for corner in 0..4 {
                            let a = &mut acc[local[p][corner] as usize];
                            let val = value(p, corner);
                            for i in 0..3 {
                                a[i] += val[i];
                            }
                        }
                    }
                    end - c * TET_CHUNK
                });
                assert_eq!(parts.iter().sum::<usize>(), k);
                out
            });
            let bits = |o: &[Vec3]| o.iter().flatten().map(|g| g.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "{threads} threads");
        }
    }
}
