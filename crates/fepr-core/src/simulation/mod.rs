//! `Simulation`: a model, a state, a base integrator and an optional projection, stepped together; keeps
//! the running references of fepr-spec section 2 and one diagnostics row per step.
//!
//! The simulation owns the [`HandOver`] between the base step and the projection (what one evaluated that the
//! other would evaluate again): it passes it to every base step and moves its entries to and from the
//! projection; [`crate::integrators::HandOver`]'s module says what it carries and when an entry is valid.

mod bodies;
mod body_constraints;
mod body_newton;
mod history;
mod policy;
mod resume;
pub use bodies::*;
pub use history::*;
pub use policy::*;

use std::time::Instant;

use crate::error::{FeprError, Result};
use crate::exec::{copy_rows, copy_rows2};
use crate::integrators::{HandOver, Integrator, StepReport};
use crate::invariants::{center_of_mass, measure, Invariants};
use crate::math::{add, cross, dot, norm, scale, sub, Vec3};
use crate::model::{Model, State};
use crate::projection::{ProjectionReport, Projector, SystemMetric, Targets};
use crate::world::{
    max_penetration, near_obstacles, resolve_contacts, Obstacle, RESTING_SPEED_STEPS,
};
use crate::world::{BodyExchange, BodySurface, Drag, KinematicPins, SelfContact, Work, World};

/// The strain whose elastic energy over the body is the least energy scale of a step (a body at rest without
/// gravity has no other; its runaway test and its projection's tolerance need one).
pub const STRAIN_SCALE: f64 = 1e-4;

/// Contact push-outs deeper than this fraction of the mean rest edge length make the step redo itself in
/// substeps (see [`Simulation::step`]).
const IMPACT_DEPTH_FRACTION: f64 = 0.1;
const MAX_IMPACT_SUBSTEPS: usize = 16;

/// What a step did before its projection (one or several [`Simulation::advance`] calls).
#[derive(Clone, Copy, Debug, Default)]
struct Advance {
    report: StepReport,
    work: Work,
    contacts: usize,
    max_depth: f64,
    has_forces: bool,
    force_impulse: Vec3,
}

impl Advance {
    /// Accumulate a substep.
    fn add(&mut self, a: &Advance) {
        let (r, s) = (&mut self.report, &a.report);
        r.impulse = add(r.impulse, s.impulse);
        r.angular_impulse = add(r.angular_impulse, s.angular_impulse);
        r.impulsive |= s.impulsive;
        r.iterations += s.iterations;
        r.residual = r.residual.max(s.residual);
        r.line_search_steps += s.line_search_steps;
        self.work.contact += a.work.contact;
        self.work.damping += a.work.damping;
        self.work.pins += a.work.pins;
        self.work.forces += a.work.forces;
        self.work.unresolved += a.work.unresolved;
        self.contacts += a.contacts;
        self.max_depth = self.max_depth.max(a.max_depth);
        self.has_forces |= a.has_forces;
        self.force_impulse = add(self.force_impulse, a.force_impulse);
    }
}

/// Resting-contact bound, relative to the step's energy scale: a non-converged contact step whose energy
/// residual, or whose kinetic energy, is below it books the residual as contact work (a body resting in static
/// equilibrium; see `Simulation::step`).
const RESTING_CONTACT_RESIDUAL: f64 = 1e-4;

/// On resting contact the projection stands down, and tries again every this many steps (see `Simulation::step`).
const RESTING_RETRY: usize = 16;

/// One row of diagnostics (fepr-spec / DESIGN.md), after a step (or for the initial state, step 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepDiagnostics {
    pub step: usize,
    /// Time, s.
    pub time: f64,
    pub invariants: Invariants,
    /// The projection's report (None without projection, and for the initial row).
    pub projection: Option<ProjectionReport>,
    /// Energy budget W of the step (J) that the integrator and the world reported (the sum of `work`).
    pub energy_budget: f64,
    /// The budget by source, J.
    pub work: Work,
    /// Sum of the budgets of every step so far, J (so `H_n` should equal `H_0 + budget_total`).
    pub budget_total: f64,
    /// Vertex-obstacle contacts resolved in the step.
    pub contacts: usize,
    /// Deepest penetration of a free vertex into an obstacle after the step, m.
    pub penetration: f64,
    /// The base integrator's report (solver iterations, residual, line-search steps, impulses).
    pub base: StepReport,
    /// Wall time of the base step and of the projection, ms.
    pub base_ms: f64,
    pub proj_ms: f64,
    /// Relative energy error of the *base* step in this step, `|H* - (H_n + W)| / S` (`H_n` the start-of-step
    /// energy, `W` the step's budget, `S` the step's energy scale, see `Targets::energy_scale`).
    pub base_energy_error: f64,
    /// Runaway detected: the base step's energy error exceeded 100% of the energy scale (an unstable step)
    /// and the projection (if any) did not converge back onto the targets.
    pub runaway: bool,
    /// The running references after the step (fepr-spec section 2): the initial values advanced by every
    /// budget and impulse so far. `references.momentum` is what P should be (`P_0` plus the external impulses:
    /// gravity, contact, forces, damping), `references.energy` what H should be (`H_0 + budget_total`).
    pub references: References,
}

impl StepDiagnostics {
    /// What the angular momentum about the state's centre of mass should be after the step, kg m^2/s: the
    /// reference (held about the target centre of mass) moved to the actual one,
    /// `L_target - (C - C_target) x P_target` (they differ where the centre-of-mass rows were off: contact).
    pub fn angular_momentum_target(&self) -> Vec3 {
        let r = &self.references;
        sub(
            r.angular_momentum,
            cross(
                sub(self.invariants.center_of_mass, r.center_of_mass),
                r.momentum,
            ),
        )
    }
}

