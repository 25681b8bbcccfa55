//! Contact between bodies inside backward Euler's Newton solve ([`CoupledNewton`]): the bodies minimise their
//! objectives together, plus the contact between them.
//!
//! A surface vertex `i` of body A near the triangle `(j)` of body B (barycentric weights `w_j`, B's outward
//! normal `n`, fixed over an iteration) is a row with the relative position `r(x) = x_i - sum_j w_j x_j`. Its
//! energy, added to the bodies' objectives, is
//!
//! ```text
//! E = k/2 min(0, n . r - d)^2  +  mu lambda f0(|T^T (r(x) - r(x_n))|)
//! ```
//!
//! a penalty on the gap below `d` (`k = ROW_STIFFNESS_RATIO / (h^2 K)`, `K` the pair's effective inverse mass,
//! `d` the obstacles' activation margin: the law of the obstacles' penalty in each body's objective) and the
//! smoothed Coulomb friction of the tangential sliding over the step (`T` the tangent plane, `lambda` the
//! row's normal force at the start of the iteration, `f0` the C1 mollifier of Incremental Potential Contact:
//! static below `FRICTION_SLIP_SPEED h` of sliding, `mu lambda` above). Both depend on the bodies' positions only
//! through `r`, so their forces on the vertex and on the triangle's corners are equal and opposite at every
//! iterate: the bodies exchange momentum, they never create it.
//!
//! Each Newton iteration takes the bodies' own gradients and factorised Hessians, plus the rows' gradient and
//! Gauss-Newton Hessian `sum_q k_q s_q s_q^T` (the normal of the rows in contact, the two tangents of those that
//! rub; `s_q` is the direction on the vertex and `-w_j` times it on the corners): a block-diagonal matrix plus a
//! low-rank coupling, solved exactly by the Sherman-Morrison-Woodbury identity with the bodies' own
//! factorisations (`z_q = H^{-1} s_q`, the small dense system `(1/k + S^T Z) c = S^T u`, `dx = u - Z c` with
//! `u = -H^{-1} g`), then a backtracking line search on the joint objective. Why not push the bodies apart after
//! the step (what the other integrators do): the support then reaches only the contact vertices, after the
//! solve, and a body resting on another sinks into it each step and slides (a box on a box crept 56 mm in 8 s).
//! A hand-written solve for the reason [`super::body_constraints`] gives: no maintained crate offers a Woodbury
//! update over several sparse factorisations.

use super::bodies::{parts_after_base, parts_before_base};
use super::body_constraints::{solve_positive_definite, BodyConstraints, HeldRow};
use super::{Advance, BodyCoefficients, Simulation};
use crate::error::FeprError;
use crate::integrators::{CoupledNewton, StepReport};
use crate::math::{add, cross, dot, norm, scale, sub, Vec3};
use crate::model::Model;
use crate::world::{
    body_contact_pairs, body_pairs_at, BodyExchange, BodyIterate, BodyPair, ACTIVATION_MARGIN,
};

/// Sliding speed below which friction is static (m/s): the mollifier's width over a step. A body held by
/// static friction creeps at most about this fast.
const FRICTION_SLIP_SPEED: f64 = 1e-5;

/// A row's penalty stiffness over its pair's effective mass per step squared: a vertex carrying a force `f`
/// rests `f h^2 K / ROW_STIFFNESS_RATIO` inside the kept gap. A tenth of the obstacles'
/// ([`crate::world::STIFFNESS_RATIO`]): at theirs, a block resting on a slab with friction and FEPR crept 56 mm
/// in 300 steps where it creeps less than 5 mm at this one (`tests/test_body_contact.py`); a hundred times
/// stiffer, a block set sliding on a slab with FEPR was thrown off it.
const ROW_STIFFNESS_RATIO: f64 = 1e3;

/// The depth inside the other body, in its finer body's mean edges, past which a row is stiffened after a
/// round of Newton iterations and the solve continues: the depth the contact tests allow.
const DEEP_ROW_FRACTION: f64 = 0.01;
/// How many times a step may stiffen its deep rows, and by what factor each time.
const DEEP_ROW_ROUNDS: usize = 3;
const DEEP_ROW_STIFFENING: f64 = 10.0;

/// Iterations of each round that look for new rows and take the rows' geometry again (each a detection pass).
const GEOMETRY_ITERATIONS: usize = 4;

/// Rows a vertex may have against one other body (the faces of a crease it sits in).
const ROWS_PER_VERTEX: usize = 3;

fn newton(sim: &mut Simulation) -> &mut dyn CoupledNewton {
    sim.integrator
        .coupled_newton()
        .expect("bodies take a joint Newton solve only when every integrator can")
}

/// `f` with the body's Newton solve and its model.
fn with_newton<R>(sim: &mut Simulation, f: impl FnOnce(&mut dyn CoupledNewton, &Model) -> R) -> R {
    let Simulation {
        integrator, model, ..
    } = sim;
    f(
        integrator.coupled_newton().expect("checked by the caller"),
        model,
    )
}

/// A contact row between two bodies (see the module comment).
#[derive(Clone, Copy)]
struct Row {
    pair: BodyPair,
    /// The relative normal velocity at the start of the step (m/s, negative: approach).
    approach_speed: f64,
    /// The penalty's stiffness `k` (N/m) and the gap it keeps, `d` (m).
    stiffness: f64,
    offset: f64,
    /// The pair's Coulomb coefficient and the normal force friction is taken at (N, the start of the
    /// iteration's).
    mu: f64,
    lagged: f64,
    /// An orthonormal basis of the tangent plane.
    tangents: [Vec3; 2],
}

