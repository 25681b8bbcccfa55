//! Several bodies stepped as one scene, touching each other: [`step_bodies`].
//!
//! Each body keeps its own simulation (mesh, material, masses, pins, integrator, projection); a step of the
//! scene is every body's base step, then contact between the bodies ([`crate::world::resolve_body_contacts`]),
//! then every body's projection onto targets that include what the contact exchanged with it. When every
//! body's integrator can take its iterations together with the others' ([`crate::integrators::CoupledSolve`]:
//! Projective Dynamics), the base steps are taken together and contact between the bodies is held inside
//! their joint solve ([`BodyConstraints`]); the pass after the step then answers only what that left. Contact between
//! bodies is internal: its impulses are equal and opposite at one point and, with restitution 1 and no
//! friction, it conserves the pair's kinetic energy, so the bodies' targets together keep the scene's total
//! energy, momentum and angular momentum (about the origin); their projections enforce them body by body. Why
//! one projection per body rather than one over the scene: a body out of contact keeps exactly the trajectory
//! it has alone, and each body's books stay its own (a body's energy budget says what contact took from it).

use std::time::Instant;

use super::body_constraints::BodyConstraints;
use super::body_newton::advance_newton_together;
use super::{
    Advance, BaseStart, BegunStep, Simulation, IMPACT_DEPTH_FRACTION, MAX_IMPACT_SUBSTEPS,
};
use crate::error::{FeprError, Result};
use crate::integrators::StepReport;
use crate::world::{
    check_contact_coefficients, deepest_between_bodies, resolve_body_contacts, BodyExchange,
    BodyInContact, BodySurface,
};

/// Contact coefficients of one body among others: restitution in [0, 1], Coulomb friction >= 0. A pair uses
/// the smaller restitution and the geometric mean of the frictions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyCoefficients {
    pub restitution: f64,
    pub friction: f64,
}

