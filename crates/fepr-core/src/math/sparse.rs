//! Sparse symmetric positive definite solves with faer: the symbolic analysis (fill-reducing ordering and
//! elimination structure) is done once per sparsity pattern, then every numeric factorisation reuses it
//! (symbolic once, numeric many). The matrix is given by its lower triangle in compressed sparse column
//! form; values are updated in place between factorisations. The fill-reducing ordering is METIS nested
//! dissection where it beats approximate minimum degree (3D meshes), see [`FillOrdering`].
//!
//! Factorisation and solves use faer's parallel kernels on the current rayon pool. faer splits dense blocks
//! over output rows and columns, never over the summation index, so results are bit-identical for any
//! thread count (gated by `tests/implicit.rs`). The 3-column solve of Projective Dynamics
//! ([`SparseCholesky::solve3_in_place`]) runs in parallel over the supernodal elimination tree with every sum
//! in an order fixed by the symbolic factor, so its bits do not depend on the thread count either.
//!
//! Length: over 900 lines of code, one job: the faer wrapper and the parallel three-column solve share the
//! supernodal factor's layout and its schedule, which nothing else should see; the tests (about 380 lines) compare
//! against faer's own solve on every thread count.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, supernodal::SymbolicSupernodalCholesky, LltRef, SymbolicCholesky,
    SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, MatMut, Par, Side};
use std::ops::Range;

use crate::error::{FeprError, Result};
use crate::math::nested_dissection;
use crate::math::simd::avx2_dispatch;

/// faer parallelism for the current rayon pool.
fn parallelism() -> Par {
    match crate::exec::current_threads() {
        0 | 1 => Par::Seq,
        n => Par::rayon(n),
    }
}

/// The lower triangle (row >= column) sparsity pattern of a symmetric n x n matrix, in CSC form.
#[derive(Clone, Debug)]
pub struct LowerPattern {
    pub n: usize,
    /// Column start offsets, length n + 1.
    pub col_ptr: Vec<usize>,
    /// Row indices, sorted within each column; the first entry of each column is its diagonal.
    pub row_idx: Vec<usize>,
}

impl LowerPattern {
    /// Build from, for each column, its (unsorted, possibly repeated) row indices `>= column`.
    pub fn from_columns(n: usize, mut columns: Vec<Vec<usize>>) -> Self {
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0);
        for (c, rows) in columns.iter_mut().enumerate() {
            rows.push(c);
            rows.sort_unstable();
            rows.dedup();
            row_idx.extend_from_slice(rows);
            col_ptr.push(row_idx.len());
        }
        Self {
            n,
            col_ptr,
            row_idx,
        }
    }
    /// Position of entry (row, col), row >= col, in the values array.
    pub fn position(&self, row: usize, col: usize) -> Option<usize> {
        let (start, end) = (self.col_ptr[col], self.col_ptr[col + 1]);
        self.row_idx[start..end]
            .binary_search(&row)
            .ok()
            .map(|k| start + k)
    }
    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }
}

/// Sparse Cholesky factorisation `A = L L^T` with a reusable symbolic analysis.
pub struct SparseCholesky {
    pattern: SymbolicSparseColMat<usize>,
    symbolic: SymbolicCholesky<usize>,
    l_values: Vec<f64>,
    factor_mem: MemBuffer,
    solve_mem: MemBuffer,
    /// The right-hand sides `solve_mem` is sized for.
    solve_columns: usize,
    factorized: bool,
    /// Numeric factorisations done with this symbolic analysis.
    pub numeric_count: usize,
    ordering: FillOrdering,
    /// Permuted right-hand sides of [`SparseCholesky::solve3_in_place`] (padded rows).
    work3: Vec<Row>,
    /// Column-major right-hand sides of [`SparseCholesky::solve3_in_place`] on a simplicial factor.
    work_cols: Vec<f64>,
    /// The parallel plan of [`SparseCholesky::solve3_in_place`] on a supernodal factor, built on its first
    /// call (it depends on the symbolic factor only).
    plan3: Option<Solve3Plan>,
}

/// Fill-reducing ordering of the symbolic analysis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FillOrdering {
    /// Nested dissection for matrices of dimension >= 1000 when it gives a smaller factor than AMD (it does
    /// on 3D tet meshes: about half the fill), else AMD.
    Auto,
    /// faer's approximate minimum degree.
    Amd,
    /// METIS nested dissection on the (block-compressed) graph; falls back to AMD if METIS fails.
    NestedDissection,
}

/// Below this dimension `Auto` uses AMD only.
const ND_MIN_DIM: usize = 1000;

impl std::fmt::Debug for SparseCholesky {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SparseCholesky")
            .field("n", &self.pattern.nrows())
            .field("nnz_l", &self.l_values.len())
            .field("ordering", &self.ordering)
            .finish()
    }
}

impl SparseCholesky {
    /// Symbolic analysis of a lower pattern with the [`FillOrdering::Auto`] ordering. `rhs_columns` is the
    /// largest number of right-hand sides solved at once.
    pub fn analyse(pattern: &LowerPattern, rhs_columns: usize) -> Result<Self> {
        Self::analyse_with(pattern, rhs_columns, FillOrdering::Auto)
    }

    /// Symbolic analysis with a chosen fill-reducing ordering.
    pub fn analyse_with(
        pattern: &LowerPattern,
        rhs_columns: usize,
        ordering: FillOrdering,
    ) -> Result<Self> {
        let sym = SymbolicSparseColMat::new_checked(
            pattern.n,
            pattern.n,
            pattern.col_ptr.clone(),
            None,
            pattern.row_idx.clone(),
        );
        let symbolic_failed =
            |e| FeprError::Simulation(format!("sparse symbolic analysis failed: {e:?}"));
        let amd = || {
            factorize_symbolic_cholesky(
                sym.as_ref(),
                Side::Lower,
                SymmetricOrdering::Amd,
                Default::default(),
            )
            .map_err(symbolic_failed)
        };
        let nd = || -> Option<Result<SymbolicCholesky<usize>>> {
            let (fwd, inv) = nested_dissection(pattern.n, &pattern.col_ptr, &pattern.row_idx)?;
            Some(
                factorize_symbolic_cholesky(
                    sym.as_ref(),
                    Side::Lower,
                    SymmetricOrdering::Custom(PermRef::new_checked(&fwd, &inv, pattern.n)),
                    Default::default(),
                )
                .map_err(symbolic_failed),
            )
        };
        let (symbolic, used) = match ordering {
            FillOrdering::Amd => (amd()?, FillOrdering::Amd),
            FillOrdering::NestedDissection => match nd() {
                Some(r) => (r?, FillOrdering::NestedDissection),
                None => (amd()?, FillOrdering::Amd),
            },
            FillOrdering::Auto if pattern.n < ND_MIN_DIM => (amd()?, FillOrdering::Amd),
            FillOrdering::Auto => {
                // Both symbolic analyses are cheap next to one numeric factorisation: keep the one with
                // the smaller factor (nested dissection on 3D meshes, by a factor of about 2).
                let a = amd()?;
                match nd() {
                    Some(Ok(n)) if n.len_val() < a.len_val() => (n, FillOrdering::NestedDissection),
                    _ => (a, FillOrdering::Amd),
                }
            }
        };
        let par = parallelism();
        let factor_mem =
            MemBuffer::new(symbolic.factorize_numeric_llt_scratch::<f64>(par, Default::default()));
        let solve_mem =
            MemBuffer::new(symbolic.solve_in_place_scratch::<f64>(rhs_columns.max(1), par));
        let l_values = vec![0.0; symbolic.len_val()];
        Ok(Self {
            pattern: sym,
            symbolic,
            l_values,
            factor_mem,
            solve_mem,
            solve_columns: rhs_columns.max(1),
            factorized: false,
            numeric_count: 0,
            ordering: used,
            work3: Vec::new(),
            work_cols: Vec::new(),
            plan3: None,
        })
    }