fn tangents(n: Vec3) -> [Vec3; 2] {
    let a = if n[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let t = sub(a, scale(n, dot(a, n)));
    let t1 = scale(t, 1.0 / norm(t));
    [t1, cross(n, t1)]
}

impl Row {
    /// `r = x_i - sum_j w_j x_j` at the positions `xs` (one array per body).
    fn relative(&self, xs: &[Vec<Vec3>]) -> Vec3 {
        let p = &self.pair;
        let xb = &xs[p.other];
        (0..3).fold(xs[p.body][p.vertex], |s, c| {
            sub(s, scale(xb[p.triangle[c]], p.weights[c]))
        })
    }

    /// The gap below the kept one (m; negative: the penalty acts) and the tangential sliding since the start
    /// of the step in the tangent basis (m), at `xs`.
    fn measure(&self, xs: &[Vec<Vec3>], start: &[Vec<Vec3>]) -> (f64, [f64; 2]) {
        let r = self.relative(xs);
        let slide = sub(r, self.relative(start));
        (
            dot(self.pair.normal, r) - self.offset,
            [dot(self.tangents[0], slide), dot(self.tangents[1], slide)],
        )
    }

    /// The row's energy (J) at `xs`; `eps`: the mollifier's width (m).
    fn energy(&self, xs: &[Vec<Vec3>], start: &[Vec<Vec3>], eps: f64) -> f64 {
        let (g, u) = self.measure(xs, start);
        let mut e = if g < 0.0 {
            0.5 * self.stiffness * g * g
        } else {
            0.0
        };
        if self.mu > 0.0 && self.lagged > 0.0 {
            let y = (u[0] * u[0] + u[1] * u[1]).sqrt();
            let f0 = if y < eps {
                y * y / eps - y * y * y / (3.0 * eps * eps) + eps / 3.0
            } else {
                y
            };
            e += self.mu * self.lagged * f0;
        }
        e
    }

    /// The friction's Hessian with respect to `r` at `xs`, as rank-one terms `(direction, stiffness)` in the
    /// tangent plane: `mu lambda f0(|u|)` has the Hessian `mu lambda (f1(y) / y (I - u^ u^T) + f1'(y) u^ u^T)`
    /// (`y = |u|`, `u^ = u / y`), positive semi-definite since `f1' >= 0`: across the sliding `f1 / y`, along
    /// it `f1'` (`2 / eps - 2 y / eps^2` in the static zone, 0 beyond, where friction is a constant force).
    /// (An isotropic `f1 / y` would overstate the stiffness along the sliding by `1 / y` beyond the static
    /// zone.)
    fn friction_hessian(
        &self,
        xs: &[Vec<Vec3>],
        start: &[Vec<Vec3>],
        eps: f64,
    ) -> Vec<(Vec3, f64)> {
        if !(self.mu > 0.0 && self.lagged > 0.0) {
            return Vec::new();
        }
        let (_, u) = self.measure(xs, start);
        let y = (u[0] * u[0] + u[1] * u[1]).sqrt();
        let bound = self.mu * self.lagged;
        let t = &self.tangents;
        if y <= 1e-3 * eps {
            // At rest: isotropic, 2 / eps.
            return t.iter().map(|&d| (d, bound * 2.0 / eps)).collect();
        }
        let along = scale(add(scale(t[0], u[0]), scale(t[1], u[1])), 1.0 / y);
        let across = cross(self.pair.normal, along);
        let (per_y, slope) = if y < eps {
            (
                2.0 / eps - y / (eps * eps),
                2.0 / eps - 2.0 * y / (eps * eps),
            )
        } else {
            (1.0 / y, 0.0)
        };
        let mut out = vec![(across, bound * per_y)];
        if slope > 0.0 {
            out.push((along, bound * slope));
        }
        out
    }

    /// The row's normal force (N, >= 0), the friction's stiffness over the sliding `f1(y) / y` times
    /// `mu lambda` (N/m) and the friction force on the vertex (N), at `xs`.
    fn forces(&self, xs: &[Vec<Vec3>], start: &[Vec<Vec3>], eps: f64) -> (f64, f64, Vec3) {
        let (g, u) = self.measure(xs, start);
        let normal = if g < 0.0 { -self.stiffness * g } else { 0.0 };
        if !(self.mu > 0.0 && self.lagged > 0.0) {
            return (normal, 0.0, [0.0; 3]);
        }
        let y = (u[0] * u[0] + u[1] * u[1]).sqrt();
        // f1(y) / y: 2/eps - y/eps^2 in the static zone, 1/y beyond.
        let per_y = if y < eps {
            2.0 / eps - y / (eps * eps)
        } else {
            1.0 / y
        };
        let c = self.mu * self.lagged * per_y;
        let t = &self.tangents;
        let friction = scale(add(scale(t[0], u[0]), scale(t[1], u[1])), -c);
        (normal, c, friction)
    }
}

/// The bodies as contact detection sees them at the positions `xs`.
fn iterates<'a>(sims: &'a mut [&mut Simulation], xs: &'a [Vec<Vec3>]) -> Vec<BodyIterate<'a>> {
    sims.iter_mut()
        .zip(xs)
        .map(|(sim, x)| {
            let Simulation { model, surface, .. } = &mut **sim;
            BodyIterate {
                model,
                x,
                surface: surface.as_mut().expect("surfaces are built first"),
            }
        })
        .collect()
}

/// Add rows for the surface vertices within `margin` (m) of another body at the iterates `xs`. A new row takes
/// its face from the start of the step when the vertex was outside there (a prediction deep inside is nearest
/// to a face it never crossed); a vertex inside through a face none of its rows has gets a row for it too.
#[allow(clippy::too_many_arguments)]
fn detect(
    sims: &mut [&mut Simulation],
    xs: &[Vec<Vec3>],
    start: &[Vec<Vec3>],
    rows: &mut Vec<Row>,
    margin: f64,
    h: f64,
    coefficients: &[BodyCoefficients],
) {
    let found = body_contact_pairs(&mut iterates(sims, xs), margin);
    let mut fresh = Vec::new();
    let mut creases = Vec::new();
    for pair in found {
        let same = |r: &Row| {
            r.pair.body == pair.body && r.pair.vertex == pair.vertex && r.pair.other == pair.other
        };
        let mine: Vec<usize> = (0..rows.len()).filter(|&r| same(&rows[r])).collect();
        if mine.is_empty() {
            fresh.push(pair);
        } else if pair.depth > 0.0
            && mine.iter().all(|&r| rows[r].pair.triangle != pair.triangle)
            && (pair.depth < margin
                || (pair.depth < 4.0 * margin
                    && mine.iter().all(|&r| rows[r].measure(xs, start).0 >= 0.0)))
        {
            // Just inside through a face none of its rows has (a crease of the other's surface, or the
            // neighbour of the face its row holds): a row for that face too, or in place of its row that
            // pushes least. Deeper, only when none of its rows holds it (its faces were left behind as it slid
            // over the other's surface): the nearest face can be one the vertex never came through.
            if mine.len() < ROWS_PER_VERTEX {
                creases.push(pair);
            } else {
                let weakest = mine
                    .into_iter()
                    .min_by(|&a, &b| rows[a].lagged.total_cmp(&rows[b].lagged))
                    .expect("rows");
                rows[weakest].pair = pair;
                rows[weakest].tangents = tangents(pair.normal);
            }
        }
    }
    for pair in creases {
        let template = rows
            .iter()
            .find(|r| {
                r.pair.body == pair.body
                    && r.pair.vertex == pair.vertex
                    && r.pair.other == pair.other
            })
            .expect("a crease's vertex has a row");
        let row = Row {
            pair,
            tangents: tangents(pair.normal),
            lagged: 0.0,
            ..*template
        };
        rows.push(row);
    }
    for now in fresh {
        let at_start = body_pairs_at(
            &mut iterates(sims, start),
            &[(now.body, now.vertex, now.other)],
        )
        .pop();
        let pair = match at_start {
            Some(s) if s.depth <= 0.0 => s,
            _ => now,
        };
        let (va, vb) = (&sims[pair.body].state.v, &sims[pair.other].state.v);
        let vp = (0..3).fold([0.0; 3], |s, c| {
            add(s, scale(vb[pair.triangle[c]], pair.weights[c]))
        });
        let size = sims[pair.body]
            .model
            .length_scale
            .min(sims[pair.other].model.length_scale);
        rows.push(Row {
            approach_speed: dot(sub(va[pair.vertex], vp), pair.normal),
            stiffness: ROW_STIFFNESS_RATIO / (h * h * pair.inverse_mass),
            offset: ACTIVATION_MARGIN * size,
            mu: (coefficients[pair.body].friction * coefficients[pair.other].friction).sqrt(),
            lagged: last_normal_force(sims[pair.body], pair.vertex, pair.other),
            tangents: tangents(pair.normal),
            pair,
        });
    }
}

/// The normal force (N) vertex `v` of `sim` pressed on body `other` with at the end of the last step (0: it
/// did not touch it).
fn last_normal_force(sim: &Simulation, v: usize, other: usize) -> f64 {
    let forces = &sim.held_normal_forces;
    forces
        .binary_search_by(|(key, _)| key.cmp(&(v, other)))
        .map_or(0.0, |k| forces[k].1)
}

/// Rows take their geometry again at the iterates `xs` while their vertex is outside the other body: a vertex
/// sliding past the other's edge (whose normal there leans over it) onto its next face gets that face's normal
/// (held to the edge's, it is pushed back as if it had hit a wall).
fn follow(sims: &mut [&mut Simulation], xs: &[Vec<Vec3>], rows: &mut [Row]) {
    if rows.is_empty() {
        return;
    }
    let key = |r: &Row| (r.pair.body, r.pair.vertex, r.pair.other);
    // A vertex with rows for several faces (a crease) keeps them.
    let single: Vec<usize> = (0..rows.len())
        .filter(|&r| rows.iter().filter(|q| key(q) == key(&rows[r])).count() == 1)
        .collect();
    let candidates: Vec<(usize, usize, usize)> = single.iter().map(|&r| key(&rows[r])).collect();
    let now = body_pairs_at(&mut iterates(sims, xs), &candidates);
    let mut next = now.into_iter().peekable();
    for &r in &single {
        let row = &mut rows[r];
        let k = key(row);
        if let Some(p) = next.next_if(|p| (p.body, p.vertex, p.other) == k) {
            if p.depth <= 0.0 {
                row.pair = p;
                row.tangents = tangents(p.normal);
            }
        }
    }
}

/// One rank-one term of the coupling: `k s s^T`, `s` the direction `dir` on row `row`'s vertex and `-w_j dir`
/// on its triangle's corners.
struct Term {
    row: usize,
    dir: Vec3,
    stiffness: f64,
}

/// `s . v` for a term's `s` and a vector `v` over all bodies (one array per body).
fn apply(rows: &[Row], t: &Term, v: &[Vec<Vec3>]) -> f64 {
    let p = &rows[t.row].pair;
    let mut s = dot(t.dir, v[p.body][p.vertex]);
    for c in 0..3 {
        s -= p.weights[c] * dot(t.dir, v[p.other][p.triangle[c]]);
    }
    s
}

/// The Newton direction of the joint objective: `u = -H^{-1} g` per body, corrected through the coupling
/// terms by the Woodbury identity. `grads`: the joint gradient, one array per body.
fn direction(
    sims: &mut [&mut Simulation],
    rows: &[Row],
    terms: &[Term],
    grads: &[Vec<Vec3>],
) -> Vec<Vec<Vec3>> {
    let mut u: Vec<Vec<Vec3>> = grads
        .iter()
        .map(|g| g.iter().map(|v| scale(*v, -1.0)).collect())
        .collect();
    for (k, sim) in sims.iter_mut().enumerate() {
        newton(sim).solve(&mut u[k], 1);
    }
    if terms.is_empty() {
        return u;
    }
    let nb = sims.len();
    let nt = terms.len();
    // z_q = H^{-1} s_q, on the two bodies each term touches (zero elsewhere): per body, the columns of the
    // terms that touch it in one solve.
    let mut z: Vec<Vec<Option<Vec<Vec3>>>> = vec![vec![None; nb]; nt];
    for (k, sim) in sims.iter_mut().enumerate() {
        let m = sim.model.num_vertices();
        let touching: Vec<usize> = (0..nt)
            .filter(|&q| {
                let p = &rows[terms[q].row].pair;
                p.body == k || p.other == k
            })
            .collect();
        if touching.is_empty() {
            continue;
        }
        let mut cols = vec![[0.0; 3]; m * touching.len()];
        for (c, &q) in touching.iter().enumerate() {
            let (p, d) = (&rows[terms[q].row].pair, terms[q].dir);
            let col = &mut cols[c * m..(c + 1) * m];
            if p.body == k {
                col[p.vertex] = d;
            } else {
                for t in 0..3 {
                    col[p.triangle[t]] = sub(col[p.triangle[t]], scale(d, p.weights[t]));
                }
            }
        }
        newton(sim).solve(&mut cols, touching.len());
        for (c, &q) in touching.iter().enumerate() {
            z[q][k] = Some(cols[c * m..(c + 1) * m].to_vec());
        }
    }
    // s_q . z_p, read on the bodies both touch.
    let s_dot = |q: usize, zp: &[Option<Vec<Vec3>>]| -> f64 {
        let p = &rows[terms[q].row].pair;
        let d = terms[q].dir;
        let mut s = zp[p.body].as_ref().map_or(0.0, |v| dot(d, v[p.vertex]));
        if let Some(v) = zp[p.other].as_ref() {
            for c in 0..3 {
                s -= p.weights[c] * dot(d, v[p.triangle[c]]);
            }
        }
        s
    };
    let mut m = vec![0.0; nt * nt];
    for q in 0..nt {
        for p in 0..nt {
            m[q * nt + p] = s_dot(q, &z[p]);
        }
    }
    // Symmetric in exact arithmetic; symmetrised against rounding.
    for q in 0..nt {
        for p in 0..q {
            let a = 0.5 * (m[q * nt + p] + m[p * nt + q]);
            m[q * nt + p] = a;
            m[p * nt + q] = a;
        }
        m[q * nt + q] += 1.0 / terms[q].stiffness;
    }
    let rhs: Vec<f64> = terms.iter().map(|t| apply(rows, t, &u)).collect();
    let c = solve_positive_definite(&m, nt, &rhs);
    for (zq, cq) in z.iter().zip(&c) {
        for (k, col) in zq.iter().enumerate() {
            if let Some(col) = col {
                for (ui, zi) in u[k].iter_mut().zip(col) {
                    *ui = sub(*ui, scale(*zi, *cq));
                }
            }
        }
    }
    u
}

/// The box (m) a body sweeps over a step of `h` from `state` at its current velocities, grown by `margin`.
fn swept_box(sim: &Simulation, h: f64, margin: f64) -> (Vec3, Vec3) {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for (x, v) in sim.state.x.iter().zip(&sim.state.v) {
        for p in [*x, add(*x, scale(*v, h))] {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a] - margin);
                hi[a] = hi[a].max(p[a] + margin);
            }
        }
    }
    (lo, hi)
}

