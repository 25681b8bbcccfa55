//! Deterministic parallel reductions: the input is cut into fixed-size chunks (independent of the number of
//! threads), each chunk is reduced sequentially, and the chunk results are combined in chunk order. The
//! result is therefore bit-identical for any thread count.

use rayon::prelude::*;
use std::ops::Range;

/// Chunk length for per-tet loops.
pub const TET_CHUNK: usize = 1024;

/// Reduce `0..n` by `map` over fixed chunks and `combine` in chunk order.
pub fn reduce_chunks<A, M, C>(n: usize, chunk: usize, map: M, combine: C) -> Option<A>
where
    A: Send,
    M: Fn(Range<usize>) -> A + Sync,
    C: Fn(A, A) -> A,
{
    let num_chunks = n.div_ceil(chunk);
    let parts: Vec<A> = (0..num_chunks)
        .into_par_iter()
        .map(|c| map(c * chunk..((c + 1) * chunk).min(n)))
        .collect();
    parts.into_iter().reduce(combine)
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
            |r| r.map(|i| (i as f64).sin()).sum::<f64>(),
            |a, b| a + b,
        )
        .unwrap()
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
