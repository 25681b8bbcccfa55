//! The hand-over between a base step and the projection around it: what one of them evaluated that the
//! other would otherwise evaluate again. The [`Simulation`](crate::simulation::Simulation) owns one
//! [`HandOver`] and passes it to every [`Integrator::step`](super::Integrator::step); this is the one place
//! that says what it carries.
//!
//! **The elastic gradient at known positions** (J/m, shape (m, 3)), with those positions (m) and the
//! [`Model::elastic_key`] of the model it was evaluated for, and the elastic energy summary where its author had
//! it. It is valid for positions that are bit-identical to the stored ones and a model with the same elastic key
//! (mesh and material): then evaluating again would give the same bits, so using it changes no result. Every
//! read checks both and takes the entry (it is read at most once); a stale entry is never wrong, only unused.
//! - The **projection** fills it at the end of a step with its final gradient, at the positions it returned
//!   (the simulation puts it here, [`HandOver::put_final_gradient`], and only for an integrator that reads it).
//!   Where the projection wrote a copy of those positions as it computed them, that copy is taken by a swap.
//! - The **integrator** reads it at the start of its next step ([`HandOver::take_start_gradient`]: symplectic
//!   Euler's force evaluation), unless pins, forces or the user moved the positions in between.
//! - An **integrator** whose step ends on positions where it evaluated the gradient fills it
//!   ([`HandOver::put_result_gradient`]: backward Euler's last Newton iterate, with the energy summary).
//! - The **projection** that follows reads that ([`HandOver::take_result_gradient`], called by the
//!   simulation) and skips its first elastic evaluation, unless contact, pins or forces moved the positions.
//!
//! **The system metric**: a position metric the integrator has factorised for its own solves (Projective
//! Dynamics: its global matrix), shared with the hand-over ([`HandOver::share_metric`]) so that the
//! projection can use it ([`HandOver::metric`], see [`SystemMetric`]). It answers for the model and step size
//! it was factorised for only (its `solve` says false otherwise).
//!
//! Buffers move by swaps: the hand-over, the integrator and the projection exchange their gradient and position
//! buffers, and no step allocates or copies for them once every buffer has its length.

use std::sync::{Arc, Mutex, MutexGuard};

use crate::elasticity::ElasticSummary;
use crate::exec::copy_rows;
use crate::math::{same_bits, Vec3};
use crate::model::{Model, ModelKey};
use crate::projection::SystemMetric;

/// A position metric an integrator shares with the hand-over.
pub type SharedMetric = Arc<Mutex<dyn SystemMetric + Send>>;

/// What a base step and the projection hand each other (see the module documentation).
#[derive(Default)]
pub struct HandOver {
    /// The elastic gradient at `x`, J/m (m, 3).
    grad: Vec<Vec3>,
    /// The positions `grad` was evaluated at, m (m, 3).
    x: Vec<Vec3>,
    /// [`Model::elastic_key`] of the model `grad` belongs to; `None`: no entry.
    key: Option<ModelKey>,
    /// The elastic energy summary at `x`, where the entry's author computed it.
    summary: Option<ElasticSummary>,
    /// The integrator asked for the gradient at its start positions: the projection's final one is kept.
    reads_start_gradient: bool,
    /// Entries whose positions came as the projection's own copy (taken by a swap instead of copied).
    positions_swapped: usize,
    metric: Option<SharedMetric>,
}

impl std::fmt::Debug for HandOver {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HandOver")
            .field("key", &self.key)
            .field("summary", &self.summary)
            .field("reads_start_gradient", &self.reads_start_gradient)
            .field("metric", &self.metric.is_some())
            .finish()
    }
}

impl HandOver {
    pub fn new() -> Self {
        Self::default()
    }

    /// Take the entry if it holds the gradient of `model` at exactly `x`.
    fn take_at(&mut self, model: &Model, x: &[Vec3]) -> bool {
        let key = self.key.take();
        key == Some(model.elastic_key())
            && self.x.len() == x.len()
            && self.grad.len() == x.len()
            && same_bits(&self.x, x)
    }

    /// Store an entry for `model`: the caller has put its gradient in `grad` and its positions in `x`.
    fn stored(&mut self, model: &Model, summary: Option<ElasticSummary>) {
        self.key = Some(model.elastic_key());
        self.summary = summary;
    }

    // --- the integrator's side ----------------------------------------------------------------------------