    /// The fill-reducing ordering in use (never `Auto`).
    pub fn ordering(&self) -> FillOrdering {
        self.ordering
    }

    pub fn dim(&self) -> usize {
        self.pattern.nrows()
    }

    /// True when faer chose a supernodal factor (large matrices), false for a simplicial one.
    pub fn is_supernodal(&self) -> bool {
        matches!(self.symbolic.raw(), SymbolicCholeskyRaw::Supernodal(_))
    }

    /// Non-zeros of the factor L.
    pub fn factor_nnz(&self) -> usize {
        self.l_values.len()
    }

    /// Numeric factorisation of the matrix with the analysed pattern and these values (lower triangle).
    /// Fails if the matrix is not (numerically) positive definite.
    pub fn factorize(&mut self, values: &[f64]) -> Result<()> {
        assert_eq!(values.len(), self.pattern.row_idx().len());
        let a = SparseColMatRef::new(self.pattern.as_ref(), values);
        let stack = MemStack::new(&mut self.factor_mem);
        self.factorized = false;
        self.symbolic
            .factorize_numeric_llt::<f64>(
                &mut self.l_values,
                a,
                Side::Lower,
                LltRegularization::default(),
                parallelism(),
                stack,
                Default::default(),
            )
            .map_err(|e| {
                FeprError::Simulation(format!(
                    "sparse Cholesky factorisation failed (matrix not positive definite): {e:?}"
                ))
            })?;
        self.factorized = true;
        self.numeric_count += 1;
        Ok(())
    }

    /// Solve `A X = B` in place for `ncols` right-hand sides stored column-major in `rhs` (length n * ncols).
    pub fn solve_in_place(&mut self, rhs: &mut [f64], ncols: usize) {
        assert!(self.factorized, "solve before a successful factorisation");
        let n = self.dim();
        assert_eq!(rhs.len(), n * ncols);
        let mat = MatMut::from_column_major_slice_mut(rhs, n, ncols);
        let stack = MemStack::new(&mut self.solve_mem);
        LltRef::new(&self.symbolic, &self.l_values).solve_in_place_with_conj(
            Conj::No,
            mat,
            Par::Seq,
            stack,
        );
    }

    /// [`SparseCholesky::solve_in_place`] for any number of right-hand sides (the solve's scratch grows to
    /// the largest number asked for).
    pub fn solve_many_in_place(&mut self, rhs: &mut [f64], ncols: usize) {
        if ncols > self.solve_columns {
            self.solve_mem = MemBuffer::new(
                self.symbolic
                    .solve_in_place_scratch::<f64>(ncols, parallelism()),
            );
            self.solve_columns = ncols;
        }
        self.solve_in_place(rhs, ncols);
    }

    /// Solve `A X = B` in place for 3 right-hand sides stored interleaved (`rhs[i]` = row i of B, shape
    /// (n, 3)): the x, y and z coordinates of a vertex problem, as Projective Dynamics solves them.
    ///
    /// faer's supernodal solve runs a small dense matrix product per supernode, whose set-up dominates with 3
    /// columns; this walks the same supernodal factor column by column with the 3 right-hand sides side by
    /// side in registers (measured 2-3x faster on the bunny's vertex matrix). It runs in parallel over the
    /// supernodal elimination tree on the current rayon pool (see `Solve3Plan`): disjoint subtrees are
    /// independent tasks, and their updates of the shared ancestors are summed in a fixed order, so the result
    /// has the same bits for any thread count. Simplicial factors (small matrices) go through faer.
    pub fn solve3_in_place(&mut self, rhs: &mut [[f64; 3]]) {
        self.solve3(rhs, true);
    }

    /// [`SparseCholesky::solve3_in_place`] with the sequential supernodal walk (no tree parallelism; its bits
    /// differ from the parallel solve's in the last places). For benchmarks.
    #[doc(hidden)]
    pub fn solve3_in_place_sequential(&mut self, rhs: &mut [[f64; 3]]) {
        self.solve3(rhs, false);
    }

    /// The work (stored factor values) of each task of the parallel 3-column solve's plan, in task order,
    /// and of the sequential rest; no tasks when the solve is sequential (simplicial factor, or fewer than 2
    /// tasks). Builds the plan if needed. For tests and benchmarks.
    #[doc(hidden)]
    pub fn solve3_plan_work(&mut self) -> (Vec<usize>, usize) {
        let SymbolicCholeskyRaw::Supernodal(sym) = self.symbolic.raw() else {
            return (Vec::new(), 0);
        };
        let plan = self.plan3.get_or_insert_with(|| Solve3Plan::new(sym));
        if plan.tasks.len() < 2 {
            return (Vec::new(), plan.total_work);
        }
        (plan.tasks.iter().map(|t| t.work).collect(), plan.rest_work)
    }

