//! Deterministic parallel reductions: the input is cut into fixed-size chunks (independent of the number of
//! threads), each chunk is reduced sequentially, and the chunk results are combined in chunk order. The
//! result is therefore bit-identical for any thread count.

use std::ops::Range;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

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

/// Vertices per task of every pass over the vertices' rows (the elastic gradient's vertex sums, the
/// projection's passes, symplectic Euler's update), for a mesh of `m` vertices: about an eighth of the mesh,
/// 64 to 2048, a multiple of 4 (the projection's moment lanes).
///
/// One length for all of them, because [`for_each_task`] gives a task index the same home thread in every
/// pass: a thread then reads the rows that it wrote itself in the pass before, from its own cache. On two
/// threads of this project's benchmark machine, the projection's first moment pass on the elephant (7,008
/// vertices) took 70 us after a base step that had written the state on one thread, and 49 us after one
/// that wrote it in these tasks.
///
/// The length depends on `m` alone, never on the thread count: sums taken per task and combined in task
/// order keep their bits for any number of threads. About an eighth, so that two threads get equal shares of
/// the small and mid-sized meshes (with 2048-vertex tasks the armadillo's 1,446 vertices were one task, and
/// its projection ran slower on two threads than on one); at least 64 (a task's overhead); at most 2048 (a
/// task's rows stay in L1/L2).
pub fn vertex_task_len(m: usize) -> usize {
    m.div_ceil(8).next_multiple_of(4).clamp(64, 2048)
}

/// Rows below which the per-row passes of a step ([`row_tasks2`], [`copy_rows`], [`all_rows`]) run on the
/// calling thread: there a parallel region (about a microsecond on this project's benchmark machine; `fepr
/// bench` reports it) costs more than the pass. Measured there (two threads), symplectic Euler's base step
/// with its kick and drift and the step's copies and checks of the state: the 1k box (343 vertices) took
/// 3.4-3.5 us with all of them serial, 5.6 with the kick and drift in tasks, 7.5-7.7 with everything in
/// tasks; the armadillo (1,446) 14.7-14.8 us in tasks, 16.1-17.2 with the copies and checks serial.
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
/// tasks of [`vertex_task_len`] from [`SERIAL_ROWS`] rows on. Why in those tasks: a step's copies of the
/// state (the start of step kept for an undo, an offered gradient's positions) were serial passes, a third of
/// a symplectic Euler step's base time on the elephant; in the tasks, each thread copies the rows that it
/// wrote, from its own cache.
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

