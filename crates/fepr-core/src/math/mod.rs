//! Small fixed-size linear algebra, batched polar decompositions, sparse Cholesky and its fill-reducing ordering.

mod linalg;
mod line_search;
mod ordering;
mod polar;
mod preconditioned;
pub(crate) mod simd;
mod sparse;

pub use linalg::*;
pub use line_search::golden_section;
pub use ordering::*;
pub use polar::*;
pub use preconditioned::solve_preconditioned;
pub use sparse::*;

use crate::exec::all_rows;

/// True when the two position arrays agree bit for bit (so a cached evaluation is exactly the fresh one).
pub(crate) fn same_bits(a: &[Vec3], b: &[Vec3]) -> bool {
    a.len() == b.len()
        && all_rows(a.len(), |r| {
            // Or-ing the differences, which vectorises (an early exit per row does not).
            let diff = a[r.clone()].iter().zip(&b[r]).fold(0, |d, (p, q)| {
                (0..3).fold(d, |d, k| d | (p[k].to_bits() ^ q[k].to_bits()))
            });
            diff == 0
        })
}