    fn solve3(&mut self, rhs: &mut [[f64; 3]], parallel: bool) {
        assert!(self.factorized, "solve before a successful factorisation");
        let n = self.dim();
        assert_eq!(rhs.len(), n);
        let SymbolicCholeskyRaw::Supernodal(sym) = self.symbolic.raw() else {
            // Column-major copy in a kept buffer (no allocation per solve), solved by faer.
            let mut cols = std::mem::take(&mut self.work_cols);
            cols.resize(3 * n, 0.0);
            for (i, r) in rhs.iter().enumerate() {
                for a in 0..3 {
                    cols[a * n + i] = r[a];
                }
            }
            self.solve_in_place(&mut cols, 3);
            for (i, r) in rhs.iter_mut().enumerate() {
                *r = [cols[i], cols[n + i], cols[2 * n + i]];
            }
            self.work_cols = cols;
            return;
        };
        let plan = match parallel {
            true => Some(self.plan3.get_or_insert_with(|| Solve3Plan::new(sym)))
                .filter(|p| p.tasks.len() >= 2),
            false => None,
        };
        let l = &self.l_values;
        let y = &mut self.work3;
        y.resize(n, [0.0; 4]);
        // faer factors P A P^T = L L^T with (P b)[i] = b[fwd[i]].
        let pad = |r: &[f64; 3]| [r[0], r[1], r[2], 0.0];
        let fwd = self.symbolic.perm().map(|p| p.arrays().0);
        match fwd {
            Some(fwd) => y
                .iter_mut()
                .zip(fwd)
                .for_each(|(yi, &f)| *yi = pad(&rhs[f])),
            None => y
                .iter_mut()
                .zip(rhs.iter())
                .for_each(|(yi, r)| *yi = pad(r)),
        }
        match plan {
            Some(plan) => plan.solve(sym, l, y),
            None => supernodal_solve3(sym, l, y),
        }
        match fwd {
            Some(fwd) => y
                .iter()
                .zip(fwd)
                .for_each(|(yi, &f)| rhs[f] = [yi[0], yi[1], yi[2]]),
            None => y
                .iter()
                .zip(rhs.iter_mut())
                .for_each(|(yi, r)| *r = [yi[0], yi[1], yi[2]]),
        }
    }
}

/// Supernode `s` of the factor: its first column, its column count k, its values (column-major, k + r rows:
/// the dense diagonal block, then the r rows of `pattern`) and the row indices below the diagonal block.
#[inline(always)]
fn supernode<'a>(
    sym: &'a SymbolicSupernodalCholesky<usize>,
    l: &'a [f64],
    s: usize,
) -> (usize, usize, &'a [f64], &'a [usize]) {
    let (b, e) = (sym.supernode_begin()[s], sym.supernode_end()[s]);
    let k = e - b;
    let vals = &l[sym.col_ptr_for_val()[s]..sym.col_ptr_for_val()[s + 1]];
    let r = vals.len() / k - k;
    let start = sym.col_ptr_for_row_idx()[s];
    (b, k, vals, &sym.row_idx()[start..start + r])
}

/// A row of the right-hand sides, padded to 4 lanes so that each update is one 4-wide SIMD operation.
type Row = [f64; 4];

avx2_dispatch! {
    /// `L y = b` then `L^T x = y` in place, the 3 right-hand sides side by side (4th lane unused); compiled
    /// for AVX2 where the CPU has it (the same bits).
    fn supernodal_solve3<'a>(
        sym: &'a SymbolicSupernodalCholesky<usize>,
        l: &'a [f64],
        y: &'a mut [Row],
    ) => supernodal_solve3_body
}

#[inline(always)]
fn supernodal_solve3_body(sym: &SymbolicSupernodalCholesky<usize>, l: &[f64], y: &mut [Row]) {
    supernodal_forward3(sym, l, y);
    supernodal_backward3(sym, l, y);
}

#[inline(always)]
fn axpy_neg(y: &mut Row, c: f64, x: &Row) {
    for a in 0..4 {
        y[a] -= c * x[a];
    }
}

/// `L y = b` in place.
#[inline(always)]
fn supernodal_forward3(sym: &SymbolicSupernodalCholesky<usize>, l: &[f64], y: &mut [Row]) {
    for s in 0..sym.n_supernodes() {
        let (b, k, vals, pattern) = supernode(sym, l, s);
        forward_supernode(vals, k, b, pattern, y);
    }
}

/// `L^T x = y` in place.
#[inline(always)]
fn supernodal_backward3(sym: &SymbolicSupernodalCholesky<usize>, l: &[f64], y: &mut [Row]) {
    for s in (0..sym.n_supernodes()).rev() {
        let (b, k, vals, pattern) = supernode(sym, l, s);
        backward_supernode(vals, k, b, pattern, y);
    }
}

/// A row index: faer's (`usize`) or one renumbered into a task's workspace (`u32`).
trait RowIndex: Copy {
    fn get(self) -> usize;
}

impl RowIndex for usize {
    #[inline(always)]
    fn get(self) -> usize {
        self
    }
}

impl RowIndex for u32 {
    #[inline(always)]
    fn get(self) -> usize {
        self as usize
    }
}

/// The forward step (`L y = b`) of a supernode: values `vals` (k columns), its columns at `y[b..b + k]`, the
/// rows of its pattern at `y[pattern[i]]`.
#[inline(always)]
fn forward_supernode<I: RowIndex>(vals: &[f64], k: usize, b: usize, pattern: &[I], y: &mut [Row]) {
    let rows = vals.len() / k;
    // The diagonal block.
    for j in 0..k {
        let col = &vals[j * rows..(j + 1) * rows];
        let d = col[j];
        let yj = y[b + j].map(|v| v / d);
        y[b + j] = yj;
        for i in j + 1..k {
            axpy_neg(&mut y[b + i], col[i], &yj);
        }
    }
    // The pattern rows, two columns at a time (each row's terms in column order).
    let mut j = 0;
    while j + 2 <= k {
        let c0 = &vals[j * rows + k..(j + 1) * rows];
        let c1 = &vals[(j + 1) * rows + k..(j + 2) * rows];
        let (y0, y1) = (y[b + j], y[b + j + 1]);
        for ((&u, &v), &r) in c0.iter().zip(c1).zip(pattern) {
            let yr = &mut y[r.get()];
            axpy_neg(yr, u, &y0);
            axpy_neg(yr, v, &y1);
        }
        j += 2;
    }
    if j < k {
        let c0 = &vals[j * rows + k..(j + 1) * rows];
        let y0 = y[b + j];
        for (&u, &r) in c0.iter().zip(pattern) {
            axpy_neg(&mut y[r.get()], u, &y0);
        }
    }
}