/// Whether `check(range)` holds for every task's range of rows `0..n` (the vertex tasks of
/// [`vertex_task_len`], on the calling thread below [`SERIAL_ROWS`] rows). Every task is checked (no early
/// exit across threads): for the checks of a step that nearly always hold.
pub fn all_rows(n: usize, check: impl Fn(Range<usize>) -> bool + Sync) -> bool {
    if n < SERIAL_ROWS {
        return check(0..n);
    }
    let len = vertex_task_len(n);
    let all = std::sync::atomic::AtomicBool::new(true);
    for_each_task(n.div_ceil(len), |t| {
        if !check(t * len..((t + 1) * len).min(n)) {
            all.store(false, Ordering::Relaxed);
        }
    });
    all.into_inner()
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

/// Runs `task(i)` exactly once for every `i` in `0..n`, on up to all of the current pool's threads. `0..n`
/// is cut into one contiguous home range per thread (by the thread's index in the pool, so the same thread
/// gets the same part in every call); each thread runs its own range first, in order, then helps with the
/// others' ranges, claiming their next tasks from the same counters. A thread that is late or busy elsewhere
/// simply runs fewer tasks. The caller's thread is one of the workers: it never waits for a thread that has not
/// started, only for tasks already running. Where the caller holds a [`KeepAwake`] guard whose polling threads
/// are all present, the region goes to them through one cache line (the guard's team: about 0.55 us per region
/// on two threads of this project's benchmark machine, against 0.9-1.0 us through rayon); otherwise the workers
/// are started by nested `rayon::join` (no allocation).
///
/// Why home ranges: the per-tet chunks and the per-vertex tasks follow space together (Z-curve orders), so
/// a thread that keeps the same part of the mesh in every pass and every evaluation mostly reads what it
/// wrote itself, from its own cache. With rayon's parallel iterators (split in halves, stolen at random)
/// each pass read about half of its input from the other core's cache, and the splitting itself cost more
/// than the work it balanced on small meshes (11 tet chunks on the 1k box).
///
/// Which thread runs a task changes nothing in its result: callers that keep per-task results and combine
/// them in index order are bit-identical for any thread count. `task` may use rayon itself (a worker that
/// waits there may pick up another worker of this call, which only claims more tasks).
pub fn for_each_task(n: usize, task: impl Fn(usize) + Sync) {
    let workers = current_threads().min(MAX_HOME_RANGES).min(n);
    if workers <= 1 {
        (0..n).for_each(task);
        return;
    }
    if Team::run_on_current(n, workers, &task) {
        return;
    }
    // Range r is `start(r)..start(r + 1)`; `next[r]` is its next unclaimed task.
    let start = |r: usize| r * n / workers;
    let next: [Padded; MAX_HOME_RANGES] =
        std::array::from_fn(|r| Padded(AtomicUsize::new(start(r))));
    let worker = || {
        let home = rayon::current_thread_index().unwrap_or(0) % workers;
        for r in (home..workers).chain(0..home) {
            let end = start(r + 1);
            loop {
                let i = next[r].0.fetch_add(1, Ordering::Relaxed);
                if i >= end {
                    break;
                }
                task(i);
            }
        }
    };
    start_workers(workers, &worker);
}

/// The pool's other threads while a [`KeepAwake`] guard lives, spinning on one cache line for the regions of
/// [`for_each_task`] that the guard's thread posts (as an OpenMP team waits between parallel regions).
///
/// Why: a region costs its threads the cache lines that they hand each other, about 0.1 us each on this
/// project's benchmark machine. Started through `rayon::join`, a region passes about eight (rayon's queue and
/// latch, the region's counters, written by the first thread and claimed from by the second); here the
/// post, the join, the end and the region's description share one line, and every home range keeps its own
/// counter line, tagged with the region's number, in the cache of the thread that claims from it.
///
/// The team's whole state is one word, so that posting a region, joining it, closing it and leaving the team
/// are each one atomic step on it: a region is posted only while every other thread of the pool is a member,
/// and a member leaves only after it has joined every region posted while it was one. A member that is busy
/// elsewhere (a rayon job) simply joins late or not at all: the region's tasks are claimed by whoever runs,
/// the posting thread included, so nothing waits for a member that has not joined.
struct Team {
    line: TeamLine,
    /// Per home range, `epoch << INDEX_BITS | next`: the next unclaimed task of range `r` in region `epoch`
    /// (another region's number: the range is untouched in this region, its next task is its first).
    next: [Padded64; MAX_HOME_RANGES],
    /// The first panic of a member in the current region, resumed on the posting thread.
    panic: std::sync::Mutex<Option<Box<dyn std::any::Any + Send>>>,
    /// Set when the team's guard drops: the members leave.
    stop: Arc<std::sync::atomic::AtomicBool>,
    /// Whether polling jobs are on their way to the threads that are not members (set by whoever sends them,
    /// cleared by the first that arrives): the team calls its threads back at most once at a time.
    calling: std::sync::atomic::AtomicBool,
}

/// What the members read to join and run a region: one cache line.
#[repr(align(64))]
struct TeamLine {
    /// `epoch << EPOCH_SHIFT | CLOSED? | present << PRESENT_SHIFT | joined`: the last posted region's number,
    /// whether it takes no more members, the members in their polling loop, and how many joined it.
    state: std::sync::atomic::AtomicU64,
    /// Members that have finished the current region.
    done: AtomicUsize,
    /// The posted region: its tasks (the lifetime erased: valid until the region is closed and every member
    /// that joined it is done), their count and the home ranges.
    job: std::cell::UnsafeCell<Option<&'static (dyn Fn(usize) + Sync)>>,
    tasks: std::cell::UnsafeCell<usize>,
    workers: std::cell::UnsafeCell<usize>,
}

// SAFETY: the region's description (`job`, `tasks`, `workers`) is written by the posting thread only while no
// region is open (every member of the last one has finished), and read by members only after joining an open
// region (the join's Acquire pairs with the post's Release).
unsafe impl Sync for Team {}

#[repr(align(64))]
struct Padded64(std::sync::atomic::AtomicU64);

const EPOCH_SHIFT: u32 = 32;
const CLOSED: u64 = 1 << 31;
const PRESENT_SHIFT: u32 = 16;
const PRESENT_ONE: u64 = 1 << PRESENT_SHIFT;
const JOINED: u64 = PRESENT_ONE - 1;
/// Task indices in a counter: a region of more tasks goes through rayon.
const INDEX_BITS: u32 = 24;
const INDEX: u64 = (1 << INDEX_BITS) - 1;
/// Region numbers run through `1..=LAST_EPOCH` and round again; every counter is reset to tag 0 (no region's)
/// before region 1, so that a counter left untouched for a whole round is never taken for the current region's.
const LAST_EPOCH: u64 = (1 << 32) - 1;

fn present(s: u64) -> u64 {
    (s & (CLOSED - 1)) >> PRESENT_SHIFT
}

thread_local! {
    /// The team of the [`KeepAwake`] guard that this thread holds, if any.
    static TEAM: std::cell::RefCell<Option<std::sync::Arc<Team>>> = const { std::cell::RefCell::new(None) };
    /// The team whose polling loop this thread runs, if any (null: none).
    static MEMBER_OF: std::cell::Cell<*const Team> = const { std::cell::Cell::new(std::ptr::null()) };
    /// Whether this thread is running a team region's tasks (a nested region goes through rayon).
    static IN_REGION: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

#[cfg(test)]
thread_local! {
    /// Regions that this thread posted to a team.
    static TEAM_REGIONS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

impl Team {
    /// A team whose members are on their way (`calling`).
    fn new(stop: Arc<std::sync::atomic::AtomicBool>) -> Self {
        Self {
            stop,
            calling: std::sync::atomic::AtomicBool::new(true),
            line: TeamLine {
                // Epoch 0, closed: no region yet.
                state: std::sync::atomic::AtomicU64::new(CLOSED),
                done: AtomicUsize::new(0),
                job: std::cell::UnsafeCell::new(None),
                tasks: std::cell::UnsafeCell::new(0),
                workers: std::cell::UnsafeCell::new(0),
            },
            next: std::array::from_fn(|_| Padded64(std::sync::atomic::AtomicU64::new(0))),
            panic: std::sync::Mutex::new(None),
        }
    }

    /// Runs `task(i)` for `i` in `0..n` on this thread and on the members of its guard's team, in `workers`
    /// home ranges, when it holds a team whose members are all present (`workers - 1` of them) and is not
    /// inside a region already; false (nothing run) otherwise.
    fn run_on_current(n: usize, workers: usize, task: &(dyn Fn(usize) + Sync)) -> bool {
        if IN_REGION.get() || n as u64 > INDEX / 2 {
            return false;
        }
        TEAM.with_borrow(|team| {
            team.as_ref()
                .is_some_and(|t| !t.stop.load(Ordering::Relaxed) && t.run(n, workers, task))
        })
    }

    fn run(self: &Arc<Self>, n: usize, workers: usize, task: &(dyn Fn(usize) + Sync)) -> bool {
        let line = &self.line;
        let mut s = line.state.load(Ordering::Relaxed);
        if present(s) != workers as u64 - 1 {
            if present(s) < workers as u64 - 1 {
                self.call_back();
            }
            return false;
        }
        // SAFETY: the region is closed and waited for before this function returns (or unwinds: `Close`).
        let erased: &'static (dyn Fn(usize) + Sync) = unsafe { std::mem::transmute(task) };
        // Only this thread posts and closes, and the last region is closed with its members done.
        unsafe {
            *line.job.get() = Some(erased);
            *line.tasks.get() = n;
            *line.workers.get() = workers;
        }
        line.done.store(0, Ordering::Relaxed);
        let epoch = (s >> EPOCH_SHIFT) % LAST_EPOCH + 1;
        if epoch == 1 {
            for c in &self.next {
                c.0.store(0, Ordering::Relaxed);
            }
        }
        loop {
            if present(s) != workers as u64 - 1 {
                return false;
            }
            let posted = (epoch << EPOCH_SHIFT) | (s & (CLOSED - 1) & !JOINED);
            match line
                .state
                .compare_exchange_weak(s, posted, Ordering::Release, Ordering::Relaxed)
            {
                Ok(_) => break,
                Err(now) => s = now,
            }
        }
        /// Closes the region and waits for its members, also when the worker unwinds.
        struct Close<'a>(&'a Team);
        impl Drop for Close<'_> {
            fn drop(&mut self) {
                let (team, line) = (self.0, &self.0.line);
                let joined = (line.state.fetch_or(CLOSED, Ordering::AcqRel) & JOINED) as usize;
                let mut spins = 0;
                while line.done.load(Ordering::Acquire) < joined {
                    spin_or_yield(&mut spins);
                }
                IN_REGION.set(false);
                if std::thread::panicking() {
                    // This thread's own panic goes on; a member's is dropped with the region.
                    team.panic.lock().unwrap_or_else(|e| e.into_inner()).take();
                }
            }
        }
        // (Not inside a region: checked by the caller.)
        IN_REGION.set(true);
        #[cfg(test)]
        TEAM_REGIONS.set(TEAM_REGIONS.get() + 1);
        let close = Close(self);
        self.work(epoch, n, workers, task);
        drop(close);
        // A member's panic (the tasks on this thread returned): resumed here.
        if let Some(payload) = self.panic.lock().unwrap_or_else(|e| e.into_inner()).take() {
            std::panic::resume_unwind(payload);
        }
        true
    }

    /// One thread's share of region `epoch`: its home range's tasks, then those left in the others'.
    fn work(&self, epoch: u64, n: usize, workers: usize, task: &(dyn Fn(usize) + Sync)) {
        let start = |r: usize| r * n / workers;
        let tag = epoch << INDEX_BITS;
        let home = rayon::current_thread_index().unwrap_or(0) % workers;
        for r in (home..workers).chain(0..home) {
            let (first, end) = (start(r) as u64, start(r + 1) as u64);
            if first == end {
                continue;
            }
            let counter = &self.next[r].0;
            let mut v = counter.load(Ordering::Relaxed);
            if v & !INDEX != tag {
                // Untouched in this region: claim its first task by tagging the counter.
                if counter
                    .compare_exchange(v, tag | (first + 1), Ordering::Relaxed, Ordering::Relaxed)
                    .is_ok()
                {
                    task(first as usize);
                }
                v = counter.load(Ordering::Relaxed);
            }
            // Tagged for this region from here on: claim by counting (a range already used up only reads).
            while v & INDEX < end {
                let i = counter.fetch_add(1, Ordering::Relaxed) & INDEX;
                if i >= end {
                    break;
                }
                task(i as usize);
                v = tag | (i + 1);
            }
        }
    }

    /// Sends polling jobs to the pool's threads (from the guard's thread) so that those that are not members
    /// come back: a member leaves after an idle spell (a long sequential stretch, or a thread that the
    /// operating system held back for milliseconds). Not while earlier ones are on their way.
    fn call_back(self: &Arc<Self>) {
        if !self.calling.swap(true, Ordering::AcqRel) {
            poll(
                Arc::clone(&self.stop),
                Some(Arc::clone(self)),
                rayon::current_thread_index(),
            );
        }
    }

    /// Enters the team as a member (the epoch it has seen: the last one posted).
    fn arrive(&self) -> u64 {
        let s = self.line.state.fetch_add(PRESENT_ONE, Ordering::AcqRel);
        // A region open now is one this member may join.
        if s & CLOSED == 0 {
            (s >> EPOCH_SHIFT) - 1
        } else {
            s >> EPOCH_SHIFT
        }
    }

    /// Leaves the team, after serving any region posted while it was a member.
    fn leave(&self, seen: &mut u64) {
        let state = &self.line.state;
        let mut s = state.load(Ordering::Acquire);
        loop {
            if s & CLOSED == 0 && s >> EPOCH_SHIFT != *seen {
                self.serve(seen);
                s = state.load(Ordering::Acquire);
                continue;
            }
            match state.compare_exchange_weak(
                s,
                s - PRESENT_ONE,
                Ordering::AcqRel,
                Ordering::Acquire,
            ) {
                Ok(_) => return,
                Err(now) => s = now,
            }
        }
    }

    /// Joins the posted region if it is open and not yet seen (`seen`: the last epoch this member looked at)
    /// and runs its share; whether it ran one.
    fn serve(&self, seen: &mut u64) -> bool {
        let line = &self.line;
        let mut s = line.state.load(Ordering::Acquire);
        loop {
            if s >> EPOCH_SHIFT == *seen {
                return false;
            }
            if s & CLOSED != 0 {
                *seen = s >> EPOCH_SHIFT;
                return false;
            }
            match line
                .state
                .compare_exchange_weak(s, s + 1, Ordering::Acquire, Ordering::Acquire)
            {
                Ok(_) => break,
                Err(now) => s = now,
            }
        }
        let epoch = s >> EPOCH_SHIFT;
        *seen = epoch;
        // SAFETY: joined an open region: its description stays valid until this member reports done.
        let (job, n, workers) = unsafe {
            (
                (*line.job.get()).expect("a posted region has a job"),
                *line.tasks.get(),
                *line.workers.get(),
            )
        };
        // A member may be inside another team's region (it took this team's polling job while waiting there).
        let outer = IN_REGION.replace(true);
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            self.work(epoch, n, workers, job)
        }));
        IN_REGION.set(outer);
        if let Err(payload) = result {
            self.panic
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get_or_insert(payload);
        }
        line.done.fetch_add(1, Ordering::Release);
        true
    }
}

