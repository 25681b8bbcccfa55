//! The quality guard (fepr-spec section 5b): how much of a step's energy gap the projection closes.
//!
//! An implicit step at a game time step (1/60 s, 1/30 s) removes the energy of the modes it cannot resolve. The
//! closest point that restores all of it puts the energy where it is cheapest in the projection's metric, and on a
//! real mesh that is the stiffest, worst-shaped tets, which it then inverts by the hundred where the base step
//! alone kept every tet upright. Conserving energy is no licence to destroy the mesh,
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
use super::ProjectionReport;
use crate::checkpoint::{as_count, Carry};
use crate::error::Result;
use crate::exec::{copy_rows2, for_each_mut};
use crate::math::{cross, dot, norm, sub, Vec3};
use crate::model::BLOCK;
use crate::model::{Model, State};

/// A copy of a state's positions and velocities.
#[derive(Clone, Debug, Default)]
pub(super) struct Snapshot {
    pub(super) x: Vec<Vec3>,
    pub(super) v: Vec<Vec3>,
}

impl Snapshot {
    pub(super) fn save(&mut self, state: &State) {
        copy_rows2(&state.x, &mut self.x, &state.v, &mut self.v);
    }
    pub(super) fn restore(&self, state: &mut State) {
        state.x.copy_from_slice(&self.x);
        state.v.copy_from_slice(&self.v);
    }
}

/// The guard's buffers, kept across steps.
#[derive(Clone, Debug, Default)]
pub(super) struct Restoration {
    /// The base step's state `(x*, v*)`.
    pub(super) base: Snapshot,
    /// The state of the largest fraction accepted so far.
    pub(super) kept: Snapshot,
    /// The full projection's state, where it did not converge (or the stiffness metric's, while the mass
    /// metric is tried).
    pub(super) full: Snapshot,
    parts: Vec<QualityCheck>,
    /// The bound that spares the full check where the correction is small (see [`Certificate`]).
    certificate: Certificate,
    /// Consecutive steps whose bound failed (at most 2), and the steps to go before it is tried again
    /// (`2^failures - 1`).
    certify_failures: u32,
    certify_wait: u32,
    /// The fraction of the gap the previous step's search accepted (`None`: it restored all of it, or no search
    /// ran): the first fraction this step's search tries, where it lies inside the bracket.
    pub(super) last_fraction: Option<f64>,
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
pub(super) struct QualityCheck {
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
pub(super) struct Rule {
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
    pub(super) fn measure(&self, c: &QualityCheck) -> f64 {
        if self.removing {
            ((self.base_min - c.min_now) / self.margin).max(0.0)
        } else {
            c.excess
        }
    }
    pub(super) fn holds(&self, c: &QualityCheck) -> bool {
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
    /// What the next steps' restorations depend on, into a checkpoint: the certificate's memory and back-off,
    /// and the fraction the last search accepted (the next search's first guess).
    pub(super) fn carry(&self, model: &Model, c: &mut Carry) {
        self.certificate.carry(model, "projection.certificate", c);
        c.put(
            "projection.certify_back_off",
            vec![self.certify_failures as f64, self.certify_wait as f64],
        );
        c.put_option("projection.last_fraction", self.last_fraction);
    }

    /// Back from [`Restoration::carry`].
    pub(super) fn resume(&mut self, model: &Model, c: &Carry) -> Result<()> {
        self.certificate
            .resume(model, "projection.certificate", c)?;
        let b = c.get_len("projection.certify_back_off", 2)?;
        self.certify_failures = as_count("projection.certify_back_off", b[0])? as u32;
        self.certify_wait = as_count("projection.certify_back_off", b[1])? as u32;
        self.last_fraction = c.option("projection.last_fraction")?;
        Ok(())
    }

    /// Check `state` against the base step's volume ratios (from the saved `(x*, v*)`). `same_positions`: the
    /// projection moved no position but by a translation (it took no iteration). The first check of a step
    /// (`first`) also keeps what the [`Certificate`] needs, when its bound is due to be tried again soon.
    pub(super) fn check(
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

    /// The rule for a projection that closes the energy gap `gap`, and its check of the full projection's
    /// result in `state` (report `rep`, smallest volume ratio `min_now`): by the [`Certificate`]'s bound where that settles it, else by the per-tet
    /// pass.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn judge_full(
        &mut self,
        model: &Model,
        h: f64,
        state: &State,
        rep: &ProjectionReport,
        min_now: f64,
        margin: f64,
        gap: f64,
    ) -> (Rule, QualityCheck) {
        let quick = Rule {
            removing: gap < 0.0,
            base_min: rep.base_min_j,
            margin,
        };
        let certified = rep
            .converged
            .then(|| self.certify(model, h, state, &quick, min_now))
            .flatten();
        // The verdict without the per-tet pass is the pass's (checked in debug builds): the bound is
        // conservative, and a removal's smallest ratio is the one the evaluations measured.
        #[cfg(debug_assertions)]
        if let Some(c) = &certified {
            let full = self.check(model, h, state, margin, rep.iterations == 0, false);
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
            None => self.check(model, h, state, margin, rep.iterations == 0, true),
        };
        let rule = Rule {
            base_min: first.base_min,
            ..quick
        };
        (rule, first)
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
}