/// The backward step (`L^T x = y`) of a supernode, arguments as in [`forward_supernode`].
#[inline(always)]
fn backward_supernode<I: RowIndex>(vals: &[f64], k: usize, b: usize, pattern: &[I], y: &mut [Row]) {
    let rows = vals.len() / k;
    // The pattern rows' terms of each column's sum, two columns at a time (independent chains).
    let mut j = 0;
    while j + 2 <= k {
        let c0 = &vals[j * rows + k..(j + 1) * rows];
        let c1 = &vals[(j + 1) * rows + k..(j + 2) * rows];
        let (mut a0, mut a1) = (y[b + j], y[b + j + 1]);
        for ((&u, &v), &r) in c0.iter().zip(c1).zip(pattern) {
            let yr = &y[r.get()];
            axpy_neg(&mut a0, u, yr);
            axpy_neg(&mut a1, v, yr);
        }
        y[b + j] = a0;
        y[b + j + 1] = a1;
        j += 2;
    }
    if j < k {
        let c0 = &vals[j * rows + k..(j + 1) * rows];
        let mut a0 = y[b + j];
        for (&u, &r) in c0.iter().zip(pattern) {
            axpy_neg(&mut a0, u, &y[r.get()]);
        }
        y[b + j] = a0;
    }
    // Then the diagonal block's, columns in descending order.
    for j in (0..k).rev() {
        let col = &vals[j * rows..(j + 1) * rows];
        let mut acc = y[b + j];
        for i in j + 1..k {
            axpy_neg(&mut acc, col[i], &y[b + i]);
        }
        let d = col[j];
        y[b + j] = acc.map(|v| v / d);
    }
}

/// A subtree (or several adjacent ones) of the supernodal elimination tree, solved as one parallel task:
/// the supernodes `supernodes`, which own exactly the columns `columns`.
#[derive(Clone, Debug)]
struct Task {
    supernodes: Range<usize>,
    columns: Range<usize>,
    /// Stored factor values of its supernodes.
    work: usize,
    /// Its rows in [`Solve3Plan::workspace`]: its columns, then its boundary rows.
    workspace: Range<usize>,
    /// Its entries in [`Solve3Plan::boundary`].
    boundary: Range<usize>,
}

/// Subtrees with at most this fraction of the factor's values become tasks (a fixed fraction, so the plan and
/// hence the bits do not depend on the thread count).
const TASK_WORK_DIVISOR: usize = 8;

/// The parallel plan of the 3-column supernodal solve.
///
/// Disjoint subtrees of the supernodal elimination tree (faer numbers supernodes in a postorder, so a subtree
/// is a contiguous range of supernodes and of columns; checked) are independent tasks; the supernodes above
/// them (the "rest": ancestors of the tasks, the top separators of a nested dissection) are solved
/// sequentially. A task works in its own workspace: its columns, then its boundary rows (the rest rows that
/// its supernodes' patterns reach), with its supernodes' row indices renumbered into it once, so that its
/// inner loops are those of the sequential walk.
///
/// Forward (`L y = b`): the tasks in parallel, their updates of the boundary rows accumulated from zero; the
/// boundary sums added to the rest rows task by task, in task order; then the rest supernodes in ascending
/// order. Backward (`L^T x = y`): the rest supernodes in descending order; then the tasks in parallel, their
/// boundary rows copied from the solved rest rows. Every sum is taken in an order that the plan fixes, so the
/// bits do not depend on the thread count or on the scheduling.
#[derive(Debug)]
struct Solve3Plan {
    /// Ascending, disjoint.
    tasks: Vec<Task>,
    /// The supernodes in no task, ascending.
    rest_supernodes: Vec<usize>,
    /// Concatenated, for each task, its boundary rows (ascending).
    boundary: Vec<usize>,
    /// faer's row indices of the factor (`row_idx`) with those of the task supernodes renumbered into their
    /// task's workspace (the entries of the rest supernodes are unused).
    local_rows: Vec<u32>,
    /// The tasks' workspaces, one after the other.
    workspace: Vec<Row>,
    rest_work: usize,
    total_work: usize,
}

impl Solve3Plan {
    // Long (about 120 lines): one pass over the elimination tree that sizes every task and its workspace; split,
    // its running offsets would have to travel between the parts.
    fn new(sym: &SymbolicSupernodalCholesky<usize>) -> Self {
        let ns = sym.n_supernodes();
        let n = sym.nrows();
        let begin = sym.supernode_begin();
        let end = sym.supernode_end();
        let col_ptr_val = sym.col_ptr_for_val();
        let col_ptr_row = sym.col_ptr_for_row_idx();
        let row_idx = sym.row_idx();
        // Supernode of each column.
        let mut super_of = vec![0usize; n];
        for s in 0..ns {
            super_of[begin[s]..end[s]].fill(s);
        }
        let pattern_range = |s: usize| {
            let k = end[s] - begin[s];
            let r = (col_ptr_val[s + 1] - col_ptr_val[s]) / k - k;
            col_ptr_row[s]..col_ptr_row[s] + r
        };
        // Elimination tree: the parent is the supernode of the first row below the diagonal block.
        let parent: Vec<Option<usize>> = (0..ns)
            .map(|s| row_idx[pattern_range(s)].first().map(|&r| super_of[r]))
            .collect();
        let work: Vec<usize> = (0..ns)
            .map(|s| col_ptr_val[s + 1] - col_ptr_val[s])
            .collect();
        let total_work: usize = work.iter().sum();
        // Subtree work, size and smallest supernode (children come before their parent).
        let mut sub_work = work.clone();
        let mut sub_size = vec![1usize; ns];
        let mut sub_first: Vec<usize> = (0..ns).collect();
        let mut children = vec![Vec::new(); ns];
        let mut roots = Vec::new();
        for s in 0..ns {
            match parent[s] {
                Some(p) => {
                    assert!(p > s, "supernodal elimination tree out of order");
                    sub_work[p] += sub_work[s];
                    sub_size[p] += sub_size[s];
                    sub_first[p] = sub_first[p].min(sub_first[s]);
                    children[p].push(s);
                }
                None => roots.push(s),
            }
        }
        // A subtree is a task if it is small enough and contiguous; else its root goes to the rest and its
        // children are examined.
        let small = |w: usize| w * TASK_WORK_DIVISOR <= total_work;
        let mut found: Vec<(usize, usize, usize)> = Vec::new(); // (first, last + 1, work)
        let mut in_rest = vec![false; ns];
        let mut stack = roots;
        while let Some(s) = stack.pop() {
            if small(sub_work[s]) && s + 1 - sub_first[s] == sub_size[s] {
                found.push((sub_first[s], s + 1, sub_work[s]));
            } else {
                in_rest[s] = true;
                stack.extend_from_slice(&children[s]);
            }
        }
        found.sort_unstable();
        // Merge adjacent tasks (no rest supernode in between) while they stay small.
        let mut merged: Vec<(usize, usize, usize)> = Vec::new();
        for t in found {
            match merged.last_mut() {
                Some(m) if m.1 == t.0 && small(m.2 + t.2) => {
                    m.1 = t.1;
                    m.2 += t.2;
                }
                _ => merged.push(t),
            }
        }
        let rest_supernodes: Vec<usize> = (0..ns).filter(|&s| in_rest[s]).collect();
        let rest_work = rest_supernodes.iter().map(|&s| work[s]).sum();
        let local = |i: usize| u32::try_from(i).expect("a task workspace of fewer than 2^32 rows");
        let mut local_rows = vec![0u32; row_idx.len()];
        let mut boundary = Vec::new();
        let mut workspace_len = 0;
        let tasks: Vec<Task> = merged
            .into_iter()
            .map(|(first, last, w)| {
                let columns = begin[first]..end[last - 1];
                let mut rows: Vec<usize> = (first..last)
                    .flat_map(|s| &row_idx[pattern_range(s)])
                    .copied()
                    .filter(|&r| r >= columns.end)
                    .collect();
                rows.sort_unstable();
                rows.dedup();
                for s in first..last {
                    for i in pattern_range(s) {
                        let r = row_idx[i];
                        local_rows[i] = match columns.contains(&r) {
                            true => local(r - columns.start),
                            false => {
                                // Pattern rows are ancestors: the task's own or rest rows.
                                assert!(in_rest[super_of[r]], "a task reaches another task");
                                local(columns.len() + rows.binary_search(&r).unwrap())
                            }
                        };
                    }
                }
                let ws = workspace_len..workspace_len + columns.len() + rows.len();
                let bd = boundary.len()..boundary.len() + rows.len();
                workspace_len = ws.end;
                boundary.extend_from_slice(&rows);
                Task {
                    supernodes: first..last,
                    columns,
                    work: w,
                    workspace: ws,
                    boundary: bd,
                }
            })
            .collect();
        Self {
            tasks,
            rest_supernodes,
            boundary,
            local_rows,
            workspace: vec![[0.0; 4]; workspace_len],
            rest_work,
            total_work,
        }
    }