impl BodyCoefficients {
    pub fn new(restitution: f64, friction: f64) -> Result<Self> {
        check_contact_coefficients(restitution, friction)?;
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
    assert_eq!(
        sims.len(),
        coefficients.len(),
        "one coefficient pair per body"
    );
    crate::exec::on_pool(|| crate::exec::with_threads_ready(|| step_on_pool(sims, coefficients)))
}

fn step_on_pool(
    sims: &mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
) -> std::result::Result<(), (usize, FeprError)> {
    let result = step_in_parts(sims, coefficients);
    for sim in sims.iter_mut() {
        sim.integrator.take_in_parts(1);
    }
    result
}

fn step_in_parts(
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
    for k in 0..sims.len() {
        if let Err(e) = sims[k].open_step() {
            for sim in &mut sims[..k] {
                sim.abandon_step();
            }
            return Err((k, e));
        }
    }
    // An impact between bodies deeper than a tenth of the finer body's mean edge (and fast enough to have gone
    // that deep within the part) would strain the contact layer when pushed apart after the step: the step is
    // redone from its start in parts short enough for the depth, each part every body's advance and then the
    // contact (as the obstacles' impact substeps do for one body).
    let limit = IMPACT_DEPTH_FRACTION
        * sims
            .iter()
            .map(|s| s.mean_edge)
            .fold(f64::INFINITY, f64::min);
    let dt = sims[0].dt;
    let nb = sims.len();
    let together = sims.iter_mut().all(|s| s.integrator.coupled().is_some());
    // Bodies that all minimise an objective by Newton's method (backward Euler) minimise theirs together, with
    // the contact between them in the joint objective.
    let newton_together = !together
        && nb > 1
        && sims
            .iter_mut()
            .all(|s| s.integrator.coupled_newton().is_some());
    // Bodies whose integrators take substeps of their own (XPBD) meet after each substep, as their obstacles do
    // inside it: the step is taken in as many parts as the finest body has substeps, contact between the
    // bodies answered after each. A substep's approach is a small fraction of the step's, so the push-out is
    // small and the support reaches the body from the next substep on (a whole step's push-out lets a body
    // resting on another sink and slide off it).
    let own_substeps = if together || nb < 2 {
        1
    } else {
        sims.iter()
            .map(|s| s.integrator.substeps())
            .min()
            .filter(|&n| n > 1)
            .map_or(1, |_| {
                sims.iter()
                    .map(|s| s.integrator.substeps())
                    .max()
                    .unwrap_or(1)
            })
    };
    let max_parts = MAX_IMPACT_SUBSTEPS.max(4 * own_substeps);
    let mut parts = own_substeps;
    loop {
        for sim in sims.iter_mut() {
            sim.integrator.take_in_parts(parts);
        }
        let mut advances = vec![Advance::default(); nb];
        let mut exchanges = vec![BodyExchange::default(); nb];
        let mut base_ms = vec![0.0; nb];
        // The deepest push-out out of an obstacle when the bodies take their solves together (their own impact
        // substeps are then the scene's parts), in units of that body's own impact limit: an obstacle's contact
        // concerns one body, whose own substeps answer it to its own mesh's limit (against the finest body's, a
        // scanned armadillo standing on the ground next to a finer bunny redid every step in 2-6 parts, 2-4 s per
        // step with backward Euler).
        let mut deepest_obstacle: f64 = 0.0;
        for part in 0..parts {
            let h = dt / parts as f64;
            if together || newton_together {
                let t0 = Instant::now();
                let (advs, held) = if together {
                    advance_together(sims, coefficients, h, part == 0, limit)?
                } else {
                    advance_newton_together(sims, coefficients, h, part == 0, limit)?
                };
                let ms = t0.elapsed().as_secs_f64() * 1e3 / nb as f64;
                for (k, a) in advs.into_iter().enumerate() {
                    let substeps = advances[k].report.substeps.max(a.report.substeps);
                    let own_limit = IMPACT_DEPTH_FRACTION * sims[k].mean_edge;
                    deepest_obstacle = deepest_obstacle.max(a.max_depth / own_limit);
                    advances[k].add(&a);
                    advances[k].report.substeps = substeps;
                    base_ms[k] += ms;
                }
                for (total, e) in exchanges.iter_mut().zip(held) {
                    total.accumulate(e);
                }
            } else {
                for k in 0..nb {
                    let t0 = Instant::now();
                    match sims[k].advance_part(h, part == 0) {
                        Ok(a) => {
                            let substeps = advances[k].report.substeps.max(a.report.substeps);
                            advances[k].add(&a);
                            advances[k].report.substeps = substeps;
                        }
                        Err(e) => {
                            for (j, sim) in sims.iter_mut().enumerate() {
                                if j != k {
                                    sim.abandon_step();
                                }
                            }
                            return Err((k, e));
                        }
                    }
                    base_ms[k] += t0.elapsed().as_secs_f64() * 1e3;
                }
            }
            let part = {
                // Friction on the sliding within the part only where the pass is the contact's answer: after a
                // joint solve, whose rows carry their own friction, it is a repair, and friction on the repair's
                // displacements costs the pile convergence (84 against 71 unconverged projections of 960).
                // Edges too where the pass is the contact's answer. After a joint solve, whose rows are vertex-face
                // only, the edge pass pushed edges that the next solve took back in, and its parts tripled the
                // pile's landing steps (0.3-1 s each).
                let pass_answers = !(together || newton_together);
                let start = pass_answers.then_some(part == 0);
                let mut bodies = in_contact(sims, coefficients, start);
                resolve_body_contacts(&mut bodies, pass_answers)
            };
            for (total, e) in exchanges.iter_mut().zip(part) {
                total.accumulate(e);
            }
        }
        let deepest = exchanges.iter().map(|e| e.max_depth).fold(0.0, f64::max);
        // Only an impact is redone in parts: bodies resting on each other sink by about g h^2 per step under
        // their weight, which parts would not remove (each part sinks again) and would multiply the cost by.
        let approach = exchanges.iter().map(|e| e.max_approach).fold(0.0, f64::max);
        let impact = approach * dt / parts as f64 > limit;
        let obstacle_impact = deepest_obstacle > 1.0;
        // A joint solve holds an impact with its rows, so nothing is left deep for the test above, but a fast
        // impact of thin features taken in one solve can still bend the surface through itself: a solve
        // whose rows only stop and push (inelastic) then ends with more energy than it started with
        // (two scanned armadillos meeting at 4 m/s at dt = 1/30: 45 J -> 551 J and 338 inverted tets in one
        // step). Such a step is redone in parts, as a deep one is.
        let solve_gained = (together || newton_together)
            && impact
            && parts < max_parts
            && contact_solve_gained_energy(sims, &advances);
        if ((deepest > limit && impact) || obstacle_impact || solve_gained) && parts < max_parts {
            // Parts short enough that the fastest approach goes at most `limit` deep within one (for an
            // obstacle: that the push-out would be at most `limit`).
            let need = if obstacle_impact {
                parts as f64 * deepest_obstacle
            } else {
                approach * dt / limit
            };
            parts = (need.ceil() as usize).clamp(parts + 1, max_parts);
            for sim in sims.iter_mut() {
                sim.abandon_step();
            }
            continue;
        }
        // Each body's projection and books, the bodies at once: a body's finish reads and writes only its own
        // state and exchange, so the bits are the same in any order, and a pile's small bodies (2-5k tets) keep
        // two cores busier side by side than one after another (the pile: 9 of 35 ms per step at rest, serial).
        let mut finishing: Vec<_> = sims
            .iter_mut()
            .zip(advances)
            .zip(&exchanges)
            .zip(base_ms)
            .map(|(((sim, mut adv), e), ms)| {
                adv.report.energy_budget = adv.work.total();
                if parts > own_substeps {
                    adv.report.substeps = adv.report.substeps.max(parts);
                }
                (&mut **sim, Some(BegunStep { adv, base_ms: ms }), e, Ok(()))
            })
            .collect();
        crate::exec::for_each_mut(&mut finishing, |_, (sim, begun, e, result)| {
            *result = sim.finish_step(begun.take().expect("once"), e);
        });
        // The first body that failed names the error (each failed body is back at its step's start).
        if let Some((k, err)) = finishing
            .into_iter()
            .enumerate()
            .find_map(|(k, (.., result))| result.err().map(|e| (k, e)))
        {
            return Err((k, err));
        }
        return Ok(());
    }
}

/// Whether the bodies' step (from their `previous` states, with the works in `advances`) ended with more
/// energy than its external processes (pins, forces) put in, by more than [`SOLVE_GAIN_FRACTION`] of the
/// energy of motion and strain at its start: contact inside a joint solve only stops and pushes, so a gain is
/// a solve that failed the impact. Measured on impact steps only (two energy evaluations per body).
fn contact_solve_gained_energy(sims: &[&mut Simulation], advances: &[Advance]) -> bool {
    let (mut gain, mut scale) = (0.0, 0.0);
    for (sim, adv) in sims.iter().zip(advances) {
        let start = crate::invariants::measure(&sim.model, &sim.previous);
        let end = crate::invariants::measure(&sim.model, &sim.state);
        gain += end.total - start.total - adv.work.pins - adv.work.forces;
        scale += start.kinetic + start.elastic.abs();
    }
    gain > SOLVE_GAIN_FRACTION * scale
}

/// The share of a step's energy of motion and strain that a joint contact solve may gain on an impact before the
/// step is redone in parts ([`contact_solve_gained_energy`]); a converged inelastic solve gains nothing.
const SOLVE_GAIN_FRACTION: f64 = 0.02;

/// The bodies as contact between them sees them; `part`: the step's part just taken (`Some(true)`: the first,
/// which started at the step's start), whose start positions friction reads (`None`: no part, no start).
fn in_contact<'a>(
    sims: &'a mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
    part: Option<bool>,
) -> Vec<BodyInContact<'a>> {
    sims.iter_mut()
        .zip(coefficients)
        .map(|(sim, c)| {
            let Simulation {
                model,
                state,
                surface,
                previous,
                part_start,
                ..
            } = &mut **sim;
            let start: &[_] = match part {
                Some(true) => &previous.x,
                Some(false) => &part_start.x,
                None => &[],
            };
            BodyInContact {
                model,
                state,
                surface: surface.as_mut().expect("surfaces are built first"),
                restitution: c.restitution,
                friction: c.friction,
                start,
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
        let mut bodies = in_contact(sims, coefficients, None);
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
                     deep (more than a tenth of the mean edge of body {b}, {limit:.3e} m); place the bodies apart",
                    x[0], x[1], x[2]
                )),
            ));
        }
    }
    Ok(())
}