/// Runs `f` on a thread of a rayon pool: at once on the calling thread when that is one of a pool's threads
/// (inside `ThreadPool::install`, or a task), else on a thread of the global pool while the caller waits.
///
/// Why: every parallel region that a thread outside the pools enters is sent to the global pool as a job, and
/// the caller sleeps until it is done. A step enters 6-30 regions; with the pool's threads kept polling
/// ([`KeepAwake`]), the caller then also competes with them for the CPUs. On the benchmark machine (two vCPUs),
/// symplectic Euler + FEPR steps taken from Python's thread without a pool of their own took 117-149 us on the
/// 1k box and 260-366 us on the armadillo, against 50-63 and 144-193 us inside a two-thread pool (and 55-89
/// and 195-330 on one thread). Entered once per step (or once per batch of steps), the hop costs one hand-over.
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
/// without any thread pool: [`current_threads`] reads 1, [`on_pool`] and [`KeepAwake`] do nothing.
///
/// Why: a pool of one thread runs the same work on its own thread, which the caller must wake (and which
/// parks again after the call). A one-thread simulation stepped once per call from Python paid that twice per
/// call: symplectic Euler + FEPR on the 1k box took 114-152 us per `step(1)` against 54-74 us per step in
/// batches, and 56-58 us per call here (bunny2: 1,311-1,441 us, and 1,209-1,237 here). The results keep their
/// bits (the tasks are the same fixed chunks, in order).
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

