//! A simulation's carry (see [`crate::checkpoint`]): what its next steps depend on besides its settings, taken
//! out with [`Simulation::carry`] and put back into a simulation built again from the same settings with
//! [`Simulation::resume`]. The resumed simulation then takes the same steps as the original, bit for bit.
//!
//! The integrator adds what its next steps depend on ([`crate::integrators::Integrator::carry`]: backward Euler's
//! stiffened contact penalties).
//!
//! What is left out, and why that keeps the steps the same: the integrators' and the projection's workspaces,
//! factorisations and caches (the hand-over's gradient, the metric's factors, the contact potential's distance
//! cache) are recomputed from the state and the model to the same bits when they are missing; the step's own
//! scratch (the start-of-step copies, the contact vertices, the retry's base state) is rewritten by every step
//! before it is read.

use super::{Simulation, StepDiagnostics};
use crate::checkpoint::{as_count, key_halves, Carry, CARRY_VERSION};
use crate::error::{FeprError, Result};
use crate::invariants::Invariants;
use crate::math::Vec3;
use crate::world::{Drag, Work};

impl Simulation {
    /// What the next steps depend on besides the settings (see the module docs).
    pub fn carry(&self) -> Carry {
        let mut c = Carry::new();
        c.put_scalar("version", CARRY_VERSION as f64);
        c.put("model_key", key_halves(self.model.key().bits()));
        c.put_scalar("num_vertices", self.model.num_vertices() as f64);
        c.put_scalar("dt", self.dt);
        c.put_vec3s("x", &self.state.x);
        c.put_vec3s("v", &self.state.v);
        c.put_scalar("time", self.state.time);
        let r = &self.references;
        c.put("references", references_row(r));
        c.put(
            "scales",
            vec![self.energy_scale, self.initial_potential, self.deferred],
        );
        c.put(
            "unresolved_totals",
            vec![self.unresolved_totals.0, self.unresolved_totals.1],
        );
        c.put_scalar("resting_steps", self.resting_steps as f64);
        c.put(
            "held_normal_forces",
            self.held_normal_forces
                .iter()
                .flat_map(|&((v, o), f)| [v as f64, o as f64, f])
                .collect(),
        );
        let last = self.history.last().expect("row 0 is always there");
        c.put("last_row", last_row(last));
        // The world: the kinematic pins' anchors, the forces, the drag spring, the damping (set by the user
        // between steps, so part of the state as much as of the settings).
        let anchors: Vec<Vec3> = self.world.anchors.iter().flatten().copied().collect();
        c.put_vec3s("world.anchors", &anchors);
        c.put_vec3s("world.forces", &self.world.forces);
        c.put(
            "world.drag",
            self.world.drag.map_or(Vec::new(), |d| {
                vec![
                    d.vertex as f64,
                    d.target[0],
                    d.target[1],
                    d.target[2],
                    d.stiffness,
                ]
            }),
        );
        c.put(
            "world.damping",
            vec![self.world.air_damping, self.world.rayleigh_damping],
        );
        if let Some(p) = &self.projector {
            p.carry(&self.model, &mut c);
        }
        self.integrator.carry(&mut c);
        let start_gradient = self
            .hand_over
            .start_gradient_at(&self.model, &self.state.x)
            .unwrap_or(&[]);
        c.put_vec3s("hand_over.start_gradient", start_gradient);
        c
    }

