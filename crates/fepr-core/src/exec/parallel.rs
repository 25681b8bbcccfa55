//! Deterministic parallel loops on plain rayon: the input is cut into fixed-size chunks (their length depends on
//! the input's size alone, never on the number of threads), each chunk is handled by one task, and reductions
//! combine the chunk results in chunk order on the calling thread. The results are therefore bit-identical for
//! any thread count; which thread runs a chunk changes nothing.
//!
//! Every loop runs on the calling thread, in chunk order, when one thread would run it anyway (inside
//! [`serial`], in a pool of one thread, or with a single chunk): a rayon region costs a wake-up of the pool's
//! other threads, more than a small pass.

use std::ops::Range;

use rayon::prelude::*;

/// Chunk length for per-tet loops: the largest, used on meshes of 32 chunks or more (a smaller mesh is cut
/// finer: [`tet_chunk_for`]).
pub const TET_CHUNK: usize = 1024;

/// The smallest chunk length of the per-tet loops.
pub const MIN_TET_CHUNK: usize = 128;

/// Tets per chunk of the per-tet loops on a mesh of `k` tets, a power of two: [`TET_CHUNK`] from 32,768 tets;
/// below, about a thirty-second of the mesh while that is at least 512 tets (16,384 tets and more), else about a
/// sixteenth (at least [`MIN_TET_CHUNK`]). Small and mid-sized meshes are cut finer so that two threads get
/// near-equal shares; not finer than a sixteenth, because each chunk's border vertices are summed from several
/// chunks. The length depends on `k` alone, never on the thread count: the sums keep their bits for any number
/// of threads.
pub fn tet_chunk_for(k: usize) -> usize {
    let floor_pow2 = |n: usize| 1usize << (usize::BITS - 1 - n.max(1).leading_zeros());
    let thirty_second = floor_pow2(k / 32);
    if thirty_second >= 512 {
        thirty_second.min(TET_CHUNK)
    } else {
        floor_pow2(k / 16).clamp(MIN_TET_CHUNK, TET_CHUNK)
    }
}

/// Vertices per task of every pass over the vertices' rows (the elastic gradient's vertex sums, the
/// projection's passes, symplectic Euler's update), for a mesh of `m` vertices: about an eighth of the mesh,
/// 64 to 2048, a multiple of 4 (the projection's moment lanes).
///
/// One length for all of them, so that the passes cut the rows the same way. The length depends on `m` alone,
/// never on the thread count: sums taken per task and combined in task order keep their bits for any number
/// of threads. About an eighth, so that two threads get equal shares of small and mid-sized meshes; at least
/// 64 (a task's overhead); at most 2048 (a task's rows stay in L1/L2).
pub fn vertex_task_len(m: usize) -> usize {
    m.div_ceil(8).next_multiple_of(4).clamp(64, 2048)
}

/// Rows below which the per-row passes of a step ([`row_tasks2`], [`copy_rows`], [`all_rows`]) run on the
/// calling thread: there a parallel region costs more than the pass itself.
pub const SERIAL_ROWS: usize = 1024;

/// `f(first, a_rows, b_rows)` over the vertex tasks of [`vertex_task_len`] of two slices of `n` rows each
/// (`first`: the index of the task's first row), in parallel from [`SERIAL_ROWS`] rows on, else in task order
/// on the calling thread.
pub fn row_tasks2<A: Send, B: Send>(
    a: &mut [A],
    b: &mut [B],
    f: impl Fn(usize, &mut [A], &mut [B]) + Sync,
) {
    let n = a.len();
    assert_eq!(b.len(), n, "one row of each per vertex");
    let len = vertex_task_len(n);
    if n < SERIAL_ROWS {
        for (c, (a, b)) in a.chunks_mut(len).zip(b.chunks_mut(len)).enumerate() {
            f(c * len, a, b);
        }
        return;
    }
    for_each_chunk_mut2(a, len, b, len, |c, a, b| f(c * len, a, b));
}

/// `dst` becomes a copy of `src` (resized to its length: no allocation once it has grown), in the vertex
/// tasks of [`vertex_task_len`] from [`SERIAL_ROWS`] rows on: the copies of a step's state are a sizeable part
/// of a cheap base step, and split like the passes that wrote the rows.
pub fn copy_rows<T: Copy + Default + Send + Sync>(src: &[T], dst: &mut Vec<T>) {
    let n = src.len();
    dst.resize(n, T::default());
    if n < SERIAL_ROWS {
        dst.copy_from_slice(src);
        return;
    }
    let len = vertex_task_len(n);
    for_each_chunk_mut(dst, len, |c, out| {
        out.copy_from_slice(&src[c * len..c * len + out.len()])
    });
}

