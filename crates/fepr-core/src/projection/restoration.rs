//! The quality guard (fepr-spec section 5b): how much of a step's energy gap the projection closes.
//!
//! An implicit step at a game time step (1/60 s, 1/30 s) removes the energy of the modes it cannot resolve. The
//! closest point that restores all of it puts the energy where it is cheapest in the projection's metric, and on a
//! real mesh that is the stiffest, worst-shaped tets: the seed's bunny2 at dt = 1/60 got 200-284 inverted tets in
//! 8 steps where the base step alone kept every tet upright. Conserving energy is no licence to destroy the mesh,
//! so restoration is constrained, per tet, on the quantity that inversion is about, the volume ratio `J = det F`
//! (a trust region on each tet's volume ratio). With `J*` the base step's and `J` the projected state's:
//!
//! - at the end of the step: `|J(x) - J(x*)| <= margin + 1/4 |J(x*) - J(x* - h v*)|`;
//! - one step ahead at the new velocities (the explicit prediction the next base step starts from; energy put
//!   into the velocities of a sliver shows up there, not in `x`):
//!   `|J(x + h v) - J(x* + h v*)| <= margin + 1/4 |J(x* + h v*) - J(x*)|`;
//! - and no tet that is upright in `x*` is inverted in `x`.
//!
//! The second terms let a tet change by a quarter of its own change over the step (`x* - h v*` is the start of the
//! step for every integrator): restoring a small loss in a motion the step resolves rescales each tet's motion by
//! a few percent, restoring what a step destroyed would rescale it many times over. Removing an excess (a base
//! step that gained energy) takes energy out and does not concentrate it: there the rule is on the worst tet only
//! (the smallest `J` within the margin of the base step's smallest, no tet inverted).
//!
//! Where the full projection breaks the rule (or does not converge), the projection closes the largest fraction
//! `theta` of the gap that keeps it, found by a safeguarded regula falsi on the rule's measure. Fraction 0 is the
//! energy the momentum targets give the base step's state (its rigid motion put on them), so only the internal
//! energy is limited; momentum and centre-of-mass rows are always enforced in full. The rest is the step's
//! unresolved energy: the simulation books it as a budget source of its own, so the books `H = H_0 + budget_total`
//! still close. Where no projection converges within the rule, the step is a fallback (the full projection's
//! best iterate if it keeps the rule, else the base step's own state).
//!
//! The per-tet check runs chunk by chunk on locally gathered states, with the determinants of a few tets side by
//! side; where [`Certificate`]'s cheap bound shows that the correction cannot have moved any tet far enough to
//! matter, it does not run at all.

use super::certificate::{Certificate, Sensitivity};
use super::{Metric, ProjectionReport, Projector, SystemMetric, Targets};
use crate::exec::{copy_rows, for_each_mut};
use crate::invariants::Invariants;
use crate::math::{cross, dot, norm, sub, Vec3};
use crate::model::BLOCK;
use crate::model::{Model, State};

/// Projections tried after the full restoration failed the guard, before the fraction search stops.
const MAX_FRACTION_TRIALS: usize = 4;
/// The search stops when the bracket of the restored fraction is narrower than this share of its upper end.
const FRACTION_PRECISION: f64 = 0.2;
/// The regula falsi aims at this share of the margin, so that its estimate lands inside the trust region.
const AIM: f64 = 0.8;

/// A copy of a state's positions and velocities.
#[derive(Clone, Debug, Default)]
struct Snapshot {
    x: Vec<Vec3>,
    v: Vec<Vec3>,
}

impl Snapshot {
    fn save(&mut self, state: &State) {
        copy_rows(&state.x, &mut self.x);
        copy_rows(&state.v, &mut self.v);
    }
    fn restore(&self, state: &mut State) {
        state.x.copy_from_slice(&self.x);
        state.v.copy_from_slice(&self.v);
    }
}

