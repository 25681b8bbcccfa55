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

mod moments;
mod trial_steps;

pub(crate) use moments::*;
pub(crate) use trial_steps::*;
mod names;
pub use names::*;

use crate::exec::{
    for_each_chunk_mut, for_each_chunk_mut2, for_each_chunk_mut3, for_each_chunk_mut4,
    for_each_mut, reduce_chunks,
};

use crate::elasticity::{
    deformation_gradient, elastic_gradient_chunks, ElasticSummary, ElasticWorkspace,
};
use crate::error::{invalid, Result};
use crate::invariants::Invariants;
use crate::math::{cholesky_substitute, cross, dot, solve_symmetric_psd_into, sub, Mat3, Vec3};
use crate::model::{Model, ModelKey, State};
use crate::projection as tl;
use crate::projection::{self as ml, q, UPPER, VL};

mod certificate;
mod restoration;

/// Which constraint rows the projection enforces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ActiveRows {
    /// `All` for a free body, `Energy` when vertices are pinned (supports exchange momentum with it).
    Auto,
    /// Total energy only.
    Energy,
    /// Energy, linear and angular momentum (the paper's 7 rows).
    EnergyMomentum,
    /// Energy, momenta and centre of mass (10 rows).
    All,
}

impl ActiveRows {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "auto" => Some(Self::Auto),
            "energy" => Some(Self::Energy),
            "energy_momentum" => Some(Self::EnergyMomentum),
            "all" => Some(Self::All),
            _ => None,
        }
    }
    /// Active-row mask over `[H, Px, Py, Pz, Lx, Ly, Lz, Cx, Cy, Cz]`.
    pub fn mask(self, has_pins: bool) -> [bool; ROWS] {
        let resolved = match self {
            Self::Auto if has_pins => Self::Energy,
            Self::Auto => Self::All,
            other => other,
        };
        let mut m = [false; ROWS];
        m[0] = true;
        if matches!(resolved, Self::EnergyMomentum | Self::All) {
            m[1..7].iter_mut().for_each(|r| *r = true);
        }
        if resolved == Self::All {
            m[7..10].iter_mut().for_each(|r| *r = true);
        }
        m
    }
}

/// Number of constraint rows in total.
pub const ROWS: usize = 10;

/// Units in the last place that a row's tolerance is never below (with [`rounding_terms`]): a sum of `m`
/// float64 terms of size `S` is only known to about `sqrt(m) eps S`, whatever the tolerance asks.
pub const ROUNDING_ULPS: f64 = 8.0;

/// The growth of the rounding error of a sum over `m` vertices (summed in four lanes): `sqrt(m / 4 + 1)`.
pub fn rounding_terms(m: usize) -> f64 {
    (m as f64 / 4.0 + 1.0).sqrt()
}

/// Attempts per projection (the first plus restarts with frozen vertices, see [`ProjectionReport::restarts`]).
const MAX_ATTEMPTS: usize = 3;

/// Projection settings, with the defaults of fepr-spec section 3.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectionSettings {
    /// Relative per-row tolerance (default 1e-10).
    pub tolerance: f64,
    /// Maximum iterations (default 20).
    pub max_iterations: usize,
    /// `eps = c_eps m_tot r^2` weights the slack variables s and t (default 0.01).
    pub c_eps: f64,
    /// Diagonal regularisation of the scaled small system: `delta` times each row's diagonal (default 1e-12).
    pub regularization: f64,
    /// Maximum step halvings per iteration (default 4).
    pub max_halvings: usize,
    /// Which rows are enforced (default `Auto`).
    pub rows: ActiveRows,
    /// Optional cap on the D-norm of the total correction, as a fraction of `sqrt(m_tot) r` (the correction
    /// may move the body by at most this fraction of its size, mass-weighted RMS). `None`: no cap.
    pub impact_bound: Option<f64>,
    /// When the slack variables s and t may move (default `Auto`).
    pub slack: Slack,
    /// Scaled energy error above which (and above `tolerance`) the iterations start from the velocity warm
    /// start (`>= 0`; default: infinity, i.e. off, so that the result is the closest point of fepr-spec
    /// section 3). For dissipative base steps that lose much of H in one step: the Python layer's `"auto"`
    /// uses 0 after Projective Dynamics and 0.05 after XPBD.
    pub warm_start_threshold: f64,
    /// The position block of the metric D (default `Auto`, see [`Metric`]).
    pub metric: Metric,
    /// The quality guard (fepr-spec section 5b; default `Some(0.05)`): restoring an energy deficit may not move
    /// any tet's volume ratio `J`, at the end of the step or one step ahead at the new velocities, by more than
    /// this from what the base step gave it, nor invert a tet the base step left upright. The projection then
    /// restores the largest fraction of the deficit it can within that, and books the rest as unresolved
    /// energy ([`ProjectionReport::unresolved`]). `None`: restore everything (the model's own dynamics, which
    /// on sliver tets at large steps inverts them).
    pub quality_margin: Option<f64>,
}

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
/// global matrix times `h^2`; see [`crate::integrators::Integrator::system_metric`]). Under [`Metric::Auto`]
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

/// When the slack variables s and t of fepr-spec section 2 are free to move.
///
/// With slack, the projection may keep part of the base step's own momentum change (at cost
/// `eps s^2 / 2`) instead of the target: right for steps whose impulses are known only approximately
/// (contact), wrong for a closed system, where the base integrator's momentum error (backward Euler does
/// not conserve angular momentum) would then leak into the result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Slack {
    /// Free only in steps that report an impulsive event with uncertain impulses.
    Auto,
    /// Always free.
    On,
    /// Never: s = t = 0, the momenta are held exactly at their targets.
    Off,
}

impl Slack {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "auto" => Some(Self::Auto),
            "on" => Some(Self::On),
            "off" => Some(Self::Off),
            _ => None,
        }
    }
}

impl Default for ProjectionSettings {
    fn default() -> Self {
        Self {
            tolerance: 1e-10,
            max_iterations: 20,
            c_eps: 0.01,
            regularization: 1e-12,
            max_halvings: 4,
            rows: ActiveRows::Auto,
            impact_bound: None,
            slack: Slack::Auto,
            warm_start_threshold: f64::INFINITY,
            metric: Metric::Auto,
            quality_margin: Some(DEFAULT_QUALITY_MARGIN),
        }
    }
}

/// The default [`ProjectionSettings::quality_margin`]: a twentieth of the rest volume ratio.
pub const DEFAULT_QUALITY_MARGIN: f64 = 0.05;

impl ProjectionSettings {
    pub fn validate(&self) -> Result<()> {
        if !(self.tolerance.is_finite() && self.tolerance > 0.0 && self.tolerance < 1.0) {
            return Err(invalid(
                "tolerance",
                format!("must satisfy 0 < tolerance < 1, got {}", self.tolerance),
            ));
        }
        if self.max_iterations == 0 || self.max_iterations > 10_000 {
            return Err(invalid(
                "max_iterations",
                format!("must be in 1..=10000, got {}", self.max_iterations),
            ));
        }
        if !(self.c_eps.is_finite() && self.c_eps > 0.0) {
            return Err(invalid(
                "c_eps",
                format!("must be positive and finite, got {}", self.c_eps),
            ));
        }
        if !(self.regularization.is_finite()
            && self.regularization >= 0.0
            && self.regularization < 1.0)
        {
            return Err(invalid(
                "regularization",
                format!("must satisfy 0 <= delta < 1, got {}", self.regularization),
            ));
        }
        if self.warm_start_threshold.is_nan() || self.warm_start_threshold < 0.0 {
            return Err(invalid(
                "warm_start_threshold",
                format!(
                    "must be >= 0 (infinite: off), got {}",
                    self.warm_start_threshold
                ),
            ));
        }
        if let Some(b) = self.impact_bound {
            if !(b.is_finite() && b > 0.0) {
                return Err(invalid(
                    "impact_bound",
                    format!("must be positive and finite, got {b}"),
                ));
            }
        }
        if let Some(q) = self.quality_margin {
            if !(q.is_finite() && q > 0.0 && q <= 1.0) {
                return Err(invalid(
                    "quality_margin",
                    format!("must satisfy 0 < quality_margin <= 1 (a change of the volume ratio J), got {q}"),
                ));
            }
        }
        Ok(())
    }
}

/// Targets of one projection (fepr-spec section 2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Targets {
    /// `H_target = H_ref + W`, J.
    pub energy: f64,
    /// `P_target = P_ref + J`, kg m/s.
    pub momentum: Vec3,
    /// `L_target = L_ref + K`, about the target centre of mass, kg m^2/s.
    pub angular_momentum: Vec3,
    /// `C_target`, m.
    pub center_of_mass: Vec3,
    /// The energy row's scale, J: its tolerance is `tolerance * energy_scale`. The simulation measures it on
    /// scales that do not grow with the distance fallen or the time run, and from the start of the step, not
    /// from the base step's result (so a wild base step cannot loosen it): see
    /// [`crate::simulation::Simulation`]'s energy scale.
    pub energy_scale: f64,
    /// The step's impulses are known only approximately (an impulsive event): enables the slack in `Auto`.
    pub uncertain_impulses: bool,
}

/// What one projection did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProjectionReport {
    /// Iterations taken (0 when the base step already satisfied every row).
    pub iterations: usize,
    /// Every active row is within tolerance.
    pub converged: bool,
    /// Largest scaled residual `|c_i| / scale_i` at the base step's state.
    pub initial_residual: f64,
    /// Largest scaled residual at the returned state (compare with the tolerance).
    pub final_residual: f64,
    /// D-norm of the total correction `|q - q~|_D`, sqrt(kg) m.
    pub correction: f64,
    /// Final slack values.
    pub s: f64,
    pub t: f64,
    /// Not converged: the best iterate (or the base state) was kept.
    pub fallback: bool,
    /// The impact bound limited the correction (conservation is then not exact).
    pub bound_hit: bool,
    /// Small solves that needed the least-squares fallback.
    pub least_squares_solves: usize,
    /// Step halvings taken in total.
    pub halvings: usize,
    /// Number of active rows.
    pub active_rows: usize,
    /// Total energy `H(x*, v*)` of the base step's state, J (measured by the first evaluation).
    pub base_energy: f64,
    /// Smallest volume ratio of the base step's state (measured by the first evaluation).
    pub base_min_j: f64,
    /// The velocity warm start was used (energy error above `warm_start_threshold`).
    pub warm_start: bool,
    /// The position metric was `W = M + h^2 diag(K_0)` (see [`Metric`]).
    pub stiffness_metric: bool,
    /// The position metric was the base integrator's factorised matrix (see [`SystemMetric`]); then
    /// `stiffness_metric` is false.
    pub system_metric: bool,
    /// Restarts from the base state after an attempt inverted tets the base step had upright.
    pub restarts: usize,
    /// Vertices whose positions were frozen by those restarts (their velocities stay free).
    pub frozen_vertices: usize,
    /// Elastic evaluations (energy, or energy and gradient, over all tets), the first one included unless the
    /// base step handed it over ([`Projector::offer_base_gradient`]: backward Euler): an iteration evaluates
    /// its trial point, and a second one where the full step overshoots.
    pub evaluations: usize,
    /// Fraction of the step's energy gap `H_target - H(x*, v*)` (a deficit to restore or an excess to remove)
    /// that the projection closed: 1 unless the quality guard or convergence limited it (see
    /// [`ProjectionSettings::quality_margin`]).
    pub restored: f64,
    /// Energy the projection left between the base step's energy and the target, J (`-(1 - restored) * gap`
    /// with `gap = H_target - H(x*, v*)`: negative for a deficit it did not restore, positive for an excess it
    /// did not remove): booked as the step's unresolved energy, a budget source of its own, so that
    /// `H = H_0 + budget_total` still holds.
    pub unresolved: f64,
    /// The step's energy gap `H_target - H(x*, v*)`, J: what the base step lost (positive) or gained (negative)
    /// against its target.
    pub gap: f64,
    /// Projections tried in this step (1, plus one per restored fraction tried and per metric switch).
    pub trials: usize,
    /// The diagonal stiffness metric stalled (the scaled residual did not halve in an iteration after the
    /// first) and the projection restarted from the base state in the mass metric (see [`Metric::Auto`]).
    pub metric_switched: bool,
    /// The body was translated onto the centre-of-mass target before iterating (the closest point of those rows
    /// alone; see [`Projector::project_with`]).
    pub translated: bool,
    /// Largest change of a tet's volume ratio against the base step (at the end of the step or one step
    /// ahead), as a fraction of the quality margin, at the returned state; 0 where the guard did not run.
    pub quality_excess: f64,
}

