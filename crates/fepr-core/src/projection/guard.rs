//! The projection with its guard ([`Projector::project_with`]): the metric switch around the iteration, and,
//! where closing the whole energy gap breaks the quality rule of [`restoration`](super::restoration), the
//! search over the fraction of the gap that keeps it.

use super::restoration::{QualityCheck, Restoration, Rule};
use super::{Metric, ProjectionReport, Projector, SystemMetric, Targets};
use crate::invariants::Invariants;
use crate::math::{cross, dot, sub, Mat3, Vec3};
use crate::model::{Model, State};

/// Projections tried after the full restoration failed the guard, before the fraction search stops.
const MAX_FRACTION_TRIALS: usize = 4;
/// The search stops when the bracket of the restored fraction is narrower than this share of its upper end.
const FRACTION_PRECISION: f64 = 0.2;
/// ... or narrower than this share of the gap: where a step can restore only a few percent of its gap (a sliver
/// mesh released from a stretch at a game time step), pinning that down to a fifth of itself took the whole five
/// projections on every step (the bunny with XPBD + FEPR: 16-25 ms of projection per step after the release,
/// against a 25 ms base step), for differences of a percent of the gap in what is booked as unresolved.
const FRACTION_RESOLUTION: f64 = 0.05;
/// The regula falsi aims at this share of the margin, so that its estimate lands inside the trust region.
const AIM: f64 = 0.8;

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