/// Seconds per detection pass among `sims` at their current states (each surface follows its body, then every
/// overlapping pair's vertices are queried; nothing is changed), the mean over `repeats` passes: the cost of the
/// broad and narrow phase of [`step_bodies`], for benchmarks.
pub fn time_body_detection(sims: &mut [&mut Simulation], repeats: usize) -> Result<f64> {
    for sim in sims.iter_mut() {
        if sim.surface.is_none() {
            sim.surface = Some(BodySurface::new(&sim.model)?);
        }
    }
    let coefficients = vec![BodyCoefficients::new(1.0, 0.0)?; sims.len()];
    let mut bodies = in_contact(sims, &coefficients, None);
    let t0 = Instant::now();
    for _ in 0..repeats.max(1) {
        std::hint::black_box(deepest_between_bodies(&mut bodies));
    }
    Ok(t0.elapsed().as_secs_f64() / repeats.max(1) as f64)
}

/// One part (`h` seconds) of a step of bodies whose integrators take their solves together
/// ([`crate::integrators::CoupledSolve`], Projective Dynamics): every body's iterations run in lockstep, with
/// contact between the bodies as constraints of their joint global step ([`BodyConstraints`]): rows for the
/// surface vertices the inertial prediction puts within `margin` (m) of another body, and for those the
/// first iterations bring inside one. Returns each body's advance and what the constraints exchanged with it.
fn advance_together(
    sims: &mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
    h: f64,
    first: bool,
    margin: f64,
) -> std::result::Result<(Vec<Advance>, Vec<BodyExchange>), (usize, FeprError)> {
    let nb = sims.len();
    let starts = parts_before_base(sims, h, first);
    for sim in sims.iter_mut() {
        let Simulation {
            integrator,
            model,
            state,
            hand_over,
            ..
        } = &mut **sim;
        integrator
            .coupled()
            .expect("checked by the caller")
            .begin(model, state, h, hand_over);
    }
    let iterations: Vec<usize> = sims
        .iter_mut()
        .map(|s| s.integrator.coupled().expect("coupled").iterations())
        .collect();
    let mut constraints = BodyConstraints::new(sims, h, margin, coefficients);
    let mut done: Vec<bool> = iterations.iter().map(|&n| n == 0).collect();
    for it in 0..iterations.iter().copied().max().unwrap_or(0) {
        if done.iter().all(|&d| d) {
            break;
        }
        if it < DETECTIONS {
            constraints.detect(sims, if it == 0 { 0.25 * margin } else { 0.0 });
        }
        solve_bodies(sims, &done);
        constraints.correct(sims, &done);
        let accepted = accept_bodies(sims, &done, it);
        for k in 0..nb {
            done[k] |= accepted[k] || it + 1 >= iterations[k];
        }
    }
    // While a vertex is still inside another body deeper than a tenth of the limit (the rows' planes are their
    // triangles' at the iterate before the last solve, and the solve moves the triangles), more iterations,
    // each one with the rows taken again from the iterate: cheaper than redoing the step in parts, and no
    // push-out straining the surface afterwards.
    let last = iterations.iter().copied().max().unwrap_or(0);
    if last > 0 {
        for it in last..last + EXTRA_ITERATIONS {
            let d = constraints.detect(sims, 0.0);
            let grew = sims
                .iter_mut()
                .any(|s| s.integrator.coupled().expect("coupled").contacts_grew());
            if d <= 0.1 * margin && !grew {
                break;
            }
            let none_done = vec![false; nb];
            solve_bodies(sims, &none_done);
            constraints.correct(sims, &none_done);
            accept_bodies(sims, &none_done, it);
        }
    }
    let mut reports = Vec::with_capacity(nb);
    for sim in sims.iter_mut() {
        let Simulation {
            integrator,
            model,
            state,
            ..
        } = &mut **sim;
        reports.push(
            integrator
                .coupled()
                .expect("coupled")
                .finish(model, state, h),
        );
    }
    let exchanges = constraints.exchanges(sims, coefficients);
    Ok((parts_after_base(sims, h, starts, reports)?, exchanges))
}

