//! `Simulation`: a model, a state, a base integrator and an optional projection, stepped together; keeps
//! the running references of fepr-spec section 2 and one diagnostics row per step.

use std::time::Instant;

use crate::error::{FeprError, Result};
use crate::integrators::{Integrator, StepReport};
use crate::invariants::{center_of_mass, measure, Invariants};
use crate::linalg::{add, scale, Vec3};
use crate::model::{Model, State};
use crate::projection::{ProjectionReport, Projector, Targets};

/// One row of diagnostics (fepr-spec / DESIGN.md), after a step (or for the initial state, step 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepDiagnostics {
    pub step: usize,
    /// Time, s.
    pub time: f64,
    pub invariants: Invariants,
    /// The projection's report (None without projection, and for the initial row).
    pub projection: Option<ProjectionReport>,
    /// Energy budget of the step (J) that the integrator and world reported.
    pub energy_budget: f64,
    /// The base integrator's report (solver iterations, residual, line-search steps, impulses).
    pub base: StepReport,
    /// Wall time of the base step and of the projection, ms.
    pub base_ms: f64,
    pub proj_ms: f64,
    /// Relative energy error of the *base* step against its target, `|H* - H_target| / H_scale0`.
    pub base_energy_error: f64,
    /// Runaway detected: the base step's energy error exceeded 100% of the energy scale (an unstable step)
    /// and the projection (if any) did not converge back onto the targets.
    pub runaway: bool,
}

/// Running references (fepr-spec section 2): initial values advanced by every step's budget and impulses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct References {
    pub energy: f64,
    pub momentum: Vec3,
    pub angular_momentum: Vec3,
    pub center_of_mass: Vec3,
}

impl References {
    fn measured(inv: &Invariants) -> Self {
        Self {
            energy: inv.total,
            momentum: inv.momentum,
            angular_momentum: inv.angular_momentum,
            center_of_mass: inv.center_of_mass,
        }
    }
}

/// A running simulation.
pub struct Simulation {
    pub model: Model,
    pub state: State,
    integrator: Box<dyn Integrator>,
    projector: Option<Projector>,
    dt: f64,
    references: References,
    /// Energy scale of the initial state, `K + |E_el| + |E_grav|` (for runaway detection).
    energy_scale: f64,
    history: Vec<StepDiagnostics>,
    previous: State,
}