/// The most home ranges of [`for_each_task`] (threads beyond share them).
const MAX_HOME_RANGES: usize = 16;

/// A counter on a cache line of its own (two threads' counters on one line would make every claim a
/// cross-core transfer).
#[repr(align(64))]
struct Padded(AtomicUsize);

/// Runs `worker` on `k` threads of the pool (the caller's included) and returns when all have returned.
fn start_workers(k: usize, worker: &(impl Fn() + Sync)) {
    if k <= 1 {
        worker();
    } else {
        rayon::join(worker, || start_workers(k - 1, worker));
    }
}

/// `f(c, chunk)` for every chunk `c` of `data` cut into chunks of `len` (the last may be shorter), in
/// parallel ([`for_each_task`]).
pub fn for_each_chunk_mut<T: Send>(data: &mut [T], len: usize, f: impl Fn(usize, &mut [T]) + Sync) {
    let chunks = DisjointChunks::new(data, len);
    // SAFETY: for_each_task hands out every index once, and distinct indices are disjoint chunks.
    for_each_task(chunks.count, |c| f(c, unsafe { chunks.get(c) }));
}

/// `f(i, &mut items[i])` for every item, in parallel ([`for_each_task`]): one result slot per task.
pub fn for_each_mut<T: Send>(items: &mut [T], f: impl Fn(usize, &mut T) + Sync) {
    for_each_chunk_mut(items, 1, |i, item| f(i, &mut item[0]));
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
    // Two more slices of zero-sized slots, one per chunk (no allocation).
    let chunks = a.len().div_ceil(len_a.max(1));
    let (mut c, mut d) = (vec![(); chunks], vec![(); chunks]);
    for_each_chunk_mut4(a, len_a, b, len_b, &mut c, 1, &mut d, 1, |k, a, b, _, _| {
        f(k, a, b)
    });
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
    // A fourth slice of zero-sized slots, one per chunk (no allocation).
    let mut slots = vec![(); a.len().div_ceil(len_a.max(1))];
    for_each_chunk_mut4(
        a,
        len_a,
        b,
        len_b,
        c,
        len_c,
        &mut slots,
        1,
        |k, a, b, c, _| f(k, a, b, c),
    );
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
    let (a, b, c, d) = (
        DisjointChunks::new(a, len_a),
        DisjointChunks::new(b, len_b),
        DisjointChunks::new(c, len_c),
        DisjointChunks::new(d, len_d),
    );
    assert!(
        a.count == b.count && b.count == c.count && c.count == d.count,
        "the same number of chunks"
    );
    // SAFETY: as in for_each_chunk_mut, for each slice.
    for_each_task(a.count, |k| unsafe {
        f(k, a.get(k), b.get(k), c.get(k), d.get(k))
    });
}

/// A mutable slice cut into chunks that tasks on different threads take one each, by index.
struct DisjointChunks<'a, T> {
    ptr: *mut T,
    total: usize,
    len: usize,
    count: usize,
    _data: std::marker::PhantomData<&'a mut [T]>,
}

// SAFETY: it hands out disjoint `&mut [T]` (see `get`), which may move between threads when `T: Send`.
unsafe impl<T: Send> Sync for DisjointChunks<'_, T> {}