/// Everything an evaluation of `c(q)` produces.
#[derive(Clone, Copy, Debug)]
struct Eval {
    /// The moments for `S` (below) were summed; without them (a trial point, most of which end the
    /// projection) they are zero and must be summed before a solve.
    s_moments: bool,
    c: [f64; ROWS],
    el: ElasticSummary,
    kinetic: f64,
    gravitational: f64,
    momentum: Vec3,
    /// About the target centre of mass.
    angular_momentum: Vec3,
    com: Vec3,
    // Moments over the free vertices, for S. With the position metric `w_i = m_i / a_i` (`a_i = 1` for the
    // mass metric), the position-block moments carry the factor `a_i`; the velocity-block ones do not.
    grad_sq_over_w: f64,
    a_grad_sum: Vec3,
    a_grad_cross_v: Vec3,
    free_mass: f64,
    a_free_mass: f64,
    free_p: Vec3,
    a_free_p: Vec3,
    free_l: Vec3,
    free_r: Vec3,
    tr_vv: f64,
    a_vv: [[f64; 3]; 3],
    rr: [[f64; 3]; 3],
    // For the angular momentum's second-order term along a step (`angular_second_order`), with
    // `r_i = x_i - C_target`: `sum a_i g_i r_i^T`, `sum a_i m_i r_i x v_i`, `sum a_i m_i r_i`.
    a_grad_r: [[f64; 3]; 3],
    a_r_cross_v: Vec3,
    a_mass_r: Vec3,
    /// `sum m_i x_i` (for the centre of mass).
    mass_x: Vec3,
    /// The vertices' part of the squared D-norm distance from the base step's state, where the evaluation
    /// summed it (a trial point: [`Step::measured_from`]); the projection's correction is then known without
    /// a pass of its own when this point is the result.
    correction_sq: Option<f64>,
}

impl Default for Eval {
    fn default() -> Self {
        let z = [0.0; 3];
        Self {
            s_moments: false,
            c: [0.0; ROWS],
            el: ElasticSummary {
                energy: 0.0,
                min_j: f64::INFINITY,
                inverted: 0,
            },
            kinetic: 0.0,
            gravitational: 0.0,
            momentum: z,
            angular_momentum: z,
            com: z,
            grad_sq_over_w: 0.0,
            a_grad_sum: z,
            a_grad_cross_v: z,
            free_mass: 0.0,
            a_free_mass: 0.0,
            free_p: z,
            a_free_p: z,
            free_l: z,
            free_r: z,
            tr_vv: 0.0,
            a_vv: [z; 3],
            rr: [z; 3],
            a_grad_r: [z; 3],
            a_r_cross_v: z,
            a_mass_r: z,
            mass_x: z,
            correction_sq: None,
        }
    }
}

impl Eval {
    /// Add the vertex sums of `b` (a later chunk) to these.
    fn add(&mut self, b: &Eval) {
        self.s_moments &= b.s_moments;
        // In task order from the first task's value, as `d_norm` adds its task sums: the same bits.
        self.correction_sq = match (self.correction_sq, b.correction_sq) {
            (Some(a), Some(b)) => Some(a + b),
            _ => None,
        };
        let add3 = |a: &mut Vec3, b: &Vec3| (0..3).for_each(|k| a[k] += b[k]);
        self.kinetic += b.kinetic;
        self.gravitational += b.gravitational;
        self.grad_sq_over_w += b.grad_sq_over_w;
        self.free_mass += b.free_mass;
        self.a_free_mass += b.a_free_mass;
        self.tr_vv += b.tr_vv;
        add3(&mut self.momentum, &b.momentum);
        add3(&mut self.angular_momentum, &b.angular_momentum);
        add3(&mut self.a_grad_sum, &b.a_grad_sum);
        add3(&mut self.a_grad_cross_v, &b.a_grad_cross_v);
        add3(&mut self.free_p, &b.free_p);
        add3(&mut self.a_free_p, &b.a_free_p);
        add3(&mut self.free_l, &b.free_l);
        add3(&mut self.free_r, &b.free_r);
        add3(&mut self.mass_x, &b.mass_x);
        add3(&mut self.a_r_cross_v, &b.a_r_cross_v);
        add3(&mut self.a_mass_r, &b.a_mass_r);
        for a in 0..3 {
            add3(&mut self.a_vv[a], &b.a_vv[a]);
            add3(&mut self.rr[a], &b.rr[a]);
            add3(&mut self.a_grad_r[a], &b.a_grad_r[a]);
        }
    }
}

/// Scratch memory of an evaluation: the elastic pass's, and the vertex tasks' partial sums.
#[derive(Clone, Debug, Default)]
struct EvalScratch {
    ws: ElasticWorkspace,
    parts: Vec<Eval>,
    /// The D-norm's per-task sums.
    norms: Vec<f64>,
    /// The warm start's per-task kinetic energies.
    kinetic: Vec<[f64; 3]>,
}

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
/// of the gradient the projection hands over, to check at its next step that the state still has them; it
/// copied them in a pass of its own after each projection, a parallel region that counts in the projection's
/// time (two threads: the armadillo 2.5-2.6 us, the elephant 6.2-6.9 us per step). The trial pass writes the
/// copy instead, task by task, from the rows it has just written (in L1), for 0.3-0.5 us (armadillo) and a few
/// us (elephant) more, and the buffer is handed over by a swap. The tracking is conservative: anything but an
/// accepted trial point that the projection returns as it is leaves no copy, and the caller then copies as
/// before. A wrong copy could only cost a reuse (symplectic Euler still compares the positions bit for bit);
/// debug builds assert it is right.
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

/// What a projector's metric factors and rows were computed from: the next projection keeps them when it
/// would compute the same ones (the metric of the same kind and step size, the same masses and pins, no
/// frozen positions). They are the same every step of a typical simulation, and computing them was a serial
/// pass over four arrays per projection: 15 us of the elephant's 550 us on two threads.
#[derive(Clone, Debug, PartialEq)]
struct MetricSource {
    /// `None` for `W = M`; the step size's bits and the model's key for the stiffness metric.
    stiffness: Option<(u64, ModelKey)>,
    /// The masses and the pins the rows were derived from (the model's public fields, which a user may
    /// change between steps; [`Model::key`] would hash them serially, about as long as deriving the rows).
    masses: Vec<f64>,
    pinned: Vec<bool>,
}

impl MetricSource {
    /// Whether these are the metric of `model` with `stiffness` (compared bit for bit).
    fn matches(&self, model: &Model, stiffness: Option<(u64, ModelKey)>) -> bool {
        self.stiffness == stiffness
            && self.pinned == model.pinned
            && self.masses.len() == model.masses.len()
            // Bits, not values (-0.0 == 0.0); or-ing the differences, which vectorises.
            && self.masses.iter().zip(&model.masses).fold(0, |d, (a, b)| d | (a.to_bits() ^ b.to_bits())) == 0
    }
}

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

struct Problem<'a> {
    model: &'a Model,
    h: f64,
    targets: &'a Targets,
    /// `P* - P_target` and `L* - L_target`.
    dp_star: Vec3,
    dl_star: Vec3,
    active: [bool; ROWS],
    row_scale: [f64; ROWS],
    eps: f64,
    /// `a_i = m_i / w_i`: the position block of D is `diag(m_i / a_i)`; 0 freezes a vertex's position.
    metric_factor: Vec<f64>,
    /// Per-vertex arrays of the metric and the pins, kept with `metric_factor` ([`Problem::refresh_rows`]).
    rows: MetricRows,
}

/// Per-vertex arrays derived from the metric factors, the masses and the pins, each of length m: read by
/// the vertex passes as contiguous rows (the moment kernels load four at a time).
#[derive(Clone, Debug, Default)]
struct MetricRows {
    /// `a_i / m_i` (the position block of D^-1).
    a_over_m: Vec<f64>,
    /// `m_i` of a free vertex, 0 of a pinned one (kg).
    free_mass: Vec<f64>,
    /// `a_i` of a free vertex, 0 of a pinned one.
    free_factor: Vec<f64>,
    /// No vertex is pinned and every `a_i` is 1 (the mass metric without frozen positions): the moment
    /// kernels skip the sums that then repeat others ([`ml::Rows::unit`]).
    unit: bool,
}