/// The kinetic energy of a rotation with angular momentum `l` (kg m^2/s) of a body whose inverse inertia about
/// its centre is `inv`, J: `l . I^-1 l / 2`.
fn spin_energy(inv: &Mat3, l: Vec3) -> f64 {
    let w = [0, 1, 2].map(|a| (0..3).map(|b| inv[a][b] * l[b]).sum::<f64>());
    0.5 * dot(w, l)
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
    /// The change of kinetic energy that putting the rigid part of `v` on the momentum targets would make, J
    /// (the warm start's rigid part: `V = P_target / m`, `omega = I^-1 L_target` about the centre of mass; the
    /// deformational rest carries no momenta, so it keeps its energy). 0 where the momentum rows do not hold the
    /// whole body (pins, rows off, slack free) or the body is degenerate.
    fn momentum_energy(&self, model: &Model, x: &[Vec3], v: &[Vec3], targets: &Targets) -> f64 {
        if !self.momenta_hold_the_body(model, targets) {
            return 0.0;
        }
        let rigid = crate::invariants::rigid_motion(&model.masses, x, v);
        let Some(inv) = rigid.inertia_inv else {
            return 0.0;
        };
        let m = rigid.mass;
        let (vt, l_t) = targets.rigid_motion_at(m, rigid.center);
        let k_now = 0.5 * dot(rigid.momentum, rigid.momentum) / m
            + spin_energy(&inv, rigid.angular_momentum);
        let k_next = 0.5 * m * dot(vt, vt) + spin_energy(&inv, l_t);
        k_next - k_now
    }

    /// The kinetic energy that the momentum rows keep in a state `(x, v)` (J): that of its rigid motion (`V = P / m`,
    /// `omega = I^-1 L` about the centre of mass), which a projection that holds the momenta cannot take out (up
    /// to their slack); 0 where a momentum row is off or vertices are pinned. What a projection can remove from
    /// the kinetic energy is the rest.
    pub(crate) fn fixed_kinetic(&self, model: &Model, state: &State, targets: &Targets) -> f64 {
        if !self.momentum_rows_on(model, targets) {
            return 0.0;
        }
        let rigid = crate::invariants::rigid_motion(&model.masses, &state.x, &state.v);
        rigid.inertia_inv.map_or(0.0, |inv| {
            0.5 * dot(rigid.momentum, rigid.momentum) / rigid.mass
                + spin_energy(&inv, rigid.angular_momentum)
        })
    }

    /// Whether the momentum rows hold the whole body to their targets (no pins, every row on, no slack).
    fn momenta_hold_the_body(&self, model: &Model, targets: &Targets) -> bool {
        let slack = match self.settings.slack {
            super::Slack::On => true,
            super::Slack::Off => false,
            super::Slack::Auto => targets.uncertain_impulses,
        };
        self.momentum_rows_on(model, targets) && !slack
    }

    /// Whether every momentum row is on and no vertex is pinned.
    fn momentum_rows_on(&self, model: &Model, targets: &Targets) -> bool {
        let rows = self.active_rows(model, targets);
        model.num_pinned() == 0 && rows[1..7].iter().all(|&a| a)
    }

    /// Put the rigid part of `state`'s velocities on the momentum targets (the change
    /// [`Projector::momentum_energy`] prices: `V = P_target / m`, `omega = I^-1 L_target` about the centre of mass;
    /// the deformational rest keeps its velocities), where the momentum rows hold the whole body. A step whose
    /// projection fell back to an unconverged state keeps the scene's momenta so: they are the targets the
    /// processes set (impulses exchanged between bodies cancel), while the base step's own drift (Projective
    /// Dynamics' unconverged iterations, a contact solve) would stay in the state and add up step after step.
    /// The energy this changes is the simulation's to book (the state is off its energy target either way).
    fn hold_momenta(&self, model: &Model, state: &mut State, targets: &Targets) {
        if !self.momenta_hold_the_body(model, targets) {
            return;
        }
        let rigid = crate::invariants::rigid_motion(&model.masses, &state.x, &state.v);
        let Some(inv) = rigid.inertia_inv else {
            return;
        };
        let m = rigid.mass;
        let (vt, l_t) = targets.rigid_motion_at(m, rigid.center);
        let omega = |l: Vec3| [0, 1, 2].map(|a| (0..3).map(|b| inv[a][b] * l[b]).sum::<f64>());
        let (w_now, w_t) = (omega(rigid.angular_momentum), omega(l_t));
        let dv = [0, 1, 2].map(|a| vt[a] - rigid.momentum[a] / m);
        let dw = sub(w_t, w_now);
        for (xi, vi) in state.x.iter().zip(state.v.iter_mut()) {
            let spin = cross(dw, sub(*xi, rigid.center));
            *vi = [0, 1, 2].map(|a| vi[a] + dv[a] + spin[a]);
        }
    }

    /// The change of gravitational energy that putting the centre of mass of `x` on its target would make, J
    /// (`-M g . (C_target - C)`, a rigid translation, which leaves the elastic and kinetic energy as they are),
    /// over the centre-of-mass rows that are active; 0 where vertices are pinned (as
    /// [`Projector::momentum_energy`]).
    fn centre_energy(&self, model: &Model, x: &[Vec3], targets: &Targets) -> f64 {
        if model.num_pinned() > 0 {
            return 0.0;
        }
        let rows = self.active_rows(model, targets);
        let c = crate::invariants::center_of_mass(&model.masses, model.total_mass, x);
        (0..3)
            .filter(|&a| rows[7 + a])
            .map(|a| -model.total_mass * model.gravity[a] * (targets.center_of_mass[a] - c[a]))
            .sum()
    }

    /// Project the base step's state (put back into `state` from `rs`) with the energy target
    /// `anchor + theta (H_target - anchor)`, and check the result against the base step's volume ratios.
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
        anchor: f64,
    ) -> (ProjectionReport, Invariants, QualityCheck) {
        rs.base.restore(state);
        let t = Targets {
            energy: anchor + theta * (targets.energy - anchor),
            ..*targets
        };
        let (r, i) = self.project_once(model, state, h, &t, system);
        let margin = self
            .settings
            .quality_margin
            .unwrap_or(super::DEFAULT_QUALITY_MARGIN);
        let check = rs.check(model, h, state, margin, r.iterations == 0, false);
        (r, i, check)
    }

    /// Project `state` (holding the base step's result `(x*, v*)`) in place, for step size `h` and the given
    /// targets, with the base integrator's factorised position metric if it offers one
    /// (handed over by the simulation; used under [`Metric::Auto`] where the energy is the
    /// only active row and no position is frozen, see [`SystemMetric`]). Returns the report and the invariants
    /// measured at the returned state.
    ///
    /// Around the iteration of fepr-spec section 3 (`project_once`):
    /// - the metric switch: under [`Metric::Auto`] after an implicit base step, an iteration in the diagonal
    ///   stiffness metric that makes no progress (its scaled residual falls by less than a tenth in an iteration
    ///   after the first) restarts from `(x*, v*)` in the mass metric (`metric_switched`); the better result of
    ///   the two is kept;
    /// - the quality guard (module `restoration`): where closing the whole energy gap breaks
    ///   [`super::ProjectionSettings::quality_margin`]'s rule or does not converge, the largest fraction that
    ///   converges within the rule is closed, and the rest is reported as `unresolved` for the simulation to
    ///   book; where nothing does, the step is a fallback.
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
            rs.base.save(state);
        }
        // The previous step's fraction is a guess for this step's search only if that search runs.
        let last_fraction = rs.last_fraction.take();
        let mut tally = Tally::default();
        let (rep, inv, switched) = self.project_full(
            model,
            state,
            h,
            targets,
            &mut rs,
            &mut tally,
            system.as_deref_mut(),
        );
        let base_energy = rep.base_energy;
        // The energy the projection is asked to restore (positive) or remove (negative).
        let gap = targets.energy - base_energy;
        let mut outcome = Outcome {
            rep,
            inv,
            excess: 0.0,
            restored: 1.0,
        };
        if let (Some(margin), true) = (margin, base_energy.is_finite()) {
            let (rule, first) = rs.judge_full(
                model,
                h,
                state,
                &outcome.rep,
                outcome.inv.min_j,
                margin,
                gap,
            );
            outcome.excess = rule.measure(&first);
            if !(outcome.rep.converged && rule.holds(&first)) {
                let guard = Guard {
                    model,
                    h,
                    targets,
                    rule,
                    first,
                    gap,
                };
                rs.last_fraction = last_fraction;
                outcome = self.restore_in_part(state, &guard, &mut rs, &mut tally, system, outcome);
            }
        }
        self.restoration = rs;
        let Outcome {
            rep,
            inv,
            excess,
            restored,
        } = outcome;
        let mut rep = tally.into_report(rep);
        rep.base_energy = base_energy;
        rep.restored = restored;
        rep.gap = gap;
        rep.unresolved = if restored != 1.0 {
            -(1.0 - restored) * gap
        } else {
            0.0
        };
        rep.metric_switched = switched;
        rep.quality_excess = excess;
        (rep, inv)
    }

    /// The guard's search where the full projection broke the rule or did not converge: the largest fraction
    /// of the gap that converges within the rule (the rest unresolved), else the full projection if it keeps
    /// the rule, else the base step's state unprojected (a fallback). `state` gets the chosen result.
    fn restore_in_part(
        &mut self,
        state: &mut State,
        guard: &Guard,
        rs: &mut Restoration,
        tally: &mut Tally,
        system: Option<&mut dyn SystemMetric>,
        full: Outcome,
    ) -> Outcome {
        let (model, targets, gap) = (guard.model, guard.targets, guard.gap);
        let Outcome {
            mut rep,
            mut inv,
            mut excess,
            ..
        } = full;
        let tolerance = self.settings.tolerance * targets.energy_scale;
        let base_energy = rep.base_energy;
        // The fractions run from the energy the momentum and centre-of-mass targets alone give the base step's
        // state (its rigid motion put on them: a spinning body that lost angular momentum gets its rotational
        // energy back with it; a body whose base step fell short of the exact centre-of-mass path in gravity is
        // lifted onto it, with its potential energy) to the full target: only the rest, the internal energy, is
        // the guard's to limit. Without the lift, a body in flight whose base step damped its vibration had no
        // fraction to close: the lower ones asked for less energy than the lift alone adds, every step failed
        // and the centre of mass fell further behind its target (a ball bounced off a box in the pile: 100
        // iterations on every step of its flight).
        let anchor = base_energy
            + self.momentum_energy(model, &rs.base.x, &rs.base.v, targets)
            + self.centre_energy(model, &rs.base.x, targets);
        let rest = targets.energy - anchor;
        let search = Search {
            targets,
            anchor,
            rule: guard.rule,
            // An excess that the full projection could not remove (it did not converge) is not reduced:
            // keeping part of the energy a base step gained would feed a runaway.
            allowed: rest > tolerance || (rest < -tolerance && rep.converged),
            full_converged: rep.converged,
            full_excess: excess,
        };
        // A full projection that did not converge but keeps the rule is the fallback if no fraction converges
        // either: then it was not the energy that stopped it.
        let full = (!rep.converged && guard.rule.holds(&guard.first)).then(|| {
            rs.full.save(state);
            (rep, inv, excess)
        });
        let chosen = self.search_fraction(model, state, guard.h, &search, rs, tally, system);
        let mut restored = 1.0;
        match (chosen, full) {
            (Some(((r, i, e), theta, in_state)), _) => {
                if !in_state {
                    rs.kept.restore(state);
                    // The hand-over buffers belong to the last projection, not to this state.
                    self.invalidate_hand_over();
                }
                // The share of the whole gap closed.
                let left = (1.0 - theta) * rest;
                restored = if gap != 0.0 { 1.0 - left / gap } else { 1.0 };
                (rep, inv, excess) = (r, i, e);
            }
            (None, Some((r, _, e))) => {
                rs.full.restore(state);
                self.invalidate_hand_over();
                (rep, excess) = (r, e);
                // Its invariants are measured again after the momenta are held.
                self.hold_momenta(model, state, targets);
                inv = crate::invariants::measure(model, state);
            }
            (None, None) => {
                // Every projection broke the rule or failed: the base step's state, unprojected (the
                // references keep their targets, so the next step tries again).
                let base_residual = rep.initial_residual;
                rs.base.restore(state);
                self.invalidate_hand_over();
                self.hold_momenta(model, state, targets);
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
        Outcome {
            rep,
            inv,
            excess,
            restored,
        }
    }

    /// The projection onto the full targets, with the metric switch (see [`Projector::project_with`]): the
    /// report, the invariants and whether it switched to the mass metric.
    #[allow(clippy::too_many_arguments)]
    fn project_full<'d>(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        targets: &Targets,
        rs: &mut Restoration,
        tally: &mut Tally,
        mut system: Option<&mut (dyn SystemMetric + 'd)>,
    ) -> (ProjectionReport, Invariants, bool) {
        self.switch_on_stall = self.settings.metric == Metric::Auto && self.implicit_base;
        let (rep, inv) = self.project_once(model, state, h, targets, system.as_deref_mut());
        tally.add(&rep);
        self.switch_on_stall = false;
        if !self.stalled {
            return (rep, inv, false);
        }
        // Keep the stalled result aside, try the mass metric from q~, and keep whichever ends closer.
        rs.full.save(state);
        rs.base.restore(state);
        self.metric_override = Some(Metric::Mass);
        let (mass, mass_inv) = self.project_once(model, state, h, targets, system);
        self.metric_override = None;
        tally.add(&mass);
        if mass.converged || mass.final_residual <= rep.final_residual {
            (mass, mass_inv, true)
        } else {
            rs.full.restore(state);
            self.invalidate_hand_over();
            (rep, inv, false)
        }
    }

    /// The search over the fraction theta of the energy gap (see the module docs): the accepted projection
    /// (report, invariants, measure under the rule), its fraction, and whether `state` holds it (else it is in
    /// `rs`'s kept buffers); `None` where no fraction converges within the rule.
    #[allow(clippy::too_many_arguments)]
    fn search_fraction<'d>(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        search: &Search,
        rs: &mut Restoration,
        tally: &mut Tally,
        mut system: Option<&mut (dyn SystemMetric + 'd)>,
    ) -> Option<((ProjectionReport, Invariants, f64), f64, bool)> {
        if !search.allowed {
            return None;
        }
        // `lo` is accepted (0: untried), `hi` is not.
        let (mut lo, mut e_lo) = (0.0, 0.0);
        let (mut hi, mut e_hi) = (1.0, search.full_excess);
        let mut kept: Option<(ProjectionReport, Invariants, f64)> = None;
        let mut last_is_kept = false;
        if !search.full_converged {
            // The full projection did not converge: try the base step's energy first. If that does not
            // converge either, it was not the energy that stopped the projection: no fraction will.
            let (r, i, e, holds) = self.project_judged(
                model,
                state,
                h,
                search,
                rs,
                tally,
                0.0,
                system.as_deref_mut(),
            );
            if !r.converged {
                return None;
            }
            if !holds {
                // Converged but broke the rule with the energy untouched (the momenta's correction did).
                return Some(((r, i, e), 0.0, true));
            }
            (lo, e_lo, e_hi) = (0.0, e, f64::INFINITY);
            rs.kept.save(state);
            kept = Some((r, i, e));
            last_is_kept = true;
        }
        // The previous step's accepted fraction first (the limit changes little from one step to the next; the
        // regula falsi from the full projection's measure alone undershoots, as the measure grows faster than
        // linearly towards the full restoration), and where it is accepted, the fraction just above the
        // search's precision next: where that one is refused, the bracket is narrow enough after two trials.
        // The stop is on the bracket, not on the measure: the measure can be flat in the fraction.
        let mut guess = rs.last_fraction.take().filter(|&t| t > lo && t < hi);
        let mut grow = false;
        for _ in 0..MAX_FRACTION_TRIALS {
            let above = lo / (1.0 - FRACTION_PRECISION);
            let theta = if let Some(t) = guess.take() {
                grow = true;
                t
            } else if std::mem::take(&mut grow) && lo > 0.0 && above < hi {
                above
            } else {
                next_fraction(lo, e_lo, hi, e_hi)
            };
            let (r, i, e, holds) = self.project_judged(
                model,
                state,
                h,
                search,
                rs,
                tally,
                theta,
                system.as_deref_mut(),
            );
            last_is_kept = holds;
            if holds {
                (lo, e_lo) = (theta, e);
                rs.kept.save(state);
                kept = Some((r, i, e));
            } else {
                (hi, e_hi) = (theta, if r.converged { e } else { f64::INFINITY });
            }
            if hi - lo <= FRACTION_PRECISION * hi || hi - lo <= FRACTION_RESOLUTION {
                break;
            }
        }
        if let Some(k) = kept {
            rs.last_fraction = Some(lo);
            return Some((k, lo, last_is_kept));
        }
        // Nothing of the gap fits: keep the base step's energy and fix the momenta.
        let (r, i, e, holds) = self.project_judged(model, state, h, search, rs, tally, 0.0, system);
        (r.converged && (holds || search.full_converged)).then_some(((r, i, e), 0.0, true))
    }

    /// [`Projector::project_fraction`] for `search`, tallied and judged: the report, the invariants, the rule's
    /// measure and whether it converged within the rule.
    #[allow(clippy::too_many_arguments)]
    fn project_judged<'d>(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        search: &Search,
        rs: &mut Restoration,
        tally: &mut Tally,
        theta: f64,
        system: Option<&mut (dyn SystemMetric + 'd)>,
    ) -> (ProjectionReport, Invariants, f64, bool) {
        let (r, i, check) = self.project_fraction(
            model,
            state,
            h,
            search.targets,
            rs,
            theta,
            system,
            search.anchor,
        );
        tally.add(&r);
        let rule = &search.rule;
        (
            r,
            i,
            rule.measure(&check),
            r.converged && rule.holds(&check),
        )
    }
}

/// What the fraction search of one step works with.
struct Search<'a> {
    targets: &'a Targets,
    /// The energy of fraction 0 (the base step's, with its rigid motion on the momentum targets), J.
    anchor: f64,
    rule: Rule,
    /// Whether the gap may be closed in part at all.
    allowed: bool,
    /// The full projection converged (and broke the rule), with the rule's measure `full_excess`.
    full_converged: bool,
    full_excess: f64,
}

