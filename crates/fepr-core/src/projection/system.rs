//! The small system of one iteration (fepr-spec section 3): `S = G^T D^-1 G` in closed form from the mass
//! moments, and its scaled, regularised solve for the multipliers with the constraints' known second-order
//! terms along the step.

use super::evaluate::Eval;
use super::problem::Problem;
use super::ROWS;
use crate::math::{cholesky_substitute, cross, dot, solve_symmetric_psd_into, Vec3};

/// The full 10x10 `S = G^T D^-1 G` from the moments (fepr-spec section 3; derivation in docs/fepr.md) and its
/// velocity block `sv` ([`velocity_block`], which the solve also needs for the second-order terms).
pub(super) fn small_matrix(pb: &Problem, e: &Eval, sv: [[f64; ROWS]; ROWS]) -> [[f64; ROWS]; ROWS] {
    let mt = pb.model.total_mass;
    let mut s = sv;
    let unit = |a: usize| {
        let mut u = [0.0; 3];
        u[a] = 1.0;
        u
    };
    // Position-block terms carry the metric factor a_i (the `a_` moments); velocity-block terms do not.
    let tr_avv = e.a_vv[0][0] + e.a_vv[1][1] + e.a_vv[2][2];
    s[0][0] += e.grad_sq_over_w;
    for a in 0..3 {
        s[0][4 + a] += e.a_grad_cross_v[a];
        s[0][7 + a] = e.a_grad_sum[a] / mt;
        let pxa = cross(e.a_free_p, unit(a));
        for b in 0..3 {
            let delta = if a == b { 1.0 } else { 0.0 };
            s[1 + a][1 + b] += pb.dp_star[a] * pb.dp_star[b] / pb.eps;
            s[4 + a][4 + b] = (tr_avv * delta - e.a_vv[a][b])
                + s[4 + a][4 + b]
                + pb.dl_star[a] * pb.dl_star[b] / pb.eps;
            s[4 + a][7 + b] = pxa[b] / mt;
            s[7 + a][7 + b] = e.a_free_mass / (mt * mt) * delta;
        }
    }
    for i in 0..ROWS {
        for j in 0..i {
            s[i][j] = s[j][i];
        }
    }
    s
}

/// The velocity block's part of `S`: the sum over the free vertices of `dc/dv_i (h^2 m_i)^-1 dc/dv_i^T`
/// (H, P and L depend on the velocities; C does not), upper triangle. With it the kinetic energy's change
/// along a step is known exactly: `K(v + dv) = K(v) + (linear part) + lambda^T S_v lambda / (2 h^2)`.
pub(super) fn velocity_block(pb: &Problem, e: &Eval) -> [[f64; ROWS]; ROWS] {
    let h2 = pb.h * pb.h;
    let mut s = [[0.0; ROWS]; ROWS];
    let unit = |a: usize| {
        let mut u = [0.0; 3];
        u[a] = 1.0;
        u
    };
    let tr_rr = e.rr[0][0] + e.rr[1][1] + e.rr[2][2];
    s[0][0] = e.tr_vv / h2;
    for a in 0..3 {
        s[0][1 + a] = e.free_p[a] / h2;
        s[0][4 + a] = e.free_l[a] / h2;
        for b in 0..3 {
            let delta = if a == b { 1.0 } else { 0.0 };
            s[1 + a][1 + b] = e.free_mass * delta / h2;
            // e_a . (e_b x R) = eps_abc R_c
            s[1 + a][4 + b] = dot(unit(a), cross(unit(b), e.free_r)) / h2;
            s[4 + a][4 + b] = (tr_rr * delta - e.rr[a][b]) / h2;
        }
    }
    s
}

/// The multipliers of one iteration.
pub(super) struct Multipliers {
    pub(super) lambda: [f64; ROWS],
    /// The small system needed the least-squares fallback.
    pub(super) least_squares: bool,
    /// The second-order offsets `d` (zero but in the H and L rows): the multipliers solve `S lambda = c + d`,
    /// with `d` the constraints' second-order terms along the full step (see [`solve_multipliers`]).
    pub(super) offset: [f64; ROWS],
}

