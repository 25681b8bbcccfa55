//! Backward (implicit) Euler as an optimisation (fepr-spec section 5):
//!
//! ```text
//! x_{n+1} = argmin_x  Phi(x) = 1/(2 h^2) |x - y|_M^2 + E_el(x) + E_grav(x),   y = x_n + h v_n
//! v_{n+1} = (x_{n+1} - x_n) / h
//! ```
//!
//! solved by Newton's method, a sparse Cholesky factorisation whose symbolic analysis is done once per mesh and
//! pin set (redone when [`Model::structure_key`] changes, e.g. after pins were changed between steps) and reused
//! for every numeric factorisation, and a backtracking (Armijo) line search.
//! Pinned degrees of freedom are eliminated. A step's first iteration factorises; the iterations after it solve
//! their Newton systems (exact Hessian) by conjugate gradients preconditioned with that factor, to a relative
//! residual that tightens with the decrement (inexact Newton), and factorise again only when conjugate gradients
//! need many iterations (the factor went stale) or meet negative curvature. Near the solution the Hessian
//! hardly changes, so the last iterations, which decide convergence, cost a few solves instead of a
//! factorisation each (measured on the 19,379-tet bunny at dt = 1/30: 4 factorisations per step become 1 to 2).
//! The factor is not kept across steps: with it, the first iterations of a step needed more conjugate gradient
//! iterations than a factorisation costs, and a resumed checkpoint would have to rebuild it.
//! A factorisation first tries the exact Hessian
//! `M/h^2 + d2E_el`; only when that is not positive definite are the element Hessians projected to positive
//! semi-definite (and the matrix refactorised). The projected Hessian always gives a descent direction, but it
//! is not the Hessian: where many elements are compressed (typically after FEPR has put the dissipated energy
//! back), projected Newton converges only linearly (about 0.8 per iteration on the 0.5 m bunny, so 20
//! iterations reached a relative decrement of 1e-3 to 1e-2), while the exact Hessian, positive definite
//! thanks to the mass term in most iterations, converges quadratically near the solution.
//! Backward Euler is unconditionally stable but numerically dissipative: FEPR on top restores the energy.
//!
//! Obstacles ([`Integrator::set_obstacles`]) enter `Phi` as the contact penalty `E_c`
//! ([`ContactPotential`]: gradient and Gauss-Newton Hessian blocks), so the elastic response to a contact is
//! solved with it and the push-out after the step only repairs the penalty's micrometre depth.

use crate::elasticity::HessianAssembler;
use crate::elasticity::{
    elastic_energy, elastic_energy_gradient, ElasticSummary, ElasticWorkspace,
};
use crate::error::{invalid, FeprError, Result};
use crate::integrators::{finish_positional_step, HandOver, Integrator, StepReport};
use crate::math::{add, dot, scale, sub, Vec3};
use crate::math::{solve_preconditioned, SparseCholesky};
use crate::model::{Model, ModelKey, State};
use crate::world::{ContactPotential, ContactReport, Obstacle};

/// Newton settings for backward Euler.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NewtonSettings {
    /// Stop when the Newton decrement `lambda = sqrt(g^T H^-1 g)` falls below `tolerance` times its value at
    /// the first iteration (default 1e-6).
    pub tolerance: f64,
    /// Maximum Newton iterations per step (default 20).
    pub max_iterations: usize,
    /// Project element Hessians to positive semi-definite when the exact Hessian is not positive definite
    /// (default true; false only for tests: then a failed factorisation ends the step).
    pub project_psd: bool,
}

impl Default for NewtonSettings {
    fn default() -> Self {
        Self {
            tolerance: 1e-6,
            max_iterations: 20,
            project_psd: true,
        }
    }
}

impl NewtonSettings {
    pub fn validate(&self) -> Result<()> {
        if !(self.tolerance.is_finite() && self.tolerance > 0.0 && self.tolerance < 1.0) {
            return Err(invalid(
                "newton_tolerance",
                format!("must satisfy 0 < tolerance < 1, got {}", self.tolerance),
            ));
        }
        if self.max_iterations == 0 || self.max_iterations > 1000 {
            return Err(invalid(
                "newton_max_iterations",
                format!("must be in 1..=1000, got {}", self.max_iterations),
            ));
        }
        Ok(())
    }
}