/// What a step's part keeps from before its base step for after it ([`Simulation::advance`]).
struct BaseStart {
    /// The time at the end of the part, s.
    t_next: f64,
    /// The pins' work so far, J.
    work: Work,
    /// The external forces' kick: impulse (kg m/s) and its moment about the centre of mass (kg m^2/s).
    force_impulse: Vec3,
    force_torque: Vec3,
    has_forces: bool,
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

/// A step between [`Simulation::begin_step`] and [`Simulation::finish_step`].
struct BegunStep {
    adv: Advance,
    base_ms: f64,
}

/// A running simulation.
pub struct Simulation {
    pub model: Model,
    pub state: State,
    integrator: Box<dyn Integrator>,
    projector: Option<Projector>,
    /// What the base step and the projection share (see [`HandOver`]).
    hand_over: HandOver,
    dt: f64,
    references: References,
    /// Energy scale of the initial state, `K + |E_el|` (J; see [`Simulation::step_energy_scale`]).
    energy_scale: f64,
    /// The elastic energy of a uniform strain of [`STRAIN_SCALE`] over the body, `m_tot c^2 eps^2 / 2` (J, `c`
    /// the pressure wave speed): the least energy scale, so that a body at rest without gravity has one.
    strain_energy: f64,
    /// Gravitational energy of the initial state, J: energies are measured from this potential.
    initial_potential: f64,
    history: Vec<StepDiagnostics>,
    previous: State,
    world: World,
    /// Vertices in contact this step (their positions are frozen in the projection).
    contact_vertices: Vec<u32>,
    contact_dv: Vec<(u32, Vec3)>,
    x_start: Vec<Vec3>,
    /// The free vertices' positions at the start of the (sub)step, m (kept only with obstacles).
    x_begin: Vec<Vec3>,
    /// Mean rest edge length, m (the scale of an impact's push-out).
    mean_edge: f64,
    /// Running sums for [`Simulation::unresolved_energy`], J.
    unresolved_totals: (f64, f64),
    /// The state was set (or the obstacles changed) since the last step: check that it starts outside the
    /// obstacles ([`Simulation::check_start_outside_obstacles`]).
    start_unchecked: bool,
    /// Consecutive contact steps at rest whose projection did not converge or stood down.
    resting_steps: usize,
    /// The base step's positions and velocities on a step that retries the projection at rest (m, m/s): a retry
    /// that does not converge gives them back (see [`Simulation::project_or_measure`]).
    retry_base: (Vec<Vec3>, Vec<Vec3>),
    /// Energy the last step's projection left off its target, J (state minus target; 0 after a step that
    /// reached it): booked as `Work::deferred` until a later step places it.
    deferred: f64,
    /// The body's surface as other bodies collide with it (built at the first step among bodies or with self
    /// contact).
    surface: Option<BodySurface>,
    /// Contact of the body with its own surface (its coefficients and detection data), or off.
    self_contact: Option<SelfContact>,
    /// The state at the start of a later part of a step among bodies (what its impact substeps start again
    /// from; the first part starts again from `previous`).
    part_start: State,
    /// Contact with other bodies held in a joint Newton solve ([`body_newton`]): the normal force (N) each of
    /// this body's vertices pressed on each other body with at the end of the last step, `(vertex, other)`
    /// sorted: the next step's friction bound.
    held_normal_forces: Vec<((usize, usize), f64)>,
    /// `held_normal_forces` at the start of the step: a step redone in parts starts again from them, not from
    /// what its abandoned attempt held.
    held_at_step_start: Vec<((usize, usize), f64)>,
}

/// Where a step stands in the resting rule (see [`Simulation::step`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Resting {
    /// Not at rest: the projection runs.
    No,
    /// At rest after a failed projection: the projection stands down if the rule still holds.
    StandDown,
    /// At rest, on a step that tries the projection again (every [`RESTING_RETRY`]-th).
    Retry,
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
        if model.damping > 0.0 && !integrator.applies_step_damping() {
            return Err(crate::error::invalid(
                "damping",
                format!(
                    "the per-step damping factor ({}) is applied by symplectic_euler only; {} would ignore it: \
                     use air_damping or rayleigh_damping (applied after any integrator)",
                    model.damping,
                    integrator.name()
                ),
            ));
        }
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
            hand_over: HandOver::new(),
            dt,
            references: References {
                energy: 0.0,
                momentum: [0.0; 3],
                angular_momentum: [0.0; 3],
                center_of_mass: [0.0; 3],
            },
            energy_scale: 0.0,
            strain_energy: 0.0,
            initial_potential: 0.0,
            history: Vec::new(),
            previous,
            world: World::default(),
            contact_vertices: Vec::new(),
            contact_dv: Vec::new(),
            x_start: Vec::new(),
            x_begin: Vec::new(),
            mean_edge: 0.0,
            unresolved_totals: (0.0, 0.0),
            start_unchecked: true,
            resting_steps: 0,
            retry_base: (Vec::new(), Vec::new()),
            deferred: 0.0,
            surface: None,
            self_contact: None,
            part_start: State {
                x: Vec::new(),
                v: Vec::new(),
                time: 0.0,
            },
            held_normal_forces: Vec::new(),
            held_at_step_start: Vec::new(),
        };
        sim.mean_edge = sim.model.mean_rest_edge();
        let c = sim.model.pressure_wave_speed();
        sim.strain_energy = 0.5 * sim.model.total_mass * c * c * STRAIN_SCALE * STRAIN_SCALE;
        sim.reset_references();
        let inv = measure(&sim.model, &sim.state);
        sim.history.push(StepDiagnostics {
            step: 0,
            time: sim.state.time,
            invariants: inv,
            projection: None,
            energy_budget: 0.0,
            work: Work::default(),
            budget_total: 0.0,
            contacts: 0,
            penetration: 0.0,
            base: StepReport::default(),
            base_ms: 0.0,
            proj_ms: 0.0,
            base_energy_error: 0.0,
            runaway: false,
            references: sim.references,
        });
        Ok(sim)
    }

    /// Re-measure the references from the current state (call after the state was set by hand).
    pub fn reset_references(&mut self) {
        let inv = measure(&self.model, &self.state);
        self.references = References::measured(&inv);
        self.energy_scale = (inv.kinetic + inv.elastic.abs())
            .max(self.strain_energy)
            .max(f64::MIN_POSITIVE);
        self.initial_potential = inv.gravitational;
        // Before the first step, row 0 must describe the state the run starts from.
        if let [only] = self.history.as_mut_slice() {
            if only.step > 0 {
                // A trimmed history's last step, not the start of the run.
                return self.after_reset();
            }
            only.invariants = inv;
            only.time = self.state.time;
            only.references = self.references;
        }
        self.after_reset();
    }

    fn after_reset(&mut self) {
        // Kinematic pins follow their path from where the state now has them.
        self.world.anchor_pins(&self.state);
        self.start_unchecked = true;
        self.deferred = 0.0;
    }

    /// An error naming the vertex, the obstacle and the depth when a free vertex starts deeper inside an obstacle
    /// than one step's contact can resolve (a tenth of the mean rest edge, the impact limit). Why an error and not a
    /// push-out: pushed out, a body placed inside an obstacle is thrown metres in its first step (a box inside a box
    /// obstacle: 10 m, H from 1,551 to 53,074 J), a result no user asked for.
    fn check_start_outside_obstacles(&self) -> Result<()> {
        let limit = IMPACT_DEPTH_FRACTION * self.mean_edge;
        for (i, x) in self.state.x.iter().enumerate() {
            if self.model.pinned[i] {
                continue;
            }
            for (k, ob) in self.world.obstacles.iter().enumerate() {
                if let Some((phi, _)) = ob.signed_distance_below(*x, -limit) {
                    let depth = -phi;
                    return Err(FeprError::Simulation(format!(
                        "vertex {i} at ({:.4}, {:.4}, {:.4}) m starts {depth:.4} m inside obstacle {k} ({}); a body must \
                         start outside the obstacles (at most {limit:.2e} m inside, a tenth of its mean edge): move \
                         the body or the obstacle",
                        x[0],
                        x[1],
                        x[2],
                        ob.kind_name()
                    )));
                }
            }
        }
        Ok(())
    }

    // --- the world around the body (see [`crate::world`]) ------------------------------------------------

    /// The obstacles the free vertices collide with (static, or moving along their prescribed motion: placed
    /// for the current time now and for each step as it is taken).
    pub fn set_obstacles(&mut self, mut obstacles: Vec<Obstacle>) {
        self.start_unchecked = true;
        for ob in obstacles.iter_mut() {
            ob.place(self.state.time, 0.0);
        }
        self.integrator.set_obstacles(&obstacles);
        self.world.obstacles = obstacles;
    }

    /// Contact of the body with its own surface (a fold, a limb swung into the torso), with these coefficients,
    /// or none (`None`, the default), after the base step ([`crate::world::SelfContact`]).
    pub fn set_self_contact(&mut self, coefficients: Option<BodyCoefficients>) {
        self.self_contact = coefficients.map(|c| SelfContact::new(c.restitution, c.friction));
    }

    /// The self-contact coefficients, if self contact is on.
    pub fn self_contact(&self) -> Option<BodyCoefficients> {
        self.self_contact.as_ref().map(|c| BodyCoefficients {
            restitution: c.restitution,
            friction: c.friction,
        })
    }

    /// Contact of the body with its own surface after the base step, over the step (or its part) from the
    /// positions `x_begin`.
    fn resolve_self_contact(&mut self) -> Result<BodyExchange> {
        let Some(contact) = self.self_contact.as_mut() else {
            return Ok(BodyExchange::default());
        };
        if self.surface.is_none() {
            self.surface = Some(BodySurface::new(&self.model)?);
        }
        let surface = self.surface.as_mut().expect("built above");
        Ok(contact.resolve(
            &self.model,
            &mut self.state,
            surface,
            &self.x_begin,
            self.mean_edge,
        ))
    }

    pub fn obstacles(&self) -> &[Obstacle] {
        self.world.obstacles()
    }
    /// Kinematic pins: groups of pinned vertices that follow a prescribed path from their current
    /// positions. Their vertices must be pinned in the model.
    pub fn set_kinematic_pins(&mut self, pins: Vec<KinematicPins>) -> Result<()> {
        self.world.set_pins(&self.model, &self.state, pins)
    }
    /// Mass-proportional damping rate `air` (1/s: `dv/dt = -air v`) and stiffness-proportional (Rayleigh)
    /// coefficient `rayleigh` (s: `f = -rayleigh K v`).
    pub fn set_damping(&mut self, air: f64, rayleigh: f64) -> Result<()> {
        self.world.set_damping(air, rayleigh)
    }
    /// Constant external force per vertex, N (an empty vector removes it).
    pub fn set_external_forces(&mut self, forces: Vec<Vec3>) -> Result<()> {
        self.world.set_forces(&self.model, forces)
    }
    /// The user's drag spring (None releases it).
    pub fn set_drag(&mut self, drag: Option<Drag>) -> Result<()> {
        self.world.set_drag(&self.model, drag)
    }

    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// A time step that resolves the body's fast elastic modes, s: a tenth of the time a pressure wave takes to
    /// cross the body (`2 r / c_p`, `r` half the rest bounding-box diagonal, [`Model::pressure_wave_speed`]).
    /// At that step a dissipative integrator loses a small share of the energy of the body's breathing per step,
    /// which the projection restores within its quality guard; at a game step (1/60 s) a 0.3 m body of a soft
    /// rubber (1e5 Pa) is crossed in about two steps and most of that energy is unresolved.
    pub fn resolving_time_step(&self) -> f64 {
        0.1 * 2.0 * self.model.length_scale / self.model.pressure_wave_speed()
    }

    /// Energy booked as unresolved so far (J, the sum of every step's [`Work::unresolved`]), the energy the base
    /// steps lost against their targets (J, the sum of the positive gaps `H_target - H(x*, v*)` of the projected
    /// steps; their ratio is the share of the lost energy the projection could not restore), and the run's
    /// initial energy scale (J: the initial `K + |E_el|`, at least `m_tot |g| r`) to judge them by.
    pub fn unresolved_energy(&self) -> (f64, f64, f64) {
        let lift =
            self.model.total_mass * crate::math::norm(self.model.gravity) * self.model.length_scale;
        (
            self.unresolved_totals.0,
            self.unresolved_totals.1,
            self.energy_scale.max(lift),
        )
    }
    pub fn integrator_name(&self) -> &'static str {
        self.integrator.name()
    }
    pub fn projector(&self) -> Option<&Projector> {
        self.projector.as_ref()
    }
    /// What the base step and the projection share between them (see [`HandOver`]).
    pub fn hand_over(&self) -> &HandOver {
        &self.hand_over
    }
    pub fn references(&self) -> &References {
        &self.references
    }
    pub fn history(&self) -> &[StepDiagnostics] {
        &self.history
    }
    /// Drop every row of the history but the last (the one the next step reads): a caller that keeps the rows
    /// elsewhere (the Python package's bounded history) calls this after taking them, so that the core's
    /// memory does not grow with the steps.
    pub fn trim_history(&mut self) {
        let n = self.history.len();
        if n > 1 {
            self.history.drain(..n - 1);
        }
    }
    /// Number of steps taken.
    pub fn num_steps(&self) -> usize {
        self.history.last().map_or(0, |d| d.step)
    }

    /// Energy scale of a step with energy target `target` (J), for the energy row's tolerance and for runaway
    /// detection, on scales that do not grow with the distance fallen or the time run (fepr-spec section 5b):
    /// energies measured from the initial state's potential. The largest of
    /// - the target measured from that potential, `|H_target - E_grav,0|` (the initial `K + E_el` plus the
    ///   budget so far);
    /// - the initial state's `K + |E_el|`;
    /// - the start-of-step state's internal energy `K - |P|^2 / (2 m_tot) + |E_el|` (the kinetic energy in the
    ///   centre-of-mass frame: a falling body's growing `K` and `|E_grav|` do not count);
    /// - `m_tot |g| r`, the energy of lifting the body by its size (a body starting at rest has a scale), and
    ///   the elastic energy of a uniform strain of [`STRAIN_SCALE`] (one starting at rest without gravity too);
    /// - the rounding of the start-of-step energies, `8 sqrt(m/4 + 1) eps (K + |E_el| + |E_grav|) / tolerance`:
    ///   far from the origin H itself is known no better than that.
    ///
    /// Measured from the start of the step and the targets, not from the base step's result: a wild base step
    /// cannot loosen it.
    fn step_energy_scale(&self, target: f64) -> f64 {
        let mt = self.model.total_mass;
        let last = self.history.last().map(|d| d.invariants);
        let internal = last.map_or(0.0, |i| {
            let p2 = dot(i.momentum, i.momentum);
            (i.kinetic - 0.5 * p2 / mt).max(0.0) + i.elastic.abs()
        });
        let g = crate::math::norm(self.model.gravity);
        let lift = mt * g * self.model.length_scale;
        let tolerance = self
            .projector
            .as_ref()
            .map_or(1e-10, |p| p.settings.tolerance);
        let rounding = last.map_or(0.0, |i| {
            crate::projection::ROUNDING_ULPS
                * crate::projection::rounding_terms(self.model.num_vertices())
                * f64::EPSILON
                * (i.kinetic + i.elastic.abs() + i.gravitational.abs())
                / tolerance
        });
        (target - self.initial_potential)
            .abs()
            .max(self.energy_scale)
            .max(internal)
            .max(lift)
            .max(self.strain_energy)
            .max(rounding)
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
        let energy = r.energy + report.energy_budget;
        Targets {
            energy_scale: self.step_energy_scale(energy),
            uncertain_impulses: report.impulsive,
            energy,
            momentum: add(r.momentum, report.impulse),
            angular_momentum: add(r.angular_momentum, report.angular_impulse),
            center_of_mass: com,
        }
    }

    /// Everything of a step before the projection, over `h` seconds from the current state: kinematic pins,
    /// the force kick, the base step, damping and contact. Appends the vertices to freeze to
    /// `contact_vertices`.
    fn advance(&mut self, h: f64) -> Result<Advance> {
        let start = self.advance_before_base(h);
        let report = self
            .integrator
            .step(&self.model, &mut self.state, h, &mut self.hand_over);
        self.advance_after_base(h, start, report)
    }

    /// What comes before the base step over `h`: kinematic pins to their end-of-step path, the copies of the
    /// start positions, the kick of the external forces.
    fn advance_before_base(&mut self, h: f64) -> BaseStart {
        let t_next = self.state.time + h;
        // Kinematic pins move to their end-of-step path first (a Dirichlet condition at t_{n+1}), with the free
        // vertices held: that is their work. The base step then moves the free vertices with the pins held
        // there, which conserves H (to the integrator's accuracy, and exactly with the projection).
        let work = Work {
            pins: self.world.pin_work(&self.model, &self.state, t_next),
            ..Default::default()
        };
        if self.world.has_pins() {
            let (x, v) = (&mut self.state.x, &mut self.state.v);
            self.world.place_pins(x, v, t_next);
        }
        // Moving obstacles where they are over this step (or part): the contacts after the base step answer for
        // their end placement and their surface's velocity over it.
        let t_start = self.state.time;
        for ob in self.world.obstacles.iter_mut() {
            ob.place(t_start, h);
        }
        // The start positions, for the contacts' crossing tests (a vertex that passed through a thin obstacle or
        // through a part of its own surface).
        if !self.world.obstacles.is_empty() || self.self_contact.is_some() {
            copy_rows(&self.state.x, &mut self.x_begin);
        }
        // External forces: a kick h f / m before the base step (their work needs the start positions).
        if self.world.has_forces() {
            copy_rows(&self.state.x, &mut self.x_start);
        }
        let (mut force_impulse, mut force_torque) = ([0.0; 3], [0.0; 3]);
        let has_forces = match self.world.step_forces(&self.model, &self.state.x) {
            Some(f) => {
                let c = center_of_mass(&self.model.masses, self.model.total_mass, &self.state.x);
                for (i, fi) in f.iter().enumerate() {
                    if self.model.pinned[i] {
                        continue;
                    }
                    self.state.v[i] = add(self.state.v[i], scale(*fi, h / self.model.masses[i]));
                    force_impulse = add(force_impulse, scale(*fi, h));
                    force_torque = add(force_torque, scale(cross(sub(self.state.x[i], c), *fi), h));
                }
                true
            }
            None => false,
        };
        BaseStart {
            t_next,
            work,
            force_impulse,
            force_torque,
            has_forces,
        }
    }

    /// What comes after the base step over `h` (its `report`): pins' velocities, the forces' work, damping,
    /// the obstacles' contacts.
    fn advance_after_base(
        &mut self,
        h: f64,
        start: BaseStart,
        mut report: StepReport,
    ) -> Result<Advance> {
        let BaseStart {
            t_next,
            mut work,
            force_impulse,
            force_torque,
            has_forces,
        } = start;
        work.damping += report.energy_budget;
        // Contacts held inside an implicit solve: their work is contact work (their impulses are in the report's).
        work.contact += report.contact.work;
        if self.world.has_pins() {
            // The integrator left the kinematic vertices in place with zero velocity: give them the path's.
            let (x, v) = (&mut self.state.x, &mut self.state.v);
            self.world.place_pins(x, v, t_next);
        }
        if has_forces {
            let f = self
                .world
                .step_forces(&self.model, &self.x_start)
                .expect("forces present");
            work.forces = f
                .iter()
                .zip(self.state.x.iter().zip(&self.x_start))
                .map(|(fi, (x1, x0))| dot(*fi, sub(*x1, *x0)))
                .sum();
            report.impulse = add(report.impulse, force_impulse);
            // The torque of the forces about the centre of mass, at the start of the step (the kick's moment).
            report.angular_impulse = add(report.angular_impulse, force_torque);
        }
        let mut contacts = report.contact.contacts;
        let mut max_depth = 0.0;
        report.impulsive |= contacts > 0;
        if self.state.is_finite() {
            let (dw, imp, ang) =
                self.world
                    .damp(&self.model, &mut self.state, h, self.previous.time)?;
            work.damping += dw;
            report.impulse = add(report.impulse, imp);
            report.angular_impulse = add(report.angular_impulse, ang);
            let c = resolve_contacts(
                &self.world.obstacles,
                &self.model,
                &mut self.state,
                &self.x_begin,
                h,
                &mut self.contact_vertices,
                &mut self.contact_dv,
            );
            if c.contacts > 0 {
                contacts += c.contacts;
                max_depth = c.max_depth;
                work.contact += c.work;
                report.impulse = add(report.impulse, c.impulse);
                report.angular_impulse = add(report.angular_impulse, c.angular_impulse);
                report.impulsive = true;
            }
            if self.self_contact.is_some() {
                // Internal impulses: no change of momentum or angular momentum, only of kinetic energy.
                let e = self.resolve_self_contact()?;
                if e.contacts > 0 {
                    contacts += e.contacts;
                    max_depth = f64::max(max_depth, e.max_depth);
                    work.contact += e.work;
                    self.contact_vertices.extend_from_slice(&e.vertices);
                }
            }
        }
        report.energy_budget = work.total();
        Ok(Advance {
            report,
            work,
            contacts,
            max_depth,
            has_forces,
            force_impulse,
        })
    }

    /// Take one step: kinematic pins and external forces, the base integrator, damping and contact, then
    /// the projection (if enabled). On a non-finite state the step is undone and an error names the step
    /// (runaway of an unstable step size).
    ///
    /// Impacts: when the contact resolution had to move a vertex out by more than a tenth of the mean rest
    /// edge length (a large step hitting an obstacle fast), the push-out would strain the contact layer hard
    /// (spikes of elastic energy with implicit integrators at large steps). The step is then redone from its
    /// start in substeps small enough for the depth, up to 16; the projection runs once, at the end.
    ///
    /// Called from a thread outside every rayon pool (a program's main thread, Python's), the step runs on a
    /// thread of the global pool ([`crate::exec::on_pool`]), as it does inside `ThreadPool::install`. The
    /// pool's other threads stay ready for the step's parallel passes until it returns
    /// ([`crate::exec::with_threads_ready`]).
    pub fn step(&mut self) -> Result<&StepDiagnostics> {
        crate::exec::on_pool(|| crate::exec::with_threads_ready(|| self.step_on_pool()))?;
        Ok(self.history.last().expect("a step pushes its diagnostics"))
    }

    /// [`Simulation::step`], on a thread of a rayon pool: the base step (with impact substeps), the targets, the
    /// projection (or a measurement), the books, one history row.
    fn step_on_pool(&mut self) -> Result<()> {
        let begun = self.begin_step()?;
        self.finish_step(begun, &BodyExchange::default())
    }

    /// The first half of a step, up to the projection: the base step with the world's processes (impact
    /// substeps included). Between it and [`Simulation::finish_step`] the state is the base step's result, which
    /// contact between bodies may still change ([`crate::world::resolve_body_contacts`]); a step begun must be
    /// finished or abandoned ([`Simulation::abandon_step`]). On a non-finite result the step is undone and an
    /// error names it.
    fn begin_step(&mut self) -> Result<BegunStep> {
        self.open_step()?;
        let t0 = Instant::now();
        let adv = self.advance_part(self.dt, true)?;
        let base_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(BegunStep { adv, base_ms })
    }

    /// Start a step made of parts ([`Simulation::advance_part`]): the start-of-step checks and the copy of the
    /// state the step can be undone to.
    fn open_step(&mut self) -> Result<()> {
        if self.start_unchecked {
            let t = self.state.time;
            for ob in self.world.obstacles.iter_mut() {
                ob.place(t, 0.0);
            }
            self.check_start_outside_obstacles()?;
            self.start_unchecked = false;
        }
        copy_state(&self.state, &mut self.previous);
        self.held_at_step_start.clear();
        self.held_at_step_start
            .extend_from_slice(&self.held_normal_forces);
        Ok(())
    }

    /// Advance the base step and the world's processes over `h` (the whole step, or a part of it when bodies
    /// in contact take the step in substeps; `first`: the part starts at the start of the step), with the
    /// obstacles' impact substeps. On a non-finite result the whole step is undone and an error names it.
    fn advance_part(&mut self, h: f64, first: bool) -> Result<Advance> {
        let (adv, finite) = self.advance_resolving_impacts(h, first)?;
        if !finite {
            return Err(self.abandon_non_finite());
        }
        Ok(adv)
    }

    /// Undo a step whose state became non-finite; the error that names it.
    fn abandon_non_finite(&mut self) -> FeprError {
        let step = self.num_steps() + 1;
        self.abandon_step();
        self.unstable(
            step,
            "the state became non-finite",
            "use a smaller dt or a stiffer-stable integrator",
        )
    }

    /// A part of a step whose base step the caller takes (bodies that take their solves together,
    /// [`bodies`]): what comes before the base step. `first` as for [`Simulation::advance_part`].
    fn part_before_base(&mut self, h: f64, first: bool) -> BaseStart {
        self.contact_vertices.clear();
        if !first {
            copy_state(&self.state, &mut self.part_start);
        }
        self.advance_before_base(h)
    }

    /// The rest of a part begun with [`Simulation::part_before_base`], after its base step (`report`): the
    /// world's processes, the vertices in or near contact. Impacts with the obstacles are not redone here (the
    /// caller redoes the whole scene's step in parts). On a non-finite result the whole step is undone and an
    /// error names it.
    fn part_after_base(&mut self, h: f64, start: BaseStart, report: StepReport) -> Result<Advance> {
        let adv = self.advance_after_base(h, start, report)?;
        self.contact_vertices.sort_unstable();
        self.contact_vertices.dedup();
        if !self.state.is_finite() {
            return Err(self.abandon_non_finite());
        }
        near_obstacles(
            &self.world.obstacles,
            &self.model,
            &self.state,
            &mut self.contact_vertices,
        );
        Ok(adv)
    }

    /// Undo a step begun with [`Simulation::open_step`] (its parts, or another body's step, failed, or it is
    /// redone in substeps): the state is the one before it.
    fn abandon_step(&mut self) {
        copy_state(&self.previous, &mut self.state);
        let t = self.state.time;
        for ob in self.world.obstacles.iter_mut() {
            ob.place(t, 0.0);
        }
        self.held_normal_forces.clear();
        self.held_normal_forces
            .extend_from_slice(&self.held_at_step_start);
    }

    /// The second half of a step: what contact with other bodies did to this one (`exchange`: its velocity
    /// changes' work, impulse and moment, the vertices it touched), the targets, the projection (or a
    /// measurement), the books, one history row.
    ///
    /// Contact between bodies is internal to the scene: the impulses are equal and opposite at one point, so
    /// the bodies' targets together keep the scene's total momenta. The angular target is set so that the body's
    /// angular momentum about the world origin, `L_cm + C x P`, changes by exactly the moment of its contact
    /// impulses about the origin, given the centre of mass and momentum the projection holds it to (for a step
    /// without obstacle impacts: `C' = C_ref + h/M (P_ref + J/2)`, `P' = P_ref + J`). Then the bodies' changes
    /// cancel and the scene's angular momentum is conserved to the projection's tolerance.
    fn finish_step(&mut self, begun: BegunStep, exchange: &BodyExchange) -> Result<()> {
        let BegunStep { adv, base_ms } = begun;
        let h = self.dt;
        // The step's end time exactly: a step taken in parts (impact substeps, bodies meeting after each
        // substep) added its parts' lengths, which differ from `dt` in the last bits.
        self.state.time = self.previous.time + h;
        let Advance {
            mut report,
            mut work,
            mut contacts,
            has_forces,
            force_impulse,
            ..
        } = adv;
        // Impulses known only approximately (obstacle impacts): the projection may use its slack.
        let uncertain = report.impulsive;
        if exchange.contacts > 0 {
            contacts += exchange.contacts;
            work.contact += exchange.work;
            let j = exchange.impulse;
            let r = &self.references;
            let moment = if exchange.held {
                // Forces held in the solve: the centre of mass is not held, and it moved with them. About where
                // it is now, less what that move adds to `C x P` beyond the path without them
                // (`C_o = C_ref + h/M (P_ref + J_o/2)`, `J_o` the other impulses), so that the body's angular
                // momentum about the origin changes by exactly the moment of the exchange there, and the
                // bodies' changes cancel.
                let c = center_of_mass(&self.model.masses, self.model.total_mass, &self.state.x);
                let p_o = add(r.momentum, report.impulse);
                let c_o = add(
                    r.center_of_mass,
                    scale(
                        add(r.momentum, scale(report.impulse, 0.5)),
                        h / self.model.total_mass,
                    ),
                );
                sub(sub(exchange.moment, cross(c, j)), cross(sub(c, c_o), p_o))
            } else if report.impulsive {
                // Obstacle impacts too: the centre of mass is not held; the moment about where it is now.
                let c = center_of_mass(&self.model.masses, self.model.total_mass, &self.state.x);
                sub(exchange.moment, cross(c, j))
            } else {
                let about_ref = sub(exchange.moment, cross(r.center_of_mass, j));
                sub(
                    about_ref,
                    scale(cross(r.momentum, j), 0.5 * h / self.model.total_mass),
                )
            };
            report.impulse = add(report.impulse, j);
            report.angular_impulse = add(report.angular_impulse, moment);
            self.contact_vertices.extend_from_slice(&exchange.vertices);
            self.contact_vertices.sort_unstable();
            self.contact_vertices.dedup();
        }
        report.energy_budget = work.total();
        let step = self.num_steps() + 1;
        // Forces held inside the solve between bodies move the centre of mass with them (as an obstacle's held
        // contacts do): the projection keeps the step's centre of mass (the exchange's moment above follows
        // it). Their impulses are exact (equal and opposite), so they do not loosen the targets.
        report.impulsive |= exchange.held;
        let mut targets = self.targets(&report);
        targets.uncertain_impulses = uncertain;
        if has_forces && !report.impulsive {
            // The work of the forces' resultant belongs to the centre of mass's path, which the projection
            // puts on the exact target (uniform fields: exactly F . (C_target - C_n)), not on the base
            // step's own centre of mass: symplectic Euler's path would add h^2 |F|^2 / (2 m) per step.
            let c_star = center_of_mass(&self.model.masses, self.model.total_mass, &self.state.x);
            let correction = dot(force_impulse, sub(targets.center_of_mass, c_star)) / h;
            work.forces += correction;
            report.energy_budget += correction;
            targets.energy += correction;
        }
        let t1 = Instant::now();
        // Resting contact: after a contact step whose projection could not converge at rest (or was asked to take
        // out more energy than the velocities can give up), the projection stands down (its residual is booked
        // below) on the next contact steps while that holds, and tries again every RESTING_RETRY-th step.
        let resting = match (
            contacts > 0 && self.resting_steps > 0,
            self.resting_steps.is_multiple_of(RESTING_RETRY),
        ) {
            (false, _) => Resting::No,
            (true, false) => Resting::StandDown,
            (true, true) => Resting::Retry,
        };
        let (projection, inv, base_total) = self.project_or_measure(&targets, resting);
        if !(inv.total.is_finite()
            && inv
                .momentum
                .iter()
                .chain(&inv.angular_momentum)
                .all(|c| c.is_finite()))
        {
            std::mem::swap(&mut self.state, &mut self.previous);
            return Err(self.unstable(
                step,
                "the energy or momentum became non-finite",
                "use a smaller dt",
            ));
        }
        let proj_ms = if projection.is_some() {
            t1.elapsed().as_secs_f64() * 1e3
        } else {
            0.0
        };
        let scale_h = targets.energy_scale;
        // The base step's own error in this step: against the start-of-step energy plus the step's budget (with
        // the projection on, that is the target up to the tolerance; without it, the references do not follow the
        // base integrator's drift, and a stable drift accumulated over a long run is not a runaway).
        let start_energy = self
            .history
            .last()
            .map_or(targets.energy, |d| d.invariants.total);
        let base_energy_error = (base_total - start_energy - report.energy_budget).abs() / scale_h;
        self.book_unplaced_energy(
            projection,
            &inv,
            contacts,
            &mut work,
            &mut report,
            &mut targets,
        );
        // At rest (kinetic energy below the residual's share of the scale), or asked to take out more energy
        // than the velocities can give up: near static equilibrium H is stationary in the positions, and the
        // velocities cannot give up more than they carry beyond the rigid motion the momentum targets fix, so the
        // next contact steps would fail the same way (a ball squeezed into the pile's bottom layer failed 26 steps
        // in a row at 22 iterations each; a ball rolling slowly on the pile, its kinetic energy nearly all its
        // rolling, failed every step at 23 iterations).
        let resting = contacts > 0
            && projection.is_some_and(|p| {
                !p.converged
                    && (inv.kinetic <= RESTING_CONTACT_RESIDUAL * scale_h
                        || -p.gap > self.removable_kinetic(&inv, &targets))
            });
        self.resting_steps = if resting { self.resting_steps + 1 } else { 0 };
        // The references advance to this step's targets even when the projection did not converge: a failed
        // step does not lower the bar (re-basing on the measured state would make a one-step failure a
        // permanent loss of energy); the next projection starts from the fallback state and tries again.
        self.references = References {
            energy: targets.energy,
            momentum: targets.momentum,
            angular_momentum: targets.angular_momentum,
            center_of_mass: targets.center_of_mass,
        };
        let budget_total =
            self.history.last().map_or(0.0, |d| d.budget_total) + report.energy_budget;
        let penetration = max_penetration(&self.world.obstacles, &self.model, &self.state.x);
        self.history.push(StepDiagnostics {
            step,
            time: self.state.time,
            invariants: inv,
            projection,
            energy_budget: report.energy_budget,
            work,
            budget_total,
            contacts,
            penetration,
            base: report,
            base_ms,
            proj_ms,
            base_energy_error,
            // The base step gained or lost more than 100% of the energy scale, and no converged projection
            // rescued the step.
            runaway: (base_energy_error.is_nan() || base_energy_error > 1.0)
                && !projection.is_some_and(|p| p.converged),
            references: self.references,
        });
        Ok(())
    }

    /// The base step over `h`, redone from the start in substeps (up to [`MAX_IMPACT_SUBSTEPS`]) when an obstacle's
    /// push-out was deeper than the impact limit; collects the vertices in or near contact (frozen for the
    /// projection). Returns the advance and whether the state is finite.
    fn advance_resolving_impacts(&mut self, h: f64, first: bool) -> Result<(Advance, bool)> {
        self.contact_vertices.clear();
        // Where impact substeps start again: the step's start (kept in `previous`), or, for a later part of a
        // step among bodies, a copy of where this part starts.
        if !first {
            copy_state(&self.state, &mut self.part_start);
        }
        let mut adv = self.advance(h)?;
        let limit = IMPACT_DEPTH_FRACTION * self.mean_edge;
        if adv.max_depth > limit && self.state.is_finite() {
            let k = ((adv.max_depth / limit).ceil() as usize).clamp(2, MAX_IMPACT_SUBSTEPS);
            let start = if first {
                &self.previous
            } else {
                &self.part_start
            };
            copy_state(start, &mut self.state);
            self.contact_vertices.clear();
            let mut total = Advance::default();
            for _ in 0..k {
                let a = self.advance(h / k as f64)?;
                total.add(&a);
                if !self.state.is_finite() {
                    break;
                }
            }
            total.report.energy_budget = total.work.total();
            adv = total;
            adv.report.substeps = k;
        }
        self.contact_vertices.sort_unstable();
        self.contact_vertices.dedup();
        let finite = self.state.is_finite();
        if finite {
            near_obstacles(
                &self.world.obstacles,
                &self.model,
                &self.state,
                &mut self.contact_vertices,
            );
        }
        Ok((adv, finite))
    }

    /// The report of a projection standing down on the current state (measured as `inv`), if the resting rule
    /// holds there: kinetic energy below the resting bound, or more to take out than the velocities can give up.
    fn stood_down(&self, targets: &Targets, inv: &Invariants) -> Option<ProjectionReport> {
        let gap = targets.energy - inv.total;
        let at_rest = inv.kinetic <= RESTING_CONTACT_RESIDUAL * targets.energy_scale
            || -gap > self.removable_kinetic(inv, targets);
        at_rest.then(|| {
            let residual = gap.abs() / targets.energy_scale;
            ProjectionReport {
                stood_down: true,
                initial_residual: residual,
                final_residual: residual,
                base_energy: inv.total,
                base_min_j: inv.min_j,
                gap,
                frozen_vertices: self.contact_vertices.len(),
                ..Default::default()
            }
        })
    }

    /// The kinetic energy a projection could take out of the current state (J), as the resting rule counts it:
    /// for a body slower than the contact's resting speed ([`RESTING_SPEED_STEPS`] `|g| h`: settling, rocking or
    /// rolling on its support, where the positions cannot give energy up either), all of it but the rigid motion
    /// the momentum rows keep ([`Projector::fixed_kinetic`]); for a faster one (an impact, whose strain can
    /// still give energy up), all of it.
    fn removable_kinetic(&self, inv: &Invariants, targets: &Targets) -> f64 {
        let resting_speed = RESTING_SPEED_STEPS * norm(self.model.gravity) * self.dt;
        if inv.kinetic > 0.5 * self.model.total_mass * resting_speed * resting_speed {
            return inv.kinetic;
        }
        let fixed = self
            .projector
            .as_ref()
            .map_or(0.0, |p| p.fixed_kinetic(&self.model, &self.state, targets));
        inv.kinetic - fixed
    }

    /// The error of a step that made the state unusable (`what`), with the integrator, the step size and `advice`.
    fn unstable(&self, step: usize, what: &str, advice: &str) -> FeprError {
        FeprError::Simulation(format!(
            "{what} in step {step} (t = {:.6} s): the {} step of dt = {} s is unstable for this material and mesh \
             (runaway); {advice}. The state was left at step {}.",
            self.state.time + self.dt,
            self.integrator.name(),
            self.dt,
            step - 1
        ))
    }

    /// The projection of the base step's state onto `targets` (with what the integrator handed over), or, without a
    /// projector, the state's measurement. Returns the report, the invariants and the base state's energy.
    ///
    /// `resting`: on a step of resting contact after one whose projection could not converge (see
    /// [`Simulation::step`]), if the base state's kinetic energy is below the resting bound, the projection stands
    /// down (no iteration; the report says `stood_down`, its residual is the energy's, relative to the energy
    /// scale). On the steps that retry it, a projection that does not converge and whose best iterate has more
    /// kinetic energy than the base step's state gives that state back and stands down too (reporting the
    /// iterations it tried): the iterate would kick a body at rest every retry (an XPBD block resting on a slab
    /// jumped from 6e-5 to 2e-3 J of kinetic energy every 16th step).
    fn project_or_measure(
        &mut self,
        targets: &Targets,
        resting: Resting,
    ) -> (Option<ProjectionReport>, Invariants, f64) {
        // A retry's way back: the base state's stand-down report and invariants.
        let mut at_rest = None;
        if resting != Resting::No && self.projector.is_some() {
            let inv = measure(&self.model, &self.state);
            if let Some(rep) = self.stood_down(targets, &inv) {
                if resting == Resting::StandDown {
                    return (Some(rep), inv, inv.total);
                }
                let (x, v) = &mut self.retry_base;
                copy_rows2(&self.state.x, x, &self.state.v, v);
                at_rest = Some((rep, inv));
            }
        }
        match self.projector.as_mut() {
            Some(p) => {
                p.set_frozen_positions(&self.contact_vertices);
                // Backward Euler ends on an iterate whose elastic gradient it evaluated: the projection's first
                // evaluation is then that one, if pins, obstacles and forces left the positions untouched.
                let hand_over = &mut self.hand_over;
                if let Some((summary, grad)) =
                    hand_over.take_result_gradient(&self.model, &self.state.x)
                {
                    p.offer_base_gradient(summary, grad);
                }
                let (rep, inv) = {
                    let mut metric = hand_over.metric();
                    let system = metric.as_deref_mut().map(|m| m as &mut dyn SystemMetric);
                    p.project_with(&self.model, &mut self.state, self.dt, targets, system)
                };
                let kicked =
                    |(_, base): &(ProjectionReport, Invariants)| inv.kinetic > base.kinetic;
                if let (Some((stood, inv)), false) = (at_rest.filter(kicked), rep.converged) {
                    p.take_final_hand_over();
                    let (x, v) = &self.retry_base;
                    self.state.x.copy_from_slice(x);
                    self.state.v.copy_from_slice(v);
                    let rep = ProjectionReport {
                        iterations: rep.iterations,
                        evaluations: rep.evaluations,
                        trials: rep.trials,
                        ..stood
                    };
                    return (Some(rep), inv, inv.total);
                }
                // The projection's final gradient, for an integrator that starts its next step with it.
                if let Some((grad, x_copy)) = p.take_final_hand_over() {
                    if hand_over.reads_start_gradient() {
                        hand_over.put_final_gradient(&self.model, &self.state.x, x_copy, grad);
                    }
                }
                (Some(rep), inv, rep.base_energy)
            }
            None => {
                let inv = measure(&self.model, &self.state);
                (None, inv, inv.total)
            }
        }
    }

    /// Books the energy the projection did not place: what its quality guard could not restore (`unresolved`), and
    /// after a contact step that did not converge, the residual as contact work (see the cases below).
    fn book_unplaced_energy(
        &mut self,
        projection: Option<ProjectionReport>,
        inv: &Invariants,
        contacts: usize,
        work: &mut Work,
        report: &mut StepReport,
        targets: &mut Targets,
    ) {
        let scale_h = targets.energy_scale;
        if let Some(p) = projection {
            // What the projection could not restore within its quality guard is the step's unresolved energy:
            // booked, so that the references (and the books) follow the energy the state really has.
            work.unresolved = p.unresolved;
            report.energy_budget += p.unresolved;
            targets.energy += p.unresolved;
            self.unresolved_totals.0 += p.unresolved;
            self.unresolved_totals.1 += p.gap.max(0.0);
        }
        if contacts > 0 && projection.is_some_and(|p| !p.converged) {
            let residual = inv.total - targets.energy;
            let resting = residual.abs() <= RESTING_CONTACT_RESIDUAL * scale_h
                || inv.kinetic <= RESTING_CONTACT_RESIDUAL * scale_h;
            // What the projection could not place is booked as contact work:
            // - a body resting in static equilibrium: H is stationary there (forces and velocities vanish),
            //   so no small correction changes it; the contact's position correction against gravity leaves
            //   a residual every step, which is booked in full;
            // - a moving body that kept more energy than the contact's velocity changes claimed to remove (a
            //   sliding corner whose friction impulse the elastic forces undo next step): the contact is
            //   credited with the loss the state really has, but never with a gain (contact does no positive
            //   work), so a failed step that gained energy is not accepted; the next projection tries again.
            let booked = if resting {
                residual
            } else if residual > 0.0 {
                residual.min(-work.contact).max(0.0)
            } else {
                0.0
            };
            work.contact += booked;
            report.energy_budget += booked;
            targets.energy += booked;
        }
        // What a failed step leaves off its target is deferred, not lost from the books: the state's energy
        // differs from the target by `pending`, which the budget carries (the references do not: the next
        // projection still aims at the target and, when it reaches it, the deferral is reversed). So
        // `total - (H0 + budget_total)` stays closed through steps the projection could not converge (a body
        // that left a contact still vibrating can fail a projection in flight a few steps later), and the
        // history says which steps they were (`proj_converged`, `work_deferred`).
        let pending = match projection {
            Some(p) if !p.converged => inv.total - targets.energy,
            _ => 0.0,
        };
        work.deferred = pending - self.deferred;
        report.energy_budget += work.deferred;
        self.deferred = pending;
    }
}

/// `dst` becomes a copy of `src` ([`copy_rows2`] for its rows).
fn copy_state(src: &State, dst: &mut State) {
    copy_rows2(&src.x, &mut dst.x, &src.v, &mut dst.v);
    dst.time = src.time;
}