/// The kinetic energy's second-order term along the step of multipliers `u` (J): with the step's velocity
/// change `dv_i = -(h^2 m_i)^-1 dc/dv_i^T u`, `sum m_i |dv_i|^2 / 2 = u^T S_v u / (2 h^2)` (`sv`: the velocity
/// block of `S`, [`velocity_block`], upper triangle; rows H, P and L). Bilinear in `u` and `w`: the term is
/// `kinetic_second_order(sv, h, u, u)`.
pub(super) fn kinetic_second_order(
    sv: &[[f64; ROWS]; ROWS],
    h: f64,
    u: &[f64; ROWS],
    w: &[f64; ROWS],
) -> f64 {
    let mut sum = 0.0;
    for i in 0..7 {
        sum += sv[i][i] * u[i] * w[i];
        for j in i + 1..7 {
            sum += sv[i][j] * (u[i] * w[j] + u[j] * w[i]);
        }
    }
    sum / (2.0 * h * h)
}

/// The angular momentum's second-order term along the step of multipliers `lambda` (kg m^2/s): L is
/// quadratic along a step, `L(q + dq) = L + (linear part) + sum m_i dx_i x dv_i`, and with
/// `dx_i = -a_i (lambda_H g_i / m_i + v_i x lambda_L + lambda_C / m_t)` and
/// `dv_i = -(lambda_H v_i + lambda_P + lambda_L x r_i) / h^2` (`g_i` the potential's gradient, `r_i = x_i - C_t`)
/// the sum expands into moments of the free vertices (`e`'s, summed with S's).
pub(super) fn angular_second_order(pb: &Problem, e: &Eval, lambda: &[f64; ROWS]) -> Vec3 {
    let (lh, lp, ll) = (
        lambda[0],
        [lambda[1], lambda[2], lambda[3]],
        [lambda[4], lambda[5], lambda[6]],
    );
    let lc_over_mt = [7, 8, 9].map(|k| lambda[k] / pb.model.total_mass);
    let tr_agr = e.a_grad_r[0][0] + e.a_grad_r[1][1] + e.a_grad_r[2][2];
    let tr_avv = e.a_vv[0][0] + e.a_vv[1][1] + e.a_vv[2][2];
    // sum a g x (l x r) = l tr(AGR) - AGR^T l;  sum m a (v x l) x v = (tr AVV) l - AVV l.
    let agr_t_l: Vec3 = std::array::from_fn(|k| (0..3).map(|j| e.a_grad_r[j][k] * ll[j]).sum());
    let avv_l: Vec3 = std::array::from_fn(|k| (0..3).map(|j| e.a_vv[k][j] * ll[j]).sum());
    // sum m a (v x l) x (l x r) = l (l . sum m a r x v).
    let l_dot_arxv = dot(ll, e.a_r_cross_v);
    // sum m a (lh v + lp + l x r) = lh AFP + AFM lp + l x AR.
    let l_x_ar = cross(ll, e.a_mass_r);
    let afp_x_l = cross(e.a_free_p, ll);
    let gs_x_lp = cross(e.a_grad_sum, lp);
    let afp_x_l_x_lp = cross(afp_x_l, lp);
    let sum_mae: Vec3 =
        std::array::from_fn(|k| lh * e.a_free_p[k] + e.a_free_mass * lp[k] + l_x_ar[k]);
    let lc_x = cross(lc_over_mt, sum_mae);
    let inv_h2 = 1.0 / (pb.h * pb.h);
    std::array::from_fn(|k| {
        (lh * lh * e.a_grad_cross_v[k]
            + lh * gs_x_lp[k]
            + lh * (ll[k] * tr_agr - agr_t_l[k])
            + lh * (tr_avv * ll[k] - avv_l[k])
            + afp_x_l_x_lp[k]
            + ll[k] * l_dot_arxv
            + lc_x[k])
            * inv_h2
    })
}