/// A projection's result as the guard hands it on: the report, the invariants, the measure under the rule
/// and the fraction of the energy gap closed.
struct Outcome {
    rep: ProjectionReport,
    inv: Invariants,
    excess: f64,
    restored: f64,
}

/// What the guard's search of one step starts from: the step, the rule and the full projection's check.
struct Guard<'a> {
    model: &'a Model,
    h: f64,
    targets: &'a Targets,
    rule: Rule,
    first: QualityCheck,
    /// `H_target - H(x*, v*)`, J.
    gap: f64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::projection::test_support::{cube_model, stretched_and_moving};
    use crate::projection::ProjectionSettings;

    #[test]
    fn the_kinetic_energy_a_projection_cannot_remove_is_the_rigid_motions() {
        // A body in rigid motion (translating and spinning): all its kinetic energy is fixed by the momentum
        // rows; its deformational velocities add energy that is not.
        let model = cube_model(1e4, [0.0; 3]);
        let (mut state, targets) = stretched_and_moving(&model);
        let c = crate::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
        let (v0, w) = ([0.3, -0.1, 0.2], [0.5, 1.0, -2.0]);
        for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
            *v = [0, 1, 2].map(|a| v0[a] + cross(w, sub(*x, c))[a]);
        }
        let proj = Projector::new(ProjectionSettings::default()).unwrap();
        let kinetic = crate::invariants::measure(&model, &state).kinetic;
        let fixed = proj.fixed_kinetic(&model, &state, &targets);
        assert!(
            (fixed - kinetic).abs() <= 1e-12 * kinetic,
            "{fixed} vs {kinetic}"
        );
        // A squeeze on top: the kinetic energy grows, the fixed part does not.
        for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
            *v = [0, 1, 2].map(|a| v[a] + 0.2 * (x[a] - c[a]));
        }
        let squeezed = crate::invariants::measure(&model, &state).kinetic;
        let fixed_squeezed = proj.fixed_kinetic(&model, &state, &targets);
        assert!((fixed_squeezed - fixed).abs() <= 1e-9 * fixed && squeezed > 1.01 * kinetic);
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
