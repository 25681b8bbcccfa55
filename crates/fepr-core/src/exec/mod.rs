//! Deterministic chunking and parallel loops: the same inputs give the same bits on any thread count.

mod parallel;

pub use parallel::*;
