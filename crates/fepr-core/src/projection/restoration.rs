//! The quality guard (fepr-spec section 5b): how much of a step's energy deficit the projection restores.
//!
//! An implicit step at a game time step (1/60 s, 1/30 s) removes the energy of the modes it cannot resolve. The
//! closest point that restores all of it puts the energy where it is cheapest in the projection's metric, and on a
//! real mesh that is the stiffest, worst-shaped tets: the seed's bunny2 at dt = 1/60 got 200-284 inverted tets in
//! 8 steps where the base step alone kept every tet upright. Conserving energy is no licence to destroy the mesh,
//! so restoration is constrained, per tet, on the quantity that inversion is about, the volume ratio
//! `J = det F` (a trust region on each tet's volume ratio):
//!
//! - at the end of the step: `|J_e(x) - J_e(x*)| <= margin`;
//! - one step ahead at the new velocities (the explicit prediction `x + h v`, which is what the next base step
//!   starts from; energy put into the velocities of a sliver shows up there, not in `x`):
//!   `|J_e(x + h v) - J_e(x* + h v*)| <= margin`;
//! - and no tet that is upright in `x*` is inverted in `x`.
//!
//! Where the full projection breaks the rule (or does not converge), the projection closes the largest
//! fraction `theta` of the energy gap `H_target - H(x*, v*)` that keeps it, found by a safeguarded regula falsi
//! on the largest change (`theta = 0` keeps the base step's energy and only fixes the momenta). The rest,
//! `-(1 - theta) gap`, is the step's unresolved energy: the simulation books it as a budget source of its own,
//! so the books `H = H_0 + budget_total` still close. Momentum and centre-of-mass rows are always enforced in
//! full. The rule holds for a gap of either sign: removing an excess (a base step that gained energy) through
//! the positions can crush a sliver as well; in practice an excess is removed in full, since a small change of
//! the velocities does it within the trust region. Where no projection keeps the rule, the step returns the base
//! step's own state, reported as a fallback.
//!
//! In a resolved motion the base step loses a small fraction of the energy per step, the restoration changes the
//! velocities by that fraction and the volume ratios by a fraction of their change over a step: far below the
//! margin, so the guard only acts where the time step cannot carry the motion.

use super::{Metric, ProjectionReport, Projector, SystemMetric, Targets};
use crate::invariants::Invariants;
use crate::linalg::{cross, dot, sub, Vec3};
use crate::model::{Model, State};
use crate::parallel::{copy_rows, for_each_chunk_mut2, for_each_mut};

/// Projections tried after the full restoration failed the guard, before the fraction search stops.
const MAX_FRACTION_TRIALS: usize = 5;
/// The search stops when the bracket of the restored fraction is narrower than this share of its upper end.
const FRACTION_PRECISION: f64 = 0.1;
/// The regula falsi aims at this share of the margin, so that its estimate lands inside the trust region.
const AIM: f64 = 0.8;
/// Tets per task of the guard's passes.
const TETS_PER_TASK: usize = 4096;

/// The guard's buffers, kept across steps.
#[derive(Clone, Debug, Default)]
pub(super) struct Restoration {
    /// The base step's state `(x*, v*)`.
    x_base: Vec<Vec3>,
    v_base: Vec<Vec3>,
    /// The state of the largest fraction accepted so far.
    x_kept: Vec<Vec3>,
    v_kept: Vec<Vec3>,
    /// The full restoration's state, where it did not converge.
    x_full: Vec<Vec3>,
    v_full: Vec<Vec3>,
    /// Per tet (user order): its volume ratios in the base step's state and what they may become.
    tets: Vec<TetBase>,
    parts: Vec<QualityCheck>,
}

/// A tet's volume ratios in the base step's state, `J(x*)` and one step ahead `J(x* + h v*)`, with the
/// inverses of the changes each may undergo: `margin + MOTION_SHARE |J(x*) - J(x* - h v*)|` (the change over
/// the base step itself: `x* - h v*` is the start of the step for every integrator) and
/// `margin + MOTION_SHARE |J(x* + h v*) - J(x*)|`.
#[derive(Clone, Copy, Debug, Default)]
struct TetBase {
    now: f64,
    ahead: f64,
    inv_allowed_now: f64,
    inv_allowed_ahead: f64,
}

