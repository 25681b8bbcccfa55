//! FEPR: the fast energy projection of fepr-spec sections 2 and 3.
//!
//! Given the base step's result `q~ = (x*, v*, s = 0, t = 0)`, find the closest `q` in the metric
//! `D = diag(M, h^2 M, eps, eps)` with `c(q) = 0`, where the rows are (each optional, see [`ActiveRows`]):
//!
//! ```text
//! c_H = H(x, v) - H_target
//! c_P = P(v) - [P_target + s (P* - P_target)]          (3 rows)
//! c_L = L_Ct(x, v) - [L_target + t (L* - L_target)]    (3 rows, about C_target)
//! c_C = C(x) - C_target                                (3 rows)
//! ```
//!
//! Each iteration evaluates `c` and its gradient (one elastic energy + gradient evaluation), tests
//! convergence *before* solving (at rest the system is singular but `c = 0`), forms the small matrix
//! `S = G^T D^-1 G` from closed-form mass moments (never a dense `(6m+2)^2` matrix), solves the scaled,
//! regularised system, and steps `q <- q - D^-1 G lambda`, halving the step if it would increase the scaled
//! residual. Non-convergence keeps the best iterate (or `q~`) and is reported; the result is never NaN and
//! never has more inverted tets than the base step.
//!
//! The module's files, one job each:
//! - `settings`: [`ProjectionSettings`], the rows ([`ActiveRows`]), the slack ([`Slack`]), validation;
//! - `targets`: [`Targets`] and the rounding floor of the rows' scales;
//! - `report`: [`ProjectionReport`];
//! - `metric`: the position metric ([`Metric`], [`SystemMetric`]) and its per-vertex factors;
//! - `problem`: one projection's problem (targets, rows, scales, metric rows) and its scaled residuals;
//! - `evaluate`: `c(q)`, the elastic gradient and the mass moments, in deterministic vertex tasks;
//! - `system`: the small system `S lambda = c` with its second-order terms;
//! - `step`: the trial point `q - alpha D^-1 G lambda`;
//! - `warm_start`: the velocity warm start;
//! - `iteration`: the iteration, step acceptance and restarts; `result`: the choice of the result, its
//!   correction and the impact bound;
//! - `guard`: [`Projector::project_with`], the metric switch and the search over the restored fraction;
//! - `restoration` (with `certificate`): the quality guard's rule and its per-tet check;
//! - `moments`, `trial_steps`: the vertex kernels (lanes) that `evaluate` and `step` sum with.

/// The current iterate's `(x, v)` of a [`Projector`] inside `project`: q~ itself (`x_base`, `v_base`) until
/// a trial point is accepted, then `x`, `v`. A macro, not a method, so that it borrows those fields alone.
macro_rules! current {
    ($p:expr) => {
        if $p.at_base {
            (&$p.x_base[..], &$p.v_base[..])
        } else {
            (&$p.x[..], &$p.v[..])
        }
    };
}

mod certificate;
mod evaluate;
mod guard;
mod iteration;
mod metric;
mod moments;
mod problem;
mod report;
mod restoration;
mod result;
mod settings;
mod step;
mod system;
mod targets;
#[cfg(test)]
mod test_support;
mod trial_steps;
mod warm_start;

pub(crate) use moments::*;
pub(crate) use trial_steps::*;
mod names;
pub use names::*;

pub use metric::{Metric, SystemMetric};
pub use report::ProjectionReport;
pub use settings::{ActiveRows, ProjectionSettings, Slack, DEFAULT_QUALITY_MARGIN, ROWS};
pub use targets::{rounding_terms, Targets, ROUNDING_ULPS};

use crate::elasticity::ElasticSummary;
use crate::error::Result;
use crate::invariants::Invariants;
use crate::math::Vec3;
use crate::model::{Model, ModelKey, State};
use evaluate::EvalScratch;
use metric::MetricSource;
use problem::MetricRows;

