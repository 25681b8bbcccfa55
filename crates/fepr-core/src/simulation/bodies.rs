//! Several bodies stepped as one scene, touching each other: [`step_bodies`].
//!
//! Each body keeps its own simulation (mesh, material, masses, pins, integrator, projection); a step of the
//! scene is every body's base step, then contact between the bodies ([`crate::world::resolve_body_contacts`]),
//! then every body's projection onto targets that include what the contact exchanged with it. Contact between
//! bodies is internal: its impulses are equal and opposite at one point and, with restitution 1 and no
//! friction, it conserves the pair's kinetic energy, so the bodies' targets together keep the scene's total
//! energy, momentum and angular momentum (about the origin); their projections enforce them body by body. Why
//! one projection per body rather than one over the scene: a body out of contact keeps exactly the trajectory
//! it has alone, and each body's books stay its own (a body's energy budget says what contact took from it).

use super::{Simulation, IMPACT_DEPTH_FRACTION};
use crate::error::{invalid, FeprError, Result};
use crate::world::{deepest_between_bodies, resolve_body_contacts, BodyInContact, BodySurface};

/// Contact coefficients of one body among others: restitution in [0, 1], Coulomb friction >= 0. A pair uses
/// the smaller restitution and the geometric mean of the frictions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyCoefficients {
    pub restitution: f64,
    pub friction: f64,
}

impl BodyCoefficients {
    pub fn new(restitution: f64, friction: f64) -> Result<Self> {
        if !(restitution.is_finite() && (0.0..=1.0).contains(&restitution)) {
            return Err(invalid(
                "restitution",
                format!("must be in [0, 1], got {restitution}"),
            ));
        }
        if !(friction.is_finite() && friction >= 0.0) {
            return Err(invalid(
                "friction",
                format!("must be a finite coefficient >= 0, got {friction}"),
            ));
        }
        Ok(Self {
            restitution,
            friction,
        })
    }
}

/// One step of the scene made of `sims` (same `dt`), with contact between them. On an error the failing
/// body's index comes with it, and no body has advanced (the bodies begun are put back).
pub fn step_bodies(
    sims: &mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
) -> std::result::Result<(), (usize, FeprError)> {
    assert_eq!(sims.len(), coefficients.len(), "one coefficient pair per body");
    crate::exec::on_pool(|| crate::exec::with_threads_ready(|| step_on_pool(sims, coefficients)))
}

fn step_on_pool(
    sims: &mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
) -> std::result::Result<(), (usize, FeprError)> {
    for (k, sim) in sims.iter_mut().enumerate() {
        if sim.surface.is_none() {
            sim.surface = Some(BodySurface::new(&sim.model).map_err(|e| (k, e))?);
        }
    }
    if sims.iter().any(|s| s.start_unchecked) {
        check_apart(sims, coefficients)?;
    }
    let mut begun = Vec::with_capacity(sims.len());
    for k in 0..sims.len() {
        match sims[k].begin_step() {
            Ok(b) => begun.push(b),
            Err(e) => {
                for sim in &mut sims[..k] {
                    sim.abandon_step();
                }
                return Err((k, e));
            }
        }
    }
    let exchanges = {
        let mut bodies = in_contact(sims, coefficients);
        resolve_body_contacts(&mut bodies)
    };
    for (k, (b, e)) in begun.into_iter().zip(&exchanges).enumerate() {
        if let Err(err) = sims[k].finish_step(b, e) {
            for sim in &mut sims[k + 1..] {
                sim.abandon_step();
            }
            return Err((k, err));
        }
    }
    Ok(())
}

fn in_contact<'a>(
    sims: &'a mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
) -> Vec<BodyInContact<'a>> {
    sims.iter_mut()
        .zip(coefficients)
        .map(|(sim, c)| {
            let Simulation {
                model,
                state,
                surface,
                ..
            } = &mut **sim;
            BodyInContact {
                model,
                state,
                surface: surface.as_mut().expect("surfaces are built first"),
                restitution: c.restitution,
                friction: c.friction,
            }
        })
        .collect()
}

/// Bodies that start inside each other deeper than one step's contact can resolve (a tenth of the mean edge
/// of the body entered) are an error naming both bodies, the vertex and the depth: pushed apart, they would fly
/// off with the energy of the overlap.
fn check_apart(
    sims: &mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
) -> std::result::Result<(), (usize, FeprError)> {
    let found = {
        let mut bodies = in_contact(sims, coefficients);
        deepest_between_bodies(&mut bodies)
    };
    if let Some((a, i, b, depth)) = found {
        let limit = IMPACT_DEPTH_FRACTION * sims[b].mean_edge;
        if depth > limit {
            let x = sims[a].state.x[i];
            return Err((
                a,
                FeprError::Simulation(format!(
                    "body {a} starts inside body {b}: its vertex {i} at [{:.4}, {:.4}, {:.4}] m is {depth:.4} m \
                     deep (more than a tenth of body {b}'s mean edge, {limit:.3e} m); place the bodies apart",
                    x[0], x[1], x[2]
                )),
            ));
        }
    }
    Ok(())
}
