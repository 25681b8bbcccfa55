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

#[cfg(test)]
mod tests {
    use super::*;

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
