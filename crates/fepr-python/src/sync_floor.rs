//! What synchronising threads costs on this machine: the floor under the two-thread speed-up of a small
//! evaluation, which `fepr bench` reports with the machine (`bench_sync_floor`).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The two numbers of [`measure`].
pub struct SyncFloor {
    /// Seconds per rayon region that every thread of the current pool joins (`rayon::broadcast`, no work in
    /// it), regions back to back: the best batch's mean.
    pub region_s: f64,
    /// Seconds for a value to go from one thread to another and back through two atomics on cache lines of
    /// their own, both threads spinning: the best batch's mean. NaN where the machine has a single CPU.
    pub round_trip_s: f64,
}

/// Measures [`SyncFloor`] on the current pool in about `budget`, after 20 ms of warm-up (a fresh pool's
/// threads take milliseconds to start on a virtual machine). The round trip uses a thread of its own.
pub fn measure(budget: Duration) -> SyncFloor {
    let half = budget / 2;
    let region = || {
        rayon::broadcast(|ctx| {
            std::hint::black_box(ctx.index());
        });
    };
    let warm = Instant::now();
    while warm.elapsed() < Duration::from_millis(20) {
        region();
    }
    let region_s = best_batch_mean(half, 200, region);
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    let round_trip_s = if cpus < 2 { f64::NAN } else { round_trip(half) };
    SyncFloor {
        region_s,
        round_trip_s,
    }
}

/// The smallest mean seconds per call of `f` over batches of `per_batch` calls, for about `budget` (at least
/// one batch).
fn best_batch_mean(budget: Duration, per_batch: u32, mut f: impl FnMut()) -> f64 {
    let start = Instant::now();
    let mut best = f64::INFINITY;
    loop {
        let t0 = Instant::now();
        for _ in 0..per_batch {
            f();
        }
        best = best.min(t0.elapsed().as_secs_f64() / f64::from(per_batch));
        if start.elapsed() >= budget {
            return best;
        }
    }
}

/// A counter on a cache line of its own.
#[repr(align(64))]
struct Padded(AtomicUsize);

/// [`SyncFloor::round_trip_s`]: the caller writes `n` to one line, a second thread answers `n` on another.
fn round_trip(budget: Duration) -> f64 {
    let ping = Arc::new([Padded(AtomicUsize::new(0)), Padded(AtomicUsize::new(0))]);
    let pong = Arc::clone(&ping);
    // usize::MAX tells the answering thread to stop.
    let answer = std::thread::spawn(move || {
        let (mut seen, mut spins) = (0, 0u32);
        loop {
            let n = pong[0].0.load(Ordering::Acquire);
            if n == usize::MAX {
                return;
            }
            if n != seen {
                seen = n;
                pong[1].0.store(n, Ordering::Release);
                spins = 0;
            } else {
                spin_or_yield(&mut spins);
            }
        }
    });
    let mut n = 0;
    let mut once = || {
        n += 1;
        ping[0].0.store(n, Ordering::Release);
        let mut spins = 0;
        while ping[1].0.load(Ordering::Acquire) != n {
            spin_or_yield(&mut spins);
        }
    };
    // The answering thread's first answer includes its start: warm up before timing.
    for _ in 0..1000 {
        once();
    }
    let best = best_batch_mean(budget, 2000, &mut once);
    ping[0].0.store(usize::MAX, Ordering::Release);
    answer.join().expect("the answering thread does not panic");
    best
}

/// A spin-wait step that gives the CPU to the OS after many fruitless spins (the other thread descheduled).
fn spin_or_yield(spins: &mut u32) {
    *spins += 1;
    if *spins < 10_000 {
        std::hint::spin_loop();
    } else {
        std::thread::yield_now();
    }
}