/// The projection with its scratch memory (reused across steps).
#[derive(Clone, Debug, Default)]
pub struct Projector {
    pub settings: ProjectionSettings,
    scratch: EvalScratch,
    grad: Vec<Vec3>,
    grad_trial: Vec<Vec3>,
    x_base: Vec<Vec3>,
    v_base: Vec<Vec3>,
    x: Vec<Vec3>,
    v: Vec<Vec3>,
    x_trial: Vec<Vec3>,
    v_trial: Vec<Vec3>,
    x_best: Vec<Vec3>,
    v_best: Vec<Vec3>,
    /// The base integrator is implicit (resolves `Metric::Auto`).
    implicit_base: bool,
    /// `diag(K_0)_i / m_i` per vertex, 1/s^2 (for the stiffness metric; computed again when the model's
    /// [`Model::key`] differs from `stiffness_key`, the key it was computed for).
    stiffness_ratio: Vec<f64>,
    stiffness_key: Option<ModelKey>,
    /// `a_i = m_i / w_i` of this step's metric.
    metric_factor: Vec<f64>,
    /// The per-vertex arrays kept with the metric (`Problem::rows`).
    metric_rows: MetricRows,
    /// What `metric_factor` and `metric_rows` hold, if they may be kept for the next projection.
    metric_source: Option<MetricSource>,
    /// Vertices whose positions this step's projection must not move (in contact with an obstacle).
    frozen_positions: Vec<u32>,
    /// The full step's trial point while the model step length is tried.
    x_spare: Vec<Vec3>,
    v_spare: Vec<Vec3>,
    grad_spare: Vec<Vec3>,
    /// `grad` holds the elastic gradient at the positions the last projection returned.
    grad_is_final: bool,
    /// The base step's elastic summary at the positions the next projection starts from, its gradient in
    /// `grad` ([`Projector::offer_base_gradient`]).
    base_elastic: Option<ElasticSummary>,
    /// The current iterate is q~ itself, in `x_base`/`v_base` (`x`/`v` hold stale rows): see `current!`.
    at_base: bool,
    /// Iterations of the last projection: the trial points of the iterations before that count sum the
    /// moments for `S` in their own pass (the next iteration solves with them), the last one does not.
    expected_iterations: usize,
    /// With a [`SystemMetric`]: the potential's gradient at the iterate and `W^-1` of it (the positions'
    /// direction of the energy row).
    system_rhs: Vec<Vec3>,
    system_dir: Vec<Vec3>,
    /// A copy of the trial positions, written by the trial pass as it writes them (see [`Mirror`]), while
    /// the caller takes it ([`Projector::take_final_hand_over`]).
    x_mirror: Vec<Vec3>,
    /// What `x_mirror` holds.
    mirror: Mirror,
    /// The caller took the last projection's copy of its positions: this projection's trial passes write one.
    mirror_wanted: bool,
    /// This projection's trial passes write `x_mirror`.
    mirror_rows: bool,
    /// The metric of the current attempt where it differs from the settings' (the mass metric after the
    /// stiffness metric stalled; see [`Projector::project_with`]).
    metric_override: Option<Metric>,
    /// The current attempt stops when the diagonal stiffness metric stalls (`Metric::Auto` only).
    switch_on_stall: bool,
    /// The quality guard's buffers (see [`restoration`]).
    restoration: restoration::Restoration,
    /// The last attempt stopped because the stiffness metric stalled (see `switch_on_stall`).
    stalled: bool,
}

/// Which positions [`Projector`]'s `x_mirror` holds a bit-for-bit copy of. Symplectic Euler keeps the positions
/// of the gradient the projection hands over, to check at its next step that the state still has them. A copy
/// in a pass of its own after each projection is a parallel region of its own; the trial pass writes the copy
/// instead, task by task, from the rows it has just written (still in L1), and the buffer is handed over by a
/// swap. The tracking is conservative: anything but an accepted trial point that the projection returns as it
/// is leaves no copy, and the caller then copies as before. A wrong copy could only cost a reuse (symplectic
/// Euler still compares the positions bit for bit); debug builds assert it is right.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
enum Mirror {
    /// Nothing usable.
    #[default]
    None,
    /// The trial buffers' positions (`x_trial`).
    Trial,
    /// The current iterate's (`x`, an accepted trial point).
    Iterate,
    /// The positions the last projection returned (the state's).
    Returned,
}

impl Projector {
    pub fn new(settings: ProjectionSettings) -> Result<Self> {
        settings.validate()?;
        Ok(Self {
            settings,
            ..Default::default()
        })
    }

    /// Tell the projection whether the base integrator is implicit (resolves [`Metric::Auto`]).
    pub fn set_implicit_base(&mut self, implicit: bool) {
        self.implicit_base = implicit;
    }

    /// The position metric that [`Metric::Auto`] resolves to here.
    pub fn uses_stiffness_metric(&self) -> bool {
        match self.metric_override.unwrap_or(self.settings.metric) {
            Metric::Mass => false,
            Metric::Stiffness => true,
            Metric::Auto => self.implicit_base,
        }
    }