/// The share of a tet's own change of `J` over a step that the restoration may add to it, besides the margin:
/// restoring a small loss in a resolved motion rescales each tet's motion a little (a few percent), restoring
/// what a step destroyed would rescale it many times over.
const MOTION_SHARE: f64 = 0.25;

/// How far a state's volume ratios moved from the base step's.
#[derive(Clone, Copy, Debug, PartialEq)]
struct QualityCheck {
    /// Largest change `|J - J_base|` over the tets, at the end of the step and one step ahead, over the change
    /// that tet may undergo.
    excess: f64,
    /// Tets upright in the base step's state that are inverted here.
    inverted: usize,
    /// Smallest volume ratio at the end of the step.
    min_now: f64,
    /// Smallest volume ratio of the base step's state (measured by [`Restoration::check_against_base`] only).
    base_min: f64,
}

impl Default for QualityCheck {
    fn default() -> Self {
        Self {
            excess: 0.0,
            inverted: 0,
            min_now: f64::INFINITY,
            base_min: f64::INFINITY,
        }
    }
}

impl QualityCheck {
    fn combine(a: Self, b: Self) -> Self {
        Self {
            excess: a.excess.max(b.excess),
            inverted: a.inverted + b.inverted,
            // A NaN ratio is an inversion (counted above); `min` keeps the finite ones.
            min_now: a.min_now.min(b.min_now),
            base_min: a.base_min.min(b.base_min),
        }
    }
}

/// What the guard asks of a projection, by the sign of the energy gap it closes.
#[derive(Clone, Copy, Debug)]
struct Rule {
    /// The projection removes an excess (a base step that gained energy).
    removing: bool,
    /// The base step's smallest volume ratio.
    base_min: f64,
    margin: f64,
}

impl Rule {
    /// How far `c` is from breaking the rule, as a fraction of what the rule allows (above 1: broken).
    /// Restoring a deficit: the per-tet trust region (energy put into the motion concentrates in the tets
    /// it can move most). Removing an excess takes energy out, which does not concentrate it: there the
    /// worst tet may not end more than the margin below the base step's worst (an excess removed through the
    /// positions of a stiff mesh in the mass metric can crush a sliver all the same), and no tet may invert.
    fn measure(&self, c: &QualityCheck) -> f64 {
        if self.removing {
            ((self.base_min - c.min_now) / self.margin).max(0.0)
        } else {
            c.excess
        }
    }
    fn holds(&self, c: &QualityCheck) -> bool {
        c.inverted == 0 && self.measure(c) <= 1.0
    }
}

/// Volume ratio `det [b - a, c - a, d - a] / (6 V_rest)` of a tet with corners `a, b, c, d`.
#[inline]
fn volume_ratio(p: [Vec3; 4], six_volume: f64) -> f64 {
    let [a, b, c, d] = p;
    dot(sub(b, a), cross(sub(c, a), sub(d, a))) / six_volume
}

/// The corners of tet `t` at `x + s v`.
#[inline]
fn corners(x: &[Vec3], v: &[Vec3], s: f64, t: &[usize; 4]) -> [Vec3; 4] {
    t.map(|i| std::array::from_fn(|a| x[i][a] + s * v[i][a]))
}

/// One tet's contribution to a [`QualityCheck`]: `now` and `ahead` its volume ratios at the checked state.
#[inline]
fn tet_check(base: &TetBase, now: f64, ahead: f64) -> QualityCheck {
    // Upright before (`J > 0`), not after (`J <= 0` or NaN).
    let flipped = |before: f64, after: f64| {
        (before > 0.0 && after.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)) as usize
    };
    // A NaN ratio counts as an inversion and an infinite change (`f64::max` would drop it).
    let excess = if now.is_nan() || ahead.is_nan() {
        f64::INFINITY
    } else {
        ((now - base.now).abs() * base.inv_allowed_now)
            .max((ahead - base.ahead).abs() * base.inv_allowed_ahead)
    };
    // One step ahead only the change counts: the next base step resists a compression that the explicit
    // prediction `x + h v` would carry through, and a tet the base step already drives towards inversion may
    // cross zero in the prediction by a small change.
    QualityCheck {
        excess,
        min_now: now,
        inverted: flipped(base.now, now),
        base_min: f64::INFINITY,
    }
}