/// Stiffen the rows deeper than `limit` (m) at `xs` by [`DEEP_ROW_STIFFENING`]; returns how many. The plain
/// penalty holds a vertex at `f h^2 K / ROW_STIFFNESS_RATIO` inside, which is deep where a few vertices stop a
/// body much heavier than theirs: a scanned bunny landing on an armadillo at 2.6 m/s ended a step 1 cm inside it,
/// and the step was redone in 16 parts.
fn stiffen_deep_rows(rows: &mut [Row], xs: &[Vec<Vec3>], start: &[Vec<Vec3>], limit: f64) -> usize {
    let mut count = 0;
    for row in rows.iter_mut() {
        if row.measure(xs, start).0 < -limit {
            row.stiffness *= DEEP_ROW_STIFFENING;
            count += 1;
        }
    }
    count
}

/// The largest fraction `alpha` in [0, 1] of the way from `start` to `xs` at which no row's gap is below its
/// kept one (each row's gap is linear along the way, its face held): 1 where no row is inside at `xs`, 0 where
/// a row inside at `xs` was not outside at the start.
fn start_fraction(rows: &[Row], xs: &[Vec<Vec3>], start: &[Vec<Vec3>]) -> f64 {
    let mut alpha: f64 = 1.0;
    for row in rows {
        let (g1, _) = row.measure(xs, start);
        let (g0, _) = row.measure(start, start);
        if g1 < 0.0 && g0 > 0.0 {
            alpha = alpha.min(g0 / (g0 - g1));
        } else if g1 < 0.0 {
            alpha = 0.0;
        }
    }
    alpha
}

