//! The iteration of fepr-spec section 3 for one projection: the first evaluation and the rows' scales, the
//! rigid translation onto the centre-of-mass target, the warm start, the iterations (solve, step length,
//! halvings, acceptance) and the restarts with frozen vertices; `result` chooses and measures what it returns.

use super::evaluate::{
    evaluate, evaluate_energy, evaluate_step, evaluate_with_elastic, vertex_chunk, Eval,
};
use super::metric::system_direction;
use super::problem::{max_scaled, norm_scaled, Problem};
use super::step::Step;
use super::system::{solve_multipliers, Multipliers};
use super::warm_start::warm_start_velocities;
use super::{Metric, Mirror, ProjectionReport, Projector, Slack, SystemMetric, Targets, ROWS};
use crate::elasticity::{deformation_gradient, ElasticSummary};
use crate::exec::for_each_chunk_mut;
use crate::invariants::Invariants;
use crate::math::{sub, Vec3};
use crate::model::{Model, State};

/// Attempts per projection (the first plus restarts with frozen vertices, see [`ProjectionReport::restarts`]).
pub(super) const MAX_ATTEMPTS: usize = 3;

/// A trial point: its evaluation, scaled residual norm and slack values `(s, t)`.
type Candidate = (Eval, f64, f64, f64);

/// The best iterate of a projection so far (kept as the fallback where it does not converge).
pub(super) struct Best {
    pub(super) norm: f64,
    /// The best is q~ itself.
    pub(super) is_base: bool,
    pub(super) eval: Eval,
    pub(super) s: f64,
    pub(super) t: f64,
    /// The best iterate lives in `x`/`v` while it is the current one, and is moved to `x_best`/`v_best` by a
    /// buffer swap only when a later iterate replaces it: no copies per iteration.
    pub(super) in_x: bool,
}

/// What the stages of one projection ([`Projector::project_once`]) share: the problem, the current iterate's
/// evaluation and slack values, the best iterate and the report being filled.
pub(super) struct Run<'a, 's, 'd> {
    pub(super) pb: Problem<'a>,
    /// The base integrator's factorised position metric, while it is used (see [`SystemMetric`]).
    pub(super) system: Option<&'s mut (dyn SystemMetric + 'd)>,
    pub(super) report: ProjectionReport,
    pub(super) cur: Eval,
    pub(super) cur_norm: f64,
    pub(super) s: f64,
    pub(super) t: f64,
    /// `grad` holds the elastic gradient at the current iterate (the first evaluation may skip it).
    pub(super) grad_at_x: bool,
    /// The scaled residual norm, the inverted tets and the finiteness of q~.
    pub(super) base_norm: f64,
    pub(super) base_inverted: usize,
    pub(super) base_finite: bool,
    pub(super) best: Best,
    pub(super) tol: f64,
    /// The attempt stops where the diagonal stiffness metric stalls (`stalled`; see
    /// [`Projector::project_with`]).
    pub(super) stall_exit: bool,
    pub(super) stalled: bool,
}

impl Run<'_, '_, '_> {
    /// Make the current iterate the best if it is better and finite (after a translation or a warm start).
    fn keep_if_better(&mut self) {
        if self.cur_norm < self.best.norm && self.cur.c.iter().all(|c| c.is_finite()) {
            self.best.norm = self.cur_norm;
            self.best.is_base = false;
            self.best.eval = self.cur;
            self.best.in_x = true;
        }
    }

    /// The current iterate meets every active row and inverts no tet the base step had upright.
    fn on_manifold(&self) -> bool {
        max_scaled(&self.pb, &self.cur.c) <= self.tol && self.cur.el.inverted <= self.base_inverted
    }
}