impl TetBase {
    /// The base ratios of tet `t` (six times its rest volume `six_v`) in the state `(x, v)`.
    fn measure(x: &[Vec3], v: &[Vec3], h: f64, t: &[usize; 4], six_v: f64, margin: f64) -> Self {
        let now = volume_ratio(corners(x, v, 0.0, t), six_v);
        let ahead = volume_ratio(corners(x, v, h, t), six_v);
        let before = volume_ratio(corners(x, v, -h, t), six_v);
        // Non-finite base ratios (a base step that blew up) allow any change: the guard cannot judge them.
        let inv = |change: f64| {
            let allowed = margin + MOTION_SHARE * change.abs();
            if allowed.is_finite() {
                1.0 / allowed
            } else {
                0.0
            }
        };
        Self {
            now,
            ahead,
            inv_allowed_now: inv(now - before),
            inv_allowed_ahead: inv(ahead - now),
        }
    }
}

impl Restoration {
    /// Keep `(x*, v*)`.
    fn save_base(&mut self, state: &State) {
        copy_rows(&state.x, &mut self.x_base);
        copy_rows(&state.v, &mut self.v_base);
    }

    /// Put `(x*, v*)` back into `state`.
    fn restore_base(&self, state: &mut State) {
        state.x.copy_from_slice(&self.x_base);
        state.v.copy_from_slice(&self.v_base);
    }

    fn keep(&mut self, state: &State) {
        copy_rows(&state.x, &mut self.x_kept);
        copy_rows(&state.v, &mut self.v_kept);
    }

    fn restore_kept(&self, state: &mut State) {
        state.x.copy_from_slice(&self.x_kept);
        state.v.copy_from_slice(&self.v_kept);
    }

    fn keep_full(&mut self, state: &State) {
        copy_rows(&state.x, &mut self.x_full);
        copy_rows(&state.v, &mut self.v_full);
    }

    fn restore_full(&self, state: &mut State) {
        state.x.copy_from_slice(&self.x_full);
        state.v.copy_from_slice(&self.v_full);
    }

    /// Measure the base step's volume ratios (from the saved `(x*, v*)`) and check `state` against them.
    fn check_against_base(
        &mut self,
        model: &Model,
        h: f64,
        state: &State,
        margin: f64,
    ) -> QualityCheck {
        let k = model.num_tets();
        self.tets.resize(k, TetBase::default());
        self.parts
            .resize(k.div_ceil(TETS_PER_TASK), QualityCheck::default());
        let (tets, volume) = (model.mesh.tets(), &model.rest_volume);
        let (xb, vb, x, v) = (
            &self.x_base[..],
            &self.v_base[..],
            &state.x[..],
            &state.v[..],
        );
        for_each_chunk_mut2(
            &mut self.tets,
            TETS_PER_TASK,
            &mut self.parts,
            1,
            |c, bases, part| {
                let mut sum = QualityCheck::default();
                for (k, base) in bases.iter_mut().enumerate() {
                    let e = c * TETS_PER_TASK + k;
                    let (t, six_v) = (&tets[e], 6.0 * volume[e]);
                    *base = TetBase::measure(xb, vb, h, t, six_v, margin);
                    let now = volume_ratio(corners(x, v, 0.0, t), six_v);
                    let ahead = volume_ratio(corners(x, v, h, t), six_v);
                    let mut tet = tet_check(base, now, ahead);
                    tet.base_min = base.now;
                    sum = QualityCheck::combine(sum, tet);
                }
                part[0] = sum;
            },
        );
        self.parts
            .iter()
            .copied()
            .fold(QualityCheck::default(), QualityCheck::combine)
    }

    /// Check `state` against the base ratios measured by the last [`Restoration::check_against_base`].
    fn check(&mut self, model: &Model, h: f64, state: &State) -> QualityCheck {
        let (tets, volume, bases) = (model.mesh.tets(), &model.rest_volume, &self.tets[..]);
        let (x, v) = (&state.x[..], &state.v[..]);
        let k = tets.len();
        for_each_mut(&mut self.parts, |c, part| {
            let mut sum = QualityCheck::default();
            for e in c * TETS_PER_TASK..((c + 1) * TETS_PER_TASK).min(k) {
                let (t, six_v) = (&tets[e], 6.0 * volume[e]);
                let now = volume_ratio(corners(x, v, 0.0, t), six_v);
                let ahead = volume_ratio(corners(x, v, h, t), six_v);
                sum = QualityCheck::combine(sum, tet_check(&bases[e], now, ahead));
            }
            *part = sum;
        });
        self.parts
            .iter()
            .copied()
            .fold(QualityCheck::default(), QualityCheck::combine)
    }
}