    /// What the next projections depend on besides their input, into a checkpoint (see [`crate::checkpoint`]):
    /// the quality guard's memory and the iteration count the next projection expects (it decides which passes
    /// sum the moments, and so the order of their sums).
    pub fn carry(&self, model: &Model, c: &mut crate::checkpoint::Carry) {
        self.restoration.carry(model, c);
        c.put_scalar(
            "projection.expected_iterations",
            self.expected_iterations as f64,
        );
    }

    /// Back from [`Projector::carry`], for the same model and settings.
    pub fn resume(&mut self, model: &Model, c: &crate::checkpoint::Carry) -> Result<()> {
        self.restoration.resume(model, c)?;
        self.expected_iterations = c.count("projection.expected_iterations")?;
        Ok(())
    }

    /// Freeze the positions of these vertices in the next projections (their velocities stay free): the
    /// simulation passes the vertices that touched an obstacle this step, so that the projection cannot
    /// push them back into it. Replaces the previous set.
    pub fn set_frozen_positions(&mut self, vertices: &[u32]) {
        self.frozen_positions.clear();
        self.frozen_positions.extend_from_slice(vertices);
    }

    /// The rows this projection enforces. `Auto` also drops the centre-of-mass rows in a step with an
    /// impulsive event (contact): its centre of mass comes from impulses that act at unknown times within the
    /// step, and with the contact vertices' positions frozen, holding it at the base step's value
    /// over-constrains the correction (the energy books of a box rocking on a frictional corner do not close
    /// with them).
    fn active_rows(&self, model: &Model, targets: &Targets) -> [bool; ROWS] {
        let mut m = self.settings.rows.mask(model.num_pinned() > 0);
        if self.settings.rows == ActiveRows::Auto && targets.uncertain_impulses {
            m[7..10].iter_mut().for_each(|r| *r = false);
        }
        m
    }

    /// Project `state` (holding the base step's result `(x*, v*)`) in place, for step size `h` and the given
    /// targets. Returns the report and the invariants measured at the returned state.
    pub fn project(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        targets: &Targets,
    ) -> (ProjectionReport, Invariants) {
        self.project_with(model, state, h, targets, None)
    }
}

impl Projector {
    /// The elastic gradient at the positions the last [`Projector::project`] returned (J/m, shape (m, 3)), if
    /// it is at hand, as a buffer the caller may swap out (the simulation hands it to an integrator that reads it). A
    /// second call returns `None` until the next projection.
    pub fn take_final_gradient(&mut self) -> Option<&mut Vec<Vec3>> {
        std::mem::take(&mut self.grad_is_final).then_some(&mut self.grad)
    }

    /// [`Projector::take_final_gradient`], with a bit-for-bit copy of the positions the last projection returned
    /// (shape (m, 3), m) where it has one, as a buffer the caller may swap out (so that
    /// the integrator can check the positions without a copy pass). Taking it asks the next projection to write such a
    /// copy as it writes its trial points (the first projection after the caller starts taking it has none).
    pub fn take_final_hand_over(&mut self) -> Option<(&mut Vec<Vec3>, Option<&mut Vec<Vec3>>)> {
        if !std::mem::take(&mut self.grad_is_final) {
            return None;
        }
        // Below `SERIAL_ROWS` the caller's serial copy is cheaper than the trial tasks' extra writes.
        self.mirror_wanted = self.grad.len() >= crate::exec::SERIAL_ROWS;
        let positions =
            (std::mem::take(&mut self.mirror) == Mirror::Returned).then_some(&mut self.x_mirror);
        Some((&mut self.grad, positions))
    }

    /// Offer the elastic energy summary `summary` and gradient `grad` (J/m, shape (m, 3)) of the model at the
    /// positions the next [`Projector::project`] starts from (the base step's result), as the base step
    /// evaluated them there (handed over by the simulation): that call skips
    /// its first elastic evaluation. The caller guarantees the positions are bit-identical to the ones they
    /// were evaluated at (then the projection's result has the same bits either way). The buffer is taken
    /// by a swap.
    pub fn offer_base_gradient(&mut self, summary: ElasticSummary, grad: &mut Vec<Vec3>) {
        std::mem::swap(&mut self.grad, grad);
        self.base_elastic = Some(summary);
    }

    /// Forget the gradient and positions the last projection would hand over: the state no longer holds the
    /// positions it returned.
    fn invalidate_hand_over(&mut self) {
        self.grad_is_final = false;
        self.mirror = Mirror::None;
    }
}
