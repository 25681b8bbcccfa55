//! One projection's problem: the model, step size and targets, the active rows and their scales, the slack
//! directions and the metric's per-vertex rows; and the scaled residuals the iteration measures progress by.

use super::{Targets, ROWS};
use crate::math::Vec3;
use crate::model::Model;

pub(super) struct Problem<'a> {
    pub(super) model: &'a Model,
    pub(super) h: f64,
    pub(super) targets: &'a Targets,
    /// `P* - P_target` and `L* - L_target`.
    pub(super) dp_star: Vec3,
    pub(super) dl_star: Vec3,
    pub(super) active: [bool; ROWS],
    pub(super) row_scale: [f64; ROWS],
    pub(super) eps: f64,
    /// `a_i = m_i / w_i`: the position block of D is `diag(m_i / a_i)`; 0 freezes a vertex's position.
    pub(super) metric_factor: Vec<f64>,
    /// Per-vertex arrays of the metric and the pins, kept with `metric_factor` ([`Problem::refresh_rows`]).
    pub(super) rows: MetricRows,
}

/// Per-vertex arrays derived from the metric factors, the masses and the pins, each of length m: read by
/// the vertex passes as contiguous rows (the moment kernels load four at a time).
#[derive(Clone, Debug, Default)]
pub(super) struct MetricRows {
    /// `a_i / m_i` (the position block of D^-1).
    pub(super) a_over_m: Vec<f64>,
    /// `m_i` of a free vertex, 0 of a pinned one (kg).
    pub(super) free_mass: Vec<f64>,
    /// `a_i` of a free vertex, 0 of a pinned one.
    pub(super) free_factor: Vec<f64>,
    /// No vertex is pinned and every `a_i` is 1 (the mass metric without frozen positions): the moment
    /// kernels skip the sums that then repeat others ([`ml::Rows::unit`]).
    pub(super) unit: bool,
}

impl<'a> Problem<'a> {
    /// The problem of one projection with the metric factors `metric_factor` and their per-vertex rows `rows`
    /// (a reused buffer: derived from the factors already, kept from the last projection, or to be derived by
    /// [`Problem::with_fresh_rows`]), slack directions and row scales not yet set (zero and one).
    pub(super) fn new(
        model: &'a Model,
        h: f64,
        targets: &'a Targets,
        metric_factor: Vec<f64>,
        rows: MetricRows,
        active: [bool; ROWS],
        eps: f64,
    ) -> Self {
        Problem {
            model,
            h,
            targets,
            dp_star: [0.0; 3],
            dl_star: [0.0; 3],
            active,
            row_scale: [1.0; ROWS],
            eps,
            metric_factor,
            rows,
        }
    }

    /// The problem with its rows derived from its metric factors ([`Problem::refresh_rows`]).
    #[cfg(test)]
    pub(super) fn with_fresh_rows(mut self) -> Self {
        self.refresh_rows();
        self
    }

    /// `rows` from `metric_factor`, the masses and the pins.
    pub(super) fn refresh_rows(&mut self) {
        let (model, rows, factor) = (self.model, &mut self.rows, &self.metric_factor[..]);
        let n = factor.len();
        // Sized first, then filled by plain loops over slices of one length (no `push`): they compile to
        // packed divisions and selects. This runs on one thread once per projection; the pushing loop took
        // 1.3% of a projection on the elephant (perf, one thread), and the projection 1-2% less time on two
        // threads without it (elephant, bunny, alternated runs).
        for row in [
            &mut rows.a_over_m,
            &mut rows.free_mass,
            &mut rows.free_factor,
        ] {
            row.resize(n, 0.0);
        }
        let (masses, pinned) = (&model.masses[..n], &model.pinned[..n]);
        for ((out, &a), &m) in rows.a_over_m.iter_mut().zip(factor).zip(masses) {
            *out = a / m;
        }
        for ((out, &m), &p) in rows.free_mass.iter_mut().zip(masses).zip(pinned) {
            *out = if p { 0.0 } else { m };
        }
        for ((out, &a), &p) in rows.free_factor.iter_mut().zip(factor).zip(pinned) {
            *out = if p { 0.0 } else { a };
        }
        rows.unit = !pinned.contains(&true) && factor.iter().all(|&a| a == 1.0);
    }
}

pub(super) fn max_scaled(pb: &Problem, c: &[f64; ROWS]) -> f64 {
    (0..ROWS)
        .filter(|&i| pb.active[i])
        .map(|i| (c[i] / pb.row_scale[i]).abs())
        .fold(0.0, f64::max)
}

pub(super) fn norm_scaled(pb: &Problem, c: &[f64; ROWS]) -> f64 {
    (0..ROWS)
        .filter(|&i| pb.active[i])
        .map(|i| (c[i] / pb.row_scale[i]).powi(2))
        .sum::<f64>()
        .sqrt()
}
