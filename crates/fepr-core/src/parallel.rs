//! Deterministic parallel reductions: the input is cut into fixed-size chunks (independent of the number of
//! threads), each chunk is reduced sequentially, and the chunk results are combined in chunk order. The
//! result is therefore bit-identical for any thread count.

use rayon::prelude::*;
use std::ops::Range;

/// Chunk length for per-tet loops: the largest, used on meshes of 32 chunks or more (a smaller mesh is cut
/// finer: [`tet_chunk_for`]).
pub const TET_CHUNK: usize = 1024;

/// The smallest chunk length of the per-tet loops.
pub const MIN_TET_CHUNK: usize = 128;

/// Tets per chunk of the per-tet loops on a mesh of `k` tets, a power of two: [`TET_CHUNK`] from 32,768 tets;
/// below, about a thirty-second of the mesh while that is at least 512 tets (16,384 tets and more), else about a
/// sixteenth (at least [`MIN_TET_CHUNK`]). So two threads get near-equal shares of small and mid-sized meshes:
/// with 1024-tet chunks the 4,406-tet armadillo had five chunks, three on one thread and two on the other (at
/// most 1.43x on two threads), a 1,296-tet box two (1.27x), and the 19,379-tet bunny 19 (measured 1.59-1.62x
/// against 1.80x with 512-tet chunks, alternated). Finer than a sixteenth below 16,384 tets measured no
/// better (box 10k) or worse (armadillo: 1.66x with 128-tet chunks against 1.85x with 256): each chunk's
/// border vertices are summed from several chunks. The length depends on `k` alone, never on the thread
/// count: the sums keep their bits for any number of threads.
pub fn tet_chunk_for(k: usize) -> usize {
    let floor_pow2 = |n: usize| 1usize << (usize::BITS - 1 - n.max(1).leading_zeros());
    let thirty_second = floor_pow2(k / 32);
    if thirty_second >= 512 {
        thirty_second.min(TET_CHUNK)
    } else {
        floor_pow2(k / 16).clamp(MIN_TET_CHUNK, TET_CHUNK)
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
    A: Send,
    M: Fn(Range<usize>) -> A + Sync,
    C: Fn(A, A) -> A,
{
    (0..n.div_ceil(chunk))
        .into_par_iter()
        .map(|c| map(c * chunk..((c + 1) * chunk).min(n)))
        .collect_into_vec(parts);
    parts.drain(..).reduce(combine)
}

/// While alive, keeps the thread pool's other threads polling for work (as OpenMP runtimes spin-wait between
/// parallel regions) instead of parking, so that the parallel regions of one simulation step start on
/// threads that are already running. Rayon parks an idle thread after a few dozen yields, and waking it
/// costs tens of microseconds on a virtual machine (an interrupt between virtual CPUs), once per region;
/// a Projective Dynamics step enters about 30 (three per PD iteration: local step, right-hand side, solve),
/// a symplectic Euler + FEPR step 6-8 (counted in the code). Measured on the
/// bunny (2 threads, alternating runs): PD + FEPR 25.6-26.1 -> 17.5-25.6 ms per step, and bunny2 symplectic
/// Euler + FEPR 2.29-3.13 -> 2.15-2.52 ms. The other threads run at full load while the guard lives, doing the
/// pool's work as soon as there is any, and yield to the operating system whenever there is none (other
/// processes that want the CPU get it); nothing about the results changes (the work is cut into the same
/// fixed chunks).
pub struct KeepAwake {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl KeepAwake {
    /// Start polling on the current pool's other threads (all of them when called from outside the pool).
    #[allow(clippy::new_without_default)] // starting threads is not a default value
    pub fn new() -> Self {
        use std::sync::atomic::{AtomicBool, Ordering};
        let stop = std::sync::Arc::new(AtomicBool::new(false));
        let own = rayon::current_thread_index();
        let others = rayon::current_num_threads().saturating_sub(own.is_some() as usize);
        for _ in 0..others {
            let stop = std::sync::Arc::clone(&stop);
            rayon::spawn(move || {
                // The thread that holds the guard may pick this job up while it waits for other work: it
                // must not poll for its own guard's end (it would wait for itself).
                if rayon::current_thread_index() == own {
                    return;
                }
                while !stop.load(Ordering::Acquire) {
                    if rayon::yield_now() != Some(rayon::Yield::Executed) {
                        // Nothing to do: let any other runnable thread of the machine (a viewer, a browser)
                        // go first; with none, this returns at once and the thread stays awake.
                        std::thread::yield_now();
                    }
                }
            });
        }
        Self { stop }
    }
}

impl Drop for KeepAwake {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Release);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn keep_awake_changes_no_bits_and_never_waits_for_itself() {
        let want = sum_of_sines(50_000).to_bits();
        for threads in [1, 2, 3] {
            let got = finishes(move || {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                // Held inside the pool (its own spinner may come back to it), across many regions.
                let inside = pool.install(|| {
                    let _awake = KeepAwake::new();
                    (0..20)
                        .map(|_| sum_of_sines(50_000).to_bits())
                        .collect::<Vec<_>>()
                });
                // Guards held by pool tasks running side by side, each doing parallel work.
                let nested: Vec<u64> = pool.install(|| {
                    (0..8)
                        .into_par_iter()
                        .map(|_| {
                            let _awake = KeepAwake::new();
                            sum_of_sines(50_000).to_bits()
                        })
                        .collect()
                });
                (inside, nested)
            });
            assert!(
                got.0.iter().chain(&got.1).all(|&b| b == want),
                "{threads} threads"
            );
        }
        // Held outside any pool: the global pool's threads poll.
        let outside = finishes(|| {
            let _awake = KeepAwake::new();
            sum_of_sines(50_000).to_bits()
        });
        assert_eq!(outside, want);
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
}
