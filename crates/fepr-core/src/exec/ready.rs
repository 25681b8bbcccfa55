//! Keeping a pool's threads ready through one step: between the parallel passes of a step, the pool's other
//! threads poll for the next pass's chunks instead of parking.
//!
//! Why: rayon parks a worker that has found no job for a few dozen polls (a few microseconds), and waking it
//! takes a system call and a reschedule (about 15 us on a 2-core virtual machine, measured per pass). A step
//! enters 10 to 20 parallel passes separated by short serial stretches (the projection's small solves, the
//! books), so the parked worker joins each pass late, and the caller does most of the pass alone: an explicit
//! step with FEPR on 20k-100k tets ran 13-15% slower than with workers that stayed ready. rayon has no
//! setting for that; its public `yield_now` (run a pending job of this pool if there is one) lets a job poll.
//!
//! How: for the duration of `f`, one polling job per other thread of the pool is spawned in a scope; each runs
//! the pool's pending jobs as they appear (the chunks of every pass, faer's tasks) and spins between them. A
//! poller leaves when `f` has returned (or unwound), or when it has found no job for [`IDLE_LIMIT`]: a poller
//! that a busy thread picked up while it waited for its own work (two steps of two simulations on one pool)
//! holds that thread for at most that long, and a long serial stretch (an ordering, a factorisation) costs
//! no more than that of spinning. Which thread runs a chunk changes no result bit (see [`super::parallel`]).

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// How long a poller spins without finding a job before it leaves (and the thread parks as rayon's do).
/// Longer than a step's serial stretches between passes (at most tens of microseconds), far shorter than a
/// step.
pub const IDLE_LIMIT: Duration = Duration::from_micros(250);

/// Runs `f` on the calling thread while the current rayon pool's other threads poll for its parallel passes'
/// chunks (see the module's comment). Runs `f` alone where there is no other thread to keep ready: outside
/// every pool, inside [`super::serial`], or in a pool of one thread.
pub fn with_threads_ready<R>(f: impl FnOnce() -> R) -> R {
    let others = super::current_threads().saturating_sub(1);
    if others == 0 || rayon::current_thread_index().is_none() {
        return f();
    }
    /// Tells the pollers to leave when `f` returns or unwinds (else the scope would wait for them forever).
    struct Done<'a>(&'a AtomicBool);
    impl Drop for Done<'_> {
        fn drop(&mut self) {
            self.0.store(true, Ordering::Release);
        }
    }
    let done = AtomicBool::new(false);
    rayon::in_place_scope(|scope| {
        for _ in 0..others {
            scope.spawn(|_| poll_until(&done));
        }
        let _done = Done(&done);
        f()
    })
}

/// Runs this pool's pending jobs until `done` is set or none has appeared for [`IDLE_LIMIT`].
fn poll_until(done: &AtomicBool) {
    let mut last_job = Instant::now();
    while !done.load(Ordering::Acquire) {
        if rayon::yield_now() == Some(rayon::Yield::Executed) {
            last_job = Instant::now();
        } else if last_job.elapsed() > IDLE_LIMIT {
            return;
        } else {
            std::hint::spin_loop();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;

    fn pool(threads: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
    }

    #[test]
    fn passes_inside_keep_their_bits_and_every_task_runs_once() {
        let sum = |threads: usize, ready: bool| {
            pool(threads).install(|| {
                let run = || {
                    let mut parts = Vec::new();
                    let mut total = 0.0f64;
                    for pass in 0..20 {
                        let s = super::super::reduce_chunks(
                            10_000,
                            97,
                            &mut parts,
                            |r| r.map(|i| ((i * (pass + 1)) as f64).sin()).sum::<f64>(),
                            |a, b| a + b,
                        );
                        total += s.unwrap();
                    }
                    total.to_bits()
                };
                if ready {
                    with_threads_ready(run)
                } else {
                    run()
                }
            })
        };
        let want = sum(1, false);
        for threads in 1..=4 {
            assert_eq!(sum(threads, true), want, "{threads} threads");
        }
        let count = AtomicUsize::new(0);
        pool(3).install(|| {
            with_threads_ready(|| {
                super::super::for_each_task(1000, |_| {
                    count.fetch_add(1, Ordering::Relaxed);
                })
            })
        });
        assert_eq!(count.into_inner(), 1000);
    }

    #[test]
    fn a_panic_inside_reaches_the_caller_and_releases_the_pollers() {
        let p = pool(3);
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            p.install(|| with_threads_ready(|| panic!("inside the step")))
        }));
        assert!(caught.is_err());
        // The pool is free again: a pass on all its threads finishes.
        let n = p.install(|| with_threads_ready(|| (0..1000u64).map(|i| i * i).sum::<u64>()));
        assert_eq!(n, 332_833_500);
    }

    #[test]
    fn two_steps_on_one_pool_both_finish() {
        // Each step's pollers may be picked up by the thread running the other step while it waits for a
        // chunk; the idle limit releases them, so neither waits on the other for good.
        let p = pool(2);
        let step = || {
            with_threads_ready(|| {
                let mut parts = Vec::new();
                let mut t = 0.0;
                for _ in 0..200 {
                    t += super::super::reduce_chunks(
                        4096,
                        64,
                        &mut parts,
                        |r| r.len() as f64,
                        |a, b| a + b,
                    )
                    .unwrap();
                }
                t
            })
        };
        let (a, b) = p.install(|| rayon::join(step, step));
        assert_eq!((a, b), (819_200.0, 819_200.0));
    }

    #[test]
    fn without_other_threads_it_just_runs() {
        assert_eq!(with_threads_ready(|| 7), 7, "outside every pool");
        assert_eq!(pool(1).install(|| with_threads_ready(|| 8)), 8);
        assert_eq!(super::super::serial(|| with_threads_ready(|| 9)), 9);
    }
}