impl<'a, T> DisjointChunks<'a, T> {
    fn new(data: &'a mut [T], len: usize) -> Self {
        assert!(len > 0, "chunks of at least one element");
        Self {
            ptr: data.as_mut_ptr(),
            total: data.len(),
            len,
            count: data.len().div_ceil(len),
            _data: std::marker::PhantomData,
        }
    }

    /// Chunk `c` (`c < count`).
    ///
    /// # Safety
    /// No two live results may come from the same `c`.
    #[allow(clippy::mut_from_ref)] // disjoint by the contract above
    unsafe fn get(&self, c: usize) -> &'a mut [T] {
        assert!(c < self.count, "chunk {c} of {}", self.count);
        let first = c * self.len;
        let len = self.len.min(self.total - first);
        // SAFETY: `first..first + len` lies inside the slice; the caller keeps chunks unaliased.
        unsafe { std::slice::from_raw_parts_mut(self.ptr.add(first), len) }
    }
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
///
/// Held on a pool thread, the guard's polling threads form a team (an OpenMP-style team): they spin on one
/// cache line, and the guard thread's [`for_each_task`] regions are posted there instead of through rayon's
/// queues (the region's start, its members' joins and its end on that line, each home range's counter on a
/// line of its own that stays in the cache of the thread claiming from it). A guard created while the same
/// thread holds another one does nothing but call back the polling threads that have left (after 2 ms without
/// work): a batch of steps keeps one team, each step holding its own guard inside it.
pub struct KeepAwake {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    /// The team whose regions this guard's thread posts (`None` in [`serial`], outside the pools, and for a
    /// guard nested in another).
    team: Option<std::sync::Arc<Team>>,
}

impl KeepAwake {
    /// Start polling on the current pool's other threads (all of them when called from outside the pool).
    #[allow(clippy::new_without_default)] // starting threads is not a default value
    pub fn new() -> Self {
        use std::sync::atomic::{AtomicBool, Ordering};
        let stop = std::sync::Arc::new(AtomicBool::new(false));
        let quiet = |stop| Self { stop, team: None };
        if is_serial() {
            return quiet(stop);
        }
        let own = rayon::current_thread_index();
        let others = rayon::current_num_threads().saturating_sub(own.is_some() as usize);
        // Inside another guard of this thread (a batch of steps, each holding its own): that guard's team goes
        // on serving, and this one does nothing but call back the members that have left it (after an idle
        // spell: a long sequential stretch, or a thread the operating system held back for milliseconds).
        let outer = own.and_then(|_| {
            TEAM.with_borrow(|t| t.clone())
                .filter(|t| !t.stop.load(Ordering::Acquire))
        });
        if let Some(team) = outer {
            if present(team.line.state.load(Ordering::Relaxed)) < others as u64 {
                team.call_back();
            }
            return quiet(stop);
        }
        // Regions are posted to a team only from a pool thread (from outside, `for_each_task` goes through
        // rayon as before).
        let team = own.map(|_| Arc::new(Team::new(Arc::clone(&stop))));
        if others > 0 {
            poll(Arc::clone(&stop), team.clone(), own);
        }
        if let Some(team) = &team {
            // Replaces only a team whose guard has dropped (a live one would have made this guard quiet).
            TEAM.set(Some(Arc::clone(team)));
        }
        Self { stop, team }
    }
}

/// Starts a polling loop on every thread of the current pool but `own` (the guard's thread), serving `team`
/// where there is one, until `stop`.
fn poll(stop: Arc<std::sync::atomic::AtomicBool>, team: Option<Arc<Team>>, own: Option<usize>) {
    // One job for each thread of the pool (not a queue's job that any thread may take: the guard's own thread,
    // waiting in a join, would take it back and no other thread would poll).
    rayon::spawn_broadcast(move |_| {
        // The thread that holds the guard may pick this job up while it waits for other work: it
        // must not poll for its own guard's end (it would wait for itself).
        if rayon::current_thread_index() == own {
            return;
        }
        // A member of this team already (this job taken from the queue inside its own loop): one loop
        // per thread.
        let team_ptr = team
            .as_ref()
            .map_or(std::ptr::null(), std::sync::Arc::as_ptr);
        if !team_ptr.is_null() && MEMBER_OF.get() == team_ptr {
            return;
        }
        let outer_membership = MEMBER_OF.replace(team_ptr);
        if let Some(team) = &team {
            team.calling.store(false, Ordering::Release);
        }
        let mut seen = team.as_ref().map_or(0, |t| t.arrive());
        // A thread may pick this job up while it waits inside a nested `rayon::join` (for work that
        // is already done, or that only it will finish): polling until the guard drops would then hold
        // that join, and whatever waits for it, as long as the guard lives, which can be for ever
        // (`a_polling_job_picked_up_inside_a_wait_gives_the_thread_back`). So the job gives the thread
        // back after `POLL_IDLE_LIMIT` without work: a gap that long between a step's parallel regions
        // is rare, and costs only a wake-up after it.
        let mut idle_since = std::time::Instant::now();
        let mut spins = 0u32;
        while !stop.load(Ordering::Acquire) {
            if team.as_ref().is_some_and(|t| t.serve(&mut seen)) {
                idle_since = std::time::Instant::now();
                continue;
            }
            // Mostly spinning on the team's line (a read of this core's own copy until the guard's
            // thread writes it), now and then looking into rayon's queues (rayon work of the step: a
            // sparse solve's tasks), and yielding to the operating system once idle for a while.
            spins = spins.wrapping_add(1);
            if !spins.is_multiple_of(SPINS_PER_LOOK) {
                std::hint::spin_loop();
                continue;
            }
            if rayon::yield_now() == Some(rayon::Yield::Executed) {
                idle_since = std::time::Instant::now();
                continue;
            }
            let idle = idle_since.elapsed();
            if idle > POLL_IDLE_LIMIT {
                break;
            }
            if idle > YIELD_AFTER {
                // Let any other runnable thread of the machine (a viewer, a browser) go first; with
                // none, this returns at once and the thread stays awake.
                std::thread::yield_now();
            }
        }
        if let Some(team) = &team {
            team.leave(&mut seen);
        }
        MEMBER_OF.set(outer_membership);
    });
}

