//! The iteration of fepr-spec section 3 for one projection: the first evaluation and the rows' scales, the
//! rigid translation onto the centre-of-mass target, the warm start, the iterations (solve, step length,
//! halvings, acceptance), the restarts with frozen vertices, and the choice and measurement of the result.

use super::evaluate::{
    d_norm, d_norm_from, evaluate, evaluate_energy, evaluate_step, evaluate_with_elastic,
    vertex_chunk, Eval,
};
use super::metric::system_direction;
use super::problem::{max_scaled, norm_scaled, Problem};
use super::rounding_terms;
use super::step::Step;
use super::system::{solve_multipliers, Multipliers};
use super::warm_start::warm_start_velocities;
use super::{
    Metric, Mirror, ProjectionReport, Projector, Slack, SystemMetric, Targets, ROUNDING_ULPS, ROWS,
};
use crate::elasticity::deformation_gradient;
use crate::exec::for_each_chunk_mut;
use crate::invariants::Invariants;
use crate::math::{cross, dot, sub, Vec3};
use crate::model::{Model, State};

/// Attempts per projection (the first plus restarts with frozen vertices, see [`ProjectionReport::restarts`]).
pub(super) const MAX_ATTEMPTS: usize = 3;

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