/// Each body's solve of the iteration, the bodies not `done` at once: a body's solve reads and writes only its
/// own state, so the bits are the same in any order, and on two cores a pile's bodies (2-5k tets each) keep
/// both busy better side by side than one after another, each split in chunks.
fn solve_bodies(sims: &mut [&mut Simulation], done: &[bool]) {
    crate::exec::for_each_mut(sims, |k, sim| {
        if !done[k] {
            let Simulation {
                integrator, model, ..
            } = &mut **sim;
            integrator.coupled().expect("coupled").solve(model);
        }
    });
}

/// Each body's acceptance of its corrected iterate `it` (whether it is done), the bodies not `done` at once (as
/// [`solve_bodies`]); `false` for those done.
fn accept_bodies(sims: &mut [&mut Simulation], done: &[bool], it: usize) -> Vec<bool> {
    let mut bodies: Vec<(&mut Simulation, bool)> =
        sims.iter_mut().map(|s| (&mut **s, false)).collect();
    crate::exec::for_each_mut(&mut bodies, |k, (sim, accepted)| {
        if !done[k] {
            let Simulation {
                integrator, model, ..
            } = &mut **sim;
            *accepted = integrator.coupled().expect("coupled").accept(model, it);
        }
    });
    bodies.into_iter().map(|(_, a)| a).collect()
}