    /// `L y = b` then `L^T x = y` in place.
    fn solve(&mut self, sym: &SymbolicSupernodalCholesky<usize>, l: &[f64], y: &mut [Row]) {
        let ctx = TaskContext {
            sym,
            l,
            local_rows: &self.local_rows,
        };
        let (tasks, ws) = (&self.tasks, &mut self.workspace);
        // Forward: the tasks, their boundary sums added to the rest rows in task order, the rest.
        for_each_task(tasks, y, ws, &|t, y, w| forward_task(&ctx, t, y, w));
        forward_rest(sym, l, tasks, &self.boundary, ws, &self.rest_supernodes, y);
        // Backward: the rest, then the tasks with their boundary rows from the rest.
        backward_rest(sym, l, &self.rest_supernodes, y);
        for t in tasks {
            let tail = &mut ws[t.workspace.start + t.columns.len()..t.workspace.end];
            for (w, &r) in tail.iter_mut().zip(&self.boundary[t.boundary.clone()]) {
                *w = y[r];
            }
        }
        for_each_task(tasks, y, ws, &|t, y, w| backward_task(&ctx, t, y, w));
    }
}

/// What every task of a [`Solve3Plan`] reads.
struct TaskContext<'a> {
    sym: &'a SymbolicSupernodalCholesky<usize>,
    l: &'a [f64],
    local_rows: &'a [u32],
}

/// Runs `f(task, its columns of y, its workspace)` for each of `tasks`, `y` and `ws` the whole right-hand
/// side and workspace. The tasks touch disjoint data, so the schedule does not change any bit:
/// - on a pool of one thread, a loop on the calling thread;
/// - in a rayon worker, a fixed binary split with `rayon::join` (no allocation);
/// - outside the pool (Projective Dynamics steps from the caller's thread), the caller and jobs spawned on
///   the pool (one per further thread, one small allocation each) take tasks from a shared queue: a `join`
///   from outside would hand the whole phase to the pool and put the caller to sleep, which costs more than
///   the phase gains on two threads.
fn for_each_task<F>(tasks: &[Task], y: &mut [Row], ws: &mut [Row], f: &F)
where
    F: Fn(&Task, &mut [Row], &mut [Row]) + Sync,
{
    let threads = crate::exec::current_threads();
    if threads < 2 {
        let mut queue = TaskQueue::new(tasks, y, ws);
        while let Some((t, y, w)) = queue.pop() {
            f(t, y, w);
        }
    } else if rayon::current_thread_index().is_some() {
        join_tasks(tasks, y, 0, ws, 0, f);
    } else {
        let queue = std::sync::Mutex::new(TaskQueue::new(tasks, y, ws));
        let work = || loop {
            let next = queue.lock().map(|mut q| q.pop());
            match next {
                Ok(Some((t, y, w))) => f(t, y, w),
                _ => break,
            }
        };
        rayon::in_place_scope(|scope| {
            for _ in 1..threads.min(tasks.len()) {
                scope.spawn(|_| work());
            }
            work();
        });
    }
}

/// [`for_each_task`] in a rayon worker: `y` holds the rows from `y0` on, `ws` the workspace rows from `w0` on.
fn join_tasks<F>(tasks: &[Task], y: &mut [Row], y0: usize, ws: &mut [Row], w0: usize, f: &F)
where
    F: Fn(&Task, &mut [Row], &mut [Row]) + Sync,
{
    match tasks {
        [] => {}
        [t] => f(
            t,
            &mut y[t.columns.start - y0..t.columns.end - y0],
            &mut ws[t.workspace.start - w0..t.workspace.end - w0],
        ),
        _ => {
            let (a, b) = tasks.split_at(tasks.len() / 2);
            let (y1, w1) = (b[0].columns.start, b[0].workspace.start);
            let (ya, yb) = y.split_at_mut(y1 - y0);
            let (wa, wb) = ws.split_at_mut(w1 - w0);
            rayon::join(
                || join_tasks(a, ya, y0, wa, w0, f),
                || join_tasks(b, yb, y1, wb, w1, f),
            );
        }
    }
}

/// The tasks in order, each with its rows of the right-hand side and of the workspace (split off as it goes).
struct TaskQueue<'a> {
    tasks: &'a [Task],
    /// The rows from `y0` on.
    y: &'a mut [Row],
    y0: usize,
    /// The workspace rows from `w0` on.
    ws: &'a mut [Row],
    w0: usize,
}