/// The tightest relative residual `|H d + g| / |g|` asked of conjugate gradients (near the solution).
const CG_TOLERANCE: f64 = 1e-8;
/// The loosest relative residual asked of conjugate gradients (far from the solution).
const CG_LOOSEST: f64 = 1e-2;
/// Conjugate gradient iterations after which a Newton system is factorised instead.
const CG_MAX_ITERATIONS: usize = 10;
/// Conjugate gradient iterations above which the next Newton iteration factorises (the factor went stale).
const CG_REFACTOR: usize = 5;
/// A vertex the solve leaves deeper than this share of the mean rest edge inside an obstacle gets a stiffer penalty
/// and the solve continues ([`ContactPotential::stiffen_deep`]): the depth a test of contact allows.
const DEEP_CONTACT_FRACTION: f64 = 0.01;
/// How many times a step may stiffen its deep vertices' penalty.
const DEEP_CONTACT_ROUNDS: usize = 3;
/// The factor of each stiffening.
const DEEP_CONTACT_STIFFENING: f64 = 10.0;
/// The stiffest penalty, in units of the plain one (a vertex keeps its stiffening from step to step while it stays
/// in an obstacle's reach, [`ContactPotential::relax_stiffening`]).
const DEEP_CONTACT_MOST: f64 = 1e3;

/// Backward Euler with Newton's method and a reused sparse symbolic factorisation.
#[derive(Debug, Default)]
pub struct ImplicitEuler {
    pub settings: NewtonSettings,
    assembler: Option<HessianAssembler>,
    cholesky: Option<SparseCholesky>,
    /// The model's [`Model::structure_key`] that `assembler` and `cholesky` were built for.
    structure: Option<ModelKey>,
    /// Symbolic analyses performed (one per mesh and pin set).
    pub symbolic_analyses: usize,
    /// Newton decrements of the last step, one per iteration (for convergence studies).
    pub last_decrements: Vec<f64>,
    /// Numeric factorisations and conjugate gradient iterations of the last step's Newton systems.
    pub last_factorisations: usize,
    pub last_cg_iterations: usize,
    values: Vec<f64>,
    /// The gradient of `Phi` at the current iterate.
    grad: Vec<Vec3>,
    /// Its elastic part, and the elastic energy summary (handed over where the step ends on the iterate).
    elastic_grad: Vec<Vec3>,
    elastic: ElasticSummary,
    ws: ElasticWorkspace,
    y: Vec<Vec3>,
    x_trial: Vec<Vec3>,
    rhs: Vec<f64>,
    neg_grad: Vec<f64>,
    /// The obstacles as a penalty in `Phi` (empty: none).
    contact: ContactPotential,
    /// The factor holds this step's exact Hessian at an earlier iterate (conjugate gradients may use it).
    factor_fresh: bool,
    /// The last factorisation was of the projected (positive semi-definite) Hessian.
    projected: bool,
    /// Conjugate gradients have not failed yet in this step.
    cg_usable: bool,
    /// Depth inside an obstacle past which a vertex's penalty is stiffened after the solve, m
    /// ([`DEEP_CONTACT_FRACTION`] of the mean rest edge).
    deep_limit: f64,
    /// A step taken with other bodies ([`CoupledNewton`]): the iterate, the start positions, the step size.
    x_iter: Vec<Vec3>,
    x_n: Vec<Vec3>,
    h: f64,
}

impl ImplicitEuler {
    pub fn new(settings: NewtonSettings) -> Result<Self> {
        settings.validate()?;
        Ok(Self {
            settings,
            ..Default::default()
        })
    }

    /// `Phi(x)` (J), with the obstacles' penalty `contact`.
    fn objective(model: &Model, contact: &ContactPotential, x: &[Vec3], y: &[Vec3], h: f64) -> f64 {
        let mut inertia = 0.0;
        let mut grav = 0.0;
        for i in 0..x.len() {
            let d = [x[i][0] - y[i][0], x[i][1] - y[i][1], x[i][2] - y[i][2]];
            inertia += model.masses[i] * dot(d, d);
            grav -= model.masses[i] * dot(model.gravity, x[i]);
        }
        inertia / (2.0 * h * h)
            + grav
            + elastic_energy(model, x).energy
            + contact.energy(model, x, h)
    }