    /// For an integrator at the start of its step at positions `x`: if the entry is the gradient of `model` at
    /// exactly `x`, it is swapped into `grad` and true is returned (`grad` must then not be evaluated again);
    /// otherwise `grad` is untouched. Asking also tells the simulation to keep the projection's final gradient
    /// for the next step.
    pub fn take_start_gradient(&mut self, model: &Model, x: &[Vec3], grad: &mut Vec<Vec3>) -> bool {
        self.reads_start_gradient = true;
        if !self.take_at(model, x) {
            return false;
        }
        std::mem::swap(grad, &mut self.grad);
        true
    }

    /// For an integrator at the end of its step: the gradient `grad` of `model` and its energy summary
    /// `summary` were evaluated at `x`, the positions the step ended on. Both buffers are taken by swaps (the
    /// caller gets the hand-over's old ones, of any length and content).
    pub fn put_result_gradient(
        &mut self,
        model: &Model,
        summary: ElasticSummary,
        x: &mut Vec<Vec3>,
        grad: &mut Vec<Vec3>,
    ) {
        std::mem::swap(&mut self.x, x);
        std::mem::swap(&mut self.grad, grad);
        self.stored(model, Some(summary));
    }

    /// Share the position metric an integrator has factorised (see [`SystemMetric`]) with the projection.
    pub fn share_metric(&mut self, metric: &SharedMetric) {
        if !self.metric.as_ref().is_some_and(|m| Arc::ptr_eq(m, metric)) {
            self.metric = Some(Arc::clone(metric));
        }
    }

    // --- the simulation's side (for the projection) -------------------------------------------------------

    /// The integrator's result at exactly `x` for `model`, with its energy summary: the gradient buffer, for
    /// the projection to take by a swap. The entry is taken either way.
    pub fn take_result_gradient(
        &mut self,
        model: &Model,
        x: &[Vec3],
    ) -> Option<(ElasticSummary, &mut Vec<Vec3>)> {
        let summary = self.summary.take();
        match summary {
            Some(s) if self.take_at(model, x) => Some((s, &mut self.grad)),
            _ => {
                self.key = None;
                None
            }
        }
    }

    /// True when the integrator reads the gradient at its start positions (it asked in a step so far).
    pub fn reads_start_gradient(&self) -> bool {
        self.reads_start_gradient
    }

    /// The projection's final gradient `grad` of `model` at the positions `x` it returned, for the next step
    /// (taken by a swap). `x_copy`, where the projection has one, holds `x` bit for bit and is taken by a swap
    /// instead of copying `x`. Ignored when `grad` is not one row per position.
    pub fn put_final_gradient(
        &mut self,
        model: &Model,
        x: &[Vec3],
        x_copy: Option<&mut Vec<Vec3>>,
        grad: &mut Vec<Vec3>,
    ) {
        self.key = None;
        if grad.len() != x.len() {
            return;
        }
        std::mem::swap(&mut self.grad, grad);
        match x_copy {
            Some(copy) if copy.len() == x.len() => {
                debug_assert!(same_bits(x, copy), "the offered copy holds x bit for bit");
                std::mem::swap(&mut self.x, copy);
                self.positions_swapped += 1;
            }
            _ => copy_rows(x, &mut self.x),
        }
        self.stored(model, None);
    }

    /// The entry the next step's integrator would take at the positions `x` (the projection's final gradient),
    /// for a checkpoint: a gradient the projection handed over can differ in its last bits from one evaluated
    /// afresh at the same positions (it was evaluated before the projection's last rigid shift), so a resumed
    /// run must start from the same entry to take the same steps.
    pub fn start_gradient_at(&self, model: &Model, x: &[Vec3]) -> Option<&[Vec3]> {
        (self.key == Some(model.elastic_key())
            && self.summary.is_none()
            && self.x.len() == x.len()
            && self.grad.len() == x.len()
            && same_bits(&self.x, x))
        .then_some(&self.grad[..])
    }

    /// Put back an entry [`HandOver::start_gradient_at`] gave: `grad` of `model` at the positions `x`.
    pub fn restore_start_gradient(&mut self, model: &Model, x: &[Vec3], grad: Vec<Vec3>) {
        copy_rows(x, &mut self.x);
        self.grad = grad;
        self.reads_start_gradient = true;
        self.stored(model, None);
    }

    /// The position metric the integrator shares, locked for the projection (see [`SystemMetric`]).
    pub fn metric(&self) -> Option<MutexGuard<'_, dyn SystemMetric + Send + 'static>> {
        let m = self.metric.as_ref()?;
        Some(m.lock().unwrap_or_else(|e| e.into_inner()))
    }

    /// Entries so far whose positions came as the projection's own copy, taken by a swap instead of copied.
    pub fn positions_swapped(&self) -> usize {
        self.positions_swapped
    }
}
