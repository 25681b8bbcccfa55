//! A symmetric positive definite system `A x = b` solved by conjugate gradients preconditioned by the Cholesky
//! factor of a nearby matrix with the same pattern: an earlier Newton iteration's Hessian. Backward Euler uses
//! it so that one factorisation serves the iterations after it, whose Hessians differ little (see
//! [`crate::integrators::ImplicitEuler`]).
//!
//! Written here rather than taken from faer's `matrix_free::conjugate_gradient` (0.24): that block solver
//! returned NaN and "not positive definite" on a 5 x 5 tridiagonal SPD system in our tests, with the identity
//! as preconditioner too; this is the textbook single-vector method (Saad, Iterative Methods, alg. 9.1), with
//! the solve and the product in a fixed order, so its bits do not depend on the thread count.

use crate::math::{LowerPattern, SparseCholesky};

/// `y = A x`, `A` symmetric given by its lower triangle (CSC, `col_ptr`, `row_idx`, `values`).
fn symmetric_product(
    col_ptr: &[usize],
    row_idx: &[usize],
    values: &[f64],
    x: &[f64],
    y: &mut [f64],
) {
    y.iter_mut().for_each(|v| *v = 0.0);
    for j in 0..x.len() {
        let xj = x[j];
        let mut yj = 0.0;
        for k in col_ptr[j]..col_ptr[j + 1] {
            let (i, v) = (row_idx[k], values[k]);
            y[i] += v * xj;
            if i != j {
                yj += v * x[i];
            }
        }
        y[j] += yj;
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Solve `A x = b`, `A` the symmetric matrix whose lower triangle `values` has the pattern `pattern` (the one
/// `factor` was analysed for), by
/// conjugate gradients preconditioned with `factor` (a factorisation of a nearby matrix), from `x = 0`, until
/// `|b - A x| <= rel_tolerance |b|`. `rhs` holds `b` and receives `x`. Returns the iterations, or `None` when
/// they did not converge within `max_iterations` or `A` showed a direction of non-positive curvature (then
/// `rhs` is left unspecified).
pub fn solve_preconditioned(
    factor: &mut SparseCholesky,
    pattern: &LowerPattern,
    values: &[f64],
    rhs: &mut [f64],
    rel_tolerance: f64,
    max_iterations: usize,
) -> Option<usize> {
    let n = rhs.len();
    let (col_ptr, row_idx) = (&pattern.col_ptr, &pattern.row_idx);
    let mut r = rhs.to_vec();
    let threshold = rel_tolerance * dot(&r, &r).sqrt();
    let x = rhs;
    x.iter_mut().for_each(|v| *v = 0.0);
    if threshold == 0.0 {
        return Some(0);
    }
    let mut z = r.clone();
    factor.solve_in_place(&mut z, 1);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let mut ap = vec![0.0; n];
    for it in 1..=max_iterations {
        symmetric_product(col_ptr, row_idx, values, &p, &mut ap);
        let pap = dot(&p, &ap);
        if !(pap > 0.0 && pap.is_finite() && rz > 0.0) {
            return None;
        }
        let alpha = rz / pap;
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] -= alpha * ap[i];
        }
        if dot(&r, &r).sqrt() <= threshold {
            return Some(it);
        }
        z.copy_from_slice(&r);
        factor.solve_in_place(&mut z, 1);
        let rz_new = dot(&r, &z);
        let beta = rz_new / rz;
        rz = rz_new;
        for i in 0..n {
            p[i] = z[i] + beta * p[i];
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::LowerPattern;

    /// A tridiagonal SPD matrix `diag d, off-diagonal -1` (lower CSC values in the pattern's order).
    fn tridiagonal(n: usize, d: f64) -> (LowerPattern, Vec<f64>) {
        let columns = (0..n)
            .map(|j| if j + 1 < n { vec![j, j + 1] } else { vec![j] })
            .collect();
        let pattern = LowerPattern::from_columns(n, columns);
        let values = (0..n)
            .flat_map(|j| if j + 1 < n { vec![d, -1.0] } else { vec![d] })
            .collect();
        (pattern, values)
    }

    #[test]
    fn the_exact_factor_solves_in_one_iteration_and_a_nearby_one_in_a_few() {
        let n = 200;
        let (pattern, values) = tridiagonal(n, 2.5);
        let mut chol = SparseCholesky::analyse(&pattern, 1).unwrap();
        chol.factorize(&values).unwrap();
        let b: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
        let mut x = b.clone();
        let its = solve_preconditioned(&mut chol, &pattern, &values, &mut x, 1e-12, 50)
            .expect("converges");
        assert!(its <= 2, "{its}");
        let mut direct = b.clone();
        chol.solve_in_place(&mut direct, 1);
        for i in 0..n {
            assert!((x[i] - direct[i]).abs() < 1e-10 * direct[i].abs().max(1.0));
        }
        // The factor of a nearby matrix: a few iterations.
        let (_, nearby) = tridiagonal(n, 2.7);
        let mut x = b.clone();
        let its = solve_preconditioned(&mut chol, &pattern, &nearby, &mut x, 1e-10, 50)
            .expect("converges");
        assert!(its > 1 && its < 15, "{its}");
    }
}