/// The next restored fraction to try, inside the bracket `(lo, hi)`: `lo` is accepted (its largest change
/// `e_lo`, 0 for the untried `lo = 0`), `hi` was not (`e_hi`, infinite where it did not converge). Regula falsi
/// on `e(theta) = AIM`, kept off the bracket's ends; a halving of the distance to `hi` without a finite `e_hi`.
fn next_fraction(lo: f64, e_lo: f64, hi: f64, e_hi: f64) -> f64 {
    let w = hi - lo;
    let s = if e_hi.is_finite() && e_hi > e_lo {
        ((AIM - e_lo) / (e_hi - e_lo)).clamp(0.02, 0.7)
    } else {
        0.3
    };
    lo + s * w
}

/// What the fraction search tallies over its projections.
#[derive(Clone, Copy, Debug, Default)]
struct Tally {
    trials: usize,
    iterations: usize,
    evaluations: usize,
    halvings: usize,
    least_squares_solves: usize,
    restarts: usize,
    frozen_vertices: usize,
}

impl Tally {
    fn add(&mut self, r: &ProjectionReport) {
        self.trials += 1;
        self.iterations += r.iterations;
        self.evaluations += r.evaluations;
        self.halvings += r.halvings;
        self.least_squares_solves += r.least_squares_solves;
        self.restarts += r.restarts;
        self.frozen_vertices += r.frozen_vertices;
    }
    /// `r` with the counts of every projection of the step.
    fn into_report(self, mut r: ProjectionReport) -> ProjectionReport {
        r.trials = self.trials;
        r.iterations = self.iterations;
        r.evaluations = self.evaluations;
        r.halvings = self.halvings;
        r.least_squares_solves = self.least_squares_solves;
        r.restarts = self.restarts;
        r.frozen_vertices = self.frozen_vertices;
        r
    }
}

impl Projector {
    /// Project the base step's state (put back into `state` from `rs`) with the energy target
    /// `H* + theta (H_target - H*)`, and check the result against the base step's volume ratios.
    #[allow(clippy::too_many_arguments)]
    fn project_fraction<'d>(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        targets: &Targets,
        rs: &mut Restoration,
        theta: f64,
        system: Option<&mut (dyn SystemMetric + 'd)>,
        base_energy: f64,
    ) -> (ProjectionReport, Invariants, QualityCheck) {
        rs.restore_base(state);
        let t = Targets {
            energy: base_energy + theta * (targets.energy - base_energy),
            ..*targets
        };
        let (r, i) = self.project_once(model, state, h, &t, system);
        let check = rs.check(model, h, state);
        (r, i, check)
    }