    /// The contacts the solve held (see [`ContactPotential::apply_impacts`]), after the step ended on `state`
    /// from `x_n` (m): their work and impulses; friction is applied to `state`'s velocities.
    fn book_contacts(
        &self,
        model: &Model,
        state: &mut State,
        x_n: &[Vec3],
        h: f64,
        held: Vec3,
    ) -> ContactReport {
        let (contact, y) = (&self.contact, &self.y);
        let v_start = |i: usize| [0, 1, 2].map(|a| (y[i][a] - x_n[i][a]) / h);
        let mut report = contact.apply_impacts(model, state, h, v_start, |i, x| {
            contact.penalty_velocity_change(model, i, x, h)
        });
        if report.contacts > 0 {
            // The contact's linear impulse (friction's included) is the step's momentum change less gravity's
            // (elastic forces are internal): exact even where Newton stopped short of the optimum, where the
            // penalty's force is not the momentum change it caused. Its moment is taken from the penalty's forces.
            // `held`: what contact with other bodies in the same solve gave the body.
            let mut measured = sub(scale(model.gravity, -h * model.free_mass()), held);
            for i in (0..model.num_vertices()).filter(|&i| !model.pinned[i]) {
                measured = add(
                    measured,
                    scale(sub(state.v[i], v_start(i)), model.masses[i]),
                );
            }
            report.impulse = measured;
        }
        report
    }

    /// Prepare a step of `h` from `state`: the pattern and symbolic analysis (when the structure changed), the
    /// inertial prediction `y`; returns the first iterate.
    fn start(&mut self, model: &Model, state: &State, h: f64) -> Vec<Vec3> {
        let m = model.num_vertices();
        self.contact.relax_stiffening(model, &state.x);
        // The pattern and the symbolic analysis depend on the mesh and the pin set only (masses and material
        // are read at every assembly): rebuild them when either changed since they were built.
        let structure = model.structure_key();
        if self.assembler.is_none() || self.structure != Some(structure) {
            self.structure = Some(structure);
            let asm = HessianAssembler::new(model);
            match SparseCholesky::analyse(&asm.pattern, 1) {
                Ok(c) => self.cholesky = Some(c),
                Err(_) => self.cholesky = None,
            }
            self.symbolic_analyses += 1;
            self.deep_limit = DEEP_CONTACT_FRACTION * model.mean_rest_edge();
            self.assembler = Some(asm);
        }
        self.grad.resize(m, [0.0; 3]);
        self.y.clear();
        for i in 0..m {
            let v = if model.pinned[i] {
                [0.0; 3]
            } else {
                state.v[i]
            };
            self.y.push([
                state.x[i][0] + h * v[0],
                state.x[i][1] + h * v[1],
                state.x[i][2] + h * v[2],
            ]);
        }
        // Start Newton from the better of the inertial prediction y and x_n. Phi(x_n) = K_n + U(x_n) (the
        // start-of-step energy, less gravity's share), so with a monotone line search the step can never end
        // with more energy than it started with, even when y inverts slivers and Newton cannot recover within
        // its iterations; starting from y alone would then hand a wildly energetic state to the next step.
        if Self::objective(model, &self.contact, &state.x, &self.y, h)
            < Self::objective(model, &self.contact, &self.y, &self.y, h)
        {
            state.x.clone()
        } else {
            self.y.clone()
        }
    }

    /// At `x`: `Phi`, its magnitude and gradient (see [`ImplicitEuler::objective_gradient`]), and the Hessian
    /// factorised (see [`ImplicitEuler::factorise_at`]). `None` when no factorisation succeeded.
    fn linearise_at(&mut self, model: &Model, x: &[Vec3], h: f64) -> Option<(f64, f64)> {
        let (phi, phi_magnitude) = self.objective_gradient(model, x, h);
        self.assemble_exact(model, x, h);
        self.factorise_at(model, x, h)
            .then_some((phi, phi_magnitude))
    }

