//! Fill-reducing orderings for the sparse Cholesky factorisations: nested dissection by METIS
//! (`METIS_NodeND`, vendored C sources built by the `metis-sys` crate, Apache-2.0).
//!
//! On 3D tet meshes nested dissection gives far less fill than approximate minimum degree (faer's default),
//! and the supernodal factorisation is correspondingly faster. Matrices with `b x b` blocks per mesh vertex
//! (the 3m x 3m Newton matrix) are ordered on the vertex graph (the quotient graph of the blocks), then each
//! block's dofs are kept together. METIS runs single-threaded with a fixed seed: the ordering depends only on
//! the pattern.

use metis_sys::{
    idx_t, moptions_et_METIS_OPTION_SEED, rstatus_et_METIS_OK, METIS_NodeND,
    METIS_SetDefaultOptions, METIS_NOPTIONS,
};

/// Symmetric adjacency (both triangles, no diagonal) of a lower-triangle CSC pattern, as CSR.
fn full_adjacency(n: usize, col_ptr: &[usize], row_idx: &[usize]) -> (Vec<usize>, Vec<usize>) {
    let mut deg = vec![0usize; n + 1];
    for c in 0..n {
        for &r in &row_idx[col_ptr[c]..col_ptr[c + 1]] {
            if r != c {
                deg[r + 1] += 1;
                deg[c + 1] += 1;
            }
        }
    }
    for i in 0..n {
        deg[i + 1] += deg[i];
    }
    let ptr = deg.clone();
    let mut fill = deg;
    let mut adj = vec![0usize; ptr[n]];
    for c in 0..n {
        for &r in &row_idx[col_ptr[c]..col_ptr[c + 1]] {
            if r != c {
                adj[fill[r]] = c;
                fill[r] += 1;
                adj[fill[c]] = r;
                fill[c] += 1;
            }
        }
    }
    for i in 0..n {
        adj[ptr[i]..ptr[i + 1]].sort_unstable();
    }
    (ptr, adj)
}

/// The largest block size `b` in {3, 2} such that the dofs `b i .. b i + b` have identical closed
/// neighbourhoods (1 if none).
fn block_size(n: usize, ptr: &[usize], adj: &[usize]) -> usize {
    let closed = |i: usize| {
        let mut v = adj[ptr[i]..ptr[i + 1]].to_vec();
        let pos = v.partition_point(|&j| j < i);
        v.insert(pos, i);
        v
    };
    for b in [3usize, 2] {
        if !n.is_multiple_of(b) {
            continue;
        }
        let ok = (0..n / b).all(|blk| {
            let first = closed(b * blk);
            (1..b).all(|k| closed(b * blk + k) == first)
        });
        if ok {
            return b;
        }
    }
    1
}

