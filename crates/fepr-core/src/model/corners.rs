//! The chunk-local vertex numbering of the per-tet passes: each fixed chunk of tets (at most [`TET_CHUNK`]: [`tet_chunk_for`]) gathers
//! the positions of the vertices it touches into a small local array, and sums its corner values (the
//! elastic gradient: each vertex gets the sum of its corners' gradients) into a small accumulator over the
//! same vertices; the blocks hold every corner's local index.
//!
//! The chunks run in parallel, in block order. Each adds its corner values in ascending block position,
//! while they are still in registers: no per-tet buffer is written to memory and read back by a second
//! pass, and no permuted copy of the positions is made. A second parallel pass over the vertices (user
//! order, fixed tasks; here or in the caller's own vertex pass) then sums every vertex's partial sums in chunk order: most vertices have one (the
//! chunks are spatially compact), those on chunk borders several, a vertex no tet references none. Neither
//! order depends on the number of threads, so the sums are bit-identical for any thread count. The chunks
//! write only their own accumulators and the vertex pass writes contiguous runs of the output, so no two
//! threads write one cache line (writing the sums in user order from the chunks measured 1.2x slower on two
//! threads on the bunny).

use std::cell::Cell;

use crate::exec::{
    for_each_chunk_mut, for_each_chunk_mut2, tet_chunk_for, vertex_task_len, TET_CHUNK,
};
use crate::math::Vec3;

// Local indices are u16: a chunk touches at most 4 TET_CHUNK vertices (the largest chunk).
const _: () = assert!(4 * TET_CHUNK <= u16::MAX as usize + 1);

thread_local! {
    /// The chunk-local positions of the chunk that this thread runs (reused: no allocation once grown).
    static LOCAL_POSITIONS: Cell<Vec<Vec3>> = const { Cell::new(Vec::new()) };
}

/// The chunk-local vertex numbering of a mesh's tets, and how the chunks' sums reach the vertices. Built once
/// with the model (about 7 bytes per tet; the accumulators, in the workspace, about 9).
#[derive(Clone, Debug)]
pub(crate) struct CornerSums {
    /// Tets per chunk: [`tet_chunk_for`] the mesh's tet count.
    chunk: usize,
    /// Accumulator entries per chunk (the largest local vertex count): chunk `c`'s entries are
    /// `c * stride .. c * stride + count[c]`.
    stride: usize,
    /// Local vertex count of every chunk.
    count: Vec<u32>,
    /// Per entry (`c * stride + j`, `j < count[c]`): the user vertex that is chunk `c`'s local vertex `j`.
    vertex: Vec<u32>,
    /// The entries holding user vertex `v`'s partial sums, in chunk order:
    /// `vertex_entries[vertex_offsets[v]..vertex_offsets[v + 1]]` (none for a vertex no tet references).
    vertex_offsets: Vec<u32>,
    vertex_entries: Vec<u32>,
}