/// Solve the scaled, regularised small system for the multipliers (zero for inactive rows), with the
/// constraints' known second-order terms.
///
/// Along the step `q - D^-1 G^T lambda`, P and C are linear; L is quadratic with a second-order term that
/// the moments give exactly (`angular_second_order`), and H's has the kinetic energy's exact part
/// (`kinetic_second_order`) and the elastic energy's curvature, small after either kind of base step
/// (the stiffness metric moves stiff modes little after implicit steps; explicit steps are small: the full
/// step's H residual is the kinetic term to two or three digits after either). So the multipliers solve `S lambda = c + d(lambda)`
/// with `d` those terms (H: kinetic; L: all), and the step lands on the manifold up to the elastic
/// curvature: one iteration where the plain linearisation (fepr-spec section 3) took two after symplectic
/// Euler, and two where it took four or five, with overshoots, after backward Euler.
///
/// How: `lambda = lambda_1 + tau z` with `S lambda_1 = c + d_L`, `S z = e_H`; `tau` is the root of the scalar
/// quadratic `tau = Q(lambda_1 + tau z)` (`Q` the kinetic term) that goes to `Q(lambda_1)` as the curvature
/// vanishes; `d_L` by fixed-point rounds (small: a product of two multipliers over `h^2`). Without a real
/// root (an energy excess beyond what the kinetic curvature gives back), rounds that do not settle, or after
/// the least-squares fallback, `d = 0`: the plain linearisation.
pub(super) fn solve_multipliers(pb: &Problem, e: &Eval, delta: f64) -> Multipliers {
    let sv = velocity_block(pb, e);
    let full = small_matrix(pb, e, sv);
    let (sys, y, least_squares) = ScaledSystem::factor(pb, e, &full, delta);
    let plain = sys.unscale(&y);
    let result = Multipliers {
        lambda: plain,
        least_squares,
        offset: [0.0; ROWS],
    };
    if least_squares || !pb.active[0] || e.c[0].abs() > SECOND_ORDER_REACH * pb.row_scale[0] {
        return result;
    }
    with_second_order(pb, e, &sv, &sys, result)
}

/// The active rows' block of `S`, scaled by the rows' scales, with its regularised Cholesky factor.
struct ScaledSystem {
    /// The active rows, in order (`idx[..n]`).
    idx: [usize; ROWS],
    n: usize,
    /// `1 / row_scale`: scaled by reciprocals (ten divisions, not a hundred: the solve is serial, between
    /// parallel passes).
    inv_scale: [f64; ROWS],
    /// The scaled block (n x n, row-major) and its factor. On the stack: no allocation per iteration.
    a: [f64; ROWS * ROWS],
    factor: [f64; ROWS * ROWS],
}

impl ScaledSystem {
    /// Scale and factorise the active block of `full` (`S`) and solve it for the scaled constraint values of
    /// `e`: the system, the scaled solution and whether the least-squares fallback was needed.
    fn factor(
        pb: &Problem,
        e: &Eval,
        full: &[[f64; ROWS]; ROWS],
        delta: f64,
    ) -> (Self, [f64; ROWS], bool) {
        let mut idx = [0usize; ROWS];
        let mut n = 0;
        for i in (0..ROWS).filter(|&i| pb.active[i]) {
            idx[n] = i;
            n += 1;
        }
        let inv_scale: [f64; ROWS] = std::array::from_fn(|i| 1.0 / pb.row_scale[i]);
        let (mut a, mut b) = ([0.0; ROWS * ROWS], [0.0; ROWS]);
        for (p, &i) in idx[..n].iter().enumerate() {
            b[p] = e.c[i] * inv_scale[i];
            for (q, &j) in idx[..n].iter().enumerate() {
                a[p * n + q] = full[i][j] * inv_scale[i] * inv_scale[j];
            }
        }
        let (mut factor, mut y) = ([0.0; ROWS * ROWS], [0.0; ROWS]);
        let least_squares =
            solve_symmetric_psd_into(&a[..n * n], &b[..n], n, delta, &mut factor, &mut y);
        let sys = Self {
            idx,
            n,
            inv_scale,
            a,
            factor,
        };
        if !least_squares {
            sys.refine(&mut y, &b);
        }
        (sys, y, least_squares)
    }

    /// One step of iterative refinement of the scaled solution `y` of `rhs` against the unshifted matrix, kept
    /// where it lowers the residual: the regularisation's shift (for singular S, fepr-spec section 6, pitfall
    /// 2) otherwise leaves an error of about delta times S's condition number in the multipliers, which a step
    /// meant to end the projection cannot afford (a spinning cube's L rows missed their tolerance without it).
    fn refine(&self, y: &mut [f64; ROWS], rhs: &[f64; ROWS]) {
        let (n, a) = (self.n, &self.a);
        let residual = |y: &[f64; ROWS]| -> ([f64; ROWS], f64) {
            let mut r = [0.0; ROWS];
            for p in 0..n {
                let row = &a[p * n..p * n + n];
                r[p] = rhs[p]
                    - row
                        .iter()
                        .zip(&y[..n])
                        .map(|(apq, yq)| apq * yq)
                        .sum::<f64>();
            }
            let size = r.iter().map(|v| v * v).sum::<f64>();
            (r, size)
        };
        let (mut dy, before) = residual(y);
        cholesky_substitute(&self.factor[..n * n], &mut dy[..n], n);
        let candidate: [f64; ROWS] = std::array::from_fn(|p| y[p] + dy[p]);
        if residual(&candidate).1 < before {
            *y = candidate;
        }
    }