/// What comes before the base step of a part the bodies take together, for each body (`first`: the part starts
/// at the step's start).
pub(super) fn parts_before_base(
    sims: &mut [&mut Simulation],
    h: f64,
    first: bool,
) -> Vec<BaseStart> {
    sims.iter_mut()
        .map(|sim| sim.part_before_base(h, first))
        .collect()
}

/// The rest of a part whose base step the bodies took together: each body's processes after its base step
/// (`reports`), from what came before it (`starts`). On an error the failing body's index comes with it, and
/// the other bodies are put back.
pub(super) fn parts_after_base(
    sims: &mut [&mut Simulation],
    h: f64,
    starts: Vec<BaseStart>,
    reports: Vec<StepReport>,
) -> std::result::Result<Vec<Advance>, (usize, FeprError)> {
    let mut advances = Vec::with_capacity(sims.len());
    for (k, (start, report)) in starts.into_iter().zip(reports).enumerate() {
        match sims[k].part_after_base(h, start, report) {
            Ok(a) => advances.push(a),
            Err(e) => {
                for (j, sim) in sims.iter_mut().enumerate() {
                    if j != k {
                        sim.abandon_step();
                    }
                }
                return Err((k, e));
            }
        }
    }
    Ok(advances)
}

/// Iterations of a joint step that look for new contact rows (the first ones; each a detection pass).
const DETECTIONS: usize = 3;

/// Iterations a joint step may add while a vertex is still inside another body.
const EXTRA_ITERATIONS: usize = 10;