impl Projector {
    /// One projection of `state` onto `targets` (the iteration of fepr-spec section 3, with its restarts), in
    /// the metric of the settings or of `metric_override`; the quality guard and the metric switch are
    /// [`Projector::project_with`]'s.
    pub(super) fn project_once<'d>(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        targets: &Targets,
        system: Option<&mut (dyn SystemMetric + 'd)>,
    ) -> (ProjectionReport, Invariants) {
        self.take_base(model.num_vertices(), state);
        let mut run = self.start(model, h, targets, system);
        // Attempts: if an attempt ends with tets inverted that the base step had upright (a near-degenerate
        // sliver flipped by the position correction), freeze the positions of those tets' vertices (their
        // velocities stay free) and restart from q~. fepr-spec section 6, pitfall 5: the projection must not
        // create inverted elements.
        let mut attempt = 0;
        loop {
            self.translate_onto_center(&mut run);
            self.warm_start(&mut run);
            if run.base_finite {
                self.iterate(&mut run);
            }
            attempt += 1;
            if run.report.converged
                || run.stalled
                || !run.base_finite
                || attempt >= MAX_ATTEMPTS
                || run.cur.el.inverted <= run.base_inverted
                || !self.restart_with_frozen(&mut run)
            {
                break;
            }
        }
        let (mut fin, base_returned) = self.choose_result(&mut run, state);
        run.report.correction = self.correction(&mut run, state, &fin, base_returned);
        if !base_returned {
            self.bound_impact(&mut run, state, &mut fin);
        }
        self.finish(run, state, &fin, base_returned)
    }

    /// Size the iteration's buffers for `m` vertices and take q~ from `state`: it moves into `x_base`/`v_base`
    /// by a buffer swap (no copy), and is the current iterate itself until a trial point is accepted
    /// (`at_base`, see `current!`); the state's buffers get the result at the end.
    fn take_base(&mut self, m: usize, state: &mut State) {
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
        std::mem::swap(&mut self.x_base, &mut state.x);
        std::mem::swap(&mut self.v_base, &mut state.v);
        self.at_base = true;
        self.mirror = Mirror::None;
        self.mirror_rows = std::mem::take(&mut self.mirror_wanted);
        if self.mirror_rows {
            self.x_mirror.resize(m, [0.0; 3]);
        }
    }