    /// Put back what [`Simulation::carry`] took out of a simulation built from the same settings (mesh,
    /// material, masses, pins, integrator, projection, obstacles, kinematic pins): its next steps are then the
    /// original's. A carry of another layout version, mesh, model or time step is refused, and so is one with or
    /// without the projection's entries where this simulation has the other.
    pub fn resume(&mut self, c: &Carry) -> Result<()> {
        let version = c.scalar("version")?;
        if version != CARRY_VERSION as f64 {
            return Err(FeprError::Simulation(format!(
                "the checkpoint's layout version is {version}, this fepr reads version {CARRY_VERSION}"
            )));
        }
        let m = self.model.num_vertices();
        let n = c.count("num_vertices")?;
        if n != m {
            return Err(FeprError::Simulation(format!(
                "the checkpoint is of a body with {n} vertices, this one has {m}"
            )));
        }
        if c.get_len("model_key", 2)? != key_halves(self.model.key().bits()).as_slice() {
            return Err(FeprError::Simulation(
                "the checkpoint belongs to another model: the rest mesh, the material, the masses or the pins \
                 differ"
                    .into(),
            ));
        }
        let dt = c.scalar("dt")?;
        if dt.to_bits() != self.dt.to_bits() {
            return Err(FeprError::Simulation(format!(
                "the checkpoint was taken with dt = {dt:e} s, this simulation has dt = {:e} s",
                self.dt
            )));
        }
        if c.entries().contains_key("projection.expected_iterations") != self.projector.is_some() {
            return Err(FeprError::Simulation(format!(
                "the checkpoint was taken with the projection {}, this simulation has it {}",
                if self.projector.is_some() {
                    "off"
                } else {
                    "on"
                },
                if self.projector.is_some() {
                    "on"
                } else {
                    "off"
                },
            )));
        }
        let x = c.vec3s("x", m)?;
        let v = c.vec3s("v", m)?;
        let time = c.scalar("time")?;
        if !(x.iter().chain(&v).flatten().all(|a| a.is_finite()) && time.is_finite()) {
            return Err(FeprError::Simulation(
                "the checkpoint's state is not finite".into(),
            ));
        }
        let references = references_from(c.get_len("references", 10)?);
        let scales = c.get_len("scales", 3)?;
        let unresolved = c.get_len("unresolved_totals", 2)?;
        let resting_steps = c.count("resting_steps")?;
        let held = c.get("held_normal_forces")?;
        if held.len() % 3 != 0 {
            return Err(FeprError::Simulation(
                "the checkpoint's 'held_normal_forces' entry is not a list of triples".into(),
            ));
        }
        let held = held
            .chunks_exact(3)
            .map(|t| {
                Ok((
                    (
                        as_count("held_normal_forces", t[0])?,
                        as_count("held_normal_forces", t[1])?,
                    ),
                    t[2],
                ))
            })
            .collect::<Result<Vec<_>>>()?;
        if let Some(((v, _), _)) = held.iter().find(|((v, _), _)| *v >= m) {
            return Err(FeprError::Simulation(format!(
                "the checkpoint holds a contact force on vertex {v}, the body has {m} vertices"
            )));
        }
        let last = last_row_from(c.get_len("last_row", LAST_ROW_LEN)?)?;
        let anchors = c.vec3s_any("world.anchors")?;
        let expected: usize = self.world.pins.iter().map(|p| p.vertices.len()).sum();
        if anchors.len() != expected {
            return Err(FeprError::Simulation(format!(
                "the checkpoint anchors {} kinematic vertices, this simulation has {expected}",
                anchors.len()
            )));
        }
        let forces = c.vec3s_any("world.forces")?;
        if !(forces.is_empty() || forces.len() == m) {
            return Err(FeprError::Simulation(format!(
                "the checkpoint's forces have {} rows, the body has {m} vertices",
                forces.len()
            )));
        }
        let drag = match c.get("world.drag")? {
            [] => None,
            [vertex, tx, ty, tz, k] => Some(Drag {
                vertex: as_count("world.drag", *vertex)?,
                target: [*tx, *ty, *tz],
                stiffness: *k,
            }),
            _ => {
                return Err(FeprError::Simulation(
                    "the checkpoint's 'world.drag' entry is malformed".into(),
                ))
            }
        };
        let damping = c.get_len("world.damping", 2)?;
        let start_gradient = c.vec3s_any("hand_over.start_gradient")?;
        if !(start_gradient.is_empty() || start_gradient.len() == m) {
            return Err(FeprError::Simulation(format!(
                "the checkpoint's start gradient has {} rows, the body has {m} vertices",
                start_gradient.len()
            )));
        }
        // The integrator checks its entries before it takes them.
        self.integrator.resume(c, m)?;
        // Everything is read and checked: nothing below fails but the world's own checks, which run first.
        self.world.set_damping(damping[0], damping[1])?;
        self.world.set_forces(&self.model, forces)?;
        self.world.set_drag(&self.model, drag)?;
        if let Some(p) = self.projector.as_mut() {
            p.resume(&self.model, c)?;
        }
        let mut it = anchors.into_iter();
        for (group, anchors) in self.world.pins.iter().zip(self.world.anchors.iter_mut()) {
            *anchors = it.by_ref().take(group.vertices.len()).collect();
        }
        self.state.x = x;
        self.state.v = v;
        self.state.time = time;
        self.previous = self.state.clone();
        self.references = references;
        self.energy_scale = scales[0];
        self.initial_potential = scales[1];
        self.deferred = scales[2];
        self.unresolved_totals = (unresolved[0], unresolved[1]);
        self.resting_steps = resting_steps;
        self.held_normal_forces = held;
        self.history.clear();
        self.history.push(last);
        if !start_gradient.is_empty() {
            self.hand_over
                .restore_start_gradient(&self.model, &self.state.x, start_gradient);
        }
        self.start_unchecked = true;
        for ob in self.world.obstacles.iter_mut() {
            ob.place(time, 0.0);
        }
        Ok(())
    }
}

