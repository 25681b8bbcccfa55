//! The end of one projection ([`Projector::project_once`]): choose the result (the converged iterate, the
//! best one, or q~), measure its correction, apply the optional impact bound, and report.

use super::evaluate::{d_norm, d_norm_from, evaluate, Eval};
use super::iteration::Run;
use super::problem::max_scaled;
use super::{Mirror, ProjectionReport, Projector};
use crate::invariants::Invariants;
use crate::math::{cross, dot, sub};
use crate::model::State;

impl Projector {
    /// Put the result into `state`: the converged iterate, else the best iterate if it improved on q~, else
    /// q~. Returns its evaluation and whether it is q~ itself, handed back by a buffer swap (`x_base`/`v_base`
    /// then hold stale rows, and the correction is 0: s = t = 0 at q~).
    pub(super) fn choose_result(&mut self, run: &mut Run, state: &mut State) -> (Eval, bool) {
        let report = &mut run.report;
        let mut fin = run.cur;
        // `grad` is at `x` (every evaluation into it is at the iterate it belongs to).
        self.grad_is_final = report.converged && run.grad_at_x;
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
            return (fin, base_returned);
        }
        report.fallback = true;
        let best = &run.best;
        if !best.is_base && best.norm < run.base_norm {
            let (xb, vb) = if best.in_x {
                (&self.x, &self.v)
            } else {
                (&self.x_best, &self.v_best)
            };
            state.x.clear();
            state.x.extend_from_slice(xb);
            state.v.clear();
            state.v.extend_from_slice(vb);
            fin = best.eval;
            run.s = best.s;
            run.t = best.t;
        } else {
            std::mem::swap(&mut state.x, &mut self.x_base);
            std::mem::swap(&mut state.v, &mut self.v_base);
            base_returned = true;
            report.evaluations += 1;
            let (x, v) = (&state.x, &state.v);
            fin = evaluate(&run.pb, x, v, 0.0, 0.0, &mut self.scratch, &mut self.grad);
            run.s = 0.0;
            run.t = 0.0;
            self.grad_is_final = true;
        }
        (fin, base_returned)
    }

    /// The D-norm of the correction `|q - q~|_D` of the result `fin` in `state`.
    pub(super) fn correction(
        &mut self,
        run: &mut Run,
        state: &State,
        fin: &Eval,
        base_returned: bool,
    ) -> f64 {
        let (pb, s, t) = (&run.pb, run.s, run.t);
        let (model, h) = (pb.model, pb.h);
        if base_returned {
            debug_assert!(s == 0.0 && t == 0.0, "q~ has s = t = 0");
            0.0
        } else if let Some(sys) = run.system.as_deref() {
            let dx = &mut self.system_rhs;
            for (d, (x, xb)) in dx.iter_mut().zip(state.x.iter().zip(&self.x_base)) {
                *d = sub(*x, *xb);
            }
            let h2 = h * h;
            let velocity: f64 = (0..model.num_vertices())
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
            d_norm_from(pb, s, t, sum)
        } else {
            let (xb, vb) = (&self.x_base, &self.v_base);
            d_norm(
                pb,
                &state.x,
                &state.v,
                s,
                t,
                xb,
                vb,
                &mut self.scratch.norms,
            )
        }
    }

    /// The optional impact bound (never hit by q~ itself: its correction is 0): where the correction exceeds
    /// it, scale the correction back onto it (conservation is then not exact, and the report says so).
    pub(super) fn bound_impact(&mut self, run: &mut Run, state: &mut State, fin: &mut Eval) {
        let Some(bound) = self.settings.impact_bound else {
            return;
        };
        let (pb, report) = (&run.pb, &mut run.report);
        let model = pb.model;
        let cap = bound * model.total_mass.sqrt() * model.length_scale;
        if !(report.correction > cap && report.correction.is_finite()) {
            return;
        }
        let beta = cap / report.correction;
        for i in 0..model.num_vertices() {
            for a in 0..3 {
                let (xb, vb) = (self.x_base[i][a], self.v_base[i][a]);
                state.x[i][a] = xb + beta * (state.x[i][a] - xb);
                state.v[i][a] = vb + beta * (state.v[i][a] - vb);
            }
        }
        run.s *= beta;
        run.t *= beta;
        report.bound_hit = true;
        report.correction = cap;
        self.grad_is_final = true; // both evaluations below are at the returned state
        report.evaluations += 1;
        let (x, v) = (&state.x, &state.v);
        *fin = evaluate(pb, x, v, run.s, run.t, &mut self.scratch, &mut self.grad);
        if fin.el.inverted > run.base_inverted || !fin.c.iter().all(|c| c.is_finite()) {
            // The scaled-back state inverts tets the base step did not: keep the base state.
            state.x.copy_from_slice(&self.x_base);
            state.v.copy_from_slice(&self.v_base);
            run.s = 0.0;
            run.t = 0.0;
            report.correction = 0.0;
            report.evaluations += 1;
            let (x, v) = (&state.x, &state.v);
            *fin = evaluate(pb, x, v, run.s, run.t, &mut self.scratch, &mut self.grad);
        }
        report.converged = max_scaled(pb, &fin.c) <= run.tol;
        report.fallback |= !report.converged;
    }

    /// The report and the invariants of the result `fin` in `state`; the metric's buffers go back to the
    /// projector for the next projection.
    pub(super) fn finish(
        &mut self,
        run: Run,
        state: &State,
        fin: &Eval,
        base_returned: bool,
    ) -> (ProjectionReport, Invariants) {
        let Run {
            pb,
            mut report,
            s,
            t,
            stalled,
            ..
        } = run;
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
        let targets = pb.targets;
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
        self.metric_factor = pb.metric_factor;
        self.metric_rows = pb.rows;
        self.expected_iterations = report.iterations;
        self.stalled = stalled;
        (report, inv)
    }
}