    /// The multipliers (zero for inactive rows) of a scaled solution `y`.
    fn unscale(&self, y: &[f64; ROWS]) -> [f64; ROWS] {
        let mut out = [0.0; ROWS];
        for (p, &i) in self.idx[..self.n].iter().enumerate() {
            out[i] = y[p] * self.inv_scale[i];
        }
        out
    }

    /// `S^-1 rhs` with the factor (unscaled in, unscaled out), refined.
    fn solve(&self, rhs: &[f64; ROWS]) -> [f64; ROWS] {
        let n = self.n;
        let mut y = [0.0; ROWS];
        for (p, &i) in self.idx[..n].iter().enumerate() {
            y[p] = rhs[i] * self.inv_scale[i];
        }
        let rhs = y;
        cholesky_substitute(&self.factor[..n * n], &mut y[..n], n);
        self.refine(&mut y, &rhs);
        self.unscale(&y)
    }
}

/// [`solve_multipliers`]'s second-order part: `result` (the plain linearisation's multipliers) with the
/// kinetic and angular second-order terms (`sv`: the velocity block of `S`; `sys`: its factorised system),
/// where the rounds settle; else `result` as it is.
fn with_second_order(
    pb: &Problem,
    e: &Eval,
    sv: &[[f64; ROWS]; ROWS],
    sys: &ScaledSystem,
    mut result: Multipliers,
) -> Multipliers {
    let plain = result.lambda;
    let inv_scale = &sys.inv_scale;
    let mut unit_h = [0.0; ROWS];
    unit_h[0] = 1.0;
    let z = sys.solve(&unit_h);
    let h = pb.h;
    let l_rows = (4..7).all(|i| pb.active[i]);
    let mut d_l = [0.0; 3];
    for round in 0..SECOND_ORDER_ROUNDS {
        let mut lambda_1 = plain;
        if l_rows && round > 0 {
            let mut rhs = [0.0; ROWS];
            rhs[4..7].copy_from_slice(&d_l);
            let shift = sys.solve(&rhs);
            for i in 0..ROWS {
                lambda_1[i] += shift[i];
            }
        }
        // tau = A + 2 B tau + C tau^2, the root near A: tau = 2 A / (p + sqrt(p^2 - 4 A C)), p = 1 - 2 B.
        let qa = kinetic_second_order(sv, h, &lambda_1, &lambda_1);
        let qb = kinetic_second_order(sv, h, &lambda_1, &z);
        let qc = kinetic_second_order(sv, h, &z, &z);
        let p = 1.0 - 2.0 * qb;
        let disc = p * p - 4.0 * qa * qc;
        if !(p > 0.0 && disc >= 0.0) {
            return result;
        }
        let tau = 2.0 * qa / (p + disc.sqrt());
        let lambda: [f64; ROWS] = std::array::from_fn(|i| lambda_1[i] + tau * z[i]);
        if !(tau.is_finite() && lambda.iter().all(|l| l.is_finite())) {
            return result;
        }
        let next = if l_rows {
            angular_second_order(pb, e, &lambda)
        } else {
            [0.0; 3]
        };
        let change = (0..3).map(|k| (next[k] - d_l[k]).abs()).fold(0.0, f64::max);
        let size = (0..3).map(|k| next[k].abs()).fold(0.0, f64::max);
        if change <= 1e-9 * size
            || change * inv_scale[4].max(inv_scale[5]).max(inv_scale[6]) <= 1e-17
        {
            result.lambda = lambda;
            result.offset[0] = tau;
            if l_rows {
                result.offset[4..7].copy_from_slice(&d_l);
            }
            return result;
        }
        d_l = next;
    }
    result
}