    /// The exact Hessian of `Phi` at `x` (elastic, inertial and contact terms) into `self.values`.
    fn assemble_exact(&mut self, model: &Model, x: &[Vec3], h: f64) {
        let asm = self.assembler.as_mut().expect("prepared by start");
        asm.assemble(model, x, 1.0 / (h * h), false, &mut self.values);
        let values = &mut self.values;
        self.contact
            .hessian_blocks(model, x, h, |i, b| asm.add_vertex_block(values, i, &b));
    }

    /// Factorise the exact Hessian assembled in `self.values` (see [`ImplicitEuler::assemble_exact`]); only when
    /// that fails (and `project_psd`) are the element Hessians at `x` projected to positive semi-definite and the
    /// result factorised. Sets `self.projected`. False when no factorisation succeeded.
    ///
    /// The exact Hessian first: when the mass term keeps it positive definite, Newton converges quadratically.
    fn factorise_at(&mut self, model: &Model, x: &[Vec3], h: f64) -> bool {
        let Some(chol) = self.cholesky.as_mut() else {
            return false;
        };
        self.projected = false;
        if chol.factorize(&self.values).is_ok() {
            return true;
        }
        if !self.settings.project_psd {
            return false; // not positive definite: keep the current iterate
        }
        self.assemble_projected(model, x, h);
        self.projected = true;
        let chol = self.cholesky.as_mut().expect("checked above");
        chol.factorize(&self.values).is_ok()
    }

    /// The Hessian of `Phi` at `x` with the element Hessians projected to positive semi-definite, into
    /// `self.values`.
    fn assemble_projected(&mut self, model: &Model, x: &[Vec3], h: f64) {
        let asm = self.assembler.as_mut().expect("prepared by start");
        asm.assemble(model, x, 1.0 / (h * h), true, &mut self.values);
        let values = &mut self.values;
        self.contact
            .hessian_blocks(model, x, h, |i, b| asm.add_vertex_block(values, i, &b));
    }

    /// The Newton direction for `self.rhs` (holding `-g` on the free dofs) into `self.rhs`: `H^-1 (-g)` with `H`
    /// the exact Hessian at `x` where it gives a descent direction, else the projected Hessian's (as
    /// [`ImplicitEuler::factorise_at`] chooses). While the step holds a factor of an earlier iterate's Hessian
    /// (`self.factor_fresh`; exact or projected, `self.projected`), conjugate gradients preconditioned by it
    /// solve the exact system, and where that fails (negative curvature, no descent) and the factor is a
    /// projected one, the projected system ([`crate::math::solve_preconditioned`], to `cg_tolerance`). A
    /// factorisation and a direct solve where they fail, take more than [`CG_MAX_ITERATIONS`], or took more
    /// than [`CG_REFACTOR`] last time. False when no factorisation succeeded.
    fn newton_direction(&mut self, model: &Model, x: &[Vec3], h: f64, cg_tolerance: f64) -> bool {
        self.assemble_exact(model, x, h);
        if self.factor_fresh && self.cg_usable {
            if self.iterate_direction(cg_tolerance) {
                return true;
            }
            if self.projected {
                self.assemble_projected(model, x, h);
                if self.iterate_direction(cg_tolerance) {
                    return true;
                }
                self.assemble_exact(model, x, h);
            }
            // The Hessians of this step change too fast for an earlier factor (typically contacts coming and
            // going): the rest of the step factorises, so that at most one attempt per step is lost.
            self.cg_usable = false;
        }
        if !self.factorise_at(model, x, h) {
            self.factor_fresh = false;
            return false;
        }
        self.last_factorisations += 1;
        self.factor_fresh = true;
        self.cholesky
            .as_mut()
            .expect("factorised")
            .solve_in_place(&mut self.rhs, 1);
        true
    }

    /// Conjugate gradients on the system in `self.values`, preconditioned by the held factor; true when they
    /// converged to a descent direction (then in `self.rhs`), else `self.rhs` holds `-g` again. Marks the factor
    /// stale when they needed more than [`CG_REFACTOR`] iterations.
    fn iterate_direction(&mut self, cg_tolerance: f64) -> bool {
        let chol = self.cholesky.as_mut().expect("factorised");
        let pattern = &self.assembler.as_ref().expect("prepared by start").pattern;
        let solved = solve_preconditioned(
            chol,
            pattern,
            &self.values,
            &mut self.rhs,
            cg_tolerance,
            CG_MAX_ITERATIONS,
        );
        if let Some(k) = solved {
            self.last_cg_iterations += k;
            if self.predicted_decrease() > 0.0 {
                self.factor_fresh = k <= CG_REFACTOR;
                return true;
            }
        }
        self.rhs.clone_from(&self.neg_grad);
        false
    }