/// One part (`h` seconds) of a step of bodies whose integrators minimise an objective by Newton's method
/// ([`CoupledNewton`], backward Euler), with contact between them inside the joint minimisation (see the
/// module comment): rows for the surface vertices within `margin` (m) of another body. A body whose swept box
/// meets no other's takes its own step, exactly as alone (and the others' Newton iterations do not wait for
/// it). Returns each body's advance and what the contact exchanged with it.
pub(super) fn advance_newton_together(
    sims: &mut [&mut Simulation],
    coefficients: &[BodyCoefficients],
    h: f64,
    first: bool,
    margin: f64,
) -> std::result::Result<(Vec<Advance>, Vec<BodyExchange>), (usize, FeprError)> {
    let nb = sims.len();
    let boxes: Vec<(Vec3, Vec3)> = sims.iter().map(|s| swept_box(s, h, margin)).collect();
    let meets = |a: usize, b: usize| {
        (0..3).all(|c| boxes[a].0[c] <= boxes[b].1[c] && boxes[b].0[c] <= boxes[a].1[c])
    };
    let joint: Vec<bool> = (0..nb)
        .map(|a| (0..nb).any(|b| b != a && meets(a, b)))
        .collect();
    let mut advances = vec![Advance::default(); nb];
    let mut exchanges = vec![BodyExchange::default(); nb];
    for k in (0..nb).filter(|&k| !joint[k]) {
        match sims[k].advance_part(h, first) {
            Ok(a) => advances[k] = a,
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
    let members: Vec<usize> = (0..nb).filter(|&k| joint[k]).collect();
    if members.is_empty() {
        return Ok((advances, exchanges));
    }
    let mut group: Vec<&mut Simulation> = sims
        .iter_mut()
        .enumerate()
        .filter(|(k, _)| joint[*k])
        .map(|(_, s)| &mut **s)
        .collect();
    let group_coefficients: Vec<BodyCoefficients> =
        members.iter().map(|&k| coefficients[k]).collect();
    match minimise_together(&mut group, &group_coefficients, h, first, margin) {
        Ok((advs, held)) => {
            for ((k, a), e) in members.iter().zip(advs).zip(held) {
                advances[*k] = a;
                exchanges[*k] = e;
            }
            Ok((advances, exchanges))
        }
        Err((g, e)) => {
            drop(group);
            for (k, sim) in sims.iter_mut().enumerate() {
                if !joint[k] {
                    sim.abandon_step();
                }
            }
            Err((members[g], e))
        }
    }
}

/// What a joint minimisation holds fixed over its rounds.
struct JointSolve<'a> {
    coefficients: &'a [BodyCoefficients],
    /// The positions at the start of the part (one array per body, m).
    start: Vec<Vec<Vec3>>,
    /// The part's length (s), the impact limit rows are found within (m), the friction mollifier's width (m),
    /// the finer body's length scale (m), and the Newton settings.
    h: f64,
    margin: f64,
    eps: f64,
    length: f64,
    max_iterations: usize,
    tolerance: f64,
}

/// How a round of Newton iterations ended: converged, at the iteration cap or with a line search that found no
/// decrease (`Stopped`), or with a body whose Hessian could not be factorised (`Failed`: the solve stops).
#[derive(PartialEq)]
enum RoundEnd {
    Converged,
    Stopped,
    Failed,
}

/// One round of the joint Newton minimisation from `xs` (one array per body, m; `trial` its line search's
/// scratch), with `rows` (found and followed in the round's first iterations). `iterations` and `residual`
/// are the step's so far (iterations counted on from theirs) and are updated.
#[allow(clippy::too_many_arguments)]
fn newton_round(
    sims: &mut [&mut Simulation],
    solve: &JointSolve,
    rows: &mut Vec<Row>,
    xs: &mut Vec<Vec<Vec3>>,
    trial: &mut Vec<Vec<Vec3>>,
    first_round: bool,
    iterations: &mut usize,
    residual: &mut f64,
) -> RoundEnd {
    let nb = sims.len();
    let (eps, max_iterations) = (solve.eps, solve.max_iterations);
    let done = *iterations;
    // Each round's tolerance is relative to its own first decrement: a stiffened round's correction can be
    // below the step's first one's tolerance, and the round would end before it moved the rows out.
    let mut dec0 = 0.0;
    for it in 0..max_iterations {
        let first_iteration = first_round && it == 0;
        // Rows for the vertices the iterate brings near another body, the others' faces followed, in the
        // first iterations of each round (a stiffened round starts where the last one's iterate left the
        // vertices, which may have slid onto other faces); then the rows stay as they are, so that the later
        // iterations minimise one fixed objective.
        if it < GEOMETRY_ITERATIONS {
            detect(
                sims,
                xs,
                &solve.start,
                rows,
                solve.margin,
                solve.h,
                solve.coefficients,
            );
            follow(sims, xs, rows);
        }
        if first_iteration && *xs != solve.start {
            // The first iterate (each body's inertial prediction, or its start) may put vertices inside the
            // other body, where the rows' stiff penalty stores energy that the line search only has to lower,
            // not to remove: the minimisation then releases it into the bodies (a scanned bunny landing on an
            // armadillo was thrown back up, 32 J -> 78 J, over the 16 parts of its step, 2-4 J a part). Start
            // instead where no row's gap is below its kept one: the largest fraction of the way from the
            // step's start to that iterate (each row's gap is linear along the way with its face held).
            let alpha = start_fraction(rows, xs, &solve.start);
            if alpha < 1.0 {
                for (k, sim) in sims.iter_mut().enumerate() {
                    for (x, x0) in xs[k].iter_mut().zip(&solve.start[k]) {
                        *x = add(*x0, scale(sub(*x, *x0), alpha));
                    }
                    newton(sim).set_positions(&xs[k]);
                }
            }
        }
        let mut phi = 0.0;
        let mut magnitude = 0.0;
        let mut grads = Vec::with_capacity(nb);
        let mut failed = false;
        for sim in sims.iter_mut() {
            match with_newton(sim, |n, model| n.linearise(model)) {
                Some((p, m)) => {
                    phi += p;
                    magnitude += m;
                    grads.push(newton(sim).gradient().to_vec());
                }
                None => {
                    failed = true;
                    break;
                }
            }
        }
        if failed {
            return RoundEnd::Failed;
        }
        let mut terms = Vec::new();
        for (r, row) in rows.iter().enumerate() {
            let e = row.energy(xs, &solve.start, eps);
            phi += e;
            magnitude += e;
            let (normal, rubs, friction) = row.forces(xs, &solve.start, eps);
            // The row's gradient is minus its forces: on the vertex, and the opposite on the corners.
            let force = add(scale(row.pair.normal, normal), friction);
            let p = &row.pair;
            grads[p.body][p.vertex] = sub(grads[p.body][p.vertex], force);
            for c in 0..3 {
                let j = p.triangle[c];
                grads[p.other][j] = add(grads[p.other][j], scale(force, p.weights[c]));
            }
            if normal > 0.0 {
                terms.push(Term {
                    row: r,
                    dir: p.normal,
                    stiffness: row.stiffness,
                });
            }
            if rubs > 0.0 {
                for (dir, stiffness) in row.friction_hessian(xs, &solve.start, eps) {
                    terms.push(Term {
                        row: r,
                        dir,
                        stiffness,
                    });
                }
            }
        }
        for (k, sim) in sims.iter().enumerate() {
            for (i, g) in grads[k].iter_mut().enumerate() {
                if sim.model.pinned[i] {
                    *g = [0.0; 3];
                }
            }
        }
        let dx = direction(sims, rows, &terms, &grads);
        // Newton decrement squared: -g . dx.
        let dec = -grads
            .iter()
            .zip(&dx)
            .flat_map(|(g, d)| g.iter().zip(d).map(|(a, b)| dot(*a, *b)))
            .sum::<f64>();
        let dec = dec.max(0.0);
        let lambda = dec.sqrt();
        if it == 0 {
            dec0 = lambda;
        }
        *iterations = done + it + 1;
        *residual = if dec0 > 0.0 { lambda / dec0 } else { 0.0 };
        let step_max = dx
            .iter()
            .flatten()
            .flat_map(|v| v.iter())
            .fold(0.0f64, |a, d| a.max(d.abs()));
        if lambda.is_nan()
            || lambda <= solve.tolerance * dec0
            || lambda <= 1e-300
            || step_max <= 1e-12 * solve.length
            || dec <= 1e-13 * magnitude
        {
            *iterations = done + it;
            return RoundEnd::Converged;
        }
        // Backtracking line search on the joint objective (Armijo, c = 1e-4), as backward Euler's own.
        let mut alpha = 1.0;
        let accepted = loop {
            for k in 0..nb {
                for (i, t) in trial[k].iter_mut().enumerate() {
                    *t = add(xs[k][i], scale(dx[k][i], alpha));
                }
            }
            let mut phi_trial: f64 = rows
                .iter()
                .map(|r| r.energy(trial, &solve.start, eps))
                .sum();
            for (k, sim) in sims.iter_mut().enumerate() {
                phi_trial += with_newton(sim, |n, model| n.objective(model, &trial[k]));
            }
            if phi_trial <= phi - 1e-4 * alpha * dec {
                break true;
            }
            if dec <= 1e-10 * magnitude && phi_trial <= phi + 1e-10 * magnitude {
                break true;
            }
            if alpha < 1e-10 {
                break false;
            }
            alpha *= 0.5;
        };
        if !accepted {
            break;
        }
        std::mem::swap(xs, trial);
        for (k, sim) in sims.iter_mut().enumerate() {
            newton(sim).set_positions(&xs[k]);
        }
    }
    RoundEnd::Stopped
}

/// [`advance_newton_together`] for bodies that may touch: one joint Newton minimisation.
fn minimise_together(
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
            ..
        } = &mut **sim;
        integrator
            .coupled_newton()
            .expect("checked by the caller")
            .begin(model, state, h);
    }
    let v_start: Vec<Vec<Vec3>> = sims.iter().map(|s| s.state.v.clone()).collect();
    let mut xs: Vec<Vec<Vec3>> = sims
        .iter_mut()
        .map(|s| newton(s).positions().to_vec())
        .collect();
    let (max_iterations, tolerance) = sims.iter_mut().fold((0, 1.0f64), |(n, t), s| {
        let (ni, ti) = newton(s).limits();
        (n.max(ni), t.min(ti))
    });
    let solve = JointSolve {
        coefficients,
        start: sims.iter().map(|s| s.state.x.clone()).collect(),
        h,
        margin,
        eps: FRICTION_SLIP_SPEED * h,
        length: sims
            .iter()
            .map(|s| s.model.length_scale)
            .fold(f64::INFINITY, f64::min),
        max_iterations,
        tolerance,
    };
    let (start, eps) = (&solve.start, solve.eps);
    // The line search's trial positions (every entry written before it is read).
    let mut trial = xs.clone();
    let mut rows: Vec<Row> = Vec::new();
    let (mut iterations, mut residual) = (0, 0.0);
    // The depth (m) past which a row is stiffened after a round: a hundredth of the finer body's mean edge.
    let deep_limit = DEEP_ROW_FRACTION
        * sims
            .iter()
            .map(|s| s.mean_edge)
            .fold(f64::INFINITY, f64::min);
    // Rounds of Newton's method: the first with the plain penalty, each later one after stiffening the rows the
    // last one left deep inside (as backward Euler does with its obstacles' penalty).
    for round in 0..=DEEP_ROW_ROUNDS {
        let end = newton_round(
            sims,
            &solve,
            &mut rows,
            &mut xs,
            &mut trial,
            round == 0,
            &mut iterations,
            &mut residual,
        );
        if end == RoundEnd::Failed || round == DEEP_ROW_ROUNDS {
            break;
        }
        // Another round where a vertex is deeper inside the other body than the impact limit `margin` (exact
        // queries: through a face its rows do not hold, too; the next round's detection gives it a row), for
        // which the step would be redone in parts, each a solve; else only after a converged round with rows to
        // stiffen: a round that ran to the cap (rows that rub in static friction, whose zone is a
        // hundred-thousandth of a metre per second wide) would run to it again.
        let deep_vertex = body_contact_pairs(&mut iterates(sims, &xs), margin)
            .iter()
            .any(|p| p.depth > margin);
        if !(end == RoundEnd::Converged || deep_vertex) {
            break;
        }
        let stiffened = stiffen_deep_rows(&mut rows, &xs, start, deep_limit);
        if stiffened == 0 && !deep_vertex {
            break;
        }
    }
    // The rows' forces at the end, and what they gave each body (on its free vertices).
    let mut held = vec![[0.0; 3]; nb];
    let mut booked = Vec::with_capacity(rows.len());
    for row in &rows {
        let (normal, _, friction) = row.forces(&xs, start, eps);
        if normal == 0.0 && friction == [0.0; 3] {
            continue;
        }
        let p = &row.pair;
        let j = scale(add(scale(p.normal, normal), friction), h);
        let free_share: f64 = (0..3)
            .filter(|&c| !sims[p.other].model.pinned[p.triangle[c]])
            .map(|c| p.weights[c])
            .sum();
        held[p.body] = add(held[p.body], j);
        held[p.other] = sub(held[p.other], scale(j, free_share));
        booked.push(HeldRow {
            pair: row.pair,
            approach_speed: row.approach_speed,
            force: normal,
            friction,
        });
    }
    // Each vertex's normal force on each body it pressed on: the next step's friction bound (friction lags
    // the normal force by a step, so that within a step it is a fixed potential Newton can minimise).
    for sim in sims.iter_mut() {
        sim.held_normal_forces.clear();
    }
    for held_row in &booked {
        let p = &held_row.pair;
        sims[p.body]
            .held_normal_forces
            .push(((p.vertex, p.other), held_row.force));
    }
    for sim in sims.iter_mut() {
        let forces = &mut sim.held_normal_forces;
        forces.sort_by_key(|f| f.0);
        // A vertex with rows for several faces of one body (a crease): their forces together.
        forces.dedup_by(|later, kept| {
            later.0 == kept.0 && {
                kept.1 += later.1;
                true
            }
        });
    }
    let mut reports: Vec<StepReport> = Vec::with_capacity(nb);
    for (k, sim) in sims.iter_mut().enumerate() {
        let Simulation {
            integrator,
            model,
            state,
            ..
        } = &mut **sim;
        reports.push(
            integrator
                .coupled_newton()
                .expect("coupled")
                .finish(model, state, iterations, residual, held[k]),
        );
    }
    let exchanges =
        BodyConstraints::booking(booked, h, v_start, coefficients).exchanges(sims, coefficients);
    Ok((parts_after_base(sims, h, starts, reports)?, exchanges))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A step abandoned to be redone in parts gives back the friction bounds it held (the normal forces of the
    /// step before), so that the parts start from the same bounds as the attempt did.
    #[test]
    fn an_abandoned_step_restores_the_friction_bounds() {
        use crate::integrators::{ImplicitEuler, NewtonSettings};
        use crate::material::{Arap, Material};
        use crate::mesh::TetMesh;
        use crate::model::{ModelBuilder, State};
        let verts = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let (mesh, _) = TetMesh::new(verts, &[[0, 1, 2, 3]]).unwrap();
        let material = Material::Arap(Arap::new(1e5, 0.4).unwrap());
        let model = ModelBuilder::new(mesh, material).build().unwrap();
        let state = State::at_rest(&model);
        let integrator = Box::new(ImplicitEuler::new(NewtonSettings::default()).unwrap());
        let mut sim = Simulation::new(model, state, integrator, 1.0 / 60.0, None).unwrap();
        sim.held_normal_forces = vec![((0, 1), 2.5), ((3, 1), 1.0)];
        sim.open_step().unwrap();
        // The attempt's joint solve ends with other bounds.
        sim.held_normal_forces = vec![((2, 1), 7.0)];
        sim.abandon_step();
        assert_eq!(sim.held_normal_forces, vec![((0, 1), 2.5), ((3, 1), 1.0)]);
    }

    /// A vertex of body 0 under a triangle of body 1 (normal +z), pressed in by `depth` and slid by `slide`
    /// since the start; the row's stiffness, friction and lagged normal force.
    fn row_and_positions(depth: f64, slide: [f64; 2]) -> (Row, Vec<Vec<Vec3>>, Vec<Vec<Vec3>>) {
        let tri = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let weights = [0.5, 0.3, 0.2];
        let point = [0.3, 0.2, 0.0];
        let start = vec![vec![[0.3, 0.2, 0.001]], tri.clone()];
        let x = vec![vec![[0.3 + slide[0], 0.2 + slide[1], -depth]], tri];
        let n = [0.0, 0.0, 1.0];
        let row = Row {
            pair: BodyPair {
                body: 0,
                vertex: 0,
                other: 1,
                triangle: [0, 1, 2],
                weights,
                normal: n,
                depth,
                point,
                inverse_mass: 1.0,
            },
            approach_speed: -1.0,
            stiffness: 3e4,
            offset: 1e-5,
            mu: 0.4,
            lagged: 12.0,
            tangents: tangents(n),
        };
        (row, x, start)
    }

    /// The joint Newton solve starts where no row is inside: a vertex that the inertial prediction puts `depth`
    /// inside the other body's face, from `0.001 - offset` outside it at the start, starts at the fraction of the
    /// way where its gap is the kept one (the row then stores no energy); a row outside at the prediction asks
    /// for the whole way, and one already inside at the start for none of it.
    #[test]
    fn the_joint_solve_starts_where_no_row_is_inside() {
        let (row, x, start) = row_and_positions(2e-3, [0.0, 0.0]);
        let alpha = start_fraction(std::slice::from_ref(&row), &x, &start);
        let (g0, g1) = (0.001 - row.offset, -2e-3 - row.offset);
        assert!((alpha - g0 / (g0 - g1)).abs() < 1e-12, "{alpha}");
        let at: Vec<Vec<Vec3>> = x
            .iter()
            .zip(&start)
            .map(|(xk, sk)| {
                xk.iter()
                    .zip(sk)
                    .map(|(a, b)| add(*b, scale(sub(*a, *b), alpha)))
                    .collect()
            })
            .collect();
        assert!(row.measure(&at, &start).0.abs() < 1e-15);
        let (outside, x_out, start_out) = row_and_positions(-5e-4, [0.0, 0.0]);
        assert_eq!(start_fraction(&[outside], &x_out, &start_out), 1.0);
        let (inside, x_in, mut start_in) = row_and_positions(2e-3, [0.0, 0.0]);
        start_in[0][0][2] = -1e-3;
        assert_eq!(start_fraction(&[inside], &x_in, &start_in), 0.0);
    }

    /// After a round, only the rows deeper than the limit are stiffened, each by the stiffening factor: a row
    /// pressed 2 mm in with a limit of 1 mm, not one 0.5 mm in nor one with a gap.
    #[test]
    fn only_rows_deeper_than_the_limit_are_stiffened() {
        let mut rows = Vec::new();
        let mut positions = Vec::new();
        for depth in [2e-3, 5e-4, -1e-3] {
            let (row, x, start) = row_and_positions(depth, [0.0, 0.0]);
            rows.push(row);
            positions.push((x, start));
        }
        let k = rows[0].stiffness;
        let mut stiffened = 0;
        for (row, (x, start)) in rows.iter_mut().zip(&positions) {
            stiffened += stiffen_deep_rows(std::slice::from_mut(row), x, start, 1e-3);
        }
        assert_eq!(stiffened, 1);
        assert_eq!(rows[0].stiffness, DEEP_ROW_STIFFENING * k);
        assert_eq!(rows[1].stiffness, k);
        assert_eq!(rows[2].stiffness, k);
    }

    /// The row's forces are minus the gradient of its energy (central differences), on the vertex and on the
    /// triangle's corners (`-w_j` times the vertex's), in the penalty's range, in static friction (sliding
    /// below the mollifier's width) and in sliding friction.
    #[test]
    fn row_forces_are_minus_the_gradient_of_its_energy() {
        let eps = 1e-4;
        for (depth, slide) in [
            (1e-3, [0.0, 0.0]),
            (2e-3, [3e-5, -2e-5]),
            (5e-4, [4e-3, 1e-3]),
            (-1e-3, [2e-3, 0.0]),
        ] {
            let (row, x, start) = row_and_positions(depth, slide);
            let (normal, _, friction) = row.forces(&x, &start, eps);
            let force = add(scale(row.pair.normal, normal), friction);
            let expected = |body: usize, v: usize| -> Vec3 {
                if body == 0 {
                    force
                } else {
                    scale(force, -row.pair.weights[v])
                }
            };
            for (body, v) in [(0, 0), (1, 0), (1, 1), (1, 2)] {
                for a in 0..3 {
                    let step = 1e-8;
                    let at = |d: f64| {
                        let mut y = x.clone();
                        y[body][v][a] += d;
                        row.energy(&y, &start, eps)
                    };
                    let fd = -(at(step) - at(-step)) / (2.0 * step);
                    let want = expected(body, v)[a];
                    assert!(
                        (fd - want).abs() <= 1e-6 * (1.0 + want.abs()),
                        "depth {depth}, slide {slide:?}, body {body} vertex {v} axis {a}: {fd} vs {want}"
                    );
                }
            }
            if depth < 0.0 {
                assert_eq!(normal, 0.0, "a row with a gap pushes nothing");
            }
        }
    }

    /// The normal part of the Gauss-Newton Hessian is the penalty's exact Hessian `k n n^T`: the vertex's force
    /// changes by `-k dz` when it goes `dz` deeper.
    #[test]
    fn the_penalty_hessian_is_its_stiffness_along_the_normal() {
        let (row, x, start) = row_and_positions(1e-3, [0.0, 0.0]);
        let (f0, _, _) = row.forces(&x, &start, 1e-4);
        let mut y = x.clone();
        y[0][0][2] -= 1e-6;
        let (f1, _, _) = row.forces(&y, &start, 1e-4);
        assert!(((f1 - f0) / 1e-6 - row.stiffness).abs() < 1e-6 * row.stiffness);
    }

    /// Friction is Coulomb's beyond the static zone: `mu lambda` against the sliding, whatever its length.
    #[test]
    fn sliding_friction_is_coulomb() {
        for s in [1e-3, 1e-2, 0.1] {
            let (row, x, start) = row_and_positions(1e-3, [s, 0.0]);
            let (_, _, friction) = row.forces(&x, &start, 1e-4);
            assert!((norm(friction) - row.mu * row.lagged).abs() < 1e-12);
            assert!(friction[0] < 0.0);
        }
    }
}