/// Spins of a [`KeepAwake`] polling loop between looks into rayon's queues (a look costs the guard's thread the
/// cache lines of its queue): about 1.5 us on this project's benchmark machine.
const SPINS_PER_LOOK: u32 = 32;
/// Idle time after which a polling loop yields to the operating system at every look.
const YIELD_AFTER: std::time::Duration = std::time::Duration::from_micros(20);

/// How long a [`KeepAwake`] polling job goes on without finding work before it gives its thread back.
const POLL_IDLE_LIMIT: std::time::Duration = std::time::Duration::from_millis(2);

impl Drop for KeepAwake {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Release);
        if let Some(team) = &self.team {
            // Only where this guard's team is this thread's (a guard dropped on another thread leaves its owner's
            // entry, stopped: regions there go through rayon until the next guard replaces it).
            TEAM.with_borrow_mut(|t| {
                if t.as_ref().is_some_and(|t| std::sync::Arc::ptr_eq(t, team)) {
                    *t = None;
                }
            });
        }
    }
}

/// What synchronising threads costs on this machine, measured ([`measure_sync_floor`]): the floor under the
/// two-thread speed-up of a small evaluation. An energy + gradient on the 1,296-tet box is about 20 us of work on
/// one thread, and each parallel region of it pays a start, an end, and the cache lines its threads hand each
/// other; `fepr bench` reports these numbers with the machine, so that small meshes' speed-ups can be read
/// against them.
#[derive(Clone, Copy, Debug)]
pub struct SyncFloor {
    /// Threads of the current pool when measured.
    pub threads: usize,
    /// Seconds per parallel region that every thread must join ([`for_each_task`] with one task per thread, the
    /// first waiting until the others have started), the pool's other threads kept awake ([`KeepAwake`]) as
    /// between the regions of a step: a region's start and end with no work in it. The best batch's mean.
    pub region_s: f64,
    /// Seconds for a value to go from one thread to another and back through two atomics on cache lines of
    /// their own, both threads spinning (a cache line's round trip between two cores): the best batch's mean.
    /// NaN where the machine has a single CPU (the two threads would take turns on it).
    pub round_trip_s: f64,
}

/// Measures [`SyncFloor`] on the current pool, in about `budget` (a few tens of milliseconds suffice; the pool's
/// threads first get 20 ms of warm-up, as a fresh pool's threads take milliseconds to start helping on a virtual
/// machine). The round trip uses a thread of its own besides the caller's, not the pool's.
pub fn measure_sync_floor(budget: std::time::Duration) -> SyncFloor {
    use std::time::Instant;
    let threads = rayon::current_num_threads();
    let half = budget / 2;
    let region_s = {
        let _awake = KeepAwake::new();
        let warm = Instant::now();
        while warm.elapsed() < std::time::Duration::from_millis(20) {
            joined_region(threads);
        }
        best_batch_mean(half, 200, || joined_region(threads))
    };
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    let round_trip_s = if cpus < 2 { f64::NAN } else { round_trip(half) };
    SyncFloor {
        threads,
        region_s,
        round_trip_s,
    }
}

/// One parallel region of `threads` tasks (`threads` the pool's size) that the caller cannot finish alone: the
/// caller's first task waits until every other task has started, so each region pays the other threads' start
/// (an empty region's tasks would mostly run on the caller, which takes back a job no other thread has picked up
/// yet, and measure nothing of the kind).
fn joined_region(threads: usize) {
    if threads <= 1 {
        for_each_task(1, |i| {
            std::hint::black_box(i);
        });
        return;
    }
    let started = Padded(AtomicUsize::new(0));
    // The first task of the caller's home range (as [`for_each_task`] assigns them): the caller claims it before
    // any other, so the caller waits there and the other tasks need the other threads.
    let workers = threads.min(MAX_HOME_RANGES);
    let home = rayon::current_thread_index().unwrap_or(0) % workers;
    let mine = home * threads / workers;
    for_each_task(threads, |i| {
        if i == mine {
            let mut spins = 0;
            while started.0.load(Ordering::Acquire) < threads - 1 {
                spin_or_yield(&mut spins);
            }
        } else {
            started.0.fetch_add(1, Ordering::AcqRel);
        }
    });
}

/// The smallest mean seconds per call of `f` over batches of `per_batch` calls, for about `budget` (at least
/// one batch).
fn best_batch_mean(budget: std::time::Duration, per_batch: u32, mut f: impl FnMut()) -> f64 {
    let start = std::time::Instant::now();
    let mut best = f64::INFINITY;
    loop {
        let t0 = std::time::Instant::now();
        for _ in 0..per_batch {
            f();
        }
        best = best.min(t0.elapsed().as_secs_f64() / f64::from(per_batch));
        if start.elapsed() >= budget {
            return best;
        }
    }
}

