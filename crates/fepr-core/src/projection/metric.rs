//! The position block of the projection's metric `D = diag(W, h^2 M, eps, eps)`: the choice of `W`, its
//! per-vertex factors `a_i = m_i / w_i` (kept across projections while they would come out the same), and the
//! energy row's direction in a metric the base integrator has factorised.

use super::evaluate::vertex_chunk;
use super::problem::Problem;
use super::Projector;
use crate::exec::reduce_chunks;
use crate::math::{dot, Vec3};
use crate::model::{Model, ModelKey};

/// The position block of the projection's metric `D = diag(W, h^2 M, eps, eps)`.
///
/// fepr-spec section 3 uses `W = M`. With a stiff material at a large step that is a poor choice: the cheapest
/// way to add energy in the M-metric is to move the light vertices of the stiffest elements (slivers) along
/// their large forces, which pumps the energy deficit of a dissipative step into a few local modes and inverts
/// them. `Stiffness` uses `W = M + h^2 diag(K_0)`, with `K_0` the rest-state stiffness (the diagonal of the
/// element Hessians at rest, a scalar per vertex): the metric of the implicit step itself, up to the
/// diagonal approximation. Stiff local modes become expensive to move, so energy is restored through the
/// velocities and the smooth modes. For `W = M` both give the same result; in general the projection is then
/// the closest point in the implicit step's own metric instead of the mass metric.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Metric {
    /// `Stiffness` after an implicit base step (backward Euler, Projective Dynamics, XPBD), `Mass` after an
    /// explicit one. Resolved by the simulation from the integrator (see [`Projector::set_implicit_base`]).
    Auto,
    /// `W = M` (fepr-spec section 3).
    Mass,
    /// `W = M + h^2 diag(K_0)`.
    Stiffness,
}

impl Metric {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "auto" => Some(Self::Auto),
            "mass" => Some(Self::Mass),
            "stiffness" => Some(Self::Stiffness),
            _ => None,
        }
    }
}

/// A position metric `W` that the base integrator has factorised (Projective Dynamics: `W = M + h^2 L`, its
/// global matrix times `h^2`, handed over by the simulation). Under [`Metric::Auto`]
/// the projection uses it for the position block where the energy is its only row (the default with pins)
/// and no position is frozen: the diagonal stiffness metric moves each vertex on its own, and where the energy
/// has to come out of the positions of a stiff body (the base step left more than the kinetic energy it could
/// come from) that takes many small steps; with `W` one step moves the smooth modes as the base integrator would.
pub trait SystemMetric {
    /// `out = W^-1 rhs` (shape (m, 3)) on the free vertices, 0 on the pinned ones, for `model` and step
    /// size `h`. False (and `out` untouched) where the factorisation is not for them.
    fn solve(&mut self, model: &Model, h: f64, rhs: &[Vec3], out: &mut [Vec3]) -> bool;
    /// `dx^T W dx` (kg m^2) of a position change `dx` (shape (m, 3)) that is zero on the pinned vertices.
    fn norm_sq(&self, model: &Model, h: f64, dx: &[Vec3]) -> f64;
}

/// What a projector's metric factors and rows were computed from: the next projection keeps them when it
/// would compute the same ones (the metric of the same kind and step size, the same masses and pins, no
/// frozen positions). They are the same every step of a typical simulation, and computing them is a serial
/// pass over four arrays.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct MetricSource {
    /// `None` for `W = M`; the step size's bits and the model's key for the stiffness metric.
    pub(super) stiffness: Option<(u64, ModelKey)>,
    /// The masses and the pins the rows were derived from (the model's public fields, which a user may
    /// change between steps; [`Model::key`] would hash them serially, about as long as deriving the rows).
    pub(super) masses: Vec<f64>,
    pub(super) pinned: Vec<bool>,
}

impl MetricSource {
    /// Whether these are the metric of `model` with `stiffness` (compared bit for bit).
    pub(super) fn matches(&self, model: &Model, stiffness: Option<(u64, ModelKey)>) -> bool {
        self.stiffness == stiffness
            && self.pinned == model.pinned
            && self.masses.len() == model.masses.len()
            // Bits, not values (-0.0 == 0.0); or-ing the differences, which vectorises.
            && self.masses.iter().zip(&model.masses).fold(0, |d, (a, b)| d | (a.to_bits() ^ b.to_bits())) == 0
    }
}