impl<'a> Problem<'a> {
    /// The problem of one projection with the metric factors `metric_factor` and their per-vertex rows `rows`
    /// (a reused buffer: derived from the factors already, kept from the last projection, or to be derived by
    /// [`Problem::with_fresh_rows`]), slack directions and row scales not yet set (zero and one).
    fn new(
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
    fn with_fresh_rows(mut self) -> Self {
        self.refresh_rows();
        self
    }

    /// `rows` from `metric_factor`, the masses and the pins.
    fn refresh_rows(&mut self) {
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
    /// over-constrains the correction (the energy bookkeeping of a box rocking on a frictional corner was off by
    /// 8.5e-3 of H0 with them, 1e-10 without).
    fn active_rows(&self, model: &Model, targets: &Targets) -> [bool; ROWS] {
        let mut m = self.settings.rows.mask(model.num_pinned() > 0);
        if self.settings.rows == ActiveRows::Auto && targets.uncertain_impulses {
            m[7..10].iter_mut().for_each(|r| *r = false);
        }
        m
    }

    /// Fill `metric_factor` with `a_i = m_i / w_i` for step size `h` (0 for frozen positions). Returns false when
    /// the last projection's factors (and rows) are these already, and were kept.
    fn prepare_metric(&mut self, model: &Model, h: f64) -> bool {
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

    /// One projection of `state` onto `targets` (the iteration of fepr-spec section 3, with its restarts), in
    /// the metric of the settings or of `metric_override`; the quality guard and the metric switch are
    /// [`Projector::project_with`]'s.
    fn project_once<'d>(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        targets: &Targets,
        system: Option<&mut (dyn SystemMetric + 'd)>,
    ) -> (ProjectionReport, Invariants) {
        let m = model.num_vertices();
        self.grad_is_final = false;
        for buf in [
            &mut self.grad,
            &mut self.grad_trial,
            &mut self.x,
            &mut self.v,
            &mut self.x_trial,
            &mut self.v_trial,
        ] {
            buf.resize(m, [0.0; 3]);
        }
        // q~ moves into x_base/v_base by a buffer swap (no copy), and is the current iterate itself until a
        // trial point is accepted (`at_base`, see `current!`): four fewer copies of the state per step
        // (bunny2: about 14 us on one thread). The state's buffers get the result at the end.
        std::mem::swap(&mut self.x_base, &mut state.x);
        std::mem::swap(&mut self.v_base, &mut state.v);
        self.at_base = true;
        self.mirror = Mirror::None;
        self.mirror_rows = std::mem::take(&mut self.mirror_wanted);
        if self.mirror_rows {
            self.x_mirror.resize(m, [0.0; 3]);
        }
        let r = model.length_scale;
        let mt = model.total_mass;
        let slack = match self.settings.slack {
            Slack::On => true,
            Slack::Off => false,
            Slack::Auto => targets.uncertain_impulses,
        };
        let fresh_metric = self.prepare_metric(model, h);
        // The slack directions are set from the first evaluation below (at s = t = 0 they do not enter the
        // constraints), the row scales after it.
        let mut pb = Problem::new(
            model,
            h,
            targets,
            std::mem::take(&mut self.metric_factor),
            std::mem::take(&mut self.metric_rows),
            self.active_rows(model, targets),
            self.settings.c_eps * mt * r * r,
        );
        if fresh_metric {
            pb.refresh_rows();
        }
        let energy_only = pb.active[0] && pb.active[1..].iter().all(|&a| !a);
        let mut system = system.filter(|_| {
            self.settings.metric == Metric::Auto
                && self.metric_override.is_none()
                && energy_only
                && self.frozen_positions.is_empty()
        });
        if system.is_some() {
            self.system_rhs.resize(m, [0.0; 3]);
            self.system_dir.resize(m, [0.0; 3]);
        }
        let (mut s, mut t) = (0.0, 0.0);
        // With a warm start possible, the first evaluation skips the elastic gradient: the warm start changes
        // the velocities alone and often leaves nothing to iterate (after PD, every step on the bunny), so the
        // gradient is computed only when an iteration needs it (`grad_at_x`).
        let lazy_gradient = self.settings.warm_start_threshold.is_finite();
        let offered = self.base_elastic.take();
        let mut cur = if let Some(el) = offered {
            // The base step evaluated the elastic energy and gradient here (the same bits as evaluating).
            let (x, v) = current!(self);
            let grad = Some(&self.grad[..]);
            evaluate_with_elastic(&pb, x, v, s, t, el, grad, &mut self.scratch.parts)
        } else if lazy_gradient {
            let (x, v) = current!(self);
            evaluate_energy(&pb, x, v, s, t, &mut self.scratch.parts)
        } else {
            let (x, v) = current!(self);
            evaluate(&pb, x, v, s, t, &mut self.scratch, &mut self.grad)
        };
        let mut grad_at_x = offered.is_some() || !lazy_gradient;
        if slack {
            // P* and L* (about C_target) of the base step's state, summed by that evaluation. Without slack the
            // s and t columns vanish (their gradients are -(P* - P_t) and -(L* - L_t)).
            pb.dp_star = sub(cur.momentum, targets.momentum);
            pb.dl_star = sub(cur.angular_momentum, targets.angular_momentum);
        }
        // Row scales (fepr-spec section 3), from the targets and the start-of-step state, not from the base
        // step's result: a wild base step must not loosen the energy tolerance.
        pb.row_scale[0] = targets.energy_scale.max(1e-300);
        // Far from the origin (a body that has fallen for minutes) the positions themselves carry less than
        // tolerance * r: the centre of mass's scale is at least the rounding of its sum.
        let com_floor = ROUNDING_ULPS
            * rounding_terms(m)
            * f64::EPSILON
            * crate::math::norm(targets.center_of_mass)
            / self.settings.tolerance;
        // The momenta's scales are those of the motion, `sqrt(2 m_tot S)` with `S` the energy row's scale (and
        // `r` times that for L), not `m_tot r / h` (the momentum that moves the body by its size in one step):
        // at a small step or a slow motion the latter is hundreds of times the momenta the body has, and a
        // tolerance on it let P and L drift by 1e-8 of them.
        let momentum_scale = (2.0 * mt * pb.row_scale[0]).sqrt();
        for a in 0..3 {
            pb.row_scale[1 + a] = momentum_scale;
            pb.row_scale[4 + a] = momentum_scale * r;
            pb.row_scale[7 + a] = r.max(com_floor);
        }
        let tol = self.settings.tolerance;
        let base_inverted = cur.el.inverted;
        let base_finite = cur.c.iter().all(|c| c.is_finite());
        let mut report = ProjectionReport {
            active_rows: pb.active.iter().filter(|a| **a).count(),
            initial_residual: max_scaled(&pb, &cur.c),
            base_energy: cur.kinetic + cur.el.energy + cur.gravitational,
            base_min_j: cur.el.min_j,
            stiffness_metric: self.uses_stiffness_metric() && system.is_none(),
            system_metric: system.is_some(),
            evaluations: usize::from(offered.is_none()),
            ..Default::default()
        };
        let mut cur_norm = norm_scaled(&pb, &cur.c);
        let base_norm = cur_norm;
        let mut best_norm = cur_norm;
        let mut best_is_base = true;
        let mut best_eval = cur;
        let (mut best_s, mut best_t) = (0.0, 0.0);
        // The best iterate lives in `x`/`v` while it is the current one (`best_in_x`), and is moved to
        // `x_best`/`v_best` by a buffer swap only when a later iterate replaces it: no copies per iteration.
        let mut best_in_x = false;
        self.x_best.resize(m, [0.0; 3]);
        self.v_best.resize(m, [0.0; 3]);

        // Attempts: if an attempt ends with tets inverted that the base step had upright (a near-degenerate
        // sliver flipped by the position correction), freeze the positions of those tets' vertices (their
        // velocities stay free) and restart from q~. fepr-spec section 6, pitfall 5: the projection must not
        // create inverted elements.
        let mut attempt = 0;
        let stall_exit = self.switch_on_stall && report.stiffness_metric;
        let mut stalled = false;
        loop {
            // The centre-of-mass rows alone have a rigid closest point: translate the body onto C_target (the
            // mass metric's first step would; the diagonal stiffness metric cannot move a body rigidly, and its
            // iterates would deform a falling body to meet these rows). A translation changes neither the
            // elastic energy nor its gradient.
            if base_finite
                && pb.active[7..10].iter().all(|&a| a)
                && rigid_translation_allowed(model, &self.frozen_positions)
            {
                let d = sub(targets.center_of_mass, cur.com);
                if (0..3).any(|a| (d[a] / pb.row_scale[7 + a]).abs() > tol) {
                    self.leave_base();
                    for_each_chunk_mut(&mut self.x, vertex_chunk(m), |_, xs| {
                        for xi in xs.iter_mut() {
                            *xi = [xi[0] + d[0], xi[1] + d[1], xi[2] + d[2]];
                        }
                    });
                    let grad = grad_at_x.then_some(&self.grad[..]);
                    cur = evaluate_with_elastic(
                        &pb,
                        &self.x,
                        &self.v,
                        s,
                        t,
                        cur.el,
                        grad,
                        &mut self.scratch.parts,
                    );
                    cur_norm = norm_scaled(&pb, &cur.c);
                    report.translated = true;
                    if cur_norm < best_norm && cur.c.iter().all(|c| c.is_finite()) {
                        best_norm = cur_norm;
                        best_is_base = false;
                        best_eval = cur;
                        best_in_x = true;
                    }
                }
            }
            // Opt-in warm start for large energy errors (a dissipative base step at a large dt can lose most of H
            // in one step): scale the deformational velocities, which meets the energy row and keeps P and L; the
            // iterations then fix the rest from nearby instead of linearising a stiff position correction far
            // from the manifold.
            if base_finite
                && pb.active[0]
                && (cur.c[0] / pb.row_scale[0]).abs() > self.settings.warm_start_threshold.max(tol)
                && {
                    // The warm start changes the velocities in place: the iterate gets buffers of its own.
                    self.leave_base();
                    let parts = &mut self.scratch.kinetic;
                    warm_start_velocities(&pb, &cur, &self.x, &mut self.v, parts)
                }
            {
                // Only the velocities changed: the elastic energy (and gradient, if computed) at x still hold.
                let grad = grad_at_x.then_some(&self.grad[..]);
                cur = evaluate_with_elastic(
                    &pb,
                    &self.x,
                    &self.v,
                    s,
                    t,
                    cur.el,
                    grad,
                    &mut self.scratch.parts,
                );
                cur_norm = norm_scaled(&pb, &cur.c);
                report.warm_start = true;
                if cur_norm < best_norm && cur.c.iter().all(|c| c.is_finite()) {
                    best_norm = cur_norm;
                    best_is_base = false;
                    best_eval = cur;
                    best_in_x = true;
                }
            }

            if base_finite {
                for _ in 0..self.settings.max_iterations {
                    if max_scaled(&pb, &cur.c) <= tol {
                        // On the manifold; with new inversions, iterating further cannot help: restart.
                        report.converged = cur.el.inverted <= base_inverted;
                        break;
                    }
                    if !grad_at_x {
                        // The same constraint values (the same bits for Neo-Hookean and ARAP, whose energy-only
                        // and gradient passes are gated bit-identical), now with the gradient and S's moments.
                        report.evaluations += 1;
                        let (x, v) = current!(self);
                        cur = evaluate(&pb, x, v, s, t, &mut self.scratch, &mut self.grad);
                        grad_at_x = true;
                    } else if !cur.s_moments {
                        // An accepted trial point (summed without S's moments, which most trial points, ending
                        // the projection, never need): sum them now; the constraint values keep their bits.
                        let grad = Some(&self.grad[..]);
                        let parts = &mut self.scratch.parts;
                        let (x, v) = current!(self);
                        cur = evaluate_with_elastic(&pb, x, v, s, t, cur.el, grad, parts);
                    }
                    if let Some(sys) = system.as_deref_mut() {
                        // The energy row's position block in the metric W: its direction W^-1 grad U and
                        // S_HH's position part grad U . W^-1 grad U (in place of the diagonal metric's moment).
                        let (rhs, dir) = (&mut self.system_rhs, &mut self.system_dir);
                        let parts = &mut self.scratch.norms;
                        match system_direction(&pb, sys, &self.grad, rhs, dir, parts) {
                            Some(gz) => cur.grad_sq_over_w = gz,
                            None => {
                                system = None;
                                report.system_metric = false;
                                report.stiffness_metric = self.uses_stiffness_metric();
                            }
                        }
                    }
                    let dir = system.is_some();
                    let Multipliers {
                        lambda,
                        least_squares,
                        offset,
                    } = solve_multipliers(&pb, &cur, self.settings.regularization);
                    report.least_squares_solves += least_squares as usize;
                    let mut alpha = 1.0;
                    let mut accepted = None;
                    report.evaluations += 1;
                    // Sum S's moments with the trial point where another iteration is expected after this
                    // one (backward Euler takes two per step): the pass after an accepted trial is then not
                    // needed. Which pass sums them changes no bits (the same task sums in the same order).
                    let moments = report.iterations + 1 < self.expected_iterations;
                    let mut cand = self.trial(&pb, s, t, &lambda, 1.0, moments, dir);
                    // Curvature-aware step length: along the step, P and C are linear in alpha, L is quadratic,
                    // so c(alpha) = (1 - alpha) c(0) + alpha^2 e with e = c(1) holds for them exactly and models H's
                    // curvature (its row with the second-order offset, see `model_step_length`). Where the full
                    // step overshoots (stiff materials), take the model's best alpha.
                    // A full step that already lands within the tolerance (without inverting more tets than the
                    // base step) is taken as it is: the model's shorter step could only improve on a converged
                    // point, for a serial search (0.55 us) and, where it proposes one, a second evaluation.
                    let full_step_done =
                        max_scaled(&pb, &cand.0.c) <= tol && cand.0.el.inverted <= base_inverted;
                    if !full_step_done && cand.0.c.iter().all(|c| c.is_finite()) {
                        let a_star = model_step_length(&pb, &cur.c, &offset, &cand.0.c);
                        if a_star < 0.95 {
                            // Keep the full step's buffers aside, so that falling back to it needs no
                            // second evaluation.
                            self.swap_trial_spare();
                            report.evaluations += 1;
                            let alt = self.trial(&pb, s, t, &lambda, a_star, moments, dir);
                            if alt.0.c.iter().all(|c| c.is_finite()) && alt.1 < cand.1 {
                                cand = alt;
                                alpha = a_star;
                            } else {
                                self.swap_trial_spare();
                            }
                        }
                    }
                    for halving in 0..=self.settings.max_halvings {
                        if halving > 0 {
                            report.evaluations += 1;
                            cand = self.trial(&pb, s, t, &lambda, alpha, moments, dir);
                        }
                        let (trial, n, s_new, t_new) = cand;
                        // Intermediate iterates may pass through states with more inverted tets (the
                        // linearisation does not know about inversion); only the returned state must not have
                        // more than the base step (checked below).
                        let admissible = trial.c.iter().all(|c| c.is_finite());
                        if admissible && (n < cur_norm || halving == self.settings.max_halvings) {
                            accepted = Some((trial, n, s_new, t_new));
                            break;
                        }
                        if halving < self.settings.max_halvings {
                            report.halvings += 1;
                        }
                        alpha *= 0.5;
                    }
                    report.iterations += 1;
                    let Some((trial, n, s_new, t_new)) = accepted else {
                        break; // no admissible step: stop, keep the best so far
                    };
                    // From q~ itself, the trial buffers get x/v's stale rows (overwritten by the next trial).
                    std::mem::swap(&mut self.x, &mut self.x_trial);
                    self.mirror = match self.mirror {
                        Mirror::Trial => Mirror::Iterate,
                        _ => Mirror::None,
                    };
                    std::mem::swap(&mut self.v, &mut self.v_trial);
                    std::mem::swap(&mut self.grad, &mut self.grad_trial);
                    // (`best_in_x` implies the iterate was in x/v, never q~: see `leave_base`.)
                    self.at_base = false;
                    cur = trial;
                    let previous_norm = std::mem::replace(&mut cur_norm, n);
                    s = s_new;
                    t = t_new;
                    if n < best_norm && cur.el.inverted <= base_inverted {
                        best_norm = n;
                        best_is_base = false;
                        best_eval = cur;
                        best_s = s;
                        best_t = t;
                        best_in_x = true;
                    } else if best_in_x {
                        // The best iterate was just swapped into the trial buffers: keep it.
                        std::mem::swap(&mut self.x_trial, &mut self.x_best);
                        std::mem::swap(&mut self.v_trial, &mut self.v_best);
                        best_in_x = false;
                    }
                    // The diagonal stiffness metric cannot move the body rigidly (its position directions are
                    // scaled per vertex): where the rows need a rigid correction that the translation before the
                    // iteration did not make, its iterates deform the body and stall. Under `Metric::Auto` the
                    // caller then tries the mass metric (`stalled`).
                    if stall_exit
                        && report.iterations >= 2
                        && n > 0.9 * previous_norm
                        && max_scaled(&pb, &cur.c) > tol
                    {
                        stalled = true;
                        break;
                    }
                }
                if !report.converged
                    && max_scaled(&pb, &cur.c) <= tol
                    && cur.el.inverted <= base_inverted
                {
                    report.converged = true;
                }
            }
            attempt += 1;
            if report.converged
                || stalled
                || !base_finite
                || attempt >= MAX_ATTEMPTS
                || cur.el.inverted <= base_inverted
            {
                break;
            }
            let (x, _) = current!(self);
            let frozen = freeze_newly_inverted(model, &self.x_base, x, &mut pb.metric_factor);
            if frozen > 0 {
                self.metric_source = None;
            }
            pb.refresh_rows();
            if frozen == 0 {
                break;
            }
            // Frozen positions are outside what the factorised metric can hold: the diagonal one restarts.
            if system.take().is_some() {
                report.system_metric = false;
                report.stiffness_metric = self.uses_stiffness_metric();
            }
            report.restarts += 1;
            report.frozen_vertices += frozen;
            if best_in_x {
                self.x_best.copy_from_slice(&self.x);
                self.v_best.copy_from_slice(&self.v);
                best_in_x = false;
            }
            self.at_base = true;
            self.mirror = Mirror::None;
            s = 0.0;
            t = 0.0;
            report.evaluations += 1;
            let (x, v) = current!(self);
            cur = evaluate(&pb, x, v, s, t, &mut self.scratch, &mut self.grad);
            grad_at_x = true;
            cur_norm = norm_scaled(&pb, &cur.c);
        }

        // Choose the result: the converged iterate, else the best iterate if it improved on q~, else q~.
        let mut fin = cur;
        // `grad` is at `x` (every evaluation into it is at the iterate it belongs to).
        self.grad_is_final = report.converged && grad_at_x;
        // Whether the result is q~ itself, handed back by a buffer swap: x_base/v_base then hold stale rows,
        // and the correction is 0 (s = t = 0 at q~).
        let mut base_returned = false;
        if report.converged {
            // The result's buffers become the state's (the old ones are overwritten next time).
            if self.at_base {
                std::mem::swap(&mut state.x, &mut self.x_base);
                std::mem::swap(&mut state.v, &mut self.v_base);
                base_returned = true;
            } else {
                std::mem::swap(&mut state.x, &mut self.x);
                std::mem::swap(&mut state.v, &mut self.v);
            }
        } else {
            report.fallback = true;
            if !best_is_base && best_norm < base_norm {
                let (xb, vb) = if best_in_x {
                    (&self.x, &self.v)
                } else {
                    (&self.x_best, &self.v_best)
                };
                state.x.clear();
                state.x.extend_from_slice(xb);
                state.v.clear();
                state.v.extend_from_slice(vb);
                fin = best_eval;
                s = best_s;
                t = best_t;
            } else {
                std::mem::swap(&mut state.x, &mut self.x_base);
                std::mem::swap(&mut state.v, &mut self.v_base);
                base_returned = true;
                report.evaluations += 1;
                fin = evaluate(
                    &pb,
                    &state.x,
                    &state.v,
                    0.0,
                    0.0,
                    &mut self.scratch,
                    &mut self.grad,
                );
                s = 0.0;
                t = 0.0;
                self.grad_is_final = true;
            }
        }

        // D-norm of the correction; optional impact bound (never hit by q~ itself: its correction is 0).
        report.correction = if base_returned {
            debug_assert!(s == 0.0 && t == 0.0, "q~ has s = t = 0");
            0.0
        } else if let Some(sys) = system.as_deref() {
            let dx = &mut self.system_rhs;
            for (d, (x, xb)) in dx.iter_mut().zip(state.x.iter().zip(&self.x_base)) {
                *d = sub(*x, *xb);
            }
            let h2 = h * h;
            let velocity: f64 = (0..m)
                .filter(|&i| !model.pinned[i])
                .map(|i| {
                    let dv = sub(state.v[i], self.v_base[i]);
                    model.masses[i] * h2 * dot(dv, dv)
                })
                .sum();
            (sys.norm_sq(model, h, dx) + velocity + pb.eps * (s * s + t * t)).sqrt()
        } else if let Some(sum) = fin.correction_sq {
            // The result is a trial point, whose evaluation summed its distance from q~ (the same task sums
            // in the same order as the pass below: the same bits).
            d_norm_from(&pb, s, t, sum)
        } else {
            d_norm(
                &pb,
                &state.x,
                &state.v,
                s,
                t,
                &self.x_base,
                &self.v_base,
                &mut self.scratch.norms,
            )
        };
        if let (Some(bound), false) = (self.settings.impact_bound, base_returned) {
            let cap = bound * mt.sqrt() * r;
            if report.correction > cap && report.correction.is_finite() {
                let beta = cap / report.correction;
                for i in 0..m {
                    for a in 0..3 {
                        let (xb, vb) = (self.x_base[i][a], self.v_base[i][a]);
                        state.x[i][a] = xb + beta * (state.x[i][a] - xb);
                        state.v[i][a] = vb + beta * (state.v[i][a] - vb);
                    }
                }
                s *= beta;
                t *= beta;
                report.bound_hit = true;
                report.correction = cap;
                self.grad_is_final = true; // both branches below evaluate at the returned state
                report.evaluations += 1;
                fin = evaluate(
                    &pb,
                    &state.x,
                    &state.v,
                    s,
                    t,
                    &mut self.scratch,
                    &mut self.grad,
                );
                if fin.el.inverted > base_inverted || !fin.c.iter().all(|c| c.is_finite()) {
                    // The scaled-back state inverts tets the base step did not: keep the base state.
                    state.x.copy_from_slice(&self.x_base);
                    state.v.copy_from_slice(&self.v_base);
                    s = 0.0;
                    t = 0.0;
                    report.correction = 0.0;
                    report.evaluations += 1;
                    fin = evaluate(
                        &pb,
                        &state.x,
                        &state.v,
                        s,
                        t,
                        &mut self.scratch,
                        &mut self.grad,
                    );
                }
                report.converged = max_scaled(&pb, &fin.c) <= tol;
                report.fallback |= !report.converged;
            }
        }
        // The copy of the trial positions is the state's exactly when the result is an accepted trial point
        // returned by the swap above, untouched by the impact bound.
        let returned_iterate = report.converged && !base_returned && !report.bound_hit;
        self.mirror = match self.mirror {
            Mirror::Iterate if returned_iterate => Mirror::Returned,
            _ => Mirror::None,
        };
        debug_assert!(
            self.mirror != Mirror::Returned || crate::math::same_bits(&self.x_mirror, &state.x),
            "the projection's copy of the returned positions is theirs bit for bit"
        );
        report.final_residual = max_scaled(&pb, &fin.c);
        report.s = s;
        report.t = t;
        let com = fin.com;
        // L about the actual centre of mass: L_C = L_Ct - (C - C_t) x P.
        let l_com = sub(
            fin.angular_momentum,
            cross(sub(com, targets.center_of_mass), fin.momentum),
        );
        let inv = Invariants {
            kinetic: fin.kinetic,
            elastic: fin.el.energy,
            gravitational: fin.gravitational,
            total: fin.kinetic + fin.el.energy + fin.gravitational,
            momentum: fin.momentum,
            angular_momentum: l_com,
            center_of_mass: com,
            min_j: fin.el.min_j,
            inverted: fin.el.inverted,
        };
        self.metric_factor = std::mem::take(&mut pb.metric_factor);
        self.metric_rows = std::mem::take(&mut pb.rows);
        self.expected_iterations = report.iterations;
        self.stalled = stalled;
        (report, inv)
    }
}

impl Projector {
    /// The elastic gradient at the positions the last [`Projector::project`] returned (J/m, shape (m, 3)), if
    /// it is at hand, as a buffer the caller may swap out (see `Integrator::offer_elastic_gradient`). A
    /// second call returns `None` until the next projection.
    pub fn take_final_gradient(&mut self) -> Option<&mut Vec<Vec3>> {
        std::mem::take(&mut self.grad_is_final).then_some(&mut self.grad)
    }

    /// [`Projector::take_final_gradient`], with a bit-for-bit copy of the positions the last projection returned
    /// (shape (m, 3), m) where it has one, as a buffer the caller may swap out (see
    /// `Integrator::offer_elastic_gradient_with_positions`). Taking it asks the next projection to write such a
    /// copy as it writes its trial points (the first projection after the caller starts taking it has none).
    pub fn take_final_hand_over(&mut self) -> Option<(&mut Vec<Vec3>, Option<&mut Vec<Vec3>>)> {
        if !std::mem::take(&mut self.grad_is_final) {
            return None;
        }
        // Below `SERIAL_ROWS` the caller's copy is a serial one, cheaper than the trial tasks' (1k box: 0.3 us
        // against 0.5-0.6 us more in the trial pass).
        self.mirror_wanted = self.grad.len() >= crate::exec::SERIAL_ROWS;
        let positions =
            (std::mem::take(&mut self.mirror) == Mirror::Returned).then_some(&mut self.x_mirror);
        Some((&mut self.grad, positions))
    }

    /// Offer the elastic energy summary `summary` and gradient `grad` (J/m, shape (m, 3)) of the model at the
    /// positions the next [`Projector::project`] starts from (the base step's result), as the base step
    /// evaluated them there ([`crate::integrators::Integrator::result_elastic_gradient`]): that call skips
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

    /// Give the current iterate buffers of its own (`x`/`v`, a copy of q~) if it is still q~ itself.
    fn leave_base(&mut self) {
        if std::mem::take(&mut self.at_base) {
            self.x.copy_from_slice(&self.x_base);
            self.v.copy_from_slice(&self.v_base);
            self.mirror = Mirror::None;
        }
    }

    /// Exchange the trial buffers with the spare ones (sized on first use).
    fn swap_trial_spare(&mut self) {
        let m = self.x_trial.len();
        for buf in [&mut self.x_spare, &mut self.v_spare, &mut self.grad_spare] {
            buf.resize(m, [0.0; 3]);
        }
        std::mem::swap(&mut self.x_trial, &mut self.x_spare);
        std::mem::swap(&mut self.v_trial, &mut self.v_spare);
        std::mem::swap(&mut self.grad_trial, &mut self.grad_spare);
        // The copy of the trial positions stays with neither pair (conservative: see `Mirror`).
        self.mirror = Mirror::None;
    }

    /// Evaluate the trial point `q - alpha D^-1 G lambda` (into the trial buffers): returns its evaluation,
    /// scaled residual norm and slack values. `system_dir`: the positions move along `system_dir` (the
    /// [`SystemMetric`]'s direction of the energy row).
    #[allow(clippy::too_many_arguments)]
    fn trial(
        &mut self,
        pb: &Problem,
        s: f64,
        t: f64,
        lambda: &[f64; ROWS],
        alpha: f64,
        moments: bool,
        system_dir: bool,
    ) -> (Eval, f64, f64, f64) {
        let (x, v) = current!(self);
        let mut step = Step::new(pb, x, v, &self.grad, lambda, alpha)
            .measured_from(&self.x_base, &self.v_base);
        if system_dir {
            step.dir = Some(&self.system_dir);
        }
        let (s_new, t_new) = step.slack(s, t);
        let mirror = self.mirror_rows.then_some(&mut self.x_mirror[..]);
        let e = evaluate_step(
            pb,
            &step,
            s_new,
            t_new,
            &mut self.scratch,
            (&mut self.x_trial, &mut self.v_trial, mirror),
            &mut self.grad_trial,
            moments,
        );
        if self.mirror_rows {
            self.mirror = Mirror::Trial;
        }
        let n = norm_scaled(pb, &e.c);
        (e, n, s_new, t_new)
    }
}

/// Step length minimising the scaled residual norm of the model `c(alpha) = (1 - alpha) (c0 - alpha d) +
/// alpha^2 e`, `e = c(1)` (the residual after the full step), over `alpha` in [1/64, 1]. `d` is the
/// second-order offset of [`solve_multipliers`] (zero but in the H and L rows): the multipliers solve
/// `S lambda = c0 + d`, so the linear prediction is `c0 - alpha (c0 + d)` and the known quadratic part
/// `alpha^2 d` (with `d = 0`, the model of the plain linearisation).
fn model_step_length(pb: &Problem, c0: &[f64; ROWS], d: &[f64; ROWS], e: &[f64; ROWS]) -> f64 {
    // Per row, c(alpha) = k0 + k1 alpha + k2 alpha^2 with k0 = c0, k1 = -(c0 + d), k2 = d + e (scaled), so the
    // squared norm is a quartic in alpha with the six sums of products of k0, k1, k2: computed once, not
    // ten rows (and ten divisions) at each of the search's 125 points (about 2 us less per iteration, serial,
    // on every mesh).
    let mut sums = [[0.0; 3]; 3];
    for i in (0..ROWS).filter(|&i| pb.active[i]) {
        let inv = 1.0 / pb.row_scale[i];
        let row = [c0[i] * inv, -(c0[i] + d[i]) * inv, (d[i] + e[i]) * inv];
        for p in 0..3 {
            for q in p..3 {
                sums[p][q] += row[p] * row[q];
            }
        }
    }
    let norm2 = |alpha: f64| -> f64 {
        let a2 = alpha * alpha;
        sums[0][0]
            + 2.0 * sums[0][1] * alpha
            + (sums[1][1] + 2.0 * sums[0][2]) * a2
            + 2.0 * sums[1][2] * a2 * alpha
            + sums[2][2] * a2 * a2
    };
    let mut best = (1.0, norm2(1.0));
    for k in 1..64 {
        let a = k as f64 / 64.0;
        let v = norm2(a);
        if v < best.1 {
            best = (a, v);
        }
    }
    // Refine around the best sample by golden-section search.
    let (mut lo, mut hi) = (
        (best.0 - 1.0 / 64.0).max(1.0 / 64.0),
        (best.0 + 1.0 / 64.0).min(1.0),
    );
    for _ in 0..30 {
        let m1 = lo + 0.382 * (hi - lo);
        let m2 = lo + 0.618 * (hi - lo);
        if norm2(m1) < norm2(m2) {
            hi = m2;
        } else {
            lo = m1;
        }
    }
    let a = 0.5 * (lo + hi);
    if norm2(a) < best.1 {
        a
    } else {
        best.0
    }
}

/// The rigid part of the free vertices' velocities: `V + omega x (x - c)`, carrying all of their P and L, with
/// `omega = I^-1 L` about their centre of mass `c`. The rest `u = v - rigid` has zero momenta.
struct RigidPart {
    /// `V`, m/s.
    velocity: Vec3,
    /// `omega`, rad/s.
    omega: Vec3,
    /// `c`, m.
    center: Vec3,
    /// The free mass, kg.
    mass: f64,
    /// `I^-1` about `c`, 1/(kg m^2) (`None` for a degenerate, e.g. collinear, body).
    inertia_inv: Option<Mat3>,
}

impl RigidPart {
    /// No rigid motion (every velocity is deformational).
    fn none() -> Self {
        Self {
            velocity: [0.0; 3],
            omega: [0.0; 3],
            center: [0.0; 3],
            mass: 0.0,
            inertia_inv: None,
        }
    }

    fn at(&self, x: Vec3) -> Vec3 {
        let w = cross(self.omega, sub(x, self.center));
        [
            self.velocity[0] + w[0],
            self.velocity[1] + w[1],
            self.velocity[2] + w[2],
        ]
    }
}

/// The [`RigidPart`] of the free vertices' velocities, from the moments an evaluation `e` summed for `S`.
fn rigid_velocity(pb: &Problem, e: &Eval) -> RigidPart {
    // From the free vertices' moments about the target centre of mass C_t that the evaluation summed for S
    // (no passes of its own: on the 1k box these were two serial passes of the warm start's four). With
    // r = x - C_t, the centre of mass is c = C_t + d, d = sum m r / M; about c, the inertia is
    // [tr(R) I - R] - M (|d|^2 I - d d^T) (R = sum m r r^T), and the angular momentum of v - V is
    // sum m r x v - d x P.
    debug_assert!(e.s_moments, "the moments for S");
    let mf = e.free_mass;
    if mf <= 0.0 {
        return RigidPart::none();
    }
    let d: Vec3 = std::array::from_fn(|a| e.free_r[a] / mf);
    let vc: Vec3 = std::array::from_fn(|a| e.free_p[a] / mf);
    let (tr, dd) = (e.rr[0][0] + e.rr[1][1] + e.rr[2][2], dot(d, d));
    let inertia: Mat3 = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            let delta = if a == b { 1.0 } else { 0.0 };
            (tr * delta - e.rr[a][b]) - mf * (dd * delta - d[a] * d[b])
        })
    });
    let l = sub(e.free_l, cross(d, e.free_p));
    let inertia_inv = crate::math::inverse(&inertia);
    let omega = inertia_inv.map_or([0.0; 3], |inv| mat_vec(&inv, l));
    let ct = pb.targets.center_of_mass;
    RigidPart {
        velocity: vc,
        omega,
        center: [ct[0] + d[0], ct[1] + d[1], ct[2] + d[2]],
        mass: mf,
        inertia_inv,
    }
}