    /// The problem of this projection, the metric it uses, and q~'s evaluation: the run the attempts start from.
    fn start<'a, 's, 'd>(
        &mut self,
        model: &'a Model,
        h: f64,
        targets: &'a Targets,
        system: Option<&'s mut (dyn SystemMetric + 'd)>,
    ) -> Run<'a, 's, 'd> {
        let m = model.num_vertices();
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
        let system = system.filter(|_| {
            self.settings.metric == Metric::Auto
                && self.metric_override.is_none()
                && energy_only
                && self.frozen_positions.is_empty()
        });
        if system.is_some() {
            self.system_rhs.resize(m, [0.0; 3]);
            self.system_dir.resize(m, [0.0; 3]);
        }
        let offered = self.base_elastic.take();
        let (cur, grad_at_x) = self.first_evaluation(&pb, offered);
        if slack {
            // P* and L* (about C_target) of the base step's state, summed by that evaluation. Without slack the
            // s and t columns vanish (their gradients are -(P* - P_t) and -(L* - L_t)).
            pb.dp_star = sub(cur.momentum, targets.momentum);
            pb.dl_star = sub(cur.angular_momentum, targets.angular_momentum);
        }
        pb.set_row_scales(self.settings.tolerance);
        let report = ProjectionReport {
            active_rows: pb.active.iter().filter(|a| **a).count(),
            initial_residual: max_scaled(&pb, &cur.c),
            base_energy: cur.kinetic + cur.el.energy + cur.gravitational,
            base_min_j: cur.el.min_j,
            stiffness_metric: self.uses_stiffness_metric() && system.is_none(),
            system_metric: system.is_some(),
            evaluations: usize::from(offered.is_none()),
            ..Default::default()
        };
        let cur_norm = norm_scaled(&pb, &cur.c);
        self.x_best.resize(m, [0.0; 3]);
        self.v_best.resize(m, [0.0; 3]);
        let stall_exit = self.switch_on_stall && report.stiffness_metric;
        Run {
            system,
            report,
            cur,
            cur_norm,
            s: 0.0,
            t: 0.0,
            grad_at_x,
            base_norm: cur_norm,
            base_inverted: cur.el.inverted,
            base_finite: cur.c.iter().all(|c| c.is_finite()),
            best: Best {
                norm: cur_norm,
                is_base: true,
                eval: cur,
                s: 0.0,
                t: 0.0,
                in_x: false,
            },
            tol: self.settings.tolerance,
            stall_exit,
            stalled: false,
            pb,
        }
    }

    /// q~'s evaluation (at s = t = 0), and whether it left the elastic gradient in `grad`: the base step's
    /// own where it `offered` it, none where a warm start is possible.
    fn first_evaluation(&mut self, pb: &Problem, offered: Option<ElasticSummary>) -> (Eval, bool) {
        let (s, t) = (0.0, 0.0);
        // With a warm start possible, the first evaluation skips the elastic gradient: the warm start changes
        // the velocities alone and often leaves nothing to iterate (after Projective Dynamics, most steps), so the
        // gradient is computed only when an iteration needs it (`grad_at_x`).
        let lazy_gradient = self.settings.warm_start_threshold.is_finite();
        let cur = if let Some(el) = offered {
            // The base step evaluated the elastic energy and gradient here (the same bits as evaluating).
            let (x, v) = current!(self);
            let grad = Some(&self.grad[..]);
            evaluate_with_elastic(pb, x, v, s, t, el, grad, &mut self.scratch.parts)
        } else if lazy_gradient {
            let (x, v) = current!(self);
            evaluate_energy(pb, x, v, s, t, &mut self.scratch.parts)
        } else {
            let (x, v) = current!(self);
            evaluate(pb, x, v, s, t, &mut self.scratch, &mut self.grad)
        };
        (cur, offered.is_some() || !lazy_gradient)
    }

    /// The centre-of-mass rows alone have a rigid closest point: translate the body onto C_target (the mass
    /// metric's first step would; the diagonal stiffness metric cannot move a body rigidly, and its iterates
    /// would deform a falling body to meet these rows). A translation changes neither the elastic energy nor
    /// its gradient.
    fn translate_onto_center(&mut self, run: &mut Run) {
        let (model, tol) = (run.pb.model, run.tol);
        if !(run.base_finite
            && run.pb.active[7..10].iter().all(|&a| a)
            && rigid_translation_allowed(model, &self.frozen_positions))
        {
            return;
        }
        let d = sub(run.pb.targets.center_of_mass, run.cur.com);
        if !(0..3).any(|a| (d[a] / run.pb.row_scale[7 + a]).abs() > tol) {
            return;
        }
        self.leave_base();
        let m = model.num_vertices();
        for_each_chunk_mut(&mut self.x, vertex_chunk(m), |_, xs| {
            for xi in xs.iter_mut() {
                *xi = [xi[0] + d[0], xi[1] + d[1], xi[2] + d[2]];
            }
        });
        self.reevaluate_same_elastic(run);
        run.report.translated = true;
        run.keep_if_better();
    }

    /// Re-evaluates the constraints after a change that leaves the elastic energy (and its gradient, if
    /// computed) at `x` as they were: a rigid translation, or velocities alone.
    fn reevaluate_same_elastic(&mut self, run: &mut Run) {
        let grad = run.grad_at_x.then_some(&self.grad[..]);
        run.cur = evaluate_with_elastic(
            &run.pb,
            &self.x,
            &self.v,
            run.s,
            run.t,
            run.cur.el,
            grad,
            &mut self.scratch.parts,
        );
        run.cur_norm = norm_scaled(&run.pb, &run.cur.c);
    }

    /// Opt-in warm start for large energy errors (a dissipative base step at a large dt can lose most of H in
    /// one step): scale the deformational velocities, which meets the energy row and keeps P and L; the
    /// iterations then fix the rest from nearby instead of linearising a stiff position correction far from
    /// the manifold.
    fn warm_start(&mut self, run: &mut Run) {
        let pb = &run.pb;
        let threshold = self.settings.warm_start_threshold.max(run.tol);
        if !(run.base_finite && pb.active[0] && (run.cur.c[0] / pb.row_scale[0]).abs() > threshold)
        {
            return;
        }
        // The warm start changes the velocities in place: the iterate gets buffers of its own.
        self.leave_base();
        let parts = &mut self.scratch.kinetic;
        if !warm_start_velocities(pb, &run.cur, &self.x, &mut self.v, parts) {
            return;
        }
        // Only the velocities changed: the elastic energy (and gradient, if computed) at x still hold.
        self.reevaluate_same_elastic(run);
        run.report.warm_start = true;
        run.keep_if_better();
    }

    /// The iterations of one attempt: until every row is within tolerance, no admissible step is left, the
    /// diagonal stiffness metric stalls, or `max_iterations`.
    fn iterate(&mut self, run: &mut Run) {
        for _ in 0..self.settings.max_iterations {
            if max_scaled(&run.pb, &run.cur.c) <= run.tol {
                // On the manifold; with new inversions, iterating further cannot help: restart.
                run.report.converged = run.cur.el.inverted <= run.base_inverted;
                break;
            }
            self.prepare_solve(run);
            let Multipliers {
                lambda,
                least_squares,
                offset,
            } = solve_multipliers(&run.pb, &run.cur, self.settings.regularization);
            run.report.least_squares_solves += least_squares as usize;
            let accepted = self.search_step(run, &lambda, &offset);
            run.report.iterations += 1;
            let Some(candidate) = accepted else {
                break; // no admissible step: stop, keep the best so far
            };
            let previous_norm = self.accept(run, candidate);
            // The diagonal stiffness metric cannot move the body rigidly (its position directions are scaled
            // per vertex): where the rows need a rigid correction that the translation before the iteration
            // did not make, its iterates deform the body and stall. Under `Metric::Auto` the caller then tries
            // the mass metric (`stalled`).
            if run.stall_exit
                && run.report.iterations >= 2
                && run.cur_norm > 0.9 * previous_norm
                && max_scaled(&run.pb, &run.cur.c) > run.tol
            {
                run.stalled = true;
                break;
            }
        }
        if !run.report.converged && run.on_manifold() {
            run.report.converged = true;
        }
    }

    /// What the solve needs at the current iterate: the elastic gradient and S's moments where the evaluation
    /// skipped them, and with a [`SystemMetric`] the energy row's direction in it.
    fn prepare_solve(&mut self, run: &mut Run) {
        let (pb, s, t) = (&run.pb, run.s, run.t);
        if !run.grad_at_x {
            // The same constraint values (the same bits for Neo-Hookean and ARAP, whose energy-only and
            // gradient passes are gated bit-identical), now with the gradient and S's moments.
            run.report.evaluations += 1;
            let (x, v) = current!(self);
            run.cur = evaluate(pb, x, v, s, t, &mut self.scratch, &mut self.grad);
            run.grad_at_x = true;
        } else if !run.cur.s_moments {
            // An accepted trial point (summed without S's moments, which most trial points, ending the
            // projection, never need): sum them now; the constraint values keep their bits.
            let grad = Some(&self.grad[..]);
            let parts = &mut self.scratch.parts;
            let (x, v) = current!(self);
            run.cur = evaluate_with_elastic(pb, x, v, s, t, run.cur.el, grad, parts);
        }
        if let Some(sys) = run.system.as_deref_mut() {
            // The energy row's position block in the metric W: its direction W^-1 grad U and S_HH's position
            // part grad U . W^-1 grad U (in place of the diagonal metric's moment).
            let (rhs, dir) = (&mut self.system_rhs, &mut self.system_dir);
            let parts = &mut self.scratch.norms;
            match system_direction(&run.pb, sys, &self.grad, rhs, dir, parts) {
                Some(gz) => run.cur.grad_sq_over_w = gz,
                None => {
                    run.system = None;
                    run.report.system_metric = false;
                    run.report.stiffness_metric = self.uses_stiffness_metric();
                }
            }
        }
    }

    /// The step along the multipliers `lambda` (with the solve's second-order `offset`): the full step, or the
    /// model's step length where the full step overshoots, halved while it does not lower the scaled residual
    /// norm. `None` where no step is admissible (finite).
    fn search_step(
        &mut self,
        run: &mut Run,
        lambda: &[f64; ROWS],
        offset: &[f64; ROWS],
    ) -> Option<Candidate> {
        let (pb, s, t, tol) = (&run.pb, run.s, run.t, run.tol);
        let dir = run.system.is_some();
        let report = &mut run.report;
        let mut alpha = 1.0;
        report.evaluations += 1;
        // Sum S's moments with the trial point where another iteration is expected after this one (backward
        // Euler takes two per step): the pass after an accepted trial is then not needed. Which pass sums them
        // changes no bits (the same task sums in the same order).
        let moments = report.iterations + 1 < self.expected_iterations;
        let mut cand = self.trial(pb, s, t, lambda, 1.0, moments, dir);
        // Curvature-aware step length: along the step, P and C are linear in alpha, L is quadratic, so
        // c(alpha) = (1 - alpha) c(0) + alpha^2 e with e = c(1) holds for them exactly and models H's curvature
        // (its row with the second-order offset, see `model_step_length`). Where the full step overshoots
        // (stiff materials), take the model's best alpha. A full step that already lands within the tolerance
        // (without inverting more tets than the base step) is taken as it is: the model's shorter step could
        // only improve on a converged point, for a serial search and, where it proposes one, a second
        // evaluation.
        let full_step_done =
            max_scaled(pb, &cand.0.c) <= tol && cand.0.el.inverted <= run.base_inverted;
        if !full_step_done && cand.0.c.iter().all(|c| c.is_finite()) {
            let a_star = model_step_length(pb, &run.cur.c, offset, &cand.0.c);
            if a_star < 0.95 {
                // Keep the full step's buffers aside, so that falling back to it needs no second evaluation.
                self.swap_trial_spare();
                report.evaluations += 1;
                let alt = self.trial(pb, s, t, lambda, a_star, moments, dir);
                if alt.0.c.iter().all(|c| c.is_finite()) && alt.1 < cand.1 {
                    cand = alt;
                    alpha = a_star;
                } else {
                    self.swap_trial_spare();
                }
            }
        }
        let max_halvings = self.settings.max_halvings;
        for halving in 0..=max_halvings {
            if halving > 0 {
                report.evaluations += 1;
                cand = self.trial(pb, s, t, lambda, alpha, moments, dir);
            }
            // Intermediate iterates may pass through states with more inverted tets (the linearisation does
            // not know about inversion); only the returned state must not have more than the base step
            // (checked by the attempts).
            let admissible = cand.0.c.iter().all(|c| c.is_finite());
            if admissible && (cand.1 < run.cur_norm || halving == max_halvings) {
                return Some(cand);
            }
            if halving < max_halvings {
                report.halvings += 1;
            }
            alpha *= 0.5;
        }
        None
    }

    /// Make the accepted trial point the current iterate (by buffer swaps), and the best if it is; returns the
    /// previous iterate's scaled residual norm.
    fn accept(&mut self, run: &mut Run, (trial, n, s_new, t_new): Candidate) -> f64 {
        // From q~ itself, the trial buffers get x/v's stale rows (overwritten by the next trial).
        std::mem::swap(&mut self.x, &mut self.x_trial);
        self.mirror = match self.mirror {
            Mirror::Trial => Mirror::Iterate,
            _ => Mirror::None,
        };
        std::mem::swap(&mut self.v, &mut self.v_trial);
        std::mem::swap(&mut self.grad, &mut self.grad_trial);
        // (`best.in_x` implies the iterate was in x/v, never q~: see `leave_base`.)
        self.at_base = false;
        run.cur = trial;
        let previous_norm = std::mem::replace(&mut run.cur_norm, n);
        run.s = s_new;
        run.t = t_new;
        let best = &mut run.best;
        if n < best.norm && run.cur.el.inverted <= run.base_inverted {
            best.norm = n;
            best.is_base = false;
            best.eval = run.cur;
            best.s = run.s;
            best.t = run.t;
            best.in_x = true;
        } else if best.in_x {
            // The best iterate was just swapped into the trial buffers: keep it.
            std::mem::swap(&mut self.x_trial, &mut self.x_best);
            std::mem::swap(&mut self.v_trial, &mut self.v_best);
            best.in_x = false;
        }
        previous_norm
    }

    /// After an attempt that inverted tets the base step had upright: freeze the positions of their vertices
    /// and restart from q~. False where no vertex was newly frozen (then the attempts end).
    fn restart_with_frozen(&mut self, run: &mut Run) -> bool {
        let (x, _) = current!(self);
        let model = run.pb.model;
        let frozen = freeze_newly_inverted(model, &self.x_base, x, &mut run.pb.metric_factor);
        if frozen > 0 {
            self.metric_source = None;
        }
        run.pb.refresh_rows();
        if frozen == 0 {
            return false;
        }
        let report = &mut run.report;
        // Frozen positions are outside what the factorised metric can hold: the diagonal one restarts.
        if run.system.take().is_some() {
            report.system_metric = false;
            report.stiffness_metric = self.uses_stiffness_metric();
        }
        report.restarts += 1;
        report.frozen_vertices += frozen;
        if run.best.in_x {
            self.x_best.copy_from_slice(&self.x);
            self.v_best.copy_from_slice(&self.v);
            run.best.in_x = false;
        }
        self.at_base = true;
        self.mirror = Mirror::None;
        run.s = 0.0;
        run.t = 0.0;
        report.evaluations += 1;
        let (x, v) = current!(self);
        run.cur = evaluate(
            &run.pb,
            x,
            v,
            run.s,
            run.t,
            &mut self.scratch,
            &mut self.grad,
        );
        run.grad_at_x = true;
        run.cur_norm = norm_scaled(&run.pb, &run.cur.c);
        true
    }
}

