//! Deterministic chunking and parallel loops: the same inputs give the same bits on any thread count.

mod parallel;
mod ready;

pub use parallel::*;
pub use ready::{with_threads_ready, IDLE_LIMIT};