impl Projector {
    /// Fill `metric_factor` with `a_i = m_i / w_i` for step size `h` (0 for frozen positions). Returns false when
    /// the last projection's factors (and rows) are these already, and were kept.
    pub(super) fn prepare_metric(&mut self, model: &Model, h: f64) -> bool {
        let m = model.num_vertices();
        let stiffness = self.uses_stiffness_metric().then(|| {
            // From the mesh, the material and the masses, which a user of the Rust API may change between steps.
            let key = model.key();
            if self.stiffness_key != Some(key) {
                self.stiffness_ratio = rest_stiffness_ratio(model);
                self.stiffness_key = Some(key);
            }
            (h.to_bits(), key)
        });
        let keep = self.frozen_positions.is_empty()
            && self.metric_factor.len() == m
            && (self.metric_source.as_ref()).is_some_and(|src| src.matches(model, stiffness));
        if keep {
            return false;
        }
        self.metric_factor.clear();
        if stiffness.is_some() {
            let h2 = h * h;
            self.metric_factor
                .extend(self.stiffness_ratio.iter().map(|k| 1.0 / (1.0 + h2 * k)));
        } else {
            self.metric_factor.resize(m, 1.0);
        }
        for &i in &self.frozen_positions {
            self.metric_factor[i as usize] = 0.0;
        }
        // Frozen positions change with the contacts, every step: no source is kept with them.
        self.metric_source = self.frozen_positions.is_empty().then(|| MetricSource {
            stiffness,
            masses: model.masses.clone(),
            pinned: model.pinned.clone(),
        });
        true
    }
}

/// `diag(K_0)_i / m_i` per vertex (1/s^2): the trace / 3 of the diagonal 3x3 blocks of the element Hessians at
/// the rest shape (projected to PSD), summed over the incident elements, over the vertex mass. Rest-state so
/// that the metric is fixed for the run (no dependence on the current, possibly inverted, state).
pub(super) fn rest_stiffness_ratio(model: &Model) -> Vec<f64> {
    let m = model.num_vertices();
    let rest = model.mesh.vertices();
    let mut k = vec![0.0; m];
    for (e, t) in model.mesh.tets().iter().enumerate() {
        let he = crate::elasticity::element_hessian(model, rest, e, true);
        for (c, &vtx) in t.iter().enumerate() {
            let mut tr = 0.0;
            for a in 0..3 {
                let d = 3 * c + a;
                tr += he[d * 12 + d];
            }
            k[vtx] += tr / 3.0;
        }
    }
    k.iter()
        .zip(&model.masses)
        .map(|(k, m)| if *m > 0.0 { (k / m).max(0.0) } else { 0.0 })
        .collect()
}

/// The energy row's position direction in the metric of `sys`: `rhs` gets the potential's gradient
/// `grad E_el - m g` (`grad`: the elastic gradient at the iterate; 0 on pinned vertices), `dir` gets `W^-1` of
/// it. Returns `rhs . dir` (S_HH's position part), summed over fixed vertex tasks in task order (the same bits
/// for any thread count), or `None` where `sys` has no factorisation for this model and step size.
pub(super) fn system_direction(
    pb: &Problem,
    sys: &mut dyn SystemMetric,
    grad: &[Vec3],
    rhs: &mut [Vec3],
    dir: &mut [Vec3],
    parts: &mut Vec<f64>,
) -> Option<f64> {
    let model = pb.model;
    let g = model.gravity;
    for (i, r) in rhs.iter_mut().enumerate() {
        let m = model.masses[i];
        *r = if model.pinned[i] {
            [0.0; 3]
        } else {
            [0, 1, 2].map(|a| grad[i][a] - m * g[a])
        };
    }
    if !sys.solve(model, pb.h, rhs, dir) {
        return None;
    }
    let chunk = vertex_chunk(rhs.len());
    let (rhs, dir) = (&*rhs, &*dir);
    let map = |r: std::ops::Range<usize>| r.map(|i| dot(rhs[i], dir[i])).sum::<f64>();
    reduce_chunks(rhs.len(), chunk, parts, map, |a, b| a + b)
}
