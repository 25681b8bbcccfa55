//! One projection's problem: the model, step size and targets, the active rows and their scales, the slack
//! directions and the metric's per-vertex rows; and the scaled residuals the iteration measures progress by.

use super::{rounding_terms, Targets, ROUNDING_ULPS, ROWS};
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

    /// The rows' scales (fepr-spec section 3), from the targets and the start-of-step state, not from the base
    /// step's result: a wild base step must not loosen the energy tolerance. `tolerance`: the settings'.
    pub(super) fn set_row_scales(&mut self, tolerance: f64) {
        let (model, targets) = (self.model, self.targets);
        let (m, r, mt) = (model.num_vertices(), model.length_scale, model.total_mass);
        self.row_scale[0] = targets.energy_scale.max(1e-300);
        // Far from the origin (a body that has fallen for minutes) the positions themselves carry less than
        // tolerance * r: the centre of mass's scale is at least the rounding of its sum.
        let com_floor = ROUNDING_ULPS
            * rounding_terms(m)
            * f64::EPSILON
            * crate::math::norm(targets.center_of_mass)
            / tolerance;
        // The momenta's scales are those of the motion, `sqrt(2 m_tot S)` with `S` the energy row's scale (and
        // `r` times that for L), not `m_tot r / h` (the momentum that moves the body by its size in one step):
        // at a small step or a slow motion the latter is hundreds of times the momenta the body has, and a
        // tolerance on it let P and L drift.
        let momentum_scale = (2.0 * mt * self.row_scale[0]).sqrt();
        for a in 0..3 {
            self.row_scale[1 + a] = momentum_scale;
            self.row_scale[4 + a] = momentum_scale * r;
            self.row_scale[7 + a] = r.max(com_floor);
        }
    }

    /// `rows` from `metric_factor`, the masses and the pins.
    pub(super) fn refresh_rows(&mut self) {
        let (model, rows, factor) = (self.model, &mut self.rows, &self.metric_factor[..]);
        let n = factor.len();
        // Sized first, then filled by plain loops over slices of one length (no `push`): they compile to
        // packed divisions and selects (this runs on one thread once per projection).
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