    /// Project `state` (holding the base step's result `(x*, v*)`) in place, for step size `h` and the given
    /// targets, with the base integrator's factorised position metric if it offers one
    /// ([`crate::integrators::Integrator::system_metric`]; used under [`Metric::Auto`] where the energy is the
    /// only active row and no position is frozen, see [`SystemMetric`]). Returns the report and the invariants
    /// measured at the returned state.
    ///
    /// Around the iteration of fepr-spec section 3 (`project_once`):
    /// - the metric switch: under [`Metric::Auto`] after an implicit base step, an iteration in the diagonal
    ///   stiffness metric that stalls (its scaled residual does not halve in an iteration after the first)
    ///   restarts from `(x*, v*)` in the mass metric (`metric_switched`);
    /// - the quality guard (see the module [`restoration`](self)): where restoring the whole energy deficit
    ///   moves a tet's volume ratio by more than [`super::ProjectionSettings::quality_margin`] or does not
    ///   converge, the largest fraction that keeps within it is restored, and the rest is reported as
    ///   `unresolved` for the simulation to book.
    pub fn project_with(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        targets: &Targets,
        mut system: Option<&mut dyn SystemMetric>,
    ) -> (ProjectionReport, Invariants) {
        let margin = self.settings.quality_margin;
        let switchable = self.settings.metric == Metric::Auto && self.implicit_base;
        let mut rs = std::mem::take(&mut self.restoration);
        if margin.is_some() || switchable {
            rs.save_base(state);
        }
        self.switch_on_stall = switchable;
        let mut tally = Tally::default();
        let (mut rep, mut inv) = self.project_once(model, state, h, targets, system.as_deref_mut());
        tally.add(&rep);
        let mut switched = false;
        if self.stalled {
            rs.restore_base(state);
            self.metric_override = Some(Metric::Mass);
            self.switch_on_stall = false;
            (rep, inv) = self.project_once(model, state, h, targets, system.as_deref_mut());
            tally.add(&rep);
            switched = true;
        }
        self.switch_on_stall = false;
        let base_energy = rep.base_energy;
        let base_residual = rep.initial_residual;
        // The energy the projection is asked to restore (positive) or remove (negative).
        let gap = targets.energy - base_energy;
        let tolerance = self.settings.tolerance * targets.energy_scale;
        let mut restored = 1.0;
        let mut excess = 0.0;
        if let (Some(margin), true) = (margin, base_energy.is_finite()) {
            let first = rs.check_against_base(model, h, state, margin);
            let rule = Rule {
                removing: gap < 0.0,
                base_min: first.base_min,
                margin,
            };
            excess = rule.measure(&first);
            if !(rep.converged && rule.holds(&first)) {
                // A full projection that did not converge but keeps the guard is the fallback if no fraction
                // converges either: then it was not the energy that stopped it.
                let full = (!rep.converged && rule.holds(&first)).then(|| {
                    rs.keep_full(state);
                    (rep, inv, excess)
                });
                // The search over the fraction theta of the gap; `lo` is accepted (0: untried), `hi` is not.
                let (mut lo, mut e_lo) = (0.0, 0.0);
                let (mut hi, mut e_hi) = (1.0, if rep.converged { excess } else { f64::INFINITY });
                let mut kept: Option<(ProjectionReport, Invariants, f64)> = None;
                let mut last_is_kept = false;
                // An excess that the full projection could not remove (it did not converge) is not reduced: keeping
                // part of the energy a base step gained would feed a runaway. That step is a plain fallback, and the
                // next one tries again from its targets.
                let search = gap > tolerance || (gap < -tolerance && rep.converged);
                let trials = if search { MAX_FRACTION_TRIALS } else { 0 };
                for _ in 0..trials {
                    let theta = next_fraction(lo, e_lo, hi, e_hi);
                    let (r, i, check) = self.project_fraction(
                        model,
                        state,
                        h,
                        targets,
                        &mut rs,
                        theta,
                        system.as_deref_mut(),
                        base_energy,
                    );
                    tally.add(&r);
                    let e = rule.measure(&check);
                    last_is_kept = r.converged && rule.holds(&check);
                    if last_is_kept {
                        (lo, e_lo) = (theta, e);
                        rs.keep(state);
                        kept = Some((r, i, e));
                    } else {
                        (hi, e_hi) = (theta, if r.converged { e } else { f64::INFINITY });
                    }
                    if hi - lo <= FRACTION_PRECISION * hi {
                        break;
                    }
                }
                let mut chosen = kept.map(|k| (k, lo, last_is_kept));
                if chosen.is_none() && search {
                    // Nothing of the gap fits: keep the base step's energy and fix the momenta.
                    let (r, i, check) = self.project_fraction(
                        model,
                        state,
                        h,
                        targets,
                        &mut rs,
                        0.0,
                        system,
                        base_energy,
                    );
                    tally.add(&r);
                    if r.converged && (rule.holds(&check) || full.is_none()) {
                        chosen = Some(((r, i, rule.measure(&check)), 0.0, true));
                    }
                }
                match (chosen, full) {
                    (Some(((r, i, e), theta, in_state)), _) => {
                        if !in_state {
                            rs.restore_kept(state);
                            // The hand-over buffers belong to the last projection, not to this state.
                            self.invalidate_hand_over();
                        }
                        (rep, inv, restored, excess) = (r, i, theta, e);
                    }
                    (None, Some((r, i, e))) => {
                        rs.restore_full(state);
                        self.invalidate_hand_over();
                        (rep, inv, excess) = (r, i, e);
                    }
                    (None, None) => {
                        // Every projection either broke the guard or failed: the base step's state, unprojected
                        // (the references keep their targets, so the next step tries again).
                        rs.restore_base(state);
                        self.invalidate_hand_over();
                        inv = crate::invariants::measure(model, state);
                        rep.converged = false;
                        rep.fallback = true;
                        rep.final_residual = base_residual;
                        rep.correction = 0.0;
                        rep.s = 0.0;
                        rep.t = 0.0;
                        excess = 0.0;
                    }
                }
            }
        }
        self.metric_override = None;
        self.restoration = rs;
        let mut rep = tally.into_report(rep);
        rep.base_energy = base_energy;
        rep.restored = restored;
        rep.gap = gap;
        rep.unresolved = if restored < 1.0 {
            -(1.0 - restored) * gap
        } else {
            0.0
        };
        rep.metric_switched = switched;
        rep.quality_excess = excess;
        (rep, inv)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flipped_tet_counts_as_inverted_and_a_nan_as_infinite() {
        let base = TetBase {
            now: 0.5,
            ahead: 0.5,
            inv_allowed_now: 20.0,
            inv_allowed_ahead: 20.0,
        };
        let restoring = Rule {
            removing: false,
            base_min: 0.5,
            margin: 0.05,
        };
        let c = tet_check(&base, -0.1, 0.5);
        assert_eq!(c.inverted, 1);
        assert!((c.excess - 12.0).abs() < 1e-12);
        assert!(!restoring.holds(&c));
        let c = tet_check(&base, f64::NAN, 0.5);
        assert_eq!(c.inverted, 1);
        assert!(c.excess.is_infinite());
        // Already inverted in the base step: not a new inversion, only its change counts.
        let inverted = TetBase { now: -0.2, ..base };
        let c = tet_check(&inverted, -0.21, 0.5);
        assert_eq!(c.inverted, 0);
        assert!(restoring.holds(&c));
    }

    #[test]
    fn removing_an_excess_is_judged_on_the_worst_tet_alone() {
        let removing = Rule {
            removing: true,
            base_min: 0.5,
            margin: 0.05,
        };
        let check = |min_now: f64, inverted: usize| QualityCheck {
            excess: 100.0, // per-tet changes do not count when energy is taken out
            inverted,
            min_now,
            base_min: f64::INFINITY,
        };
        assert!(removing.holds(&check(0.46, 0)));
        assert!((removing.measure(&check(0.4, 0)) - 2.0).abs() < 1e-12);
        assert!(!removing.holds(&check(0.4, 0)));
        assert!(!removing.holds(&check(0.6, 1)));
    }

    #[test]
    fn a_tet_may_change_by_the_margin_plus_a_share_of_its_own_motion() {
        // A unit tet moving along x at 1 m/s, compressed along z at 0.3 m/s over a step of 0.1 s.
        let x = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let v = vec![
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, -0.3],
        ];
        let base = TetBase::measure(&x, &v, 0.1, &[0, 1, 2, 3], 1.0, 0.05);
        assert!((base.now - 1.0).abs() < 1e-15 && (base.ahead - 0.97).abs() < 1e-15);
        let allowed = 0.05 + MOTION_SHARE * 0.03;
        assert!((1.0 / base.inv_allowed_now - allowed).abs() < 1e-15);
        assert!((1.0 / base.inv_allowed_ahead - allowed).abs() < 1e-15);
    }

    #[test]
    fn the_fraction_search_stays_inside_its_bracket() {
        for (lo, e_lo, hi, e_hi) in [
            (0.0, 0.0, 1.0, 40.0),
            (0.0, 0.0, 1.0, f64::INFINITY),
            (0.2, 0.9, 0.3, 1.2),
            (0.5, 0.1, 0.6, 0.05),
        ] {
            let t = next_fraction(lo, e_lo, hi, e_hi);
            assert!(t > lo && t < hi, "{t} outside ({lo}, {hi})");
        }
        // A linear change of 40 margins at theta = 1 aims at AIM margins.
        assert!((next_fraction(0.0, 0.0, 1.0, 40.0) - AIM / 40.0).abs() < 1e-15);
    }
}