/// Fixed-point rounds of [`solve_multipliers`] for the angular momentum's second-order term (it settles in
/// two or three: the term is a product of two multipliers, small against S).
pub(super) const SECOND_ORDER_ROUNDS: usize = 8;

/// The largest scaled energy residual at which [`solve_multipliers`] adds the second-order terms. Beyond it the
/// base step has blown up (symplectic Euler past its stable step), the elastic energy's curvature, which the
/// terms leave out, dominates, and the plain linearisation proved the more robust (fewer runaways and fewer
/// unconverged steps than with the terms at any residual, and than without them at all).
pub(super) const SECOND_ORDER_REACH: f64 = 1.0;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::sub;
    use crate::model::Model;
    use crate::projection::evaluate::{
        evaluate, evaluate_step, evaluate_with_elastic, EvalScratch,
    };
    use crate::projection::problem::MetricRows;
    use crate::projection::step::Step;
    use crate::projection::test_support::*;
    use crate::projection::{ProjectionSettings, Projector, Targets};
    /// The closed-form `S` must equal `G^T D^-1 G` assembled from explicit constraint gradients, and the
    /// explicit gradients must match finite differences of `c(q)`.
    #[test]
    fn small_matrix_matches_explicit_gradients_and_finite_differences() {
        let mut model = cube_model(1e3, [0.3, -0.2, -9.81]);
        let m = model.num_vertices();
        let (x, v) = skewed_and_moving(&model);
        let targets = Targets {
            energy: 10.0,
            momentum: [0.1, 0.2, -0.3],
            angular_momentum: [0.05, -0.1, 0.2],
            center_of_mass: [0.4, 0.6, 0.5],
            energy_scale: 1.0,
            uncertain_impulses: true,
        };
        // A non-uniform position metric (the stiffness metric's shape) as well as the mass metric.
        let uniform = vec![1.0; m];
        let varied: Vec<f64> = (0..m).map(|i| 1.0 / (1.0 + 0.7 * i as f64)).collect();
        for (pinned, factors) in [
            (false, &uniform),
            (true, &uniform),
            (false, &varied),
            (true, &varied),
        ] {
            model.pinned = vec![false; m];
            if pinned {
                model.pinned[3] = true;
            }
            let h = 0.02;
            let mut pb = Problem::new(
                &model,
                h,
                &targets,
                factors.clone(),
                MetricRows::default(),
                [true; ROWS],
                0.7,
            )
            .with_fresh_rows();
            pb.dp_star = [0.3, -0.1, 0.2];
            pb.dl_star = [-0.2, 0.4, 0.1];
            let at = Point {
                x: &x,
                v: &v,
                s: 0.1,
                t: -0.2,
            };
            let mut grad = vec![[0.0; 3]; m];
            let mut sc = EvalScratch::default();
            let e = evaluate(&pb, &x, &v, at.s, at.t, &mut sc, &mut grad);
            let (q0, g) = explicit_gradients(&pb, &at);
            let s_closed = small_matrix(&pb, &e, velocity_block(&pb, &e));
            for a in 0..ROWS {
                for b in 0..ROWS {
                    let explicit: f64 = (0..q0.len())
                        .map(|k| g[k][a] * d_inverse(&pb, k) * g[k][b])
                        .sum();
                    let tol = 1e-5 * (1.0 + explicit.abs());
                    assert!(
                        (explicit - s_closed[a][b]).abs() <= tol,
                        "pinned {pinned}: S[{a}][{b}] closed {} vs explicit {explicit}",
                        s_closed[a][b]
                    );
                }
            }
            // The update direction D^-1 G lambda must match the trial step's.
            let lambda = [0.3, -0.2, 0.1, 0.05, 0.02, -0.04, 0.03, 0.2, -0.1, 0.07];
            let step = Step::new(&pb, &x, &v, &grad, &lambda, 1.0);
            let (xo, vo, (s1, t1)) = trial_pass_bits(&pb, &step, &at, &lambda, &mut sc);
            for (k, dq0) in q0.iter().enumerate() {
                let dq: f64 =
                    d_inverse(&pb, k) * (0..ROWS).map(|r| g[k][r] * lambda[r]).sum::<f64>();
                let got = if k < 3 * m {
                    dq0 - xo[k / 3][k % 3]
                } else if k < 6 * m {
                    dq0 - vo[(k - 3 * m) / 3][(k - 3 * m) % 3]
                } else if k == 6 * m {
                    at.s - s1
                } else {
                    at.t - t1
                };
                assert!(
                    (dq - got).abs() <= 1e-5 * (1.0 + dq.abs()),
                    "pinned {pinned}: dof {k}: {got} vs {dq}"
                );
            }
            // The velocity block of S from the explicit gradients of the velocity degrees of freedom.
            let sv = velocity_block(&pb, &e);
            for a in 0..7 {
                for b in a..7 {
                    let explicit: f64 = (3 * m..6 * m)
                        .map(|k| g[k][a] * d_inverse(&pb, k) * g[k][b])
                        .sum();
                    assert!(
                        (explicit - sv[a][b]).abs() <= 1e-5 * (1.0 + explicit.abs()),
                        "pinned {pinned}: S_v[{a}][{b}] {} vs explicit {explicit}",
                        sv[a][b]
                    );
                }
            }
            second_order_terms_match(&pb, &at, &grad, &lambda, &e);
        }
    }

    /// A state `(x, v)` and slack values `(s, t)`.
    struct Point<'a> {
        x: &'a [Vec3],
        v: &'a [Vec3],
        s: f64,
        t: f64,
    }

    /// `model`'s rest shape sheared and stretched unevenly, with uneven velocities.
    fn skewed_and_moving(model: &Model) -> (Vec<Vec3>, Vec<Vec3>) {
        let x: Vec<Vec3> = model
            .mesh
            .vertices()
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let k = i as f64;
                [
                    1.1 * p[0] + 0.03 * k.sin(),
                    0.9 * p[1] + 0.02 * k.cos(),
                    p[2] + 0.1 * p[0] + 0.01 * k,
                ]
            })
            .collect();
        let v: Vec<Vec3> = (0..x.len())
            .map(|i| {
                let k = i as f64;
                [0.3 * k.cos(), -0.2 + 0.1 * k.sin(), 0.05 * k]
            })
            .collect();
        (x, v)
    }

    /// `q = (x, v, s, t)` of `at`, flat, and the constraints' explicit gradients there by central finite
    /// differences of `c(q)` (`g[k][row]`).
    fn explicit_gradients(pb: &Problem, at: &Point) -> (Vec<f64>, Vec<[f64; ROWS]>) {
        let m = at.x.len();
        let n = 6 * m + 2;
        let eval_c = |q: &[f64]| {
            let xs: Vec<Vec3> = (0..m)
                .map(|i| [q[3 * i], q[3 * i + 1], q[3 * i + 2]])
                .collect();
            let vs: Vec<Vec3> = (0..m)
                .map(|i| [q[3 * m + 3 * i], q[3 * m + 3 * i + 1], q[3 * m + 3 * i + 2]])
                .collect();
            let mut g = vec![[0.0; 3]; m];
            let mut w = EvalScratch::default();
            evaluate(pb, &xs, &vs, q[6 * m], q[6 * m + 1], &mut w, &mut g).c
        };
        let mut q0 = vec![0.0; n];
        for i in 0..m {
            for a in 0..3 {
                q0[3 * i + a] = at.x[i][a];
                q0[3 * m + 3 * i + a] = at.v[i][a];
            }
        }
        q0[6 * m] = at.s;
        q0[6 * m + 1] = at.t;
        let mut g = vec![[0.0; ROWS]; n];
        for k in 0..n {
            let step = 1e-6;
            let mut qp = q0.clone();
            qp[k] += step;
            let mut qm = q0.clone();
            qm[k] -= step;
            let (cp, cm) = (eval_c(&qp), eval_c(&qm));
            for r in 0..ROWS {
                g[k][r] = (cp[r] - cm[r]) / (2.0 * step);
            }
        }
        (q0, g)
    }

    /// `D^-1` at degree of freedom `k` of `q = (x, v, s, t)`, with pinned degrees of freedom excluded.
    fn d_inverse(pb: &Problem, k: usize) -> f64 {
        let (model, m) = (pb.model, pb.model.num_vertices());
        if k >= 6 * m {
            return 1.0 / pb.eps;
        }
        let (i, vel) = if k < 3 * m {
            (k / 3, false)
        } else {
            ((k - 3 * m) / 3, true)
        };
        if model.pinned[i] {
            0.0
        } else if vel {
            1.0 / (pb.h * pb.h * model.masses[i])
        } else {
            pb.metric_factor[i] / model.masses[i]
        }
    }

    /// The trial evaluation of `step` from `at` is the plain evaluation at the trial point, bit for bit, and so
    /// are its moments for S, summed afterwards or by the trial pass itself. Returns the trial point.
    fn trial_pass_bits(
        pb: &Problem,
        step: &Step,
        at: &Point,
        lambda: &[f64; ROWS],
        sc: &mut EvalScratch,
    ) -> (Vec<Vec3>, Vec<Vec3>, (f64, f64)) {
        let m = at.x.len();
        let (mut xo, mut vo, mut go) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
        let (s1, t1) = step.slack(at.s, at.t);
        let rows = (&mut xo[..], &mut vo[..], None);
        let trial = evaluate_step(pb, step, s1, t1, sc, rows, &mut go, false);
        let mut g1 = vec![[0.0; 3]; m];
        let plain = evaluate(pb, &xo, &vo, s1, t1, &mut EvalScratch::default(), &mut g1);
        let bits = |e: &Eval| (e.c.map(f64::to_bits), e.el.energy.to_bits());
        assert_eq!(bits(&trial), bits(&plain));
        assert_eq!(go, g1);
        assert!(plain.s_moments && !trial.s_moments);
        let later = evaluate_with_elastic(pb, &xo, &vo, s1, t1, trial.el, Some(&go), &mut sc.parts);
        assert_eq!(bits(&later), bits(&plain));
        let s_bits =
            |e: &Eval| small_matrix(pb, e, velocity_block(pb, e)).map(|row| row.map(f64::to_bits));
        assert_eq!(s_bits(&later), s_bits(&plain));
        // Summed by the trial pass itself (where another iteration is expected): the same bits again.
        let (mut xo2, mut vo2, mut go2) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
        let rows = (&mut xo2[..], &mut vo2[..], None);
        let with = evaluate_step(pb, step, s1, t1, sc, rows, &mut go2, true);
        assert!(with.s_moments);
        assert_eq!(bits(&with), bits(&plain));
        assert_eq!(s_bits(&with), s_bits(&plain));
        let second = |e: &Eval| angular_second_order(pb, e, lambda).map(f64::to_bits);
        assert_eq!(second(&with), second(&plain));
        (xo, vo, (s1, t1))
    }

    /// The second-order terms of K and L along the step of `lambda` from `at` (evaluated as `e`, gradient
    /// `grad`): both are exactly quadratic in alpha, so (f(1) + f(-1)) / 2 - f(0) is their alpha^2 coefficient.
    fn second_order_terms_match(
        pb: &Problem,
        at: &Point,
        grad: &[Vec3],
        lambda: &[f64; ROWS],
        e: &Eval,
    ) {
        let m = at.x.len();
        let along = |alpha: f64| {
            let step = Step::new(pb, at.x, at.v, grad, lambda, alpha);
            let (mut xo, mut vo) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
            step.write(0, &mut xo, &mut vo, false);
            let mut g = vec![[0.0; 3]; m];
            evaluate(
                pb,
                &xo,
                &vo,
                at.s,
                at.t,
                &mut EvalScratch::default(),
                &mut g,
            )
        };
        let (ep, em) = (along(1.0), along(-1.0));
        let k2 = 0.5 * (ep.kinetic + em.kinetic) - e.kinetic;
        let sv = velocity_block(pb, e);
        let k2_closed = kinetic_second_order(&sv, pb.h, lambda, lambda);
        let pinned = pb.model.num_pinned() > 0;
        assert!(
            (k2 - k2_closed).abs() <= 1e-9 * k2.abs().max(e.kinetic),
            "pinned {pinned}: kinetic second order {k2_closed} vs {k2}"
        );
        let l2_closed = angular_second_order(pb, e, lambda);
        for a in 0..3 {
            let l2 =
                0.5 * (ep.angular_momentum[a] + em.angular_momentum[a]) - e.angular_momentum[a];
            let size = l2.abs().max(e.angular_momentum[a].abs()).max(1.0);
            assert!(
                (l2 - l2_closed[a]).abs() <= 1e-9 * size,
                "pinned {pinned}: angular second order [{a}] {} vs {l2}",
                l2_closed[a]
            );
        }
    }

    /// The multipliers solve `S lambda = c + d(lambda)`, `d` the second-order terms of H (kinetic) and L along
    /// the step; on a body whose elastic energy barely curves (a very soft one, at its rest shape) the full
    /// step then lands on every row at once: one iteration for a 20% energy deficit and momenta 5% off,
    /// which the plain linearisation meets in six (ten evaluations).
    #[test]
    fn second_order_multipliers_solve_their_equations_and_land_on_the_targets_in_one_step() {
        let model = cube_model(1e-9, [0.0; 3]);
        let m = model.num_vertices();
        // At its rest shape, spinning about an axis off its centre and drifting.
        let x: Vec<Vec3> = model.mesh.vertices().to_vec();
        let v: Vec<Vec3> = x
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let wr = cross([0.3, -0.5, 1.2], sub(*p, [0.4, 0.5, 0.6]));
                [0.2 + wr[0], -0.1 + wr[1], wr[2] + 0.05 * (i as f64).sin()]
            })
            .collect();
        let state = crate::model::State { x, v, time: 0.0 };
        let inv = crate::invariants::measure(&model, &state);
        let c = inv.center_of_mass;
        let targets = Targets {
            energy: 1.2 * inv.total,
            momentum: inv.momentum.map(|p| 1.05 * p + 0.01),
            // About the target centre of mass (the centre itself), 5% off and turned.
            angular_momentum: [
                1.05 * inv.angular_momentum[0],
                0.95 * inv.angular_momentum[1] + 0.02,
                inv.angular_momentum[2],
            ],
            center_of_mass: c,
            energy_scale: inv.total,
            uncertain_impulses: false,
        };
        let h = 0.01;
        let mut proj = Projector::new(ProjectionSettings::default()).unwrap();
        let mut out = state.clone();
        let (report, got) = proj.project(&model, &mut out, h, &targets);
        assert!(report.converged, "{report:?}");
        assert_eq!(report.iterations, 1, "{report:?}");
        assert!((got.total / targets.energy - 1.0).abs() <= 1e-10, "{got:?}");
        for a in 0..3 {
            assert!(
                (got.momentum[a] - targets.momentum[a]).abs() <= 1e-10 * norm3(targets.momentum)
            );
            assert!(
                (got.angular_momentum[a] - targets.angular_momentum[a]).abs()
                    <= 1e-10 * norm3(targets.angular_momentum)
            );
        }
        // The equations themselves, at the start: S lambda = c + d with d_H and d_L the terms at lambda.
        let (factors, rows) = (vec![1.0; m], MetricRows::default());
        let mut pb =
            Problem::new(&model, h, &targets, factors, rows, [true; ROWS], 1.0).with_fresh_rows();
        pb.row_scale[0] = targets.energy;
        for a in 0..3 {
            pb.row_scale[1 + a] = model.total_mass * model.length_scale / h;
            pb.row_scale[4 + a] = model.total_mass * model.length_scale.powi(2) / h;
            pb.row_scale[7 + a] = model.length_scale;
        }
        let mut grad = vec![[0.0; 3]; m];
        let e = evaluate(
            &pb,
            &state.x,
            &state.v,
            0.0,
            0.0,
            &mut EvalScratch::default(),
            &mut grad,
        );
        let mult = solve_multipliers(&pb, &e, 0.0);
        assert!(!mult.least_squares);
        let (lambda, d) = (mult.lambda, mult.offset);
        let sv = velocity_block(&pb, &e);
        let dh = kinetic_second_order(&sv, h, &lambda, &lambda);
        assert!(
            dh > 0.0 && (d[0] - dh).abs() <= 1e-9 * dh,
            "{} vs {dh}",
            d[0]
        );
        let dl = angular_second_order(&pb, &e, &lambda);
        for a in 0..3 {
            assert!(
                (d[4 + a] - dl[a]).abs() <= 1e-8 * norm3(dl),
                "{d:?} vs {dl:?}"
            );
        }
        let full = small_matrix(&pb, &e, velocity_block(&pb, &e));
        for i in 0..ROWS {
            let s_lambda: f64 = (0..ROWS).map(|j| full[i][j] * lambda[j]).sum();
            let want = e.c[i] + d[i];
            assert!(
                (s_lambda - want).abs() <= 1e-9 * pb.row_scale[i],
                "row {i}: {s_lambda} vs {want}"
            );
        }
    }
}