impl Projector {
    /// Give the current iterate buffers of its own (`x`/`v`, a copy of q~) if it is still q~ itself.
    pub(super) fn leave_base(&mut self) {
        if std::mem::take(&mut self.at_base) {
            self.x.copy_from_slice(&self.x_base);
            self.v.copy_from_slice(&self.v_base);
            self.mirror = Mirror::None;
        }
    }

    /// Exchange the trial buffers with the spare ones (sized on first use).
    pub(super) fn swap_trial_spare(&mut self) {
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
    pub(super) fn trial(
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
pub(super) fn model_step_length(
    pb: &Problem,
    c0: &[f64; ROWS],
    d: &[f64; ROWS],
    e: &[f64; ROWS],
) -> f64 {
    // Per row, c(alpha) = k0 + k1 alpha + k2 alpha^2 with k0 = c0, k1 = -(c0 + d), k2 = d + e (scaled), so the
    // squared norm is a quartic in alpha with the six sums of products of k0, k1, k2: computed once, not
    // ten rows (and ten divisions) at each of the search's 125 points (the search is serial).
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

/// Whether the projection may translate the whole body (no vertex pinned, none held in contact).
pub(super) fn rigid_translation_allowed(model: &Model, frozen_positions: &[u32]) -> bool {
    frozen_positions.is_empty() && model.num_pinned() == 0
}

/// Set `a_i = 0` (freeze the position) for every not yet frozen vertex of a tet that is inverted (`J <= 0`) at
/// `x` but upright at `x_base`. Returns the number of vertices newly frozen.
pub(super) fn freeze_newly_inverted(
    model: &Model,
    x_base: &[Vec3],
    x: &[Vec3],
    factor: &mut [f64],
) -> usize {
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

#[cfg(test)]
mod tests {
    use crate::math::Vec3;
    use crate::projection::test_support::*;
    use crate::projection::{ProjectionSettings, Projector};

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
}