/// Serialises the calls into METIS (see [`nested_dissection`]).
static METIS_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Nested-dissection ordering of the symmetric matrix whose lower triangle has this CSC pattern.
/// Returns `(perm, inverse)`: `perm[k]` is the original index eliminated k-th. `None` if METIS fails or the
/// graph is too large for 32-bit indices.
pub fn nested_dissection(
    n: usize,
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Option<(Vec<usize>, Vec<usize>)> {
    if n == 0 {
        return None;
    }
    let (ptr, adj) = full_adjacency(n, col_ptr, row_idx);
    let b = block_size(n, &ptr, &adj);
    let nb = n / b;
    // Quotient graph on the blocks.
    let mut xadj: Vec<idx_t> = Vec::with_capacity(nb + 1);
    let mut adjncy: Vec<idx_t> = Vec::with_capacity(adj.len() / (b * b).max(1));
    xadj.push(0);
    for blk in 0..nb {
        let i = b * blk;
        let mut last = usize::MAX;
        for &j in &adj[ptr[i]..ptr[i + 1]] {
            let q = j / b;
            if q != blk && q != last {
                adjncy.push(idx_t::try_from(q).ok()?);
                last = q;
            }
        }
        xadj.push(idx_t::try_from(adjncy.len()).ok()?);
    }
    let mut nvtxs = idx_t::try_from(nb).ok()?;
    let mut options = [0 as idx_t; METIS_NOPTIONS as usize];
    let mut perm = vec![0 as idx_t; nb];
    let mut iperm = vec![0 as idx_t; nb];
    // METIS seeds one process-wide random generator (GKlib's) from `options`: two calls at once on different
    // threads would draw from it in turn and return different orderings, and a different ordering changes the
    // factorisation's rounding. One call at a time keeps every simulation's bits its own.
    let _one_at_a_time = METIS_LOCK.lock().unwrap_or_else(|e| e.into_inner());
    // SAFETY: the arrays are valid CSR of `nb` vertices (symmetric, no self loops), `options` has
    // METIS_NOPTIONS entries, `perm` and `iperm` have `nb` entries; METIS does not keep the pointers.
    let status = unsafe {
        METIS_SetDefaultOptions(options.as_mut_ptr());
        options[moptions_et_METIS_OPTION_SEED as usize] = 7;
        METIS_NodeND(
            &mut nvtxs,
            xadj.as_mut_ptr(),
            adjncy.as_mut_ptr(),
            std::ptr::null_mut(),
            options.as_mut_ptr(),
            perm.as_mut_ptr(),
            iperm.as_mut_ptr(),
        )
    };
    if status != rstatus_et_METIS_OK {
        return None;
    }
    let mut fwd = Vec::with_capacity(n);
    for &p in &perm {
        let p = usize::try_from(p).ok()?;
        if p >= nb {
            return None;
        }
        fwd.extend((0..b).map(|k| b * p + k));
    }
    let mut inv = vec![usize::MAX; n];
    for (k, &i) in fwd.iter().enumerate() {
        if inv[i] != usize::MAX {
            return None; // not a permutation
        }
        inv[i] = k;
    }
    Some((fwd, inv))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 2D grid Laplacian pattern (lower CSC), optionally with `b` dofs per node.
    fn grid(nx: usize, b: usize) -> (usize, Vec<usize>, Vec<usize>) {
        let nodes = nx * nx;
        let n = nodes * b;
        let mut cols = vec![Vec::new(); n];
        for y in 0..nx {
            for x in 0..nx {
                let p = x + nx * y;
                let mut nb = vec![p];
                if x + 1 < nx {
                    nb.push(p + 1);
                }
                if y + 1 < nx {
                    nb.push(p + nx);
                }
                for &q in &nb {
                    for a in 0..b {
                        for c in 0..b {
                            let (i, j) = (b * p + a, b * q + c);
                            if j >= i {
                                cols[i].push(j);
                            }
                        }
                    }
                }
            }
        }
        let mut col_ptr = vec![0];
        let mut row_idx = Vec::new();
        for mut c in cols {
            c.sort_unstable();
            c.dedup();
            row_idx.extend(c);
            col_ptr.push(row_idx.len());
        }
        (n, col_ptr, row_idx)
    }

    #[test]
    fn nested_dissection_is_a_permutation_and_keeps_blocks_together() {
        for b in [1, 3] {
            let (n, cp, ri) = grid(20, b);
            let (fwd, inv) = nested_dissection(n, &cp, &ri).unwrap();
            assert_eq!(fwd.len(), n);
            for (k, &i) in fwd.iter().enumerate() {
                assert_eq!(inv[i], k);
            }
            if b == 3 {
                for blk in fwd.chunks(3) {
                    assert_eq!(blk[0] % 3, 0);
                    assert_eq!([blk[1], blk[2]], [blk[0] + 1, blk[0] + 2]);
                }
            }
            // Deterministic.
            assert_eq!(nested_dissection(n, &cp, &ri).unwrap().0, fwd);
        }
    }

    /// METIS draws from one process-wide random generator: orderings computed on several threads at once (two
    /// simulations built in parallel, or tests) must still be the one a lone call returns.
    #[test]
    fn concurrent_orderings_are_the_lone_call_s() {
        let (n, cp, ri) = grid(20, 3);
        let alone = nested_dissection(n, &cp, &ri).unwrap().0;
        std::thread::scope(|s| {
            let runs: Vec<_> = (0..4)
                .map(|_| {
                    s.spawn(|| (0..20).all(|_| nested_dissection(n, &cp, &ri).unwrap().0 == alone))
                })
                .collect();
            for r in runs {
                assert!(
                    r.join().unwrap(),
                    "an ordering computed alongside others differs"
                );
            }
        });
    }
}