impl Simulation {
    /// Start at `state`. `dt` in seconds (> 0, finite).
    pub fn new(
        model: Model,
        state: State,
        integrator: Box<dyn Integrator>,
        dt: f64,
        projector: Option<Projector>,
    ) -> Result<Self> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(crate::error::invalid(
                "dt",
                format!("must be a positive finite number of seconds, got {dt}"),
            ));
        }
        let m = model.num_vertices();
        if state.x.len() != m || state.v.len() != m {
            return Err(crate::error::invalid(
                "state",
                format!("needs {m} positions and velocities"),
            ));
        }
        if !state.is_finite() {
            return Err(crate::error::invalid(
                "state",
                "positions and velocities must be finite",
            ));
        }
        integrator.check(&model)?;
        let mut projector = projector;
        if let Some(p) = projector.as_mut() {
            p.set_implicit_base(integrator.is_implicit());
        }
        let previous = state.clone();
        let mut sim = Self {
            model,
            state,
            integrator,
            projector,
            dt,
            references: References {
                energy: 0.0,
                momentum: [0.0; 3],
                angular_momentum: [0.0; 3],
                center_of_mass: [0.0; 3],
            },
            energy_scale: 0.0,
            history: Vec::new(),
            previous,
        };
        sim.reset_references();
        let inv = measure(&sim.model, &sim.state);
        sim.history.push(StepDiagnostics {
            step: 0,
            time: sim.state.time,
            invariants: inv,
            projection: None,
            energy_budget: 0.0,
            base: StepReport::default(),
            base_ms: 0.0,
            proj_ms: 0.0,
            base_energy_error: 0.0,
            runaway: false,
        });
        Ok(sim)
    }

    /// Re-measure the references from the current state (call after the state was set by hand).
    pub fn reset_references(&mut self) {
        let inv = measure(&self.model, &self.state);
        self.references = References::measured(&inv);
        self.energy_scale =
            (inv.kinetic + inv.elastic.abs() + inv.gravitational.abs()).max(f64::MIN_POSITIVE);
        // Before the first step, row 0 must describe the state the run starts from.
        if let [only] = self.history.as_mut_slice() {
            only.invariants = inv;
            only.time = self.state.time;
        }
    }

    pub fn dt(&self) -> f64 {
        self.dt
    }
    pub fn integrator_name(&self) -> &'static str {
        self.integrator.name()
    }
    pub fn projector(&self) -> Option<&Projector> {
        self.projector.as_ref()
    }
    pub fn references(&self) -> &References {
        &self.references
    }
    pub fn history(&self) -> &[StepDiagnostics] {
        &self.history
    }
    /// Number of steps taken.
    pub fn num_steps(&self) -> usize {
        self.history.last().map_or(0, |d| d.step)
    }

    /// Energy scale of a step (J), for the energy row's tolerance and for runaway detection: the largest of
    /// the initial state's and the start-of-step state's `K + |E_el| + |E_grav|`, and `m_tot |g| r` (the
    /// potential energy of lifting the body by its size), so that a body starting with zero energy (at rest,
    /// centre of mass at the origin) still has a physical scale.
    fn step_energy_scale(&self) -> f64 {
        let last = self.history.last().map(|d| d.invariants);
        let current = last.map_or(0.0, |i| i.kinetic + i.elastic.abs() + i.gravitational.abs());
        let g = crate::linalg::norm(self.model.gravity);
        let lift = self.model.total_mass * g * self.model.length_scale;
        self.energy_scale
            .max(current)
            .max(lift)
            .max(f64::MIN_POSITIVE)
    }

    fn targets(&self, report: &StepReport) -> Targets {
        let r = &self.references;
        let h = self.dt;
        let mt = self.model.total_mass;
        let com = if report.impulsive {
            center_of_mass(&self.model.masses, mt, &self.state.x)
        } else {
            // Exact centre-of-mass path for forces smooth over the step: C_ref + h/m (P_ref + J/2).
            add(
                r.center_of_mass,
                scale(add(r.momentum, scale(report.impulse, 0.5)), h / mt),
            )
        };
        Targets {
            energy_scale: self.step_energy_scale(),
            uncertain_impulses: report.impulsive,
            energy: r.energy + report.energy_budget,
            momentum: add(r.momentum, report.impulse),
            angular_momentum: add(r.angular_momentum, report.angular_impulse),
            center_of_mass: com,
        }
    }

    /// Take one step: base integrator, then the projection (if enabled). On a non-finite state the step is
    /// undone and an error names the step (runaway of an unstable step size).
    pub fn step(&mut self) -> Result<&StepDiagnostics> {
        self.previous.clone_from(&self.state);
        let t0 = Instant::now();
        let report = self.integrator.step(&self.model, &mut self.state, self.dt);
        let base_ms = t0.elapsed().as_secs_f64() * 1e3;
        let step = self.num_steps() + 1;
        if !self.state.is_finite() {
            std::mem::swap(&mut self.state, &mut self.previous);
            return Err(FeprError::Simulation(format!(
                "the state became non-finite in step {step} (t = {:.6} s): the {} step of dt = {} s is unstable for \
                 this material and mesh (runaway); use a smaller dt or a stiffer-stable integrator. The state was \
                 left at step {}.",
                self.state.time + self.dt,
                self.integrator.name(),
                self.dt,
                step - 1
            )));
        }
        let targets = self.targets(&report);
        let t1 = Instant::now();
        let (projection, inv, base_total) = match self.projector.as_mut() {
            Some(p) => {
                let (rep, inv) = p.project(&self.model, &mut self.state, self.dt, &targets);
                (Some(rep), inv, rep.base_energy)
            }
            None => {
                let inv = measure(&self.model, &self.state);
                (None, inv, inv.total)
            }
        };
        if !(inv.total.is_finite()
            && inv
                .momentum
                .iter()
                .chain(&inv.angular_momentum)
                .all(|c| c.is_finite()))
        {
            std::mem::swap(&mut self.state, &mut self.previous);
            return Err(FeprError::Simulation(format!(
                "the energy or momentum became non-finite in step {step} (t = {:.6} s): the {} step of dt = {} s \
                 is unstable for this material and mesh (runaway); use a smaller dt. The state was left at step {}.",
                self.state.time + self.dt,
                self.integrator.name(),
                self.dt,
                step - 1
            )));
        }
        let proj_ms = if projection.is_some() {
            t1.elapsed().as_secs_f64() * 1e3
        } else {
            0.0
        };
        let scale_h = targets.energy.abs().max(targets.energy_scale);
        let base_energy_error = (base_total - targets.energy).abs() / scale_h;
        // The references advance to this step's targets even when the projection did not converge: a failed
        // step does not lower the bar (re-basing on the measured state would make a one-step failure a
        // permanent loss of energy); the next projection starts from the fallback state and tries again.
        self.references = References {
            energy: targets.energy,
            momentum: targets.momentum,
            angular_momentum: targets.angular_momentum,
            center_of_mass: targets.center_of_mass,
        };
        self.history.push(StepDiagnostics {
            step,
            time: self.state.time,
            invariants: inv,
            projection,
            energy_budget: report.energy_budget,
            base: report,
            base_ms,
            proj_ms,
            base_energy_error,
            // The base step gained or lost more than 100% of the energy scale, and no converged projection
            // rescued the step.
            runaway: (base_energy_error.is_nan() || base_energy_error > 1.0)
                && !projection.is_some_and(|p| p.converged),
        });
        Ok(self.history.last().expect("just pushed"))
    }
}