impl<'a> TaskQueue<'a> {
    fn new(tasks: &'a [Task], y: &'a mut [Row], ws: &'a mut [Row]) -> Self {
        Self {
            tasks,
            y,
            y0: 0,
            ws,
            w0: 0,
        }
    }

    #[allow(clippy::type_complexity)]
    fn pop(&mut self) -> Option<(&'a Task, &'a mut [Row], &'a mut [Row])> {
        let (t, rest) = self.tasks.split_first()?;
        self.tasks = rest;
        let y = std::mem::take(&mut self.y);
        let (yt, y) = y[t.columns.start - self.y0..].split_at_mut(t.columns.len());
        (self.y, self.y0) = (y, t.columns.end);
        let ws = std::mem::take(&mut self.ws);
        let (wt, ws) = ws[t.workspace.start - self.w0..].split_at_mut(t.workspace.len());
        (self.ws, self.w0) = (ws, t.workspace.end);
        Some((t, yt, wt))
    }
}

/// The supernode `s` of a task: as [`supernode`], its first column relative to the task's and its pattern
/// in the task's workspace.
#[inline(always)]
fn task_supernode<'a>(
    ctx: &TaskContext<'a>,
    task: &Task,
    s: usize,
) -> (usize, usize, &'a [f64], &'a [u32]) {
    let (b, k, vals, pattern) = supernode(ctx.sym, ctx.l, s);
    let start = ctx.sym.col_ptr_for_row_idx()[s];
    let local = &ctx.local_rows[start..start + pattern.len()];
    (b - task.columns.start, k, vals, local)
}

avx2_dispatch! {
    /// The forward step of one task: its right-hand side rows `y` into its workspace, boundary rows from zero.
    fn forward_task<'a>(ctx: &'a TaskContext<'a>, task: &'a Task, y: &'a mut [Row], ws: &'a mut [Row]) => forward_task_body
}

#[inline(always)]
fn forward_task_body(ctx: &TaskContext, task: &Task, y: &mut [Row], ws: &mut [Row]) {
    let (own, tail) = ws.split_at_mut(y.len());
    own.copy_from_slice(y);
    tail.fill([0.0; 4]);
    for s in task.supernodes.clone() {
        let (b, k, vals, pattern) = task_supernode(ctx, task, s);
        forward_supernode(vals, k, b, pattern, ws);
    }
}

avx2_dispatch! {
    /// The backward step of one task, in its workspace (boundary rows set); the result to its rows `y`.
    fn backward_task<'a>(ctx: &'a TaskContext<'a>, task: &'a Task, y: &'a mut [Row], ws: &'a mut [Row]) => backward_task_body
}

#[inline(always)]
fn backward_task_body(ctx: &TaskContext, task: &Task, y: &mut [Row], ws: &mut [Row]) {
    for s in task.supernodes.clone().rev() {
        let (b, k, vals, pattern) = task_supernode(ctx, task, s);
        backward_supernode(vals, k, b, pattern, ws);
    }
    y.copy_from_slice(&ws[..y.len()]);
}

avx2_dispatch! {
    /// Adds the tasks' boundary sums to the rest rows (task by task, in task order), then the forward step of
    /// the rest supernodes.
    fn forward_rest<'a>(
        sym: &'a SymbolicSupernodalCholesky<usize>,
        l: &'a [f64],
        tasks: &'a [Task],
        boundary: &'a [usize],
        ws: &'a [Row],
        rest_supernodes: &'a [usize],
        y: &'a mut [Row],
    ) => forward_rest_body
}

#[inline(always)]
fn forward_rest_body(
    sym: &SymbolicSupernodalCholesky<usize>,
    l: &[f64],
    tasks: &[Task],
    boundary: &[usize],
    ws: &[Row],
    rest_supernodes: &[usize],
    y: &mut [Row],
) {
    for t in tasks {
        let tail = &ws[t.workspace.start + t.columns.len()..t.workspace.end];
        for (u, &r) in tail.iter().zip(&boundary[t.boundary.clone()]) {
            for a in 0..4 {
                y[r][a] += u[a];
            }
        }
    }
    for &s in rest_supernodes {
        let (b, k, vals, pattern) = supernode(sym, l, s);
        forward_supernode(vals, k, b, pattern, y);
    }
}

avx2_dispatch! {
    /// The backward step of the rest supernodes, in descending order.
    fn backward_rest<'a>(
        sym: &'a SymbolicSupernodalCholesky<usize>,
        l: &'a [f64],
        rest_supernodes: &'a [usize],
        y: &'a mut [Row],
    ) => backward_rest_body
}