fn references_row(r: &super::References) -> Vec<f64> {
    let mut a = vec![r.energy];
    a.extend_from_slice(&r.momentum);
    a.extend_from_slice(&r.angular_momentum);
    a.extend_from_slice(&r.center_of_mass);
    a
}

fn references_from(a: &[f64]) -> super::References {
    super::References {
        energy: a[0],
        momentum: [a[1], a[2], a[3]],
        angular_momentum: [a[4], a[5], a[6]],
        center_of_mass: [a[7], a[8], a[9]],
    }
}

/// Numbers in [`last_row`]: step, time, budget total, the invariants (4 energies, 3 x 3 vectors, min J,
/// inverted) and the references (10).
const LAST_ROW_LEN: usize = 3 + 15 + 10;

/// What the next step reads of the last row of the history: its step number, time and budget total, the
/// invariants (the next step's energy scale and base error start from them) and the references.
fn last_row(d: &StepDiagnostics) -> Vec<f64> {
    let i = &d.invariants;
    let mut a = vec![d.step as f64, d.time, d.budget_total];
    a.extend_from_slice(&[i.kinetic, i.elastic, i.gravitational, i.total]);
    a.extend_from_slice(&i.momentum);
    a.extend_from_slice(&i.angular_momentum);
    a.extend_from_slice(&i.center_of_mass);
    a.extend_from_slice(&[i.min_j, i.inverted as f64]);
    a.extend(references_row(&d.references));
    a
}

fn last_row_from(a: &[f64]) -> Result<StepDiagnostics> {
    let v3 = |k: usize| [a[k], a[k + 1], a[k + 2]];
    Ok(StepDiagnostics {
        step: as_count("last_row", a[0])?,
        time: a[1],
        budget_total: a[2],
        invariants: Invariants {
            kinetic: a[3],
            elastic: a[4],
            gravitational: a[5],
            total: a[6],
            momentum: v3(7),
            angular_momentum: v3(10),
            center_of_mass: v3(13),
            min_j: a[16],
            inverted: as_count("last_row", a[17])?,
        },
        references: references_from(&a[18..28]),
        projection: None,
        energy_budget: 0.0,
        work: Work::default(),
        contacts: 0,
        penetration: 0.0,
        base: Default::default(),
        base_ms: 0.0,
        proj_ms: 0.0,
        base_energy_error: 0.0,
        runaway: false,
    })
}