/// The guard's buffers, kept across steps.
#[derive(Clone, Debug, Default)]
pub(super) struct Restoration {
    /// The base step's state `(x*, v*)`.
    base: Snapshot,
    /// The state of the largest fraction accepted so far.
    kept: Snapshot,
    /// The full projection's state, where it did not converge (or the stiffness metric's, while the mass
    /// metric is tried).
    full: Snapshot,
    parts: Vec<QualityCheck>,
    /// The bound that spares the full check where the correction is small (see [`Certificate`]).
    certificate: Certificate,
    /// Consecutive steps whose bound failed (at most 2), and the steps to go before it is tried again
    /// (`2^failures - 1`).
    certify_failures: u32,
    certify_wait: u32,
}

/// A tet's volume ratios in the base step's state: `J(x*)` and one step ahead, `J(x* + h v*)`.
#[derive(Clone, Copy, Debug, Default)]
struct TetBase {
    now: f64,
    ahead: f64,
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
    /// Smallest volume ratio of the base step's state.
    base_min: f64,
    /// The tets' sensitivity in the base step's state (for the [`Certificate`]).
    sensitivity: Sensitivity,
}

impl Default for QualityCheck {
    fn default() -> Self {
        Self {
            excess: 0.0,
            inverted: 0,
            min_now: f64::INFINITY,
            base_min: f64::INFINITY,
            sensitivity: Sensitivity::default(),
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
            sensitivity: Sensitivity::max(a.sensitivity, b.sensitivity),
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

/// A tet's measure under the per-tet trust region: its change now and one step ahead over the change it may
/// undergo, `margin + MOTION_SHARE * (its own change over the step)`. Computed from the margin alone where the
/// change is within it (then the measure is at most `change / margin <= 1`); the tet's own motion, which needs
/// `J(x* - h v*)` (`before`, the start of the step for every integrator), only where it is not.
#[inline]
fn tet_excess(
    base: &TetBase,
    now: f64,
    ahead: f64,
    margin: f64,
    before: impl FnOnce() -> f64,
) -> f64 {
    if now.is_nan() || ahead.is_nan() {
        // A NaN ratio counts as an infinite change (`f64::max` would drop it).
        return f64::INFINITY;
    }
    let (dn, da) = ((now - base.now).abs(), (ahead - base.ahead).abs());
    if dn.max(da) <= margin {
        return dn.max(da) / margin;
    }
    let allowed = |change: f64| margin + MOTION_SHARE * change.abs();
    let (an, aa) = (allowed(base.now - before()), allowed(base.ahead - base.now));
    // Non-finite base ratios (a base step that blew up) allow any change: the guard cannot judge them.
    let ratio = |d: f64, a: f64| if a.is_finite() { d / a } else { 0.0 };
    ratio(dn, an).max(ratio(da, aa))
}

/// Tets per lane group of the guard's pass: their determinants are computed side by side, which the compiler
/// turns into packed arithmetic.
const LANES: usize = 4;

/// The volume ratios of `LANES` tets (corner `i` of lane `l` at local vertex `corners[i][l]`, `inv` their
/// `1 / (6 V_rest)`) in state `state` of the chunk's local states.
#[inline(always)]
fn lane_ratios(
    local: &[[Vec3; 4]],
    corners: &[[usize; LANES]; 4],
    state: usize,
    inv: &[f64; LANES],
) -> [f64; LANES] {
    // The edges from corner 0, by edge, axis and lane.
    let mut e = [[[0.0; LANES]; 3]; 3];
    for l in 0..LANES {
        let a = local[corners[0][l]][state];
        for k in 0..3 {
            let b = local[corners[k + 1][l]][state];
            for ax in 0..3 {
                e[k][ax][l] = b[ax] - a[ax];
            }
        }
    }
    let mut out = [0.0; LANES];
    for l in 0..LANES {
        let c0 = e[1][1][l] * e[2][2][l] - e[1][2][l] * e[2][1][l];
        let c1 = e[1][2][l] * e[2][0][l] - e[1][0][l] * e[2][2][l];
        let c2 = e[1][0][l] * e[2][1][l] - e[1][1][l] * e[2][0][l];
        out[l] = (e[0][0][l] * c0 + e[0][1][l] * c1 + e[0][2][l] * c2) * inv[l];
    }
    out
}

thread_local! {
    /// A chunk's vertex states in its local order (the guard's pass), reused by each thread.
    static LOCAL_STATES: std::cell::Cell<Vec<[Vec3; 4]>> = const { std::cell::Cell::new(Vec::new()) };
}

/// Upright before (`J > 0`), not after (`J <= 0` or NaN).
#[inline]
fn flipped(before: f64, after: f64) -> usize {
    (before > 0.0 && after.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)) as usize
}

impl Restoration {
    /// Check `state` against the base step's volume ratios (from the saved `(x*, v*)`). `same_positions`: the
    /// projection moved no position but by a translation (it took no iteration). The first check of a step
    /// (`first`) also keeps what the [`Certificate`] needs, when its bound is due to be tried again soon.
    fn check(
        &mut self,
        model: &Model,
        h: f64,
        state: &State,
        margin: f64,
        same_positions: bool,
        first: bool,
    ) -> QualityCheck {
        let keep = first && self.certify_wait == 0;
        let check = self.pass(model, h, state, margin, same_positions, keep);
        if keep {
            self.certificate
                .keep(model, &self.base.x, check.sensitivity);
        }
        check
    }

    /// The per-tet pass, chunk by chunk of the blocks: each chunk gathers its vertices' states once (the base
    /// step's now and one step ahead, `state`'s now and ahead) into a local buffer in its local order, and its
    /// tets read their corners there, a few side by side (as the elastic kernels do: gathering every tet's
    /// corners from the global arrays took twice as long). Nothing per tet is kept; with `keep_sensitivity`, the
    /// pass also takes the tets' sensitivity for the [`Certificate`].
    fn pass(
        &mut self,
        model: &Model,
        h: f64,
        state: &State,
        margin: f64,
        same_positions: bool,
        keep_sensitivity: bool,
    ) -> QualityCheck {
        let k = model.num_tets();
        let chunk = model.tet_chunk();
        let chunks = k.div_ceil(chunk);
        self.parts.resize(chunks, QualityCheck::default());
        let states = [
            &self.base.x[..],
            &self.base.v[..],
            &state.x[..],
            &state.v[..],
        ];
        let (blocks, sums) = (&model.tet_blocks.blocks, &model.corner_sums);
        for_each_mut(&mut self.parts, |c, part| {
            let mut local = LOCAL_STATES.take();
            local.clear();
            local.extend(sums.chunk_vertices(c).iter().map(|&v| {
                let v = v as usize;
                let [xb, vb, x, vn] = states.map(|a| a[v]);
                let ahead = |p: Vec3, q: Vec3| std::array::from_fn(|a| p[a] + h * q[a]);
                [xb, ahead(xb, vb), x, ahead(x, vn)]
            }));
            let mut sum = QualityCheck::default();
            let first = c * chunk;
            let len = chunk.min(k - first);
            for j0 in (0..len).step_by(LANES) {
                let n = LANES.min(len - j0);
                // The group's tets side by side: corner `i` of lane `l` at `corners[i][l]` (local indices),
                // unused lanes a copy of lane 0.
                let mut corners = [[0usize; LANES]; 4];
                let mut inv = [0.0; LANES];
                for l in 0..LANES {
                    let p = first + j0 + l.min(n - 1);
                    let block = &blocks[p / BLOCK];
                    for i in 0..4 {
                        corners[i][l] = block.loc[i][p % BLOCK] as usize;
                    }
                    inv[l] = 1.0 / (6.0 * block.vol[p % BLOCK]);
                }
                let ratios = |state: usize| lane_ratios(&local, &corners, state, &inv);
                let (now_base, ahead_base) = (ratios(0), ratios(1));
                // Positions the projection only translated keep their volume ratios.
                let now = if same_positions { now_base } else { ratios(2) };
                let ahead = ratios(3);
                for l in 0..n {
                    let base = TetBase {
                        now: now_base[l],
                        ahead: ahead_base[l],
                    };
                    // `x* - h v* = 2 x* - (x* + h v*)`: the start of the step.
                    let before = || {
                        let back = |i: usize| -> Vec3 {
                            let q = &local[corners[i][l]];
                            std::array::from_fn(|a| 2.0 * q[0][a] - q[1][a])
                        };
                        let (a, b, c, d) = (back(0), back(1), back(2), back(3));
                        dot(sub(b, a), cross(sub(c, a), sub(d, a))) * inv[l]
                    };
                    let tet = QualityCheck {
                        excess: tet_excess(&base, now[l], ahead[l], margin, before),
                        inverted: flipped(base.now, now[l]),
                        min_now: now[l],
                        base_min: base.now,
                        sensitivity: if keep_sensitivity {
                            let corner = |i: usize| local[corners[i][l]][0];
                            let longest = [1, 2, 3]
                                .map(|i| norm(sub(corner(i), corner(0))))
                                .into_iter()
                                .fold(0.0, f64::max);
                            Sensitivity::of_tet(longest, inv[l])
                        } else {
                            Sensitivity::default()
                        },
                    };
                    sum = QualityCheck::combine(sum, tet);
                }
            }
            LOCAL_STATES.set(local);
            *part = sum;
        });
        self.parts
            .iter()
            .copied()
            .fold(QualityCheck::default(), QualityCheck::combine)
    }

    /// The rule's verdict on `state` without the per-tet check, where [`Certificate`]'s bound settles it: the
    /// check it stands for (`min_now`, the returned state's smallest volume ratio, and `base_min`, the base
    /// step's, from the projection's evaluations), or `None` (the full check must run).
    fn certify(
        &mut self,
        model: &Model,
        h: f64,
        state: &State,
        rule: &Rule,
        min_now: f64,
    ) -> Option<QualityCheck> {
        if rule.removing && min_now > 0.0 {
            // Removing an excess is judged on the smallest volume ratio, which the projection's evaluations
            // measured, and on inversions, of which there are none: this is the full check's verdict.
            return Some(QualityCheck {
                excess: 0.0,
                inverted: 0,
                min_now,
                base_min: rule.base_min,
                sensitivity: Sensitivity::default(),
            });
        }
        // After failures the bound is tried less often: where the corrections are large (restoring at a game
        // step) it fails every step, and computing it would only add to the full check.
        if self.certify_wait > 0 {
            self.certify_wait -= 1;
            return None;
        }
        let base = (&self.base.x[..], &self.base.v[..]);
        // Nothing kept yet (the first step, another model): not a failure of the bound.
        let bound = self.certificate.bound(model, h, base, state)?;
        // No tet can have flipped: every base ratio is at least `base_min`, and none moved by more than `bound`
        // (or no tet is inverted at all).
        let no_flip = bound < rule.base_min || min_now > 0.0;
        let check = QualityCheck {
            excess: bound / rule.margin,
            inverted: 0,
            min_now,
            base_min: rule.base_min,
            sensitivity: Sensitivity::default(),
        };
        let certified = no_flip && rule.holds(&check);
        if certified {
            self.certify_failures = 0;
        } else {
            self.certify_failures = (self.certify_failures + 1).min(2);
            self.certify_wait = (1 << self.certify_failures) - 1;
        }
        certified.then_some(check)
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
    /// The change of kinetic energy that putting the rigid part of `v` on the momentum targets would make, J
    /// (the warm start's rigid part: `V = P_target / m`, `omega = I^-1 L_target` about the centre of mass; the
    /// deformational rest carries no momenta, so it keeps its energy). 0 where the momentum rows do not hold the
    /// whole body (pins, rows off, slack free) or the body is degenerate.
    fn momentum_energy(&self, model: &Model, x: &[Vec3], v: &[Vec3], targets: &Targets) -> f64 {
        let rows = self.active_rows(model, targets);
        let slack = match self.settings.slack {
            super::Slack::On => true,
            super::Slack::Off => false,
            super::Slack::Auto => targets.uncertain_impulses,
        };
        if model.num_pinned() > 0 || !rows[1..7].iter().all(|&a| a) || slack {
            return 0.0;
        }
        let rigid = crate::invariants::rigid_motion(&model.masses, x, v);
        let Some(inv) = rigid.inertia_inv else {
            return 0.0;
        };
        let m = rigid.mass;
        let vt = targets.momentum.map(|p| p / m);
        let offset = cross(sub(rigid.center, targets.center_of_mass), vt);
        let l_t = [0, 1, 2].map(|a| targets.angular_momentum[a] - m * offset[a]);
        let spin = |l: Vec3| {
            let w = [0, 1, 2].map(|a| (0..3).map(|b| inv[a][b] * l[b]).sum::<f64>());
            0.5 * dot(w, l)
        };
        let k_now = 0.5 * dot(rigid.momentum, rigid.momentum) / m + spin(rigid.angular_momentum);
        let k_next = 0.5 * m * dot(vt, vt) + spin(l_t);
        k_next - k_now
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
    /// ([`crate::integrators::Integrator::system_metric`]; used under [`Metric::Auto`] where the energy is the
    /// only active row and no position is frozen, see [`SystemMetric`]). Returns the report and the invariants
    /// measured at the returned state.
    ///
    /// Around the iteration of fepr-spec section 3 (`project_once`):
    /// - the metric switch: under [`Metric::Auto`] after an implicit base step, an iteration in the diagonal
    ///   stiffness metric that makes no progress (its scaled residual falls by less than a tenth in an iteration
    ///   after the first) restarts from `(x*, v*)` in the mass metric (`metric_switched`); the better result of
    ///   the two is kept;
    /// - the quality guard (see the module [`restoration`](self)): where closing the whole energy gap breaks
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
        let mut tally = Tally::default();
        let (mut rep, mut inv, switched) = self.project_full(
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
        let mut restored = 1.0;
        let mut excess = 0.0;
        if let (Some(margin), true) = (margin, base_energy.is_finite()) {
            let quick = Rule {
                removing: gap < 0.0,
                base_min: rep.base_min_j,
                margin,
            };
            let certified = rep
                .converged
                .then(|| rs.certify(model, h, state, &quick, inv.min_j))
                .flatten();
            // The verdict without the per-tet pass is the pass's (checked in debug builds): the bound is
            // conservative, and a removal's smallest ratio is the one the evaluations measured.
            #[cfg(debug_assertions)]
            if let Some(c) = &certified {
                let full = rs.check(model, h, state, margin, rep.iterations == 0, false);
                if quick.removing {
                    assert_eq!(full.inverted, 0, "a removal certified with an inverted tet");
                    assert!((full.min_now - c.min_now).abs() <= 1e-9 * c.min_now.abs().max(1.0));
                } else {
                    assert!(
                        quick.holds(&full),
                        "a certified step breaks the quality rule"
                    );
                }
            }
            let first = match certified {
                Some(check) => check,
                None => rs.check(model, h, state, margin, rep.iterations == 0, true),
            };
            let rule = Rule {
                base_min: first.base_min,
                ..quick
            };
            excess = rule.measure(&first);
            if !(rep.converged && rule.holds(&first)) {
                let tolerance = self.settings.tolerance * targets.energy_scale;
                // The fractions run from the energy the momentum targets alone give the base step's state (its
                // rigid motion put on them: a spinning body that lost angular momentum gets its rotational energy
                // back with it) to the full target: only the rest, the internal energy, is the guard's to limit.
                let anchor =
                    base_energy + self.momentum_energy(model, &rs.base.x, &rs.base.v, targets);
                let rest = targets.energy - anchor;
                let search = Search {
                    targets,
                    anchor,
                    rule,
                    // An excess that the full projection could not remove (it did not converge) is not reduced:
                    // keeping part of the energy a base step gained would feed a runaway.
                    allowed: rest > tolerance || (rest < -tolerance && rep.converged),
                    full_converged: rep.converged,
                    full_excess: excess,
                };
                // A full projection that did not converge but keeps the rule is the fallback if no fraction
                // converges either: then it was not the energy that stopped it.
                let full = (!rep.converged && rule.holds(&first)).then(|| {
                    rs.full.save(state);
                    (rep, inv, excess)
                });
                let chosen =
                    self.search_fraction(model, state, h, &search, &mut rs, &mut tally, system);
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
                    (None, Some((r, i, e))) => {
                        rs.full.restore(state);
                        self.invalidate_hand_over();
                        (rep, inv, excess) = (r, i, e);
                    }
                    (None, None) => {
                        // Every projection broke the rule or failed: the base step's state, unprojected (the
                        // references keep their targets, so the next step tries again).
                        let base_residual = rep.initial_residual;
                        rs.base.restore(state);
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
        self.restoration = rs;
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
        for _ in 0..MAX_FRACTION_TRIALS {
            let theta = next_fraction(lo, e_lo, hi, e_hi);
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
            if hi - lo <= FRACTION_PRECISION * hi {
                break;
            }
        }
        if let Some(k) = kept {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flipped_tet_counts_as_inverted_and_a_nan_as_infinite() {
        let base = TetBase {
            now: 0.5,
            ahead: 0.5,
        };
        // Moved by 0.6 with no motion of its own: 0.6 / 0.05.
        assert!((tet_excess(&base, -0.1, 0.5, 0.05, || 0.5) - 12.0).abs() < 1e-12);
        assert_eq!(flipped(0.5, -0.1), 1);
        assert_eq!(flipped(0.5, f64::NAN), 1);
        assert!(tet_excess(&base, f64::NAN, 0.5, 0.05, || 0.5).is_infinite());
        // Already inverted in the base step: not a new inversion, only its change counts.
        assert_eq!(flipped(-0.2, -0.21), 0);
        let inverted = TetBase { now: -0.2, ..base };
        assert!(tet_excess(&inverted, -0.21, 0.5, 0.05, || -0.2) <= 1.0);
    }

    #[test]
    fn a_tet_may_change_by_the_margin_plus_a_share_of_its_own_motion() {
        // A unit tet compressed along z at 0.3 m/s, over a step of 0.1 s: J 1.03 before, 1 now, 0.97 ahead.
        let (before, now, ahead) = (1.03, 1.0, 0.97);
        let base = TetBase { now, ahead };
        // Within the margin: measured against it alone, without the tet's motion.
        let untouched = || -> f64 { unreachable!("not needed within the margin") };
        assert!((tet_excess(&base, 1.04, 0.97, 0.05, untouched) - 0.8).abs() < 1e-12);
        // Beyond it: the margin plus a quarter of its own change, 0.03, now and ahead.
        let allowed = 0.05 + MOTION_SHARE * 0.03;
        assert!((tet_excess(&base, 1.06, 0.97, 0.05, || before) - 0.06 / allowed).abs() < 1e-12);
        assert!((tet_excess(&base, 1.0, 1.03, 0.05, || before) - 0.06 / allowed).abs() < 1e-12);
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
            sensitivity: Sensitivity::default(),
        };
        assert!(removing.holds(&check(0.46, 0)));
        assert!((removing.measure(&check(0.4, 0)) - 2.0).abs() < 1e-12);
        assert!(!removing.holds(&check(0.4, 0)));
        assert!(!removing.holds(&check(0.6, 1)));
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