/// [`SyncFloor::round_trip_s`]: the caller writes `n` to one line, a second thread answers `n` on another.
fn round_trip(budget: std::time::Duration) -> f64 {
    let ping = std::sync::Arc::new([Padded(AtomicUsize::new(0)), Padded(AtomicUsize::new(0))]);
    let pong = std::sync::Arc::clone(&ping);
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

/// A spin-wait step that gives the CPU to the OS after many fruitless spins, so that a busy machine (the other
/// thread descheduled) costs a yield per round trip rather than a whole time slice.
fn spin_or_yield(spins: &mut u32) {
    *spins += 1;
    if *spins < 10_000 {
        std::hint::spin_loop();
    } else {
        std::thread::yield_now();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

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

    /// A thread that waits inside a nested `rayon::join` may pick up a `KeepAwake` polling job; the job must
    /// give the thread back when there is nothing to do, or the join it waits in never returns while the
    /// guard lives (a step that needs that join would hang). Staged on two threads: thread b waits in a join
    /// whose second half runs on thread a, which creates the guard there and keeps it until b is done.
    #[test]
    fn a_polling_job_picked_up_inside_a_wait_gives_the_thread_back() {
        use std::sync::atomic::AtomicBool;
        use std::sync::Mutex;
        use std::time::{Duration, Instant};
        let finished_in_time = finishes(|| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap();
            let (inner_b_taken, b_done) = (AtomicBool::new(false), AtomicBool::new(false));
            let guard: Mutex<Option<KeepAwake>> = Mutex::new(None);
            pool.install(|| {
                rayon::join(
                    || {
                        // Thread a: take the inner join's second half from b, then wait for b.
                        let t0 = Instant::now();
                        while !b_done.load(Ordering::Acquire)
                            && t0.elapsed() < Duration::from_secs(3)
                        {
                            let _ = rayon::yield_now();
                        }
                        let in_time = b_done.load(Ordering::Acquire);
                        drop(guard.lock().unwrap().take()); // ends the polling either way
                        in_time
                    },
                    || {
                        // Thread b (stolen): a nested join whose second half thread a takes; b then waits.
                        rayon::join(
                            || {
                                let t0 = Instant::now();
                                while !inner_b_taken.load(Ordering::Acquire)
                                    && t0.elapsed() < Duration::from_secs(3)
                                {
                                    std::hint::spin_loop();
                                }
                            },
                            || {
                                // On thread a: the guard's polling job goes to a's queue, where b, waiting
                                // for this half, finds it.
                                inner_b_taken.store(true, Ordering::Release);
                                *guard.lock().unwrap() = Some(KeepAwake::new());
                                std::thread::sleep(Duration::from_millis(20));
                            },
                        );
                        b_done.store(true, Ordering::Release);
                    },
                )
                .0
            })
        });
        assert!(
            finished_in_time,
            "the waiting thread was kept polling until the guard dropped"
        );
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

    #[test]
    fn sync_floor_measures_a_region_and_a_round_trip() {
        let floor = on_pool(2, || {
            measure_sync_floor(std::time::Duration::from_millis(20))
        });
        assert_eq!(floor.threads, 2);
        // The times themselves are reported, not asserted on (no timing bounds in tests; 0.8 us and 0.25 us
        // here on a quiet machine): the measurement finishes and gives finite positive times.
        assert!(
            floor.region_s.is_finite() && floor.region_s > 0.0,
            "{floor:?}"
        );
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        if cpus >= 2 {
            assert!(
                floor.round_trip_s.is_finite() && floor.round_trip_s > 0.0,
                "{floor:?}"
            );
        } else {
            assert!(floor.round_trip_s.is_nan());
        }
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

    /// The same under a `KeepAwake` guard held on a pool thread (its polling threads take the workers), with
    /// `for_each_task` nested inside tasks and several calls in a row.
    #[test]
    fn every_task_runs_exactly_once_under_keep_awake() {
        for threads in [1, 2, 3, 5] {
            let runs = on_pool(threads, || {
                let _awake = KeepAwake::new();
                [0, 1, 2, 3, 7, 11, 64, 1000].map(|n| {
                    let runs: Vec<AtomicUsize> = (0..n).map(|_| AtomicUsize::new(0)).collect();
                    let inner: Vec<AtomicUsize> = (0..n * 7).map(|_| AtomicUsize::new(0)).collect();
                    for _ in 0..3 {
                        for_each_task(n, |i| {
                            runs[i].fetch_add(1, Ordering::Relaxed);
                            if i % 5 == 0 {
                                for_each_task(7, |k| {
                                    inner[7 * i + k].fetch_add(1, Ordering::Relaxed);
                                });
                                assert_eq!(sum_of_sines(3000), sum_of_sines(3000));
                            }
                        });
                    }
                    let outer_ok = runs.iter().all(|r| r.load(Ordering::Relaxed) == 3);
                    let inner_ok = (0..n * 7).all(|j| {
                        inner[j].load(Ordering::Relaxed) == if (j / 7) % 5 == 0 { 3 } else { 0 }
                    });
                    outer_ok && inner_ok
                })
            });
            assert!(runs.iter().all(|&once| once), "{threads} threads: {runs:?}");
        }
    }

    /// Waits (up to ten seconds) until every other thread of the pool has joined the team of the guard that
    /// this thread holds; whether they did.
    fn team_assembles(threads: usize) -> bool {
        let t0 = std::time::Instant::now();
        while t0.elapsed() < std::time::Duration::from_secs(10) {
            let full = TEAM.with_borrow(|t| {
                t.as_ref().is_some_and(|t| {
                    present(t.line.state.load(Ordering::Acquire)) == threads as u64 - 1
                })
            });
            if full {
                return true;
            }
            // A region calls back the members that left (after an idle spell).
            for_each_task(2, |_| {});
            std::thread::yield_now();
        }
        false
    }

    /// Under a guard whose team has assembled, regions go to the team (not through rayon), every task runs
    /// once, and the tasks spread over the pool's threads; the team survives guards nested in it (a step inside
    /// a batch of steps). On a busy machine a member may leave before a region (after an idle spell of
    /// milliseconds): such a region goes through rayon, and the round is tried again once the team is back.
    #[test]
    fn regions_under_a_guard_run_on_its_team_once_per_task() {
        for threads in [2, 3] {
            let (on_team, once, spread) = on_pool(threads, move || {
                let _awake = KeepAwake::new();
                let (mut on_team, mut once, mut ran_on) = (0, true, vec![false; threads]);
                for round in 0..100 {
                    let _nested = (round % 2 == 0).then(KeepAwake::new);
                    let n = threads + round % 37;
                    for _attempt in 0..100 {
                        if !team_assembles(threads) {
                            break;
                        }
                        let before = TEAM_REGIONS.get();
                        let runs: Vec<AtomicUsize> = (0..n).map(|_| AtomicUsize::new(0)).collect();
                        let seen: Vec<AtomicUsize> =
                            (0..threads).map(|_| AtomicUsize::new(0)).collect();
                        for_each_task(n, |i| {
                            runs[i].fetch_add(1, Ordering::Relaxed);
                            seen[rayon::current_thread_index().unwrap()]
                                .fetch_add(1, Ordering::Relaxed);
                            // Long enough for the members to join.
                            let t0 = std::time::Instant::now();
                            while t0.elapsed() < std::time::Duration::from_micros(50) {
                                std::hint::spin_loop();
                            }
                        });
                        once &= runs.iter().all(|r| r.load(Ordering::Relaxed) == 1);
                        if TEAM_REGIONS.get() > before {
                            on_team += 1;
                            for (t, seen) in seen.iter().enumerate() {
                                ran_on[t] |= seen.load(Ordering::Relaxed) > 0;
                            }
                            break;
                        }
                    }
                }
                (on_team, once, ran_on.iter().all(|&r| r))
            });
            assert_eq!(on_team, 100, "{threads} threads: rounds on the team");
            assert!(once, "{threads} threads: every task once");
            assert!(spread, "{threads} threads: tasks ran on every thread");
        }
    }

    /// A task that panics on a member: the panic reaches the caller of `for_each_task` (not lost on the
    /// member's thread, not a hang), and the team serves the next regions.
    #[test]
    fn a_members_panic_reaches_the_caller_and_the_team_goes_on() {
        let (assembled, caught, after) = on_pool(2, || {
            let _awake = KeepAwake::new();
            let assembled = team_assembles(2);
            let me = rayon::current_thread_index();
            let caught = std::panic::catch_unwind(|| {
                for _ in 0..1000 {
                    for_each_task(64, |_| {
                        if rayon::current_thread_index() != me {
                            panic!("a member's task panicked");
                        }
                        std::thread::sleep(std::time::Duration::from_micros(20));
                    });
                }
            });
            let message = caught
                .err()
                .and_then(|p| p.downcast_ref::<&str>().map(|m| m.to_string()));
            let before = TEAM_REGIONS.get();
            // The member may have left while this thread ran the rest of that region alone (milliseconds of
            // sleeps): a guard nested in the first calls it back.
            let _again = KeepAwake::new();
            assert!(team_assembles(2), "the member is back in the team");
            let total = AtomicUsize::new(0);
            for _ in 0..50 {
                for_each_task(16, |i| {
                    total.fetch_add(i, Ordering::Relaxed);
                });
            }
            let after = (TEAM_REGIONS.get() - before, total.into_inner());
            (assembled, message, after)
        });
        assert!(assembled);
        assert_eq!(caught.as_deref(), Some("a member's task panicked"));
        assert!(after.0 > 0, "regions on the team after the panic");
        assert_eq!(after.1, 50 * (0..16).sum::<usize>());
    }

    /// The region numbers that tag the counters come round after 2^32 - 1 regions: every task still runs
    /// once in the regions around the turn, where a stale counter could be taken for the current region's.
    #[test]
    fn tasks_run_once_where_the_region_numbers_come_round() {
        let ok = on_pool(2, || {
            let _awake = KeepAwake::new();
            assert!(team_assembles(2));
            // The last region was numbered LAST_EPOCH, and every range's counter was last used (up to task 5)
            // in the region numbered 1 of the round before: the next region's number.
            TEAM.with_borrow(|t| {
                let team = t.as_ref().unwrap();
                let s = team.line.state.load(Ordering::Acquire);
                let low = s & ((1 << EPOCH_SHIFT) - 1);
                team.line
                    .state
                    .store((LAST_EPOCH << EPOCH_SHIFT) | low, Ordering::Release);
                for c in &team.next {
                    c.0.store((1 << INDEX_BITS) | 5, Ordering::Relaxed);
                }
            });
            // Twelve regions on the team (a region that a member missed, on a busy machine, goes through
            // rayon and does not count).
            let (before, mut once, mut rounds) = (TEAM_REGIONS.get(), true, 0);
            while TEAM_REGIONS.get() - before < 12 && rounds < 10_000 {
                let n = 10 + rounds % 7;
                let runs: Vec<AtomicUsize> = (0..n).map(|_| AtomicUsize::new(0)).collect();
                for_each_task(n, |i| {
                    runs[i].fetch_add(1, Ordering::Relaxed);
                });
                once &= runs.iter().all(|r| r.load(Ordering::Relaxed) == 1);
                rounds += 1;
            }
            let epoch = TEAM.with_borrow(|t| {
                t.as_ref().unwrap().line.state.load(Ordering::Acquire) >> EPOCH_SHIFT
            });
            (once, TEAM_REGIONS.get() - before, epoch)
        });
        let (once, regions, epoch) = ok;
        assert!(once, "every task once across the turn");
        assert_eq!(regions, 12, "on the team");
        assert_eq!(
            epoch, 12,
            "the numbers came round: 1 to 12 after LAST_EPOCH"
        );
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
}