fn mat_vec(m: &Mat3, v: Vec3) -> Vec3 {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

/// The rigid part whose momenta are the targets: `P = P_target` and `L_Ct = L_target` (the slack-free targets
/// of fepr-spec section 2), for the free centre of mass `c` of `now`: `V = P_target / m` and
/// `omega = I^-1 (L_target - m (c - C_t) x V)` (u adds nothing to either: it has zero momenta about `c`).
/// `None` where the momentum rows do not all hold the whole body (pins, rows off, slack free) or `I` is singular.
fn rigid_part_on_target(pb: &Problem, now: &RigidPart) -> Option<RigidPart> {
    let momenta_rows = pb.active[1..7].iter().all(|&a| a);
    let slack_free = pb.dp_star != [0.0; 3] || pb.dl_star != [0.0; 3];
    if pb.model.num_pinned() > 0 || !momenta_rows || slack_free || now.mass <= 0.0 {
        return None;
    }
    let inv = now.inertia_inv?;
    let tg = pb.targets;
    let velocity = [0, 1, 2].map(|a| tg.momentum[a] / now.mass);
    let offset = cross(sub(now.center, tg.center_of_mass), velocity);
    let l_spin = [0, 1, 2].map(|a| tg.angular_momentum[a] - now.mass * offset[a]);
    Some(RigidPart {
        velocity,
        omega: mat_vec(&inv, l_spin),
        center: now.center,
        mass: now.mass,
        inertia_inv: now.inertia_inv,
    })
}

/// Warm start (fepr-spec section 3, before the iteration): split the free velocities into a rigid part and a
/// deformational rest `u` (see [`rigid_velocity`]); put the rigid part on the momentum targets where the
/// momentum rows cover the whole body (see [`rigid_part_on_target`]), and scale `u` by the factor that then
/// meets the energy row. The kinetic energy splits into rigid + deformational parts (u carries no momenta), so
/// the result meets the energy row and, on the whole body, the momentum rows; otherwise P and L stay what they
/// were. With no momentum row active, nothing is rigid: every free velocity is scaled. The iteration starts
/// from there and only fixes what is left (the centre of mass, round-off): a dissipative base step that lost
/// most of H is then 0-2 iterations from the manifold instead of a stiff position correction away. False if
/// that energy cannot be reached.
fn warm_start_velocities(
    pb: &Problem,
    e: &Eval,
    x: &[Vec3],
    v: &mut [Vec3],
    parts: &mut Vec<[f64; 3]>,
) -> bool {
    let c_h = e.c[0];
    // Without momentum rows (the default with pins) nothing holds P or L, so no rigid part is kept: every free
    // velocity is scaled. A pinned body's swing is mostly a best-fit rigid rotation; scaling only the small
    // rest amplified it up to 17x per step on the PD cantilever demo, and its energy error grew to 0.23.
    let momenta_rows = pb.active[1..7].iter().any(|&a| a);
    let now = if momenta_rows {
        rigid_velocity(pb, e)
    } else {
        RigidPart::none()
    };
    let target = rigid_part_on_target(pb, &now);
    let next = target.as_ref().unwrap_or(&now);
    // The kinetic energies of u, of the rigid part now and of the next one, over fixed vertex tasks added in
    // task order (the same bits for any thread count).
    let (model, chunk) = (pb.model, vertex_chunk(v.len()));
    let vr: &[Vec3] = v;
    let map = |r: std::ops::Range<usize>| {
        let mut k = [0.0; 3];
        for i in r.filter(|&i| !model.pinned[i]) {
            let m = model.masses[i];
            let (r_now, r_next) = (now.at(x[i]), next.at(x[i]));
            let u = sub(vr[i], r_now);
            k[0] += 0.5 * m * dot(u, u);
            k[1] += 0.5 * m * dot(r_now, r_now);
            k[2] += 0.5 * m * dot(r_next, r_next);
        }
        k
    };
    let add3 = |a: [f64; 3], b: [f64; 3]| [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
    let [k_u, k_now, k_next] = reduce_chunks(vr.len(), chunk, parts, map, add3).unwrap_or([0.0; 3]);
    let k_target = k_u - c_h - (k_next - k_now);
    // A (nearly) rigid motion has no deformational energy to scale: a huge factor would only amplify round-off.
    // The rigid part still goes onto its momentum targets (a spinning body after Projective Dynamics lost
    // angular momentum and rotational energy together: putting its spin back restores both, and leaves the
    // iteration a small energy residual where the angular momentum rows, linearised about a fast rotation,
    // converged a few percent per iteration).
    let scalable = k_target > 0.0 && k_target.is_finite() && k_u > 1e-6 * k_target;
    if !scalable && target.is_none() {
        return false;
    }
    let beta = if scalable {
        (k_target / k_u).sqrt()
    } else {
        1.0
    };
    for_each_chunk_mut(v, chunk, |c, vs| {
        for (k, vi) in vs.iter_mut().enumerate() {
            let i = c * chunk + k;
            if !model.pinned[i] {
                let (r_now, r_next) = (now.at(x[i]), next.at(x[i]));
                *vi = [0, 1, 2].map(|a| r_next[a] + beta * (vi[a] - r_now[a]));
            }
        }
    });
    true
}

/// `diag(K_0)_i / m_i` per vertex (1/s^2): the trace / 3 of the diagonal 3x3 blocks of the element Hessians at
/// the rest shape (projected to PSD), summed over the incident elements, over the vertex mass. Rest-state so
/// that the metric is fixed for the run (no dependence on the current, possibly inverted, state).
fn rest_stiffness_ratio(model: &Model) -> Vec<f64> {
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

/// Whether the projection may translate the whole body (no vertex pinned, none held in contact).
fn rigid_translation_allowed(model: &Model, frozen_positions: &[u32]) -> bool {
    frozen_positions.is_empty() && model.num_pinned() == 0
}

/// Set `a_i = 0` (freeze the position) for every not yet frozen vertex of a tet that is inverted (`J <= 0`) at
/// `x` but upright at `x_base`. Returns the number of vertices newly frozen.
fn freeze_newly_inverted(model: &Model, x_base: &[Vec3], x: &[Vec3], factor: &mut [f64]) -> usize {
    let mut frozen = 0;
    for (e, t) in model.mesh.tets().iter().enumerate() {
        let j = crate::math::det(&deformation_gradient(model, x, e));
        if j <= 0.0 && crate::math::det(&deformation_gradient(model, x_base, e)) > 0.0 {
            for &v in t {
                if factor[v] != 0.0 {
                    factor[v] = 0.0;
                    frozen += 1;
                }
            }
        }
    }
    frozen
}

fn max_scaled(pb: &Problem, c: &[f64; ROWS]) -> f64 {
    (0..ROWS)
        .filter(|&i| pb.active[i])
        .map(|i| (c[i] / pb.row_scale[i]).abs())
        .fold(0.0, f64::max)
}

fn norm_scaled(pb: &Problem, c: &[f64; ROWS]) -> f64 {
    (0..ROWS)
        .filter(|&i| pb.active[i])
        .map(|i| (c[i] / pb.row_scale[i]).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// The energy row's position direction in the metric of `sys`: `rhs` gets the potential's gradient
/// `grad E_el - m g` (`grad`: the elastic gradient at the iterate; 0 on pinned vertices), `dir` gets `W^-1` of
/// it. Returns `rhs . dir` (S_HH's position part), summed over fixed vertex tasks in task order (the same bits
/// for any thread count), or `None` where `sys` has no factorisation for this model and step size.
fn system_direction(
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

/// `|q - q_base|_D` with `D = diag(W, h^2 M, eps, eps)`, `W = diag(m_i / a_i)`.
#[allow(clippy::too_many_arguments)]
fn d_norm(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    xb: &[Vec3],
    vb: &[Vec3],
    parts: &mut Vec<f64>,
) -> f64 {
    d_norm_from(pb, s, t, d_norm_vertex_sum(pb, x, v, xb, vb, parts))
}

/// The vertices' part of `|q - q_base|_D^2`.
fn d_norm_vertex_sum(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    xb: &[Vec3],
    vb: &[Vec3],
    parts: &mut Vec<f64>,
) -> f64 {
    // Over fixed vertex tasks, each in lanes, added in task order (the same bits for any thread count, and
    // those of the trial pass's sums: `trial_lanes`).
    let map = |r: std::ops::Range<usize>| {
        let base = tl::BaseRows {
            x: &xb[r.clone()],
            v: &vb[r.clone()],
            h2: pb.h * pb.h,
        };
        let (mass, factor) = (&pb.model.masses[r.clone()], &pb.metric_factor[r.clone()]);
        ml::lane_sum(&tl::correction_lanes(
            &x[r.clone()],
            &v[r],
            base,
            mass,
            factor,
        ))
    };
    let sum = reduce_chunks(x.len(), vertex_chunk(x.len()), parts, map, |a, b| a + b);
    sum.unwrap_or(0.0)
}

/// `|q - q_base|_D` from the vertices' part of its square (the task sums of [`tl::correction_lanes`] added
/// in task order) and the slack values.
fn d_norm_from(pb: &Problem, s: f64, t: f64, vertex_sum: f64) -> f64 {
    (pb.eps * (s * s + t * t) + vertex_sum).sqrt()
}

/// Evaluate the constraints, the elastic gradient (into `grad`; the potential's is `grad E_el - m g`, formed
/// where it is used) and the mass moments that `S` needs: the elastic pass's chunks, then one parallel pass
/// over fixed tasks of vertices that sums each vertex's gradient and the task's moments while they are in
/// cache (combined in task order: the same bits for any thread count).
fn evaluate(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    sc: &mut EvalScratch,
    grad: &mut [Vec3],
) -> Eval {
    evaluate_sums::<true>(pb, x, v, s, t, sc, grad)
}

/// [`evaluate`], with the moments for `S` only if `S` (`Eval::s_moments`).
#[allow(clippy::too_many_arguments)]
fn evaluate_sums<const S: bool>(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    sc: &mut EvalScratch,
    grad: &mut [Vec3],
) -> Eval {
    let el = elastic_gradient_chunks(pb.model, x, &mut sc.ws);
    let ws = &sc.ws;
    let chunk = vertex_chunk(grad.len());
    let parts = task_parts(&mut sc.parts, grad.len());
    for_each_chunk_mut2(grad, chunk, parts, 1, |c, g, part| {
        let first = c * chunk;
        for (k, gk) in g.iter_mut().enumerate() {
            *gk = ws.gradient_at(pb.model, first + k);
        }
        let r = first..first + g.len();
        part[0] = vertex_moments::<S>(pb, first, &x[r.clone()], &v[r], Some(g));
    });
    finish(pb, s, t, el, sum_parts(parts))
}

/// [`evaluate`] at the trial point of `step` (`q - alpha D^-1 G lambda`, written to `x_out`, `v_out`, its
/// elastic gradient to `g_out`), with the slack values `(s, t)` of that point; with the moments for `S` only
/// if `moments` (`Eval::s_moments`). The trial point is written by a pass of its own: computing each position where the
/// elastic chunks gather it (no pass, 1.5 times the work) measured slower on bunny2, its arrays read in
/// the user's vertex order. Without the moments, that pass also sums the constraints and the D-norm distance
/// as it writes each task's rows (a symplectic Euler step's only trial point): 1.3-2% off a two-thread
/// projection of 2 iterations (bunny, elephant, armadillo; `eg_loop proj`, alternated).
#[allow(clippy::too_many_arguments)]
fn evaluate_step(
    pb: &Problem,
    step: &Step,
    s: f64,
    t: f64,
    sc: &mut EvalScratch,
    (x_out, v_out, mirror): (&mut [Vec3], &mut [Vec3], Option<&mut [Vec3]>),
    g_out: &mut [Vec3],
    moments: bool,
) -> Eval {
    let chunk = vertex_chunk(x_out.len());
    if moments {
        // The D-norm distance is summed as the rows are written (the moment pass after the chunks sums the
        // rest).
        let norms = &mut sc.norms;
        norms.resize(x_out.len().div_ceil(chunk), 0.0);
        write_tasks(x_out, v_out, mirror, norms, chunk, |c, xo, vo, norm| {
            let sums = step.write(c * chunk, xo, vo, false);
            norm[0] = sums.correction.map_or(0.0, |lanes| ml::lane_sum(&lanes));
        });
        let correction_sq = step.base.map(|_| sum_in_order(&sc.norms));
        let mut e = evaluate_sums::<true>(pb, x_out, v_out, s, t, sc, g_out);
        e.correction_sq = correction_sq;
        return e;
    }
    // Without the moments for `S`, every vertex sum of the trial point (the constraints' and its D-norm
    // distance from q~) needs its rows alone: each task sums them as it writes them, while they are in
    // registers, and the pass after the elastic chunks only gathers the gradient. The same lanes and the same
    // tasks as the moment pass's sums, so the same bits (`the_trial_pass_sums_what_an_evaluation_sums`).
    let parts = task_parts(&mut sc.parts, x_out.len());
    write_tasks(
        x_out,
        v_out,
        mirror,
        &mut parts[..],
        chunk,
        |c, xo, vo, part| {
            let sums = step.write(c * chunk, xo, vo, true);
            let constraints = sums.constraints.expect("asked for");
            part[0] = Eval {
                correction_sq: sums.correction.map(|lanes| ml::lane_sum(&lanes)),
                ..constraint_sums(&constraints)
            };
        },
    );
    let el = elastic_gradient_chunks(pb.model, x_out, &mut sc.ws);
    sc.ws.gradient_into(pb.model, g_out);
    finish(pb, s, t, el, sum_parts(parts))
}

/// `write(c, x_rows, v_rows, part)` over the vertex tasks of `chunk` rows (task `c`'s rows of `x_out` and
/// `v_out`, and `parts[c]`), in parallel; with `mirror` (as long as `x_out`), each task then copies the
/// positions it wrote into the mirror's rows, while they are in L1 (see [`Mirror`]).
fn write_tasks<P: Send>(
    x_out: &mut [Vec3],
    v_out: &mut [Vec3],
    mirror: Option<&mut [Vec3]>,
    parts: &mut [P],
    chunk: usize,
    write: impl Fn(usize, &mut [Vec3], &mut [Vec3], &mut [P]) + Sync,
) {
    match mirror {
        None => for_each_chunk_mut3(x_out, chunk, v_out, chunk, parts, 1, write),
        Some(mirror) => for_each_chunk_mut4(
            x_out,
            chunk,
            v_out,
            chunk,
            mirror,
            chunk,
            parts,
            1,
            |c, xo, vo, mo, part| {
                write(c, xo, vo, part);
                mo.copy_from_slice(xo);
            },
        ),
    }
}

/// Per-task sums added in task order.
fn sum_in_order(parts: &[f64]) -> f64 {
    parts.iter().copied().reduce(|a, b| a + b).unwrap_or(0.0)
}

/// [`evaluate`] without the elastic gradient: the same constraint values, energies and momenta; the gradient
/// moments of `S` are left at zero (not to be solved with).
fn evaluate_energy(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    parts: &mut Vec<Eval>,
) -> Eval {
    let el = crate::elasticity::elastic_energy(pb.model, x);
    evaluate_with_elastic(pb, x, v, s, t, el, None, parts)
}

/// [`evaluate`] with the elastic energy summary `el` (and gradient `grad`) at `x` already at hand (after a
/// change of the velocities alone; or the energy alone): the same result, without the elastic pass. Without
/// `grad`, the moments that need it are left at zero (not to be solved with).
#[allow(clippy::too_many_arguments)]
fn evaluate_with_elastic(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    el: ElasticSummary,
    grad: Option<&[Vec3]>,
    parts: &mut Vec<Eval>,
) -> Eval {
    let chunk = vertex_chunk(x.len());
    let parts = task_parts(parts, x.len());
    for_each_mut(parts, |c, part| {
        let first = c * chunk;
        let r = first..(first + chunk).min(x.len());
        let g = grad.map(|g| &g[r.clone()]);
        *part = vertex_moments::<true>(pb, first, &x[r.clone()], &v[r], g);
    });
    finish(pb, s, t, el, sum_parts(parts))
}

/// `parts` resized to one entry per vertex task of `m` vertices (no allocation once grown).
fn task_parts(parts: &mut Vec<Eval>, m: usize) -> &mut [Eval] {
    parts.resize(m.div_ceil(vertex_chunk(m)), Eval::default());
    &mut parts[..]
}

/// The vertex tasks' sums, added in task order.
fn sum_parts(parts: &[Eval]) -> Eval {
    match parts.split_first() {
        None => Eval::default(),
        Some((first, rest)) => rest.iter().fold(*first, |mut a, b| {
            a.add(b);
            a
        }),
    }
}

/// The constraint values of the vertex sums `e` with the elastic summary `el`, at slack values `(s, t)`.
fn finish(pb: &Problem, s: f64, t: f64, el: ElasticSummary, mut e: Eval) -> Eval {
    let mt = pb.model.total_mass;
    e.el = el;
    e.com = [e.mass_x[0] / mt, e.mass_x[1] / mt, e.mass_x[2] / mt];
    let tg = pb.targets;
    e.c[0] = e.kinetic + el.energy + e.gravitational - tg.energy;
    for a in 0..3 {
        e.c[1 + a] = e.momentum[a] - (tg.momentum[a] + s * pb.dp_star[a]);
        e.c[4 + a] = e.angular_momentum[a] - (tg.angular_momentum[a] + t * pb.dl_star[a]);
        e.c[7 + a] = e.com[a] - tg.center_of_mass[a];
    }
    e
}

/// Vertices per parallel task of the moment pass, the trial step and the D-norm: the length of every vertex
/// pass ([`crate::exec::vertex_task_len`]), a multiple of the moment lanes.
fn vertex_chunk(m: usize) -> usize {
    const { assert!(VL == 4, "vertex_task_len is a multiple of 4") };
    crate::exec::vertex_task_len(m)
}

/// The sums of [`Eval`] over the vertices `first..first + x.len()` (`x`, `v`, `grad`: their rows; `c`, `el`
/// and `com` are left at zero), in the fixed lane order of [`crate::projection`] (the same bits for any
/// thread count). With `S`, the constraints' sums and the moments for `S`; the second-order ones only with
/// a gradient. Without a gradient the moments take the elastic gradient as zero: the velocity moments (the
/// warm start's) are exact, the others are not to be solved with (an iteration evaluates the gradient first).
/// Without `S`, the constraints' sums alone.
fn vertex_moments<const S: bool>(
    pb: &Problem,
    first: usize,
    x: &[Vec3],
    v: &[Vec3],
    grad: Option<&[Vec3]>,
) -> Eval {
    let model = pb.model;
    let (g, ct) = (model.gravity, pb.targets.center_of_mass);
    let r = first..first + x.len();
    let mass = &model.masses[r.clone()];
    if !S {
        return constraint_sums(&ml::constraint_lanes(x, v, mass, g, ct));
    }
    let rows = ml::Rows {
        x,
        v,
        grad,
        mass,
        free_mass: &pb.rows.free_mass[r.clone()],
        free_factor: &pb.rows.free_factor[r],
        unit: pb.rows.unit,
    };
    // The second-order moments only with a gradient (a solve needs them; the energy-only first evaluation
    // and the warm start, which mostly end the projection after Projective Dynamics, do not).
    let (acc, second) = match grad {
        Some(_) => ml::moment_and_second_order_lanes(&rows, g, ct),
        None => (
            ml::moment_lanes(&rows, g, ct),
            [[0.0; VL]; ml::SECOND_ORDER_SUMS],
        ),
    };
    let sum = |k: usize| ml::lane_sum(&acc[k]);
    let vec3 = |k: usize| [sum(k), sum(k + 1), sum(k + 2)];
    let sym = |k: usize| {
        let mut s = [[0.0; 3]; 3];
        for (j, &(a, b)) in UPPER.iter().enumerate() {
            s[a][b] = sum(k + j);
            s[b][a] = s[a][b];
        }
        s
    };
    let sum2 = |k: usize| ml::lane_sum(&second[k]);
    Eval {
        s_moments: true,
        kinetic: sum(q::KINETIC),
        gravitational: sum(q::GRAVITATIONAL),
        momentum: vec3(q::MOMENTUM),
        angular_momentum: vec3(q::ANGULAR),
        mass_x: vec3(q::MASS_X),
        free_mass: sum(q::FREE_MASS),
        a_free_mass: sum(q::A_FREE_MASS),
        grad_sq_over_w: sum(q::GRAD_SQ_OVER_W),
        tr_vv: sum(q::TR_VV),
        a_grad_sum: vec3(q::A_GRAD_SUM),
        a_grad_cross_v: vec3(q::A_GRAD_CROSS_V),
        free_p: vec3(q::FREE_P),
        a_free_p: vec3(q::A_FREE_P),
        free_l: vec3(q::FREE_L),
        free_r: vec3(q::FREE_R),
        a_vv: sym(q::A_VV),
        rr: sym(q::RR),
        a_grad_r: std::array::from_fn(|c| [sum2(3 * c), sum2(3 * c + 1), sum2(3 * c + 2)]),
        a_r_cross_v: [sum2(9), sum2(10), sum2(11)],
        a_mass_r: [sum2(12), sum2(13), sum2(14)],
        ..Eval::default()
    }
}

/// The constraints' sums of a task from their lanes ([`ml::constraint_lanes`]), without the moments for `S`.
fn constraint_sums(acc: &[ml::Lane; ml::CONSTRAINT_SUMS]) -> Eval {
    let sum = |k: usize| ml::lane_sum(&acc[k]);
    let vec3 = |k: usize| [sum(k), sum(k + 1), sum(k + 2)];
    Eval {
        s_moments: false,
        kinetic: sum(q::KINETIC),
        gravitational: sum(q::GRAVITATIONAL),
        momentum: vec3(q::MOMENTUM),
        angular_momentum: vec3(q::ANGULAR),
        mass_x: vec3(q::MASS_X),
        ..Eval::default()
    }
}

/// The full 10x10 `S = G^T D^-1 G` from the moments (fepr-spec section 3; derivation in docs/fepr.md) and its
/// velocity block `sv` ([`velocity_block`], which the solve also needs for the second-order terms).
fn small_matrix(pb: &Problem, e: &Eval, sv: [[f64; ROWS]; ROWS]) -> [[f64; ROWS]; ROWS] {
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
fn velocity_block(pb: &Problem, e: &Eval) -> [[f64; ROWS]; ROWS] {
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
struct Multipliers {
    lambda: [f64; ROWS],
    /// The small system needed the least-squares fallback.
    least_squares: bool,
    /// The second-order offsets `d` (zero but in the H and L rows): the multipliers solve `S lambda = c + d`,
    /// with `d` the constraints' second-order terms along the full step (see [`solve_multipliers`]).
    offset: [f64; ROWS],
}

/// The kinetic energy's second-order term along the step of multipliers `u` (J): with the step's velocity
/// change `dv_i = -(h^2 m_i)^-1 dc/dv_i^T u`, `sum m_i |dv_i|^2 / 2 = u^T S_v u / (2 h^2)` (`sv`: the velocity
/// block of `S`, [`velocity_block`], upper triangle; rows H, P and L). Bilinear in `u` and `w`: the term is
/// `kinetic_second_order(sv, h, u, u)`.
fn kinetic_second_order(sv: &[[f64; ROWS]; ROWS], h: f64, u: &[f64; ROWS], w: &[f64; ROWS]) -> f64 {
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
fn angular_second_order(pb: &Problem, e: &Eval, lambda: &[f64; ROWS]) -> Vec3 {
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
/// (the stiffness metric moves stiff modes little after implicit steps; explicit steps are small): measured,
/// the full step's H residual equalled the kinetic term to two or three digits on the 1k box and bunny2
/// (symplectic Euler) and the bunny (backward Euler). So the multipliers solve `S lambda = c + d(lambda)`
/// with `d` those terms (H: kinetic; L: all), and the step lands on the manifold up to the elastic
/// curvature: one iteration where the plain linearisation (fepr-spec section 3) took two after symplectic
/// Euler, and two where it took four or five, with overshoots, after backward Euler.
///
/// How: `lambda = lambda_1 + tau z` with `S lambda_1 = c + d_L`, `S z = e_H`; `tau` is the root of the scalar
/// quadratic `tau = Q(lambda_1 + tau z)` (`Q` the kinetic term) that goes to `Q(lambda_1)` as the curvature
/// vanishes; `d_L` by fixed-point rounds (small: a product of two multipliers over `h^2`). Without a real
/// root (an energy excess beyond what the kinetic curvature gives back), rounds that do not settle, or after
/// the least-squares fallback, `d = 0`: the plain linearisation.
fn solve_multipliers(pb: &Problem, e: &Eval, delta: f64) -> Multipliers {
    let sv = velocity_block(pb, e);
    let full = small_matrix(pb, e, sv);
    // On the stack (no allocation per iteration): at most ROWS active rows.
    let mut idx = [0usize; ROWS];
    let mut n = 0;
    for i in (0..ROWS).filter(|&i| pb.active[i]) {
        idx[n] = i;
        n += 1;
    }
    let idx = &idx[..n];
    // Scaled by reciprocals (ten divisions, not a hundred: the solve is serial, between parallel passes).
    let inv_scale: [f64; ROWS] = std::array::from_fn(|i| 1.0 / pb.row_scale[i]);
    let (mut a, mut b) = ([0.0; ROWS * ROWS], [0.0; ROWS]);
    for (p, &i) in idx.iter().enumerate() {
        b[p] = e.c[i] * inv_scale[i];
        for (q, &j) in idx.iter().enumerate() {
            a[p * n + q] = full[i][j] * inv_scale[i] * inv_scale[j];
        }
    }
    let (mut factor, mut y) = ([0.0; ROWS * ROWS], [0.0; ROWS]);
    let least_squares =
        solve_symmetric_psd_into(&a[..n * n], &b[..n], n, delta, &mut factor, &mut y);
    // One step of iterative refinement against the unshifted matrix, kept where it lowers the residual: the
    // regularisation's shift (for singular S, fepr-spec section 6, pitfall 2) otherwise leaves an error of
    // about delta times S's condition number in the multipliers, which a step meant to end the projection
    // cannot afford (a spinning cube's L rows missed their tolerance by 3x after one step without it).
    let refine = |y: &mut [f64; ROWS], rhs: &[f64; ROWS]| {
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
        cholesky_substitute(&factor[..n * n], &mut dy[..n], n);
        let candidate: [f64; ROWS] = std::array::from_fn(|p| y[p] + dy[p]);
        if residual(&candidate).1 < before {
            *y = candidate;
        }
    };
    if !least_squares {
        refine(&mut y, &b);
    }
    let unscale = |y: &[f64; ROWS]| -> [f64; ROWS] {
        let mut out = [0.0; ROWS];
        for (p, &i) in idx.iter().enumerate() {
            out[i] = y[p] * inv_scale[i];
        }
        out
    };
    let plain = unscale(&y);
    let mut result = Multipliers {
        lambda: plain,
        least_squares,
        offset: [0.0; ROWS],
    };
    if least_squares || !pb.active[0] || e.c[0].abs() > SECOND_ORDER_REACH * pb.row_scale[0] {
        return result;
    }
    // S^-1 of a right-hand side with the factor above (unscaled in, unscaled out).
    let solve = |rhs: &[f64; ROWS]| -> [f64; ROWS] {
        let mut y = [0.0; ROWS];
        for (p, &i) in idx.iter().enumerate() {
            y[p] = rhs[i] * inv_scale[i];
        }
        let rhs = y;
        cholesky_substitute(&factor[..n * n], &mut y[..n], n);
        refine(&mut y, &rhs);
        unscale(&y)
    };
    let mut unit_h = [0.0; ROWS];
    unit_h[0] = 1.0;
    let z = solve(&unit_h);
    let h = pb.h;
    let l_rows = (4..7).all(|i| pb.active[i]);
    let mut d_l = [0.0; 3];
    for round in 0..SECOND_ORDER_ROUNDS {
        let mut lambda_1 = plain;
        if l_rows && round > 0 {
            let mut rhs = [0.0; ROWS];
            rhs[4..7].copy_from_slice(&d_l);
            let shift = solve(&rhs);
            for i in 0..ROWS {
                lambda_1[i] += shift[i];
            }
        }
        // tau = A + 2 B tau + C tau^2, the root near A: tau = 2 A / (p + sqrt(p^2 - 4 A C)), p = 1 - 2 B.
        let qa = kinetic_second_order(&sv, h, &lambda_1, &lambda_1);
        let qb = kinetic_second_order(&sv, h, &lambda_1, &z);
        let qc = kinetic_second_order(&sv, h, &z, &z);
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
const SECOND_ORDER_ROUNDS: usize = 8;

/// The largest scaled energy residual at which [`solve_multipliers`] adds the second-order terms. Beyond it the
/// base step has blown up (symplectic Euler past its stable step: the seed's demo 3 at dt = 1/30 s has steps
/// with 10^4 times the energy), the elastic energy's curvature, which the terms leave out, dominates, and the
/// plain linearisation proved the more robust: over 41 starts of that demo, with the terms at any residual 4
/// runs ran away and 30 steps ended unconverged, with this limit 3 and 12, without the terms at all 10 and 42.
const SECOND_ORDER_REACH: f64 = 1.0;

/// The trial point `q_trial = q - alpha D^-1 G lambda` of one iteration, vertex by vertex (every vertex's
/// update is its own: no sums), so that it can be computed wherever it is needed ([`evaluate_step`]).
struct Step<'a> {
    model: &'a Model,
    metric_factor: &'a [f64],
    a_over_m: &'a [f64],
    /// The metric rows are unit ([`MetricRows::unit`]).
    unit: bool,
    x: &'a [Vec3],
    v: &'a [Vec3],
    /// The elastic gradient at `x`.
    grad: &'a [Vec3],
    /// The multipliers, the step length and the constants of the rows' update.
    coefficients: tl::StepCoefficients,
    h2: f64,
    dp_star: Vec3,
    dl_star: Vec3,
    eps: f64,
    /// The base state `(x_base, v_base)` whose D-norm distance the trial evaluation sums (`Eval::correction_sq`).
    base: Option<(&'a [Vec3], &'a [Vec3])>,
    /// With a [`SystemMetric`] (the energy the only row): `W^-1 grad U`, the positions' direction.
    dir: Option<&'a [Vec3]>,
}

impl<'a> Step<'a> {
    fn new(
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
    fn measured_from(self, x_base: &'a [Vec3], v_base: &'a [Vec3]) -> Self {
        Self {
            base: Some((x_base, v_base)),
            ..self
        }
    }

    /// The trial positions (m) and velocities (m/s) of the vertices `first..first + x_out.len()`, into
    /// `x_out` and `v_out` (a pinned vertex keeps its own), and their sums (`trial_lanes`): the constraints'
    /// if `constraints`, the D-norm distance from the base state if the step is measured from one.
    fn write(
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
    fn write_rows_along(&self, dir: &[Vec3], first: usize, x_out: &mut [Vec3], v_out: &mut [Vec3]) {
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
    fn slack(&self, s: f64, t: f64) -> (f64, f64) {
        let c = &self.coefficients;
        (
            s + c.alpha * dot(c.lp, self.dp_star) / self.eps,
            t + c.alpha * dot(c.ll, self.dl_star) / self.eps,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::{Material, NeoHookean};
    use crate::mesh::{tests::cube, MassSpec, TetMesh};
    use crate::model::ModelBuilder;

    /// The test cube with unequal vertex masses (1 + 0.1 i kg), Neo-Hookean with Young's modulus `youngs` (Pa)
    /// and Poisson ratio 0.3, under `gravity` (m/s^2).
    fn cube_model(youngs: f64, gravity: Vec3) -> Model {
        let (v, t) = cube();
        let (mesh, _) = TetMesh::new(v, &t).unwrap();
        let masses: Vec<f64> = (0..mesh.num_vertices())
            .map(|i| 1.0 + 0.1 * i as f64)
            .collect();
        ModelBuilder::new(
            mesh,
            Material::NeoHookean(NeoHookean::new(youngs, 0.3).unwrap()),
        )
        .mass(MassSpec::PerVertex(masses))
        .gravity(gravity)
        .build()
        .unwrap()
    }

    /// `model`'s rest shape stretched 10% about a point and moving, with targets 10% below its energy and at
    /// its momenta: far enough from the manifold for a few iterations.
    fn stretched_and_moving(model: &Model) -> (State, Targets) {
        let x: Vec<Vec3> = (model.mesh.vertices().iter())
            .map(|p| [0, 1, 2].map(|a| 0.5 + 1.1 * (p[a] - 0.5)))
            .collect();
        let v: Vec<Vec3> = (0..x.len())
            .map(|i| [0.1 * (i as f64).sin(), -0.05, 0.02 * (i as f64).cos()])
            .collect();
        let state = State { x, v, time: 0.0 };
        let inv = crate::invariants::measure(model, &state);
        let targets = Targets {
            energy: 0.9 * inv.total,
            momentum: inv.momentum,
            angular_momentum: inv.angular_momentum,
            center_of_mass: inv.center_of_mass,
            energy_scale: inv.total.abs(),
            uncertain_impulses: false,
        };
        (state, targets)
    }

    /// The closed-form `S` must equal `G^T D^-1 G` assembled from explicit constraint gradients, and the
    /// explicit gradients must match finite differences of `c(q)`.
    #[test]
    fn small_matrix_matches_explicit_gradients_and_finite_differences() {
        let mut model = cube_model(1e3, [0.3, -0.2, -9.81]);
        let m = model.num_vertices();
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
        let v: Vec<Vec3> = (0..m)
            .map(|i| {
                let k = i as f64;
                [0.3 * k.cos(), -0.2 + 0.1 * k.sin(), 0.05 * k]
            })
            .collect();
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
            let (s0, t0) = (0.1, -0.2);
            let mut grad = vec![[0.0; 3]; m];
            let mut sc = EvalScratch::default();
            let e = evaluate(&pb, &x, &v, s0, t0, &mut sc, &mut grad);
            let s_closed = small_matrix(&pb, &e, velocity_block(&pb, &e));
            // Explicit gradients by finite differences of c(q), q = (x, v, s, t).
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
                evaluate(&pb, &xs, &vs, q[6 * m], q[6 * m + 1], &mut w, &mut g).c
            };
            let mut q0 = vec![0.0; n];
            for i in 0..m {
                for a in 0..3 {
                    q0[3 * i + a] = x[i][a];
                    q0[3 * m + 3 * i + a] = v[i][a];
                }
            }
            q0[6 * m] = s0;
            q0[6 * m + 1] = t0;
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
            // D^-1, with pinned degrees of freedom excluded.
            let dinv = |k: usize| -> f64 {
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
                    1.0 / (h * h * model.masses[i])
                } else {
                    factors[i] / model.masses[i]
                }
            };
            for a in 0..ROWS {
                for b in 0..ROWS {
                    let explicit: f64 = (0..n).map(|k| g[k][a] * dinv(k) * g[k][b]).sum();
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
            let (mut xo, mut vo, mut go) =
                (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
            let (s1, t1) = step.slack(s0, t0);
            let trial = evaluate_step(
                &pb,
                &step,
                s1,
                t1,
                &mut sc,
                (&mut xo, &mut vo, None),
                &mut go,
                false,
            );
            // The trial evaluation is the plain evaluation at the trial point, bit for bit; its moments for S,
            // summed afterwards, too.
            let mut g1 = vec![[0.0; 3]; m];
            let plain = evaluate(&pb, &xo, &vo, s1, t1, &mut EvalScratch::default(), &mut g1);
            let bits = |e: &Eval| (e.c.map(f64::to_bits), e.el.energy.to_bits());
            assert_eq!(bits(&trial), bits(&plain));
            assert_eq!(go, g1);
            assert!(plain.s_moments && !trial.s_moments);
            let later =
                evaluate_with_elastic(&pb, &xo, &vo, s1, t1, trial.el, Some(&go), &mut sc.parts);
            assert_eq!(bits(&later), bits(&plain));
            let s_bits = |e: &Eval| {
                small_matrix(&pb, e, velocity_block(&pb, e)).map(|row| row.map(f64::to_bits))
            };
            assert_eq!(s_bits(&later), s_bits(&plain));
            // Summed by the trial pass itself (where another iteration is expected): the same bits again.
            let (mut xo2, mut vo2, mut go2) =
                (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
            let with = evaluate_step(
                &pb,
                &step,
                s1,
                t1,
                &mut sc,
                (&mut xo2, &mut vo2, None),
                &mut go2,
                true,
            );
            assert!(with.s_moments);
            assert_eq!(bits(&with), bits(&plain));
            assert_eq!(s_bits(&with), s_bits(&plain));
            let second = |e: &Eval| angular_second_order(&pb, e, &lambda).map(f64::to_bits);
            assert_eq!(second(&with), second(&plain));
            for k in 0..n {
                let dq: f64 = dinv(k) * (0..ROWS).map(|r| g[k][r] * lambda[r]).sum::<f64>();
                let got = if k < 3 * m {
                    q0[k] - xo[k / 3][k % 3]
                } else if k < 6 * m {
                    q0[k] - vo[(k - 3 * m) / 3][(k - 3 * m) % 3]
                } else if k == 6 * m {
                    s0 - s1
                } else {
                    t0 - t1
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
                    let explicit: f64 = (3 * m..6 * m).map(|k| g[k][a] * dinv(k) * g[k][b]).sum();
                    assert!(
                        (explicit - sv[a][b]).abs() <= 1e-5 * (1.0 + explicit.abs()),
                        "pinned {pinned}: S_v[{a}][{b}] {} vs explicit {explicit}",
                        sv[a][b]
                    );
                }
            }
            // The second-order terms of K and L along the step: both are exactly quadratic in alpha, so
            // (f(1) + f(-1)) / 2 - f(0) is their alpha^2 coefficient.
            let at = |alpha: f64| {
                let step = Step::new(&pb, &x, &v, &grad, &lambda, alpha);
                let (mut xo, mut vo) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
                step.write(0, &mut xo, &mut vo, false);
                let mut g = vec![[0.0; 3]; m];
                evaluate(&pb, &xo, &vo, s0, t0, &mut EvalScratch::default(), &mut g)
            };
            let (ep, em) = (at(1.0), at(-1.0));
            let k2 = 0.5 * (ep.kinetic + em.kinetic) - e.kinetic;
            let k2_closed = kinetic_second_order(&sv, h, &lambda, &lambda);
            assert!(
                (k2 - k2_closed).abs() <= 1e-9 * k2.abs().max(e.kinetic),
                "pinned {pinned}: kinetic second order {k2_closed} vs {k2}"
            );
            let l2_closed = angular_second_order(&pb, &e, &lambda);
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
    }

    /// The trial evaluation sums its point's D-norm distance from the base state in the same task order as
    /// `d_norm`'s own pass: the projection's reported correction (taken from it when the result is a trial
    /// point) keeps its bits, for the mass and the stiffness metric and with a pinned vertex.
    #[test]
    fn the_correction_summed_by_the_trial_pass_is_the_d_norm_pass_bit_for_bit() {
        for (implicit, pin) in [(false, false), (true, false), (false, true)] {
            let mut model = cube_model(1e4, [0.0, 0.0, -9.81]);
            model.pinned[2] = pin;
            let (state, targets) = stretched_and_moving(&model);
            let h = 0.005;
            let mut proj = Projector::new(ProjectionSettings::default()).unwrap();
            proj.set_implicit_base(implicit);
            let mut out = state.clone();
            let (report, _) = proj.project(&model, &mut out, h, &targets);
            assert!(report.converged && report.iterations >= 1, "{report:?}");
            assert!(
                !report.warm_start,
                "the result is a trial point: {report:?}"
            );
            let eps = proj.settings.c_eps * model.total_mass * model.length_scale.powi(2);
            let (factors, rows) = (proj.metric_factor.clone(), MetricRows::default());
            let pb = Problem::new(&model, h, &targets, factors, rows, [true; ROWS], eps)
                .with_fresh_rows();
            let pass = d_norm(
                &pb,
                &out.x,
                &out.v,
                report.s,
                report.t,
                &proj.x_base,
                &proj.v_base,
                &mut Vec::new(),
            );
            assert!(report.correction > 0.0);
            assert_eq!(report.correction.to_bits(), pass.to_bits(), "{report:?}");

            // The trial evaluation's sum itself (so that the gate above cannot pass by both sides taking the
            // pass): a step from the base state, measured from it, against the pass's vertex sum.
            let m = model.num_vertices();
            let (xb, vb) = (proj.x_base.clone(), proj.v_base.clone());
            let mut grad = vec![[0.0; 3]; m];
            let mut sc = EvalScratch::default();
            evaluate(&pb, &xb, &vb, 0.0, 0.0, &mut sc, &mut grad);
            let lambda = [0.3, -0.2, 0.1, 0.05, 0.02, -0.04, 0.03, 0.2, -0.1, 0.07];
            let step = Step::new(&pb, &xb, &vb, &grad, &lambda, 0.5).measured_from(&xb, &vb);
            let (mut xo, mut vo, mut go) =
                (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
            let e = evaluate_step(
                &pb,
                &step,
                0.0,
                0.0,
                &mut sc,
                (&mut xo, &mut vo, None),
                &mut go,
                false,
            );
            let want = d_norm(&pb, &xo, &vo, 0.0, 0.0, &xb, &vb, &mut Vec::new());
            let got = d_norm_from(
                &pb,
                0.0,
                0.0,
                e.correction_sq.expect("summed by the trial pass"),
            );
            assert!(want > 0.0);
            assert_eq!(got.to_bits(), want.to_bits());
        }
    }

    /// A trial point without the moments for `S` has its vertex sums taken as each task writes its rows: every
    /// constraint sum, the D-norm sum, the elastic summary and the gradient keep the bits of `evaluate_sums`,
    /// which sums them after the elastic chunks (as trial points with the moments still do), over several
    /// vertex tasks and any thread count. Fails if the written rows are summed in another order or over other
    /// tasks.
    #[test]
    fn the_trial_pass_sums_what_an_evaluation_sums() {
        let model = crate::elasticity::tests::grid_model(
            6,
            Material::NeoHookean(NeoHookean::new(1e4, 0.3).unwrap()),
        );
        let m = model.num_vertices();
        assert!(m >= 4 * vertex_chunk(m), "several vertex tasks: {m}");
        let (state, targets) = stretched_and_moving(&model);
        let (x, v) = (&state.x, &state.v);
        let h = 0.005;
        let eps = 1e-6 * model.total_mass * model.length_scale.powi(2);
        let pb = Problem::new(
            &model,
            h,
            &targets,
            vec![1.0; m],
            MetricRows::default(),
            [true; ROWS],
            eps,
        )
        .with_fresh_rows();
        let mut grad = vec![[0.0; 3]; m];
        evaluate(&pb, x, v, 0.0, 0.0, &mut EvalScratch::default(), &mut grad);
        let lambda = [0.3, -0.2, 0.1, 0.05, 0.02, -0.04, 0.03, 0.2, -0.1, 0.07];
        let step = Step::new(&pb, x, v, &grad, &lambda, 0.7).measured_from(x, v);
        // The reference: the rows written, then summed by the evaluation's own pass after the chunks.
        let (mut xr, mut vr, mut gr) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
        step.write(0, &mut xr, &mut vr, false);
        let mut sc = EvalScratch::default();
        let mut want = evaluate_sums::<false>(&pb, &xr, &vr, 0.1, 0.2, &mut sc, &mut gr);
        let norms = &mut Vec::new();
        want.correction_sq = Some(d_norm_vertex_sum(&pb, &xr, &vr, x, v, norms));
        let sums = |e: &Eval| {
            let mut b = vec![e.kinetic, e.gravitational, e.el.energy, e.el.min_j];
            b.extend(e.c);
            b.extend(
                e.momentum
                    .iter()
                    .chain(&e.angular_momentum)
                    .chain(&e.mass_x),
            );
            b.push(e.correction_sq.expect("the trial's D-norm sum"));
            b.into_iter().map(f64::to_bits).collect::<Vec<_>>()
        };
        let rows = |a: &[Vec3]| a.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>();
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let (e, xo, go) = pool.install(|| {
                let (mut xo, mut vo, mut go) =
                    (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
                let mut sc = EvalScratch::default();
                let e = evaluate_step(
                    &pb,
                    &step,
                    0.1,
                    0.2,
                    &mut sc,
                    (&mut xo, &mut vo, None),
                    &mut go,
                    false,
                );
                (e, xo, go)
            });
            assert!(!e.s_moments);
            assert_eq!(sums(&e), sums(&want), "{threads} threads");
            assert_eq!(rows(&xo), rows(&xr), "{threads} threads");
            assert_eq!(rows(&go), rows(&gr), "{threads} threads");
        }
    }

    /// Where another iteration is expected, the trial pass sums the moments for `S` itself instead of a pass
    /// after the trial is accepted: the projection's result keeps every bit.
    #[test]
    fn moments_summed_by_the_trial_pass_change_no_bits() {
        let model = cube_model(1e4, [0.0, 0.0, -9.81]);
        let (state, targets) = stretched_and_moving(&model);
        let run = |expected: usize| {
            let mut proj = Projector::new(ProjectionSettings::default()).unwrap();
            proj.set_implicit_base(true);
            proj.expected_iterations = expected;
            let mut out = state.clone();
            let (report, inv) = proj.project(&model, &mut out, 0.005, &targets);
            let bits = |rows: &[Vec3]| {
                rows.iter()
                    .flatten()
                    .map(|c| c.to_bits())
                    .collect::<Vec<_>>()
            };
            (report, inv.total.to_bits(), bits(&out.x), bits(&out.v))
        };
        let (plain, with) = (run(0), run(usize::MAX));
        assert!(plain.0.iterations >= 2, "{:?}", plain.0);
        assert_eq!(format!("{:?}", plain.0), format!("{:?}", with.0));
        assert_eq!((plain.1, &plain.2, &plain.3), (with.1, &with.2, &with.3));
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

    fn norm3(a: Vec3) -> f64 {
        dot(a, a).sqrt()
    }
}