#[inline(always)]
fn backward_rest_body(
    sym: &SymbolicSupernodalCholesky<usize>,
    l: &[f64],
    rest_supernodes: &[usize],
    y: &mut [Row],
) {
    for &s in rest_supernodes.iter().rev() {
        let (b, k, vals, pattern) = supernode(sym, l, s);
        backward_supernode(vals, k, b, pattern, y);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 3D grid graph Laplacian + identity with `b` dofs per node (block diagonal coupling), lower pattern.
    fn grid3(nx: usize, b: usize) -> (LowerPattern, Vec<f64>) {
        let idx = |x: usize, y: usize, z: usize| x + nx * (y + nx * z);
        let nodes = nx * nx * nx;
        let mut cols = vec![Vec::new(); nodes * b];
        let mut edges = Vec::new();
        for z in 0..nx {
            for y in 0..nx {
                for x in 0..nx {
                    let p = idx(x, y, z);
                    for (dx, dy, dz) in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1)] {
                        if x + dx < nx && y + dy < nx && z + dz < nx {
                            edges.push((p, idx(x + dx, y + dy, z + dz)));
                        }
                    }
                }
            }
        }
        for &(p, q) in &edges {
            for a in 0..b {
                for c in 0..b {
                    cols[b * p + a].push(b * q + c);
                }
            }
        }
        for p in 0..nodes {
            for a in 0..b {
                for c in a + 1..b {
                    cols[b * p + a].push(b * p + c);
                }
            }
        }
        let pat = LowerPattern::from_columns(nodes * b, cols);
        let mut values = vec![0.0; pat.nnz()];
        let mut diag = vec![1.0; pat.n];
        for c in 0..pat.n {
            for k in pat.col_ptr[c] + 1..pat.col_ptr[c + 1] {
                values[k] = -0.1;
                diag[c] += 0.1;
                diag[pat.row_idx[k]] += 0.1;
            }
        }
        for c in 0..pat.n {
            values[pat.col_ptr[c]] = diag[c];
        }
        (pat, values)
    }

    #[test]
    fn nested_dissection_beats_amd_on_3d_grids_and_solves_the_same_system() {
        for b in [1, 3] {
            let (pat, values) = grid3(14, b);
            let mut amd = SparseCholesky::analyse_with(&pat, 1, FillOrdering::Amd).unwrap();
            let mut nd =
                SparseCholesky::analyse_with(&pat, 1, FillOrdering::NestedDissection).unwrap();
            let auto = SparseCholesky::analyse(&pat, 1).unwrap();
            assert_eq!(nd.ordering(), FillOrdering::NestedDissection);
            assert!(
                nd.factor_nnz() < amd.factor_nnz(),
                "b = {b}: nd {} vs amd {}",
                nd.factor_nnz(),
                amd.factor_nnz()
            );
            assert_eq!(auto.ordering(), FillOrdering::NestedDissection);
            amd.factorize(&values).unwrap();
            nd.factorize(&values).unwrap();
            let rhs: Vec<f64> = (0..pat.n).map(|i| (i as f64 * 0.37).sin()).collect();
            let (mut xa, mut xn) = (rhs.clone(), rhs.clone());
            amd.solve_in_place(&mut xa, 1);
            nd.solve_in_place(&mut xn, 1);
            let diff = xa
                .iter()
                .zip(&xn)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(diff < 1e-12, "{diff}");
        }
    }

    #[test]
    fn interleaved_three_column_solve_matches_faer_on_supernodal_and_simplicial_factors() {
        // 14^3 nodes: supernodal with nested dissection (and with AMD); 3^3: simplicial.
        for (nx, ordering) in [
            (14, FillOrdering::NestedDissection),
            (14, FillOrdering::Amd),
            (3, FillOrdering::Auto),
        ] {
            let (pat, values) = grid3(nx, 1);
            let mut chol = SparseCholesky::analyse_with(&pat, 3, ordering).unwrap();
            assert_eq!(chol.is_supernodal(), nx > 3);
            chol.factorize(&values).unwrap();
            let n = pat.n;
            let b: Vec<[f64; 3]> = (0..n)
                .map(|i| {
                    let t = i as f64;
                    [(0.37 * t).sin(), (0.11 * t).cos(), 1.0 + 0.01 * t]
                })
                .collect();
            let mut cols = vec![0.0; 3 * n];
            for (i, r) in b.iter().enumerate() {
                for a in 0..3 {
                    cols[a * n + i] = r[a];
                }
            }
            chol.solve_in_place(&mut cols, 3);
            let mut x = b.clone();
            chol.solve3_in_place(&mut x);
            // Three solves with the same inputs give the same bits (the workspace carries nothing over).
            let mut again = b.clone();
            chol.solve3_in_place(&mut again);
            assert!(x
                .iter()
                .flatten()
                .zip(again.iter().flatten())
                .all(|(p, q)| p.to_bits() == q.to_bits()));
            let mut worst: f64 = 0.0;
            for (i, r) in x.iter().enumerate() {
                for a in 0..3 {
                    worst = worst.max((r[a] - cols[a * n + i]).abs());
                }
            }
            assert!(worst < 1e-12, "nx {nx}, {ordering:?}: {worst}");
            // And it solves the system: A x = b (A from the lower triangle).
            let mut ax = vec![[0.0; 3]; n];
            for c in 0..n {
                for k in pat.col_ptr[c]..pat.col_ptr[c + 1] {
                    let r = pat.row_idx[k];
                    for a in 0..3 {
                        ax[r][a] += values[k] * x[c][a];
                        if r != c {
                            ax[c][a] += values[k] * x[r][a];
                        }
                    }
                }
            }
            for (i, r) in ax.iter().enumerate() {
                for a in 0..3 {
                    assert!((r[a] - b[i][a]).abs() < 1e-10, "row {i}");
                }
            }
        }
    }

    /// Right-hand sides for the 3-column solve tests.
    fn rhs3(n: usize) -> Vec<[f64; 3]> {
        (0..n)
            .map(|i| {
                let t = i as f64;
                [(0.37 * t).sin(), (0.11 * t).cos(), 1.0 + 0.01 * t]
            })
            .collect()
    }

    #[test]
    fn parallel_three_column_solve_matches_faer_and_has_the_same_bits_on_any_thread_count() {
        // Nested dissection on 3D grids: supernodal factors whose elimination trees split into tasks (and
        // AMD, whose tree may or may not).
        for (nx, b, ordering) in [
            (14, 1, FillOrdering::NestedDissection),
            (12, 3, FillOrdering::NestedDissection),
            (14, 1, FillOrdering::Amd),
        ] {
            let (pat, values) = grid3(nx, b);
            let mut chol = SparseCholesky::analyse_with(&pat, 3, ordering).unwrap();
            assert!(chol.is_supernodal());
            chol.factorize(&values).unwrap();
            let (tasks, rest) = chol.solve3_plan_work();
            if ordering == FillOrdering::NestedDissection {
                assert!(tasks.len() >= 2, "nx {nx}, b {b}: {} tasks", tasks.len());
            }
            let total = tasks.iter().sum::<usize>() + rest;
            assert_eq!(total, chol.factor_nnz());
            assert!(tasks.iter().all(|&w| w * TASK_WORK_DIVISOR <= total));
            let n = pat.n;
            let rhs = rhs3(n);
            let mut cols = vec![0.0; 3 * n];
            for (i, r) in rhs.iter().enumerate() {
                for a in 0..3 {
                    cols[a * n + i] = r[a];
                }
            }
            chol.solve_in_place(&mut cols, 3);
            let scale = cols.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let mut reference: Option<Vec<[f64; 3]>> = None;
            // Inside pools of 1, 2 and 3 threads, and from this thread (outside any pool: the global pool's
            // threads pull tasks from a queue beside this one), with the same bits.
            for threads in [1, 2, 3, 0, 1] {
                let mut x = rhs.clone();
                match threads {
                    0 => chol.solve3_in_place(&mut x),
                    _ => rayon::ThreadPoolBuilder::new()
                        .num_threads(threads)
                        .build()
                        .unwrap()
                        .install(|| chol.solve3_in_place(&mut x)),
                }
                let mut worst: f64 = 0.0;
                for (i, r) in x.iter().enumerate() {
                    for a in 0..3 {
                        worst = worst.max((r[a] - cols[a * n + i]).abs());
                    }
                }
                assert!(
                    worst <= 1e-12 * scale,
                    "nx {nx}, b {b}, {threads} threads: {worst}"
                );
                match &reference {
                    None => reference = Some(x),
                    Some(r) => assert!(
                        r.iter()
                            .flatten()
                            .zip(x.iter().flatten())
                            .all(|(p, q)| p.to_bits() == q.to_bits()),
                        "nx {nx}, b {b}: {threads} threads give other bits than 1"
                    ),
                }
            }
            // The sequential walk solves the same system (other rounding).
            let mut seq = rhs.clone();
            chol.solve3_in_place_sequential(&mut seq);
            let worst = seq
                .iter()
                .flatten()
                .zip(reference.unwrap().iter().flatten())
                .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
            assert!(worst <= 1e-12 * scale, "{worst}");
        }
    }

    /// The plain column-by-column supernodal walk (`L y = b` then `L^T x = y`), without the paired columns.
    fn plain_solve3(sym: &SymbolicSupernodalCholesky<usize>, l: &[f64], y: &mut [Row]) {
        for s in 0..sym.n_supernodes() {
            let (b, k, vals, pattern) = supernode(sym, l, s);
            let rows = vals.len() / k;
            for j in 0..k {
                let col = &vals[j * rows..(j + 1) * rows];
                let yj = y[b + j].map(|v| v / col[j]);
                y[b + j] = yj;
                for i in j + 1..k {
                    axpy_neg(&mut y[b + i], col[i], &yj);
                }
                for (&c, &r) in col[k..].iter().zip(pattern) {
                    axpy_neg(&mut y[r], c, &yj);
                }
            }
        }
        for s in (0..sym.n_supernodes()).rev() {
            let (b, k, vals, pattern) = supernode(sym, l, s);
            let rows = vals.len() / k;
            for j in (0..k).rev() {
                let col = &vals[j * rows..(j + 1) * rows];
                let mut acc = y[b + j];
                for (&c, &r) in col[k..].iter().zip(pattern) {
                    axpy_neg(&mut acc, c, &y[r]);
                }
                for i in j + 1..k {
                    axpy_neg(&mut acc, col[i], &y[b + i]);
                }
                y[b + j] = acc.map(|v| v / col[j]);
            }
        }
    }

    #[test]
    fn paired_column_kernels_give_the_bits_of_the_plain_column_walk() {
        // The paired-column kernels reorder loops, not any row's sum: the same bits as the plain walk.
        let (pat, values) = grid3(12, 3);
        let mut chol =
            SparseCholesky::analyse_with(&pat, 3, FillOrdering::NestedDissection).unwrap();
        chol.factorize(&values).unwrap();
        let n = pat.n;
        let rhs = rhs3(n);
        let mut x = rhs.clone();
        chol.solve3_in_place_sequential(&mut x);
        let SymbolicCholeskyRaw::Supernodal(sym) = chol.symbolic.raw() else {
            panic!("simplicial");
        };
        let fwd = chol.symbolic.perm().unwrap().arrays().0;
        let mut y: Vec<Row> = fwd
            .iter()
            .map(|&f| [rhs[f][0], rhs[f][1], rhs[f][2], 0.0])
            .collect();
        plain_solve3(sym, &chol.l_values, &mut y);
        for (yi, &f) in y.iter().zip(fwd) {
            for a in 0..3 {
                assert_eq!(yi[a].to_bits(), x[f][a].to_bits());
            }
        }
    }

    #[test]
    fn solve_plan_tasks_are_disjoint_subtrees_covering_the_factor_with_the_rest() {
        let (pat, _) = grid3(14, 1);
        let chol = SparseCholesky::analyse_with(&pat, 3, FillOrdering::NestedDissection).unwrap();
        let SymbolicCholeskyRaw::Supernodal(sym) = chol.symbolic.raw() else {
            panic!("simplicial");
        };
        let plan = Solve3Plan::new(sym);
        let ns = sym.n_supernodes();
        let mut owner = vec![usize::MAX; ns];
        for (t, task) in plan.tasks.iter().enumerate() {
            assert_eq!(
                task.columns.start,
                sym.supernode_begin()[task.supernodes.start]
            );
            assert_eq!(
                task.columns.end,
                sym.supernode_end()[task.supernodes.end - 1]
            );
            for s in task.supernodes.clone() {
                assert_eq!(owner[s], usize::MAX);
                owner[s] = t;
            }
        }
        for &s in &plan.rest_supernodes {
            assert_eq!(owner[s], usize::MAX);
            owner[s] = usize::MAX - 1;
        }
        assert!(owner.iter().all(|&o| o != usize::MAX));
        // A task's pattern rows are its own columns or rest columns (ancestors of the task).
        for task in &plan.tasks {
            for s in task.supernodes.clone() {
                let start = sym.col_ptr_for_row_idx()[s];
                let k = sym.supernode_end()[s] - sym.supernode_begin()[s];
                let len = (sym.col_ptr_for_val()[s + 1] - sym.col_ptr_for_val()[s]) / k - k;
                for &r in &sym.row_idx()[start..start + len] {
                    let rest = |c: usize| {
                        plan.rest_supernodes.iter().any(|&q| {
                            (sym.supernode_begin()[q]..sym.supernode_end()[q]).contains(&c)
                        })
                    };
                    assert!(task.columns.contains(&r) || rest(r));
                }
            }
        }
    }

    #[test]
    fn solves_a_small_spd_system_and_reuses_the_analysis() {
        // Tridiagonal 1-D Laplacian plus identity.
        let n = 50;
        let cols: Vec<Vec<usize>> = (0..n)
            .map(|c| if c + 1 < n { vec![c + 1] } else { vec![] })
            .collect();
        let pattern = LowerPattern::from_columns(n, cols);
        let mut chol = SparseCholesky::analyse(&pattern, 1).unwrap();
        for shift in [1.0, 3.0] {
            let mut values = vec![0.0; pattern.nnz()];
            for c in 0..n {
                values[pattern.position(c, c).unwrap()] = 2.0 + shift;
                if c + 1 < n {
                    values[pattern.position(c + 1, c).unwrap()] = -1.0;
                }
            }
            chol.factorize(&values).unwrap();
            let b: Vec<f64> = (0..n).map(|i| (i as f64 * 0.3).sin()).collect();
            let mut x = b.clone();
            chol.solve_in_place(&mut x, 1);
            for i in 0..n {
                let mut ax = (2.0 + shift) * x[i];
                if i > 0 {
                    ax -= x[i - 1];
                }
                if i + 1 < n {
                    ax -= x[i + 1];
                }
                assert!((ax - b[i]).abs() < 1e-12);
            }
        }
        assert_eq!(chol.numeric_count, 2);
        // Not positive definite: an error, not a panic.
        let values = vec![-1.0; pattern.nnz()];
        assert!(chol.factorize(&values).is_err());
    }
}