/// [`copy_rows`] of two row arrays of the same length (a state's positions and velocities) in one parallel
/// region instead of two: a step copies its state twice, and on a small mesh a region's start costs as much as
/// the copy.
pub fn copy_rows2<T: Copy + Default + Send + Sync>(
    src_a: &[T],
    dst_a: &mut Vec<T>,
    src_b: &[T],
    dst_b: &mut Vec<T>,
) {
    let n = src_a.len();
    if n < SERIAL_ROWS || src_b.len() != n {
        copy_rows(src_a, dst_a);
        copy_rows(src_b, dst_b);
        return;
    }
    dst_a.resize(n, T::default());
    dst_b.resize(n, T::default());
    let len = vertex_task_len(n);
    for_each_chunk_mut2(dst_a, len, dst_b, len, |c, a, b| {
        a.copy_from_slice(&src_a[c * len..c * len + a.len()]);
        b.copy_from_slice(&src_b[c * len..c * len + b.len()]);
    });
}

/// Whether `check(range)` holds for every task's range of rows `0..n` (the vertex tasks of
/// [`vertex_task_len`], on the calling thread below [`SERIAL_ROWS`] rows).
pub fn all_rows(n: usize, check: impl Fn(Range<usize>) -> bool + Sync) -> bool {
    if n < SERIAL_ROWS {
        return check(0..n);
    }
    let len = vertex_task_len(n);
    let tasks = n.div_ceil(len);
    let range = |t: usize| t * len..((t + 1) * len).min(n);
    if runs_serially(tasks) {
        (0..tasks).all(|t| check(range(t)))
    } else {
        (0..tasks).into_par_iter().all(|t| check(range(t)))
    }
}

/// Reduce `0..n` by `map` over fixed chunks and `combine` in chunk order. The chunk results are collected
/// in `parts` (reused: no allocation once it has grown to the chunk count).
pub fn reduce_chunks<A, M, C>(
    n: usize,
    chunk: usize,
    parts: &mut Vec<A>,
    map: M,
    combine: C,
) -> Option<A>
where
    A: Default + Send,
    M: Fn(Range<usize>) -> A + Sync,
    C: Fn(A, A) -> A,
{
    parts.clear();
    parts.resize_with(n.div_ceil(chunk), A::default);
    for_each_mut(parts, |c, part| {
        *part = map(c * chunk..((c + 1) * chunk).min(n))
    });
    parts.drain(..).reduce(combine)
}

/// Runs `task(i)` exactly once for every `i` in `0..n`: on the current rayon pool's threads, or in order on the
/// calling thread where one thread would run them anyway ([`serial`], a pool of one thread, a single task).
/// Which thread runs a task changes nothing in its result: callers that keep per-task results and combine
/// them in index order are bit-identical for any thread count. `task` may use rayon itself.
pub fn for_each_task(n: usize, task: impl Fn(usize) + Sync) {
    if runs_serially(n) {
        (0..n).for_each(task);
    } else {
        (0..n).into_par_iter().for_each(&task);
    }
}

/// Whether a loop of `tasks` tasks runs on the calling thread: a single task, or a single thread to run them.
fn runs_serially(tasks: usize) -> bool {
    tasks <= 1 || current_threads() <= 1
}

/// Runs `f` on a thread of a rayon pool: at once on the calling thread when that is one of a pool's threads
/// (inside `ThreadPool::install`, or a task), else on a thread of the global pool while the caller waits.
///
/// Why: every parallel region that a thread outside the pools enters is sent to the global pool as a job, and
/// the caller sleeps until it is done; a step enters several regions. Entered once per step (or once per batch
/// of steps), the hop is paid once.
///
/// Inside [`serial`], at once on the calling thread (no pool is used there).
pub fn on_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() || is_serial() {
        f()
    } else {
        rayon::scope(|_| f())
    }
}