    /// `-g . dx` for the direction `dx` in `self.rhs` (J): the Newton decrement squared when `dx` is the Newton
    /// step, positive for a descent direction.
    fn predicted_decrease(&self) -> f64 {
        self.neg_grad
            .iter()
            .zip(&self.rhs)
            .map(|(g, d)| g * d)
            .sum()
    }

    /// Evaluate `Phi` and its gradient (into `self.grad`). Also returns the magnitude scale of `Phi`
    /// (sum of the absolute values of its terms), which bounds its round-off.
    fn objective_gradient(&mut self, model: &Model, x: &[Vec3], h: f64) -> (f64, f64) {
        self.elastic_grad.resize(x.len(), [0.0; 3]);
        self.elastic = elastic_energy_gradient(model, x, &mut self.ws, &mut self.elastic_grad);
        self.grad.resize(x.len(), [0.0; 3]);
        let el = self.elastic.energy;
        let mut phi = el;
        let mut magnitude = el.abs();
        let inv_h2 = 1.0 / (h * h);
        for i in 0..x.len() {
            let mi = model.masses[i];
            let d = [
                x[i][0] - self.y[i][0],
                x[i][1] - self.y[i][1],
                x[i][2] - self.y[i][2],
            ];
            let (inertia, grav) = (0.5 * mi * inv_h2 * dot(d, d), mi * dot(model.gravity, x[i]));
            phi += inertia - grav;
            magnitude += inertia + grav.abs();
            for a in 0..3 {
                self.grad[i][a] = self.elastic_grad[i][a] + mi * (inv_h2 * d[a] - model.gravity[a]);
            }
        }
        let contact = self.contact.add_gradient(model, x, h, &mut self.grad);
        (phi + contact, magnitude + contact)
    }
}

impl crate::integrators::CoupledNewton for ImplicitEuler {
    fn begin(&mut self, model: &Model, state: &State, h: f64) {
        self.h = h;
        self.contact.place(state.time, h);
        self.x_n.clone_from(&state.x);
        self.x_iter = self.start(model, state, h);
    }

    fn limits(&self) -> (usize, f64) {
        (self.settings.max_iterations, self.settings.tolerance)
    }

    fn positions(&self) -> &[Vec3] {
        &self.x_iter
    }

    fn set_positions(&mut self, x: &[Vec3]) {
        self.x_iter.copy_from_slice(x);
    }

    fn linearise(&mut self, model: &Model) -> Option<(f64, f64)> {
        let x = std::mem::take(&mut self.x_iter);
        let out = self.linearise_at(model, &x, self.h);
        self.x_iter = x;
        if out.is_some() {
            for (i, g) in self.grad.iter_mut().enumerate() {
                if model.pinned[i] {
                    *g = [0.0; 3];
                }
            }
        }
        out
    }

    fn gradient(&self) -> &[Vec3] {
        &self.grad
    }

    fn solve(&mut self, rhs: &mut [Vec3], ncols: usize) {
        let asm = self.assembler.as_ref().expect("prepared by begin");
        let chol = self.cholesky.as_mut().expect("factorised by linearise");
        let (n, m) = (asm.ndof(), asm.free_index.len());
        self.rhs.clear();
        self.rhs.resize(n * ncols, 0.0);
        for c in 0..ncols {
            for (i, &fi) in asm.free_index.iter().enumerate() {
                if fi != usize::MAX {
                    self.rhs[c * n + 3 * fi..c * n + 3 * fi + 3].copy_from_slice(&rhs[c * m + i]);
                }
            }
        }
        chol.solve_many_in_place(&mut self.rhs, ncols);
        for c in 0..ncols {
            for (i, &fi) in asm.free_index.iter().enumerate() {
                rhs[c * m + i] = if fi != usize::MAX {
                    let k = c * n + 3 * fi;
                    [self.rhs[k], self.rhs[k + 1], self.rhs[k + 2]]
                } else {
                    [0.0; 3]
                };
            }
        }
    }