impl CornerSums {
    /// The numbering of `tets` (user vertex indices) placed in blocks by `tet_at` (position -> user tet;
    /// chunk `c` holds positions `c chunk ..`, [`tet_chunk_for`]), and every position's local corner indices
    /// (`local[p][corner]`).
    pub(crate) fn new(
        tets: &[[usize; 4]],
        tet_at: &[u32],
        num_vertices: usize,
    ) -> (Self, Vec<[u16; 4]>) {
        u32::try_from(num_vertices).expect("vertex indices fit in u32");
        let chunk = tet_chunk_for(tet_at.len());
        let num_chunks = tet_at.len().div_ceil(chunk);
        let mut local = vec![[0u16; 4]; tet_at.len()];
        // Every chunk's vertices in ascending vertex order. A vertex task then finds its partial sums in each
        // chunk's accumulator as one contiguous run, and the runs that another core wrote span fewer cache
        // lines than in the order the chunk's tets first load them (armadillo, two threads: 90 against 140
        // lines on the thread that reads the most). Only the layout changes: the sums keep their order.
        let (mut chunk_offsets, mut chunk_vertices) = (vec![0usize], Vec::new());
        let mut local_of = vec![u16::MAX; num_vertices];
        for (c, positions) in tet_at.chunks(chunk).enumerate() {
            let first = chunk_vertices.len();
            for &e in positions {
                for &v in &tets[e as usize] {
                    if local_of[v] == u16::MAX {
                        local_of[v] = 0;
                        chunk_vertices.push(v as u32);
                    }
                }
            }
            chunk_vertices[first..].sort_unstable();
            for (j, &v) in chunk_vertices[first..].iter().enumerate() {
                local_of[v as usize] = j as u16;
            }
            for (k, &e) in positions.iter().enumerate() {
                for (corner, &v) in tets[e as usize].iter().enumerate() {
                    local[c * chunk + k][corner] = local_of[v];
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
        let mut vertex = vec![0u32; num_chunks * stride];
        let mut vertex_offsets = vec![0u32; num_vertices + 1];
        for &v in &chunk_vertices {
            vertex_offsets[v as usize + 1] += 1;
        }
        for v in 0..num_vertices {
            vertex_offsets[v + 1] += vertex_offsets[v];
        }
        let mut fill = vertex_offsets.clone();
        let mut vertex_entries = vec![0u32; chunk_vertices.len()];
        for c in 0..num_chunks {
            let vertices = &chunk_vertices[chunk_offsets[c]..chunk_offsets[c + 1]];
            for (j, &v) in vertices.iter().enumerate() {
                let entry = c * stride + j;
                vertex[entry] = v;
                // Chunks in ascending order: each vertex's entries end up in chunk order.
                vertex_entries[fill[v as usize] as usize] = entry as u32;
                fill[v as usize] += 1;
            }
        }
        let sums = Self {
            chunk,
            stride,
            count,
            vertex,
            vertex_offsets,
            vertex_entries,
        };
        (sums, local)
    }

    /// Tets per chunk: chunk `c` holds the block positions `c * chunk() ..` (a multiple of the block length).
    #[inline]
    pub(crate) fn chunk(&self) -> usize {
        self.chunk
    }

    /// Chunk `c`'s vertices in local order (the user vertex of each local index).
    #[inline]
    pub(crate) fn chunk_vertices(&self, c: usize) -> &[u32] {
        let first = c * self.stride;
        &self.vertex[first..first + self.count[c] as usize]
    }

    /// Runs `f` with chunk `c`'s vertex positions in local order (`xl[j] = x[v]` for its local vertex `j`,
    /// user vertex `v`), gathered into this thread's reused buffer.
    pub(crate) fn with_positions<R>(
        &self,
        c: usize,
        x: &[Vec3],
        f: impl FnOnce(&[Vec3]) -> R,
    ) -> R {
        let first = c * self.stride;
        let vertices = &self.vertex[first..first + self.count[c] as usize];
        // Taken out of the cell, not borrowed: a nested call (none today) would allocate, not panic.
        let mut xl = LOCAL_POSITIONS.take();
        xl.clear();
        xl.extend(vertices.iter().map(|&v| x[v as usize]));
        let result = f(&xl);
        LOCAL_POSITIONS.set(xl);
        result
    }

    /// Runs `chunk_fn(c, xl, acc)` for every chunk `c` in parallel, where `xl` holds the chunk's vertex
    /// positions (local order, [`CornerSums::with_positions`]) and `acc` is its accumulator (zeroed, indexed
    /// by local vertex) into which it adds its corner values in ascending block position. `parts[c]` gets the
    /// chunk's return value. `acc` is scratch memory, grown on the first call; the vertices' sums are then
    /// [`CornerSums::vertex_sum`] (or all of them: [`CornerSums::sums_into`]).
    pub(crate) fn chunks<S, F>(&self, x: &[Vec3], acc: &mut Vec<Vec3>, parts: &mut [S], chunk_fn: F)
    where
        S: Send,
        F: Fn(usize, &[Vec3], &mut [Vec3]) -> S + Sync,
    {
        let num_chunks = self.count.len();
        assert_eq!(parts.len(), num_chunks, "one result per chunk");
        acc.resize(num_chunks * self.stride, [0.0; 3]);
        let count = &self.count;
        for_each_chunk_mut2(acc, self.stride.max(1), parts, 1, |c, acc, part| {
            let acc = &mut acc[..count[c] as usize];
            acc.fill([0.0; 3]);
            part[0] = self.with_positions(c, x, |xl| chunk_fn(c, xl, acc));
        });
    }

    /// User vertex `v`'s sum: its partial sums in `acc` (from [`CornerSums::chunks`]) added in chunk order
    /// (zero for a vertex no tet references).
    #[inline(always)]
    pub(crate) fn vertex_sum(&self, acc: &[Vec3], v: usize) -> Vec3 {
        let (offsets, entries) = (&self.vertex_offsets, &self.vertex_entries);
        let mine = &entries[offsets[v] as usize..offsets[v + 1] as usize];
        match mine.split_first() {
            None => [0.0; 3],
            Some((&first, rest)) => rest.iter().fold(acc[first as usize], |s, &e| {
                let p = acc[e as usize];
                [s[0] + p[0], s[1] + p[1], s[2] + p[2]]
            }),
        }
    }

    /// Every vertex's sum into `out` (user order, shape (num_vertices, 3)), in parallel over fixed tasks.
    pub(crate) fn sums_into(&self, acc: &[Vec3], out: &mut [Vec3]) {
        assert_eq!(
            out.len() + 1,
            self.vertex_offsets.len(),
            "one sum per vertex"
        );
        // Each vertex's sum is its own (no sum spans tasks), so the task length changes no bits. With one task
        // of 4096 vertices, meshes below that summed every vertex on one thread, and on two threads that
        // thread read half of the partial sums from the other core's cache: the 10k box's 2,197 vertices
        // took 11 us there against 5.4 us on one thread (perf), 7% of the whole energy + gradient.
        let task = vertex_task_len(out.len());
        for_each_chunk_mut(out, task, |t, out| {
            for (k, sum) in out.iter_mut().enumerate() {
                *sum = self.vertex_sum(acc, t * task + k);
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Corner values that identify their slot: tet position p, corner c gets (p, c, 1).
    fn sums_by_reference(tets: &[[usize; 4]], tet_at: &[u32], m: usize, chunk: usize) -> Vec<Vec3> {
        // The documented order: per chunk, ascending position; the chunks' partials in chunk order.
        let mut out = vec![[0.0; 3]; m];
        for v in 0..m {
            let mut total: Option<Vec3> = None;
            for positions in tet_at
                .chunks(chunk)
                .enumerate()
                .map(|(c, ps)| (c, ps.len()))
            {
                let (c, len) = positions;
                let mut partial = [0.0; 3];
                let mut touched = false;
                for p in c * chunk..c * chunk + len {
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

    /// A strip of several chunks in a scrambled placement (position p holds tet (p * 5) mod k): its tets, its
    /// vertex count and the placement.
    fn scrambled_strip() -> (Vec<[usize; 4]>, usize, Vec<u32>) {
        let k = 3 * TET_CHUNK + 77;
        let (tets, m) = strip(k);
        let tet_at = (0..k).map(|p| ((p * 5) % k) as u32).collect();
        (tets, m, tet_at)
    }

    #[test]
    fn sums_follow_the_documented_order_for_any_thread_count() {
        let (tets, m, tet_at) = scrambled_strip();
        let k = tets.len();
        let (sums, local) = CornerSums::new(&tets, &tet_at, m);
        let chunk = sums.chunk();
        assert!(k.div_ceil(chunk) > 4, "several chunks");
        let want = sums_by_reference(&tets, &tet_at, m, chunk);
        let x: Vec<Vec3> = (0..m).map(|v| [v as f64, 0.5 * v as f64, -1.0]).collect();
        assert_eq!(want[m - 1], [0.0; 3], "the unreferenced vertex");
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let got = pool.install(|| {
                let (mut acc, mut parts) = (Vec::new(), vec![0usize; k.div_ceil(chunk)]);
                let mut out = vec![[f64::NAN; 3]; m];
                sums.chunks(&x, &mut acc, &mut parts, |c, xl, acc| {
                    let end = ((c + 1) * chunk).min(k);
                    for p in c * chunk..end {
                        for corner in 0..4 {
                            // The local positions are the corners' own.
                            let v = tets[tet_at[p] as usize][corner];
                            assert_eq!(xl[local[p][corner] as usize], x[v]);
                            let a = &mut acc[local[p][corner] as usize];
                            let val = value(p, corner);
                            for i in 0..3 {
                                a[i] += val[i];
                            }
                        }
                    }
                    end - c * chunk
                });
                assert_eq!(parts.iter().sum::<usize>(), k);
                sums.sums_into(&acc, &mut out);
                out
            });
            let bits = |o: &[Vec3]| o.iter().flatten().map(|g| g.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "{threads} threads");
        }
    }

    /// Each chunk numbers its vertices in ascending vertex order, so that a vertex task reads each chunk's
    /// partial sums as one contiguous run (fewer cache lines from the other core than in first-seen order).
    #[test]
    fn chunk_vertices_ascend_so_vertex_tasks_read_runs() {
        let (tets, m, tet_at) = scrambled_strip();
        let (sums, _) = CornerSums::new(&tets, &tet_at, m);
        for (c, &count) in sums.count.iter().enumerate() {
            let first = c * sums.stride;
            let vertices = &sums.vertex[first..first + count as usize];
            assert!(vertices.windows(2).all(|w| w[0] < w[1]), "chunk {c}");
        }
        // Any task of contiguous vertices then finds its entries of a chunk contiguous too.
        let task = 97;
        for (t, first) in (0..m).step_by(task).enumerate() {
            let entries: Vec<u32> = (first..(first + task).min(m))
                .flat_map(|v| {
                    let (a, b) = (sums.vertex_offsets[v], sums.vertex_offsets[v + 1]);
                    sums.vertex_entries[a as usize..b as usize].to_vec()
                })
                .collect();
            for c in 0..sums.count.len() as u32 {
                let mut mine: Vec<u32> = entries
                    .iter()
                    .copied()
                    .filter(|&e| e / sums.stride as u32 == c)
                    .collect();
                mine.sort_unstable();
                assert!(
                    mine.windows(2).all(|w| w[1] == w[0] + 1),
                    "task {t}, chunk {c}"
                );
            }
        }
    }
}