thread_local! {
    /// Whether this thread is inside [`serial`].
    static SERIAL: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` on the calling thread with every parallel pass of this crate in it run there too, in task order,
/// without any thread pool: [`current_threads`] reads 1 and [`on_pool`] does nothing.
///
/// Why: a pool of one thread runs the same work on its own thread, which the caller must wake (and which
/// parks again after the call), for every call. The results keep their bits (the tasks are the same fixed
/// chunks, in order).
pub fn serial<R>(f: impl FnOnce() -> R) -> R {
    /// Restores the flag when `f` returns or unwinds.
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            SERIAL.with(|s| s.set(self.0));
        }
    }
    let _restore = Restore(SERIAL.with(|s| s.replace(true)));
    f()
}

/// Whether the calling thread is inside [`serial`].
fn is_serial() -> bool {
    SERIAL.with(|s| s.get())
}

/// The threads that this crate's parallel passes use from the calling thread: the current rayon pool's (the
/// global pool's outside every pool), or 1 inside [`serial`].
pub fn current_threads() -> usize {
    if is_serial() {
        1
    } else {
        rayon::current_num_threads()
    }
}

/// `f(c, chunk)` for every chunk `c` of `data` cut into chunks of `len` (the last may be shorter), in
/// parallel.
pub fn for_each_chunk_mut<T: Send>(data: &mut [T], len: usize, f: impl Fn(usize, &mut [T]) + Sync) {
    assert!(len > 0, "chunks of at least one element");
    if runs_serially(data.len().div_ceil(len)) {
        data.chunks_mut(len).enumerate().for_each(|(c, x)| f(c, x));
    } else {
        data.par_chunks_mut(len)
            .enumerate()
            .for_each(|(c, x)| f(c, x));
    }
}

/// `f(i, &mut items[i])` for every item, in parallel: one result slot per task.
pub fn for_each_mut<T: Send>(items: &mut [T], f: impl Fn(usize, &mut T) + Sync) {
    if runs_serially(items.len()) {
        items.iter_mut().enumerate().for_each(|(i, x)| f(i, x));
    } else {
        items.par_iter_mut().enumerate().for_each(|(i, x)| f(i, x));
    }
}

/// The number of chunks of `len` elements (the last may be shorter) in `n` elements, checked equal across
/// the slices of one loop.
fn same_count(lens: &[(usize, usize)]) -> usize {
    let count = |&(n, len): &(usize, usize)| {
        assert!(len > 0, "chunks of at least one element");
        n.div_ceil(len)
    };
    let first = count(&lens[0]);
    assert!(
        lens.iter().all(|l| count(l) == first),
        "the same number of chunks"
    );
    first
}

/// [`for_each_chunk_mut`] over two slices cut into the same number of chunks (`a` into chunks of `len_a`,
/// `b` into chunks of `len_b`): `f(c, a_chunk, b_chunk)`.
pub fn for_each_chunk_mut2<A: Send, B: Send>(
    a: &mut [A],
    len_a: usize,
    b: &mut [B],
    len_b: usize,
    f: impl Fn(usize, &mut [A], &mut [B]) + Sync,
) {
    let chunks = same_count(&[(a.len(), len_a), (b.len(), len_b)]);
    if runs_serially(chunks) {
        let pairs = a.chunks_mut(len_a).zip(b.chunks_mut(len_b));
        pairs.enumerate().for_each(|(c, (a, b))| f(c, a, b));
    } else {
        let pairs = a.par_chunks_mut(len_a).zip(b.par_chunks_mut(len_b));
        pairs.enumerate().for_each(|(c, (a, b))| f(c, a, b));
    }
}

/// [`for_each_chunk_mut2`] over three slices cut into the same number of chunks: `f(c, a_chunk, b_chunk,
/// c_chunk)`.
#[allow(clippy::too_many_arguments)]
pub fn for_each_chunk_mut3<A: Send, B: Send, C: Send>(
    a: &mut [A],
    len_a: usize,
    b: &mut [B],
    len_b: usize,
    c: &mut [C],
    len_c: usize,
    f: impl Fn(usize, &mut [A], &mut [B], &mut [C]) + Sync,
) {
    let chunks = same_count(&[(a.len(), len_a), (b.len(), len_b), (c.len(), len_c)]);
    if runs_serially(chunks) {
        let triples = a
            .chunks_mut(len_a)
            .zip(b.chunks_mut(len_b))
            .zip(c.chunks_mut(len_c));
        triples
            .enumerate()
            .for_each(|(k, ((a, b), c))| f(k, a, b, c));
    } else {
        let triples = a
            .par_chunks_mut(len_a)
            .zip(b.par_chunks_mut(len_b))
            .zip(c.par_chunks_mut(len_c));
        triples
            .enumerate()
            .for_each(|(k, ((a, b), c))| f(k, a, b, c));
    }
}

/// [`for_each_chunk_mut3`] over four slices cut into the same number of chunks: `f(k, a_chunk, b_chunk,
/// c_chunk, d_chunk)`.
#[allow(clippy::too_many_arguments)]
pub fn for_each_chunk_mut4<A: Send, B: Send, C: Send, D: Send>(
    a: &mut [A],
    len_a: usize,
    b: &mut [B],
    len_b: usize,
    c: &mut [C],
    len_c: usize,
    d: &mut [D],
    len_d: usize,
    f: impl Fn(usize, &mut [A], &mut [B], &mut [C], &mut [D]) + Sync,
) {
    let chunks = same_count(&[
        (a.len(), len_a),
        (b.len(), len_b),
        (c.len(), len_c),
        (d.len(), len_d),
    ]);
    if runs_serially(chunks) {
        let quads = (a.chunks_mut(len_a).zip(b.chunks_mut(len_b)))
            .zip(c.chunks_mut(len_c).zip(d.chunks_mut(len_d)));
        quads
            .enumerate()
            .for_each(|(k, ((a, b), (c, d)))| f(k, a, b, c, d));
    } else {
        let quads = (a.par_chunks_mut(len_a).zip(b.par_chunks_mut(len_b)))
            .zip(c.par_chunks_mut(len_c).zip(d.par_chunks_mut(len_d)));
        quads
            .enumerate()
            .for_each(|(k, ((a, b), (c, d)))| f(k, a, b, c, d));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Runs `f` on another thread and fails if it does not finish within a minute (a deadlock).
    fn finishes<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || tx.send(f()).unwrap());
        rx.recv_timeout(std::time::Duration::from_secs(60))
            .expect("finished (no deadlock)")
    }

    fn sum_of_sines(n: usize) -> f64 {
        reduce_chunks(
            n,
            1000,
            &mut Vec::new(),
            |r| r.map(|i| (i as f64).sin()).sum::<f64>(),
            |a, b| a + b,
        )
        .unwrap()
    }

    #[test]
    fn tet_chunks_are_whole_blocks_and_cut_small_meshes_finer() {
        for k in [
            0, 1, 100, 1_296, 4_406, 10_368, 16_383, 16_384, 19_379, 29_548, 32_767, 32_768,
            10_000_000,
        ] {
            let c = tet_chunk_for(k);
            assert!(
                c.is_power_of_two() && (MIN_TET_CHUNK..=TET_CHUNK).contains(&c),
                "{k}: {c}"
            );
            // At least 16 chunks where the smallest length allows it, at least 32 from 16,384 tets; fewer
            // than 64 where the mesh is cut finer than TET_CHUNK.
            if k >= 16 * MIN_TET_CHUNK {
                assert!(k.div_ceil(c) >= 16, "{k}: {c}");
            }
            if k >= 16_384 {
                assert!(k.div_ceil(c) >= 32, "{k}: {c}");
            }
            if MIN_TET_CHUNK < c && c < TET_CHUNK {
                assert!(k / c < 64, "{k}: {c}");
            }
        }
        assert_eq!(tet_chunk_for(1_296), MIN_TET_CHUNK);
        assert_eq!(tet_chunk_for(4_406), 256);
        assert_eq!(tet_chunk_for(10_368), 512);
        assert_eq!(tet_chunk_for(19_379), 512);
        assert_eq!(tet_chunk_for(29_548), 512);
        assert_eq!(tet_chunk_for(32_768), TET_CHUNK);
    }

    /// `f` inside a fresh pool of `threads` threads, on another thread, failing on a deadlock.
    fn on_pool<T: Send + 'static>(threads: usize, f: impl FnOnce() -> T + Send + 'static) -> T {
        finishes(move || {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(f)
        })
    }

    /// The step's row passes, serial below `SERIAL_ROWS` and in tasks above, on pools of 1-3 threads: a copy
    /// is exact, a failed check in any one task (first, middle, last row) is seen, and `row_tasks2` hands
    /// every row to `f` once with its index.
    #[test]
    fn row_passes_copy_check_and_visit_every_row_on_any_pool() {
        for threads in [1, 2, 3] {
            on_pool(threads, move || {
                for n in [0, 1, 300, SERIAL_ROWS - 1, SERIAL_ROWS, 5000] {
                    let src: Vec<[f64; 3]> = (0..n).map(|i| [i as f64, -(i as f64), 0.5]).collect();
                    let mut dst = vec![[9.0; 3]; 7];
                    copy_rows(&src, &mut dst);
                    assert_eq!(dst, src, "copy of {n} rows, {threads} threads");
                    assert!(all_rows(n, |r| r.into_iter().all(|i| src[i][2] == 0.5)));
                    for bad in [0, n / 2, n.saturating_sub(1)]
                        .into_iter()
                        .filter(|_| n > 0)
                    {
                        let seen = all_rows(n, |r| r.into_iter().all(|i| i != bad));
                        assert!(
                            !seen,
                            "row {bad} of {n} failed its check, {threads} threads"
                        );
                    }
                    let (mut a, mut b) = (vec![0usize; n], vec![0usize; n]);
                    row_tasks2(&mut a, &mut b, |first, a, b| {
                        for (k, (x, y)) in a.iter_mut().zip(b.iter_mut()).enumerate() {
                            (*x, *y) = (*x + first + k, *y + 1);
                        }
                    });
                    assert!(a.iter().enumerate().all(|(i, &x)| x == i), "{n} rows");
                    assert!(b.iter().all(|&y| y == 1), "every row once, {n} rows");
                }
            });
        }
    }

    #[test]
    fn every_task_runs_exactly_once_on_any_pool() {
        for threads in [1, 2, 3, 5] {
            let runs = on_pool(threads, || {
                [0, 1, 2, 3, 7, 11, 64, 1000].map(|n| {
                    let runs: Vec<AtomicUsize> = (0..n).map(|_| AtomicUsize::new(0)).collect();
                    for_each_task(n, |i| {
                        runs[i].fetch_add(1, Ordering::Relaxed);
                        // Parallel work inside a task (it may pick up another worker) must not deadlock.
                        if i % 5 == 0 {
                            assert_eq!(sum_of_sines(3000), sum_of_sines(3000));
                        }
                    });
                    runs.iter().all(|r| r.load(Ordering::Relaxed) == 1)
                })
            });
            assert!(runs.iter().all(|&once| once), "{threads} threads: {runs:?}");
        }
    }

    #[test]
    fn chunks_cover_the_slices_once_in_order() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        pool.install(|| {
            let (mut a, mut b) = (vec![0usize; 103], vec![0usize; 21]);
            // 103 elements in chunks of 5: 21 chunks, the last of 3.
            for_each_chunk_mut2(&mut a, 5, &mut b, 1, |c, ca, cb| {
                assert_eq!(ca.len(), if c == 20 { 3 } else { 5 });
                ca.iter_mut().enumerate().for_each(|(k, e)| *e += c * 5 + k);
                cb[0] += c;
            });
            assert_eq!(a, (0..103).collect::<Vec<_>>());
            assert_eq!(b, (0..21).collect::<Vec<_>>());
            let mut e: Vec<u8> = Vec::new();
            for_each_chunk_mut(&mut e, 4, |_, _| panic!("no chunks in an empty slice"));
        });
    }

    #[test]
    fn reduction_is_bit_identical_across_thread_counts() {
        let data: Vec<f64> = (0..100_003)
            .map(|i| ((i as f64) * 0.7).sin() * 1e3 + 1e-7 * i as f64)
            .collect();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    reduce_chunks(
                        data.len(),
                        1000,
                        &mut Vec::new(),
                        |r| data[r].iter().sum::<f64>(),
                        |a, b| a + b,
                    )
                    .unwrap()
                })
        };
        let one = run(1);
        assert_eq!(one.to_bits(), run(2).to_bits());
        assert_eq!(one.to_bits(), run(3).to_bits());
    }

    /// Inside `serial`, every loop runs on the calling thread (no pool thread sees a task), in chunk order, and
    /// gives the bits of a pool of three threads.
    #[test]
    fn serial_runs_every_loop_on_the_calling_thread_with_the_same_bits() {
        let want = on_pool(3, || sum_of_sines(50_000).to_bits());
        let (bits, order, on_pool_thread) = finishes(|| {
            serial(|| {
                assert_eq!(current_threads(), 1);
                let seen = std::sync::Mutex::new(Vec::new());
                let mut data = vec![0u8; 1000];
                for_each_chunk_mut(&mut data, 10, |c, _| {
                    let pool_thread = rayon::current_thread_index().is_some();
                    seen.lock().unwrap().push((c, pool_thread));
                });
                let seen = seen.into_inner().unwrap();
                let order = seen.iter().map(|s| s.0).eq(0..100);
                let on_pool_thread = seen.iter().any(|s| s.1);
                (sum_of_sines(50_000).to_bits(), order, on_pool_thread)
            })
        });
        assert_eq!(bits, want);
        assert!(order, "chunk order");
        assert!(!on_pool_thread, "no pool thread");
    }
}