    fn objective(&self, model: &Model, x: &[Vec3]) -> f64 {
        Self::objective(model, &self.contact, x, &self.y, self.h)
    }

    fn finish(
        &mut self,
        model: &Model,
        state: &mut State,
        iterations: usize,
        residual: f64,
        held_impulse: Vec3,
    ) -> StepReport {
        let h = self.h;
        let (x, x_n) = (
            std::mem::take(&mut self.x_iter),
            std::mem::take(&mut self.x_n),
        );
        finish_positional_step(model, state, &x, &x_n, h);
        let mut report = StepReport {
            impulse: scale(model.gravity, h * model.free_mass()),
            iterations,
            residual,
            ..Default::default()
        };
        if !self.contact.is_empty() {
            report.contact = self.book_contacts(model, state, &x_n, h, held_impulse);
        }
        report.impulse = add(report.impulse, report.contact.impulse);
        report.angular_impulse = add(report.angular_impulse, report.contact.angular_impulse);
        (self.x_iter, self.x_n) = (x, x_n);
        report
    }
}

impl Integrator for ImplicitEuler {
    fn name(&self) -> &'static str {
        "implicit_euler"
    }

    fn is_implicit(&self) -> bool {
        true
    }

    fn set_obstacles(&mut self, obstacles: &[Obstacle]) {
        self.contact = ContactPotential::new(obstacles);
    }

    fn carry(&self, c: &mut crate::checkpoint::Carry) {
        c.put(
            "integrator.contact_stiffening",
            self.contact.stiffening().to_vec(),
        );
    }

    fn resume(&mut self, c: &crate::checkpoint::Carry, num_vertices: usize) -> Result<()> {
        let k = c.get("integrator.contact_stiffening")?;
        if !(k.is_empty() || k.len() == num_vertices)
            || k.iter().any(|&v| !(v.is_finite() && v >= 1.0))
        {
            return Err(FeprError::Simulation(format!(
                "the checkpoint's 'integrator.contact_stiffening' entry is not one multiplier of at least 1 per \
                 vertex ({} entries, the body has {num_vertices} vertices)",
                k.len()
            )));
        }
        self.contact.set_stiffening(k.to_vec());
        Ok(())
    }

    fn coupled_newton(&mut self) -> Option<&mut dyn crate::integrators::CoupledNewton> {
        Some(self)
    }

    // Long (about 135 lines): one Newton solve of backward Euler, read top to bottom (prepare the pattern, iterate:
    // gradient, Hessian, factorisation with the PSD fallback, Armijo line search; again after stiffening deep
    // contacts; hand the last gradient over).
    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        hand_over: &mut HandOver,
    ) -> StepReport {
        let x_n = state.x.clone();
        // Moving obstacles where they are over this step (the penalty holds the vertices at the step's end).
        self.contact.place(state.time, h);
        let mut x = self.start(model, state, h);
        let mut report = StepReport {
            impulse: scale(model.gravity, h * model.free_mass()),
            ..Default::default()
        };
        (self.last_factorisations, self.last_cg_iterations) = (0, 0);
        // `elastic_grad` was evaluated at `x` (then handed over to the projection).
        let mut elastic_at_x = false;
        // Rounds of Newton's method: the first with the plain penalty, each later one after stiffening the
        // penalty of the vertices the last one left deep inside an obstacle.
        for round in 0..=DEEP_CONTACT_ROUNDS {
            let done = report.iterations;
            self.last_decrements.clear();
            let mut dec0 = 0.0;
            // Each round starts with a factorisation; the iterations after it reuse it while it serves.
            (self.factor_fresh, self.cg_usable) = (false, true);
            for it in 0..self.settings.max_iterations {
                let (phi, phi_magnitude) = self.objective_gradient(model, &x, h);
                elastic_at_x = true;
                let asm = self.assembler.as_ref().expect("prepared by start");
                let n = asm.ndof();
                self.rhs.clear();
                self.rhs.resize(n, 0.0);
                for (i, &fi) in asm.free_index.iter().enumerate() {
                    if fi != usize::MAX {
                        for a in 0..3 {
                            self.rhs[3 * fi + a] = -self.grad[i][a];
                        }
                    }
                }
                self.neg_grad.clone_from(&self.rhs);
                // Inexact Newton (Eisenstat and Walker): early iterations, far from the solution, need only a rough
                // direction; the tolerance tightens with the square of the relative decrement, which keeps Newton's
                // quadratic convergence (in that regime the next decrement is about the square of the last), so the
                // direction and the decrement are accurate where convergence is decided.
                let cg_tolerance = match self.last_decrements.last() {
                    Some(&lambda) if dec0 > 0.0 => (lambda / dec0).clamp(CG_TOLERANCE, CG_LOOSEST),
                    _ => CG_TOLERANCE,
                };
                if !self.newton_direction(model, &x, h, cg_tolerance) {
                    break;
                }
                let asm = self.assembler.as_ref().expect("prepared by start");
                // Newton decrement squared: g^T H^-1 g = -g . dx.
                let dec = self.predicted_decrease().max(0.0);
                let lambda = dec.sqrt();
                self.last_decrements.push(lambda);
                if it == 0 {
                    dec0 = lambda;
                }
                report.iterations = done + it + 1;
                report.residual = if dec0 > 0.0 { lambda / dec0 } else { 0.0 };
                // Converged: the decrement fell by the relative tolerance, or the Newton step moves no vertex by
                // more than 1e-12 of the body's size (near equilibrium the relative test meets round-off).
                let step_max = self.rhs.iter().fold(0.0f64, |a, d| a.max(d.abs()));
                // The predicted decrease dec/2 below Phi's round-off cannot be acted on either.
                if lambda.is_nan()
                    || lambda <= self.settings.tolerance * dec0
                    || lambda <= 1e-300
                    || step_max <= 1e-12 * model.length_scale
                    || dec <= 1e-13 * phi_magnitude
                {
                    report.iterations = done + it; // converged before taking this step
                    break;
                }
                // Backtracking line search on Phi (Armijo, c = 1e-4).
                let slope = -dec;
                let free_index = &asm.free_index;
                let mut alpha = 1.0;
                let accepted = loop {
                    self.x_trial.clear();
                    self.x_trial.extend_from_slice(&x);
                    for (i, &fi) in free_index.iter().enumerate() {
                        if fi != usize::MAX {
                            for a in 0..3 {
                                self.x_trial[i][a] += alpha * self.rhs[3 * fi + a];
                            }
                        }
                    }
                    let phi_trial =
                        Self::objective(model, &self.contact, &self.x_trial, &self.y, h);
                    if phi_trial <= phi + 1e-4 * alpha * slope {
                        break true;
                    }
                    // When the predicted decrease is within a few hundred ulps of Phi, the comparison measures
                    // round-off: accept a trial whose change of Phi is round-off too.
                    let resolvable = dec > 1e-10 * phi_magnitude;
                    if !resolvable && phi_trial <= phi + 1e-10 * phi_magnitude {
                        break true;
                    }
                    if alpha < 1e-10 {
                        // No decrease along the Newton direction: keep the current iterate (never accept an
                        // increase of Phi, which is what keeps backward Euler from gaining energy).
                        break false;
                    }
                    alpha *= 0.5;
                    report.line_search_steps += 1;
                };
                if !accepted {
                    break;
                }
                std::mem::swap(&mut x, &mut self.x_trial);
                elastic_at_x = false;
            }
            if round == DEEP_CONTACT_ROUNDS
                || self.contact.is_empty()
                || self.contact.stiffen_deep(
                    model,
                    &x,
                    self.deep_limit,
                    DEEP_CONTACT_STIFFENING,
                    DEEP_CONTACT_MOST,
                ) == 0
            {
                break;
            }
        }
        finish_positional_step(model, state, &x, &x_n, h);
        if !self.contact.is_empty() {
            report.contact = self.book_contacts(model, state, &x_n, h, [0.0; 3]);
        }
        report.impulse = add(report.impulse, report.contact.impulse);
        report.angular_impulse = add(report.angular_impulse, report.contact.angular_impulse);
        if elastic_at_x {
            hand_over.put_result_gradient(model, self.elastic, &mut x, &mut self.elastic_grad);
        }
        report
    }
}
