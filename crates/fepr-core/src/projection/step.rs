//! The trial point `q - alpha D^-1 G lambda` of one iteration, vertex by vertex, and its slack values.

use super::problem::Problem;
use super::ROWS;
use crate::math::{dot, Vec3};
use crate::model::Model;
use crate::projection as tl;
use crate::projection as ml;

/// The trial point `q_trial = q - alpha D^-1 G lambda` of one iteration, vertex by vertex (every vertex's
/// update is its own: no sums), so that it can be computed wherever it is needed ([`evaluate_step`]).
pub(super) struct Step<'a> {
    pub(super) model: &'a Model,
    pub(super) metric_factor: &'a [f64],
    pub(super) a_over_m: &'a [f64],
    /// The metric rows are unit ([`MetricRows::unit`](super::problem::MetricRows::unit)).
    pub(super) unit: bool,
    pub(super) x: &'a [Vec3],
    pub(super) v: &'a [Vec3],
    /// The elastic gradient at `x`.
    pub(super) grad: &'a [Vec3],
    /// The multipliers, the step length and the constants of the rows' update.
    pub(super) coefficients: tl::StepCoefficients,
    pub(super) h2: f64,
    pub(super) dp_star: Vec3,
    pub(super) dl_star: Vec3,
    pub(super) eps: f64,
    /// The base state `(x_base, v_base)` whose D-norm distance the trial evaluation sums (`Eval::correction_sq`).
    pub(super) base: Option<(&'a [Vec3], &'a [Vec3])>,
    /// With a [`SystemMetric`] (the energy the only row): `W^-1 grad U`, the positions' direction.
    pub(super) dir: Option<&'a [Vec3]>,
}

impl<'a> Step<'a> {
    pub(super) fn new(
        pb: &'a Problem,
        x: &'a [Vec3],
        v: &'a [Vec3],
        grad: &'a [Vec3],
        lambda: &[f64; ROWS],
        alpha: f64,
    ) -> Self {
        Step {
            model: pb.model,
            metric_factor: &pb.metric_factor,
            a_over_m: &pb.rows.a_over_m,
            unit: pb.rows.unit,
            x,
            v,
            grad,
            coefficients: tl::StepCoefficients {
                lh: lambda[0],
                alpha,
                inv_h2: 1.0 / (pb.h * pb.h),
                lp: [lambda[1], lambda[2], lambda[3]],
                ll: [lambda[4], lambda[5], lambda[6]],
                lc_over_mt: [7, 8, 9].map(|k| lambda[k] / pb.model.total_mass),
                gravity: pb.model.gravity,
                center: pb.targets.center_of_mass,
            },
            h2: pb.h * pb.h,
            dp_star: pb.dp_star,
            dl_star: pb.dl_star,
            eps: pb.eps,
            base: None,
            dir: None,
        }
    }

    /// The trial evaluation also sums the trial point's D-norm distance from `(x_base, v_base)`.
    pub(super) fn measured_from(self, x_base: &'a [Vec3], v_base: &'a [Vec3]) -> Self {
        Self {
            base: Some((x_base, v_base)),
            ..self
        }
    }

    /// The trial positions (m) and velocities (m/s) of the vertices `first..first + x_out.len()`, into
    /// `x_out` and `v_out` (a pinned vertex keeps its own), and their sums (`trial_lanes`): the constraints'
    /// if `constraints`, the D-norm distance from the base state if the step is measured from one.
    pub(super) fn write(
        &self,
        first: usize,
        x_out: &mut [Vec3],
        v_out: &mut [Vec3],
        constraints: bool,
    ) -> tl::TrialSums {
        let r = first..first + x_out.len();
        let model = self.model;
        let base = self.base.map(|(xb, vb)| tl::BaseRows {
            x: &xb[r.clone()],
            v: &vb[r.clone()],
            h2: self.h2,
        });
        let (mass, factor) = (&model.masses[r.clone()], &self.metric_factor[r.clone()]);
        let Some(dir) = self.dir else {
            let rows = tl::IterateRows {
                x: &self.x[r.clone()],
                v: &self.v[r.clone()],
                grad: &self.grad[r.clone()],
                mass,
                factor,
                a_over_m: &self.a_over_m[r.clone()],
                pinned: &model.pinned[r],
                unit: self.unit,
            };
            return tl::write_trial(&self.coefficients, &rows, base, constraints, x_out, v_out);
        };
        self.write_rows_along(dir, first, x_out, v_out);
        let (x, v) = (&*x_out, &*v_out);
        let (g, ct) = (self.coefficients.gravity, self.coefficients.center);
        tl::TrialSums {
            constraints: constraints.then(|| ml::constraint_lanes(x, v, mass, g, ct)),
            correction: base.map(|b| tl::correction_lanes(x, v, b, mass, factor)),
        }
    }

    /// [`Step::write`]'s rows with the positions moved along `dir = W^-1 grad U` of a [`SystemMetric`] (the energy
    /// the only active row: the other multipliers are zero).
    pub(super) fn write_rows_along(
        &self,
        dir: &[Vec3],
        first: usize,
        x_out: &mut [Vec3],
        v_out: &mut [Vec3],
    ) {
        let c = &self.coefficients;
        let (lh, alpha, inv_h2) = (c.lh, c.alpha, c.inv_h2);
        for (k, (xo, vo)) in x_out.iter_mut().zip(v_out.iter_mut()).enumerate() {
            let i = first + k;
            let (x, v) = (self.x[i], self.v[i]);
            if self.model.pinned[i] {
                (*xo, *vo) = (x, v);
                continue;
            }
            for a in 0..3 {
                xo[a] = x[a] - alpha * lh * dir[i][a];
                vo[a] = v[a] - alpha * lh * v[a] * inv_h2;
            }
        }
    }

    /// The trial point's slack values from `(s, t)`: d c_P / d s = -(P* - P_t), d c_L / d t = -(L* - L_t),
    /// and D^-1 = 1/eps on s and t.
    pub(super) fn slack(&self, s: f64, t: f64) -> (f64, f64) {
        let c = &self.coefficients;
        (
            s + c.alpha * dot(c.lp, self.dp_star) / self.eps,
            t + c.alpha * dot(c.ll, self.dl_star) / self.eps,
        )
    }
}
