//! Contact between bodies: the vertices of one body's surface against the triangles of another's, after the
//! bodies' base steps and before their projections ([`crate::simulation::step_bodies`]); and the candidates of
//! the contact held inside the bodies' joint solve ([`body_contact_pairs`], [`body_pairs_at`]).
//!
//! Each body's surface (its boundary triangles, [`crate::mesh::TetMesh::boundary_triangles`]) is a
//! [`MeshCollider`] whose vertices follow the body: `parry3d-f64` refits its BVH each step (a refit, not a
//! rebuild: the topology never changes). A pair of bodies whose bounding boxes overlap is tested vertex by
//! vertex (each surface vertex of one inside the other's box is queried against its surface, exact
//! point-triangle distance, signed with pseudo-normals); so detection costs O(n log n) in the surface sizes
//! and nothing for bodies apart.
//!
//! A vertex `i` of body A found inside body B, nearest point `p = sum_j w_j x_j` on B's triangle `(j)` with
//! outward normal `n` and depth `d`, is answered as one two-sided contact with effective inverse mass
//! `K = 1/m_i + sum_j w_j^2 / m_j` (pinned vertices: 0):
//! - positions: `x_i += n d / (m_i K)`, `x_j -= n d w_j / (m_j K)`: the gap along `n` closes and the pair's
//!   centre of mass does not move;
//! - velocities: an approaching relative normal velocity `u = n . (v_i - sum_j w_j v_j) < 0` gets the impulse
//!   `J_n = -(1 + e) u / K` (for `e = 1` it exactly conserves the pair's kinetic energy), and Coulomb friction
//!   takes at most `mu J_n` off the relative tangential velocity; `v_i += J / m_i`, `v_j -= w_j J / m_j`.
//!
//! What each body gets is booked in its [`BodyExchange`]: the kinetic energy its velocities changed by, the
//! impulse and its moment about the world origin (taken at the contact point for both sides, so the bodies'
//! moments cancel). The position corrections are not physical work: each body's projection restores the energy
//! they change, as for obstacles.
//!
//! Edge-edge: a surface edge of one body can cross a ridge of the other with neither end inside (two cubes
//! meeting edge to edge). Where this pass is the contact's answer (symplectic Euler, XPBD, bodies of different
//! integrators), each edge whose ends lie close enough to the other surface is searched for its deepest point
//! inside it ([`deepest_on_edge`]), which is answered as above as a point of the edge (its ends sharing by their
//! weights) against the nearest triangle. After a joint solve (Projective Dynamics, backward Euler), whose rows
//! are vertex-face only, edges are not answered. A body against its own surface: [`super::self_contact`].

use crate::error::Result;
use crate::math::{add, cross, dot, norm, scale, sub, Vec3};
use crate::model::{Model, State};

use super::MeshCollider;

/// A body's surface as a collider that follows its vertices.
#[derive(Clone, Debug)]
pub struct BodySurface {
    collider: MeshCollider,
    /// The vertices on the surface, increasing.
    vertices: Vec<u32>,
    /// The surface's edges (each once, ends increasing), in increasing order.
    edges: Vec<[u32; 2]>,
}

impl BodySurface {
    /// The boundary of the model's mesh, at its rest positions.
    pub fn new(model: &Model) -> Result<Self> {
        let triangles = model.mesh.boundary_triangles();
        let collider = MeshCollider::new(model.mesh.vertices(), &triangles)?;
        let mut vertices: Vec<u32> = triangles.iter().flatten().copied().collect();
        vertices.sort_unstable();
        vertices.dedup();
        let mut edges: Vec<[u32; 2]> = triangles
            .iter()
            .flat_map(|t| (0..3).map(move |k| [t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3])]))
            .collect();
        edges.sort_unstable();
        edges.dedup();
        Ok(Self {
            collider,
            vertices,
            edges,
        })
    }

    /// The surface as a collider (at the positions of the last [`BodySurface::follow`]).
    pub fn collider(&self) -> &MeshCollider {
        &self.collider
    }

    /// The vertices on the surface, increasing.
    pub fn vertices(&self) -> &[u32] {
        &self.vertices
    }

    /// Move the surface to the positions `x` (m, all the body's vertices).
    pub fn follow(&mut self, x: &[Vec3]) {
        self.collider.set_vertices(x);
    }

    /// The surface vertices' bounding box `(lo, hi)`, m.
    fn bounds(&self, x: &[Vec3]) -> (Vec3, Vec3) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for &i in &self.vertices {
            let p = x[i as usize];
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        (lo, hi)
    }
}

/// What contact with the other bodies did to one body in a step.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BodyExchange {
    /// Vertex-triangle contacts this body took part in.
    pub contacts: usize,
    /// Kinetic energy change of its velocity changes, J.
    pub work: f64,
    /// Linear impulse it received, kg m/s.
    pub impulse: Vec3,
    /// Moment of that impulse about the world origin, kg m^2/s.
    pub moment: Vec3,
    /// Its vertices that took part (the projection holds their positions).
    pub vertices: Vec<u32>,
    /// Deepest penetration resolved, m.
    pub max_depth: f64,
    /// Fastest relative approach speed of a contact, m/s (0 when none approached).
    pub max_approach: f64,
    /// Whether the impulses were forces held inside the body's solve over the step (they moved its centre of
    /// mass within it), not velocity changes after it.
    pub held: bool,
}

impl BodyExchange {
    /// Add the exchange of a later part of the same step.
    pub fn accumulate(&mut self, e: BodyExchange) {
        self.contacts += e.contacts;
        self.work += e.work;
        self.impulse = add(self.impulse, e.impulse);
        self.moment = add(self.moment, e.moment);
        self.vertices.extend(e.vertices);
        self.vertices.sort_unstable();
        self.vertices.dedup();
        self.max_depth = self.max_depth.max(e.max_depth);
        self.max_approach = self.max_approach.max(e.max_approach);
        self.held |= e.held;
    }
}

/// One body as contact between bodies sees it.
pub struct BodyInContact<'a> {
    pub model: &'a Model,
    pub state: &'a mut State,
    pub surface: &'a mut BodySurface,
    /// Coefficient of restitution in [0, 1].
    pub restitution: f64,
    /// Coulomb friction coefficient (>= 0).
    pub friction: f64,
    /// The positions where the step (or its part) started, m (all vertices), for friction on the sliding
    /// within it; empty: friction acts on the velocities only.
    pub start: &'a [Vec3],
}

/// The coefficients of a pair: the smaller restitution (the softer body decides how much bounce is left) and
/// the geometric mean of the frictions.
fn pair_coefficients(a: &BodyInContact, b: &BodyInContact) -> (f64, f64) {
    (
        a.restitution.min(b.restitution),
        (a.friction * b.friction).sqrt(),
    )
}

/// The impulse (kg m/s, on the vertex; its opposite on the face) of a vertex-face contact whose relative velocity
/// is `rel` (m/s, the vertex's less the face point's), normal `n` (unit, out of the face) and effective inverse
/// mass `k_eff` (1/kg): for an approaching `u = n . rel < 0`, `J_n = -(1 + e) u / K` along `n` and Coulomb
/// friction against the sliding (it stops the sliding when the bound `mu J_n` allows, else takes `mu J_n` off
/// it); zero for a separating one.
pub(crate) fn contact_impulse(
    rel: Vec3,
    n: Vec3,
    k_eff: f64,
    restitution: f64,
    friction: f64,
) -> Vec3 {
    let u = dot(rel, n);
    if u >= 0.0 {
        return [0.0; 3];
    }
    let jn = -(1.0 + restitution) * u / k_eff;
    let impulse = scale(n, jn);
    let vt = sub(rel, scale(n, u));
    let vt_len = norm(vt);
    if vt_len > 0.0 && friction > 0.0 {
        let jt = (friction * jn).min(vt_len / k_eff);
        return sub(impulse, scale(vt, jt / vt_len));
    }
    impulse
}

pub(crate) fn inverse_mass(model: &Model, i: usize) -> f64 {
    if model.pinned[i] {
        0.0
    } else {
        1.0 / model.masses[i]
    }
}

/// One side of a contact between bodies: a point `sum_k weights_k x_k` of a body's surface.
#[derive(Clone, Copy)]
struct Side<'s> {
    vertices: &'s [usize],
    weights: &'s [f64],
}

impl Side<'_> {
    fn at(&self, x: &[Vec3]) -> Vec3 {
        (0..self.vertices.len()).fold([0.0; 3], |s, k| {
            add(s, scale(x[self.vertices[k]], self.weights[k]))
        })
    }
}

/// What one answered contact gave each side: the impulse as it reaches A's and B's free vertices (kg m/s), the
/// contact point (m), the depth (m) and the approach speed (m/s, 0 when separating).
struct Answered {
    got_a: Vec3,
    got_b: Vec3,
    point: Vec3,
    depth: f64,
    approach: f64,
}

/// The velocities of `ba` (`first`) or `bb`, copied.
fn bodies_v(ba: &BodyInContact, bb: &BodyInContact, first: bool) -> Vec<Vec3> {
    if first {
        ba.state.v.clone()
    } else {
        bb.state.v.clone()
    }
}

/// Answer a contact between point `on_a` of body A's surface, `depth` (m) inside body B, and point `on_b` of B's
/// surface, normal `n` out of B (see the module comment: positions along `n` by inverse masses, Coulomb friction
/// on the sliding within the step, the restitution and friction impulse); `None` when neither side can move.
#[allow(clippy::too_many_arguments)]
fn answer_contact(
    ba: &mut BodyInContact,
    bb: &mut BodyInContact,
    on_a: Side,
    on_b: Side,
    n: Vec3,
    depth: f64,
    restitution: f64,
    friction: f64,
) -> Option<Answered> {
    // At most three vertices a side (a vertex, an edge's two ends, a triangle): no allocation per contact.
    let inverse = |model: &Model, side: Side| -> [f64; 3] {
        let mut inv = [0.0; 3];
        for (k, &i) in side.vertices.iter().enumerate() {
            inv[k] = inverse_mass(model, i);
        }
        inv
    };
    let (inv_a, inv_b) = (inverse(ba.model, on_a), inverse(bb.model, on_b));
    let (inv_a, inv_b) = (&inv_a[..on_a.vertices.len()], &inv_b[..on_b.vertices.len()]);
    let k_a: f64 = (0..inv_a.len())
        .map(|k| on_a.weights[k] * on_a.weights[k] * inv_a[k])
        .sum();
    let k_eff = k_a
        + (0..inv_b.len())
            .map(|c| on_b.weights[c] * on_b.weights[c] * inv_b[c])
            .sum::<f64>();
    if k_eff <= 0.0 {
        return None;
    }
    // Moves each side's vertices by `d` (A) and `-d` (B), shared by weight and inverse mass.
    let shift = |ba: &mut BodyInContact,
                 bb: &mut BodyInContact,
                 d: Vec3,
                 field: fn(&mut State) -> &mut Vec<Vec3>| {
        for (k, &i) in on_a.vertices.iter().enumerate() {
            let x = &mut field(ba.state)[i];
            *x = add(*x, scale(d, on_a.weights[k] * inv_a[k]));
        }
        for (c, &j) in on_b.vertices.iter().enumerate() {
            let x = &mut field(bb.state)[j];
            *x = sub(*x, scale(d, on_b.weights[c] * inv_b[c]));
        }
    };
    shift(ba, bb, scale(n, depth / k_eff), |s| &mut s.x);
    if friction > 0.0 && !ba.start.is_empty() && !bb.start.is_empty() {
        // Coulomb friction on the sliding within the step (the displacement of A's point relative to B's,
        // tangential part), within the cone of the push-out's depth: a body resting on another under its weight
        // sinks a little each step and is pushed back; the velocity impulse below stops its sliding velocity but
        // not the sliding already done, which adds up to millimetres of creep over seconds.
        let moved = |st: &State, start: &[Vec3], side: Side| sub(side.at(&st.x), side.at(start));
        let rel = sub(
            moved(ba.state, ba.start, on_a),
            moved(bb.state, bb.start, on_b),
        );
        let slide = sub(rel, scale(n, dot(rel, n)));
        let len = norm(slide);
        if len > 0.0 {
            let undo = scale(slide, (friction * depth / len).min(1.0) / k_eff);
            shift(ba, bb, scale(undo, -1.0), |s| &mut s.x);
        }
    }
    let rel = sub(on_a.at(&ba.state.v), on_b.at(&bb.state.v));
    let u = dot(rel, n);
    let impulse = contact_impulse(rel, n, k_eff, restitution, friction);
    shift(ba, bb, impulse, |s| &mut s.v);
    // Each side's impulse as it reaches the free vertices; the moment at the contact point.
    let share = |side: Side, inv: &[f64]| -> f64 {
        (0..inv.len())
            .filter(|&k| inv[k] > 0.0)
            .map(|k| side.weights[k])
            .sum()
    };
    Some(Answered {
        got_a: scale(impulse, share(on_a, inv_a)),
        got_b: scale(impulse, -share(on_b, inv_b)),
        point: on_a.at(&ba.state.x),
        depth,
        approach: -u,
    })
}

/// Bodies `a` and `b` of the scene in contact, with the pair's coefficients.
#[derive(Clone, Copy)]
struct Pair {
    a: usize,
    b: usize,
    restitution: f64,
    friction: f64,
}

/// Answer a contact of point `on_a` of body A found inside body B (`found`: B's outward normal, the depth (m), the
/// nearest triangle of B's surface and the nearest point's barycentric weights) and book it in both exchanges;
/// the velocities of each body are copied into `v_before` at its first contact.
fn answer_and_book(
    ba: &mut BodyInContact,
    bb: &mut BodyInContact,
    pair: Pair,
    on_a: Side,
    found: (Vec3, f64, usize, [f64; 3]),
    v_before: &mut [Option<Vec<Vec3>>],
    out: &mut [BodyExchange],
) {
    let (n, depth, tri, w) = found;
    let idx = bb.surface.collider.triangles()[tri].map(|j| j as usize);
    let on_b = Side {
        vertices: &idx,
        weights: &w,
    };
    for k in [pair.a, pair.b] {
        v_before[k].get_or_insert_with(|| bodies_v(&*ba, &*bb, k == pair.a));
    }
    let answered = answer_contact(
        ba,
        bb,
        on_a,
        on_b,
        n,
        depth,
        pair.restitution,
        pair.friction,
    );
    if let Some(got) = answered {
        book(out, pair.a, pair.b, &got, on_a.vertices, &idx);
    }
}

/// Book an answered contact in the exchanges of bodies `a` and `b` (the vertices each side involved).
fn book(
    out: &mut [BodyExchange],
    a: usize,
    b: usize,
    got: &Answered,
    on_a: &[usize],
    on_b: &[usize],
) {
    let (ea, eb) = pair_mut(out, a, b);
    for (e, g, verts) in [(ea, got.got_a, on_a), (eb, got.got_b, on_b)] {
        e.contacts += 1;
        e.impulse = add(e.impulse, g);
        e.moment = add(e.moment, cross(got.point, g));
        e.vertices.extend(verts.iter().map(|&v| v as u32));
        e.max_depth = e.max_depth.max(got.depth);
        e.max_approach = e.max_approach.max(got.approach);
    }
}

/// The deepest point of the segment `x0 -> x1` (m) inside the closed surface `collider`, when it dips inside
/// by more than [`EDGE_DIP`] of its length below both its ends: `(t, phi, n, triangle, weights)` at
/// `x0 + t (x1 - x0)` (the signed distance, the nearest triangle's outward normal, the triangle and the nearest
/// point's barycentric weights). The distance is 1-Lipschitz, so a segment whose ends are farther out together
/// than its length cannot dip inside (most edges stop there after two bounded queries); for the others a
/// golden-section search along it (to 1e-6 of its length) finds the minimum of a ridge's distance, unimodal along
/// an edge that crosses it. An end inside is the vertex pass's.
fn deepest_on_edge(
    collider: &MeshCollider,
    x0: Vec3,
    x1: Vec3,
) -> Option<(f64, f64, Vec3, usize, [f64; 3])> {
    let len = norm(sub(x1, x0));
    let (phi0, _) = collider.signed_distance_below(x0, len)?;
    let (phi1, _) = collider.signed_distance_below(x1, len)?;
    if phi0 + phi1 >= len {
        return None;
    }
    // A dip counts when it is this far below the surface and below both ends: edges lying along the other
    // body's surface (bodies resting on each other) graze it everywhere, and answering the grazes pushes nothing
    // that matters.
    let floor = phi0.min(phi1).min(0.0) - EDGE_DIP * len;
    let at = |t: f64| add(x0, scale(sub(x1, x0), t));
    let phi = |t: f64| collider.closest(at(t)).0;
    let [(c, fc), (d, fd)] = crate::math::golden_section(phi, 1e-6, |_| false);
    let t = if fc <= fd { c } else { d };
    let (phi, n, tri, w) = collider.closest(at(t));
    (phi < floor).then_some((t, phi, n, tri, w))
}

/// How far below the surface (and below both its ends) an edge must dip, in units of its length, for the edge
/// pass to answer it.
const EDGE_DIP: f64 = 1e-3;

/// Find and answer the contacts between every pair of `bodies` (see the module comment), with the edge pass when
/// `edges` (a surface edge through a ridge of the other body with neither end inside); one exchange per body,
/// in order. Deterministic: pairs in index order, vertices in increasing order.
pub fn resolve_body_contacts(bodies: &mut [BodyInContact], edges: bool) -> Vec<BodyExchange> {
    let nb = bodies.len();
    let mut out = vec![BodyExchange::default(); nb];
    if nb < 2 {
        return out;
    }
    let bounds = follow_bodies(bodies);
    // Velocities before, for each body's kinetic energy change (only touched vertices change).
    // Velocities before the contacts, copied for a body when it first takes part in one (for its kinetic energy
    // change; bodies that touch nothing are not copied).
    let mut v_before: Vec<Option<Vec<Vec3>>> = vec![None; nb];
    for a in 0..nb {
        for b in 0..nb {
            if a == b || !overlap(bounds[a], bounds[b]) {
                continue;
            }
            let (ba, bb) = pair_mut(bodies, a, b);
            let (restitution, friction) = pair_coefficients(ba, bb);
            for k in 0..ba.surface.vertices.len() {
                let i = ba.surface.vertices[k] as usize;
                let x = ba.state.x[i];
                if !inside(x, bounds[b]) {
                    continue;
                }
                let (phi, n, tri, w) = bb.surface.collider.closest(x);
                if phi >= 0.0 {
                    continue;
                }
                let on_a = Side {
                    vertices: &[i],
                    weights: &[1.0],
                };
                let found = (n, -phi, tri, w);
                let pair = Pair {
                    a,
                    b,
                    restitution,
                    friction,
                };
                answer_and_book(ba, bb, pair, on_a, found, &mut v_before, &mut out);
            }
            // Edge-edge: a surface edge of A through a ridge of B with neither end inside (the vertex pass
            // cannot see it). The deepest point of the edge inside B, found by a golden-section search along it,
            // is answered as a contact of that point (its two ends by their weights) with B's nearest triangle.
            for e in 0..if edges { ba.surface.edges.len() } else { 0 } {
                let [i0, i1] = ba.surface.edges[e].map(|v| v as usize);
                let (x0, x1) = (ba.state.x[i0], ba.state.x[i1]);
                if !(inside(x0, bounds[b]) || inside(x1, bounds[b])) {
                    continue;
                }
                let Some((t, phi, n, tri, w)) = deepest_on_edge(&bb.surface.collider, x0, x1)
                else {
                    continue;
                };
                let on_a = Side {
                    vertices: &[i0, i1],
                    weights: &[1.0 - t, t],
                };
                let found = (n, -phi, tri, w);
                let pair = Pair {
                    a,
                    b,
                    restitution,
                    friction,
                };
                answer_and_book(ba, bb, pair, on_a, found, &mut v_before, &mut out);
            }
        }
    }
    for (k, e) in out.iter_mut().enumerate() {
        e.vertices.sort_unstable();
        e.vertices.dedup();
        let body = &bodies[k];
        e.work = e
            .vertices
            .iter()
            .map(|&i| {
                let i = i as usize;
                let v0 = v_before[k].as_ref().expect("copied at its first contact")[i];
                let v1 = body.state.v[i];
                0.5 * body.model.masses[i] * (dot(v1, v1) - dot(v0, v0))
            })
            .sum();
    }
    out
}

/// One body's iterate inside a step that bodies in contact take together
/// ([`crate::integrators::CoupledSolve`]).
pub struct BodyIterate<'a> {
    pub model: &'a Model,
    /// The iterate, m (all vertices).
    pub x: &'a [Vec3],
    pub surface: &'a mut BodySurface,
}

/// A surface vertex of one body near or inside another's surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyPair {
    /// The body whose vertex is inside, and the vertex.
    pub body: usize,
    pub vertex: usize,
    /// The body it is inside, and the vertices of the nearest triangle of its surface with the nearest point's
    /// barycentric weights.
    pub other: usize,
    pub triangle: [usize; 3],
    pub weights: Vec3,
    /// The other's outward normal there, the depth (m; negative: the gap outside) and the nearest point (m).
    pub normal: Vec3,
    pub depth: f64,
    pub point: Vec3,
    /// The pair's effective inverse mass `1/m_i + sum_j w_j^2 / m_j`, 1/kg.
    pub inverse_mass: f64,
}

/// The surface vertices of each of `bodies` within `margin` (m) of another body's surface or inside it, at
/// their iterates, each with the nearest point of that surface (exact point-triangle distance): the
/// candidates of contact between bodies inside their joint solve. Deterministic: bodies in order, vertices in
/// increasing order.
pub fn body_contact_pairs(bodies: &mut [BodyIterate], margin: f64) -> Vec<BodyPair> {
    let nb = bodies.len();
    let mut pairs = Vec::new();
    if nb < 2 {
        return pairs;
    }
    let bounds: Vec<(Vec3, Vec3)> = bodies
        .iter_mut()
        .map(|b| {
            b.surface.follow(b.x);
            b.surface.bounds(b.x)
        })
        .collect();
    let grown = |(lo, hi): (Vec3, Vec3)| (lo.map(|c| c - margin), hi.map(|c| c + margin));
    for a in 0..nb {
        for b in 0..nb {
            let reach = grown(bounds[b]);
            if a == b || !overlap(bounds[a], reach) {
                continue;
            }
            let (ba, bb) = (&bodies[a], &bodies[b]);
            for &i in &ba.surface.vertices {
                let i = i as usize;
                let x = ba.x[i];
                if !inside(x, reach) {
                    continue;
                }
                if bb
                    .surface
                    .collider
                    .signed_distance_below(x, margin)
                    .is_none()
                {
                    continue;
                }
                if let Some(pair) = nearest_pair(ba, a, i, bb, b) {
                    if -pair.depth < margin {
                        pairs.push(pair);
                    }
                }
            }
        }
    }
    pairs
}

/// The pairs `(body, vertex, other)` of `candidates` with the geometry of `bodies` as they are now (each
/// surface follows its `x`): the nearest point of the other's surface to the vertex, exact. Candidates found
/// on predicted positions take their triangle and normal from the start of the step this way: a vertex the
/// prediction puts deep inside another body is nearest to a face it never crossed.
pub fn body_pairs_at(
    bodies: &mut [BodyIterate],
    candidates: &[(usize, usize, usize)],
) -> Vec<BodyPair> {
    for b in bodies.iter_mut() {
        b.surface.follow(b.x);
    }
    candidates
        .iter()
        .filter_map(|&(a, i, b)| nearest_pair(&bodies[a], a, i, &bodies[b], b))
        .collect()
}

/// Vertex `i` of body `ba` (index `a`) against the nearest point of `bb`'s surface (index `b`): exact
/// point-triangle distance, signed by pseudo-normals; `None` for a pinned vertex or a pinned triangle.
fn nearest_pair(
    ba: &BodyIterate,
    a: usize,
    i: usize,
    bb: &BodyIterate,
    b: usize,
) -> Option<BodyPair> {
    let x = ba.x[i];
    let (phi, n, tri, w) = bb.surface.collider.closest(x);
    let idx = bb.surface.collider.triangles()[tri].map(|j| j as usize);
    let inv_i = inverse_mass(ba.model, i);
    let k_eff = inv_i
        + (0..3)
            .map(|c| w[c] * w[c] * inverse_mass(bb.model, idx[c]))
            .sum::<f64>();
    (inv_i > 0.0 && k_eff > 0.0).then(|| BodyPair {
        body: a,
        vertex: i,
        other: b,
        triangle: idx,
        weights: w,
        normal: n,
        depth: -phi,
        point: sub(x, scale(n, phi)),
        inverse_mass: k_eff,
    })
}

/// The deepest surface vertex of any body inside another: `(body, vertex, other body, depth in m)`, or `None`
/// when no vertex is inside another body. Positions are not changed (the surfaces follow them).
pub fn deepest_between_bodies(bodies: &mut [BodyInContact]) -> Option<(usize, usize, usize, f64)> {
    let bounds = follow_bodies(bodies);
    let mut deepest: Option<(usize, usize, usize, f64)> = None;
    for a in 0..bodies.len() {
        for b in 0..bodies.len() {
            if a == b || !overlap(bounds[a], bounds[b]) {
                continue;
            }
            for &i in &bodies[a].surface.vertices {
                let x = bodies[a].state.x[i as usize];
                if !inside(x, bounds[b]) {
                    continue;
                }
                let Some((phi, _)) = bodies[b].surface.collider.signed_distance_below(x, 0.0)
                else {
                    continue;
                };
                if deepest.is_none_or(|d| -phi > d.3) {
                    deepest = Some((a, i as usize, b, -phi));
                }
            }
        }
    }
    deepest
}

/// Move every body's surface to its positions; each surface's bounding box `(lo, hi)`, m.
fn follow_bodies(bodies: &mut [BodyInContact]) -> Vec<(Vec3, Vec3)> {
    bodies
        .iter_mut()
        .map(|b| {
            b.surface.follow(&b.state.x);
            b.surface.bounds(&b.state.x)
        })
        .collect()
}

fn overlap(a: (Vec3, Vec3), b: (Vec3, Vec3)) -> bool {
    (0..3).all(|k| a.0[k] <= b.1[k] && b.0[k] <= a.1[k])
}

fn inside(x: Vec3, b: (Vec3, Vec3)) -> bool {
    (0..3).all(|k| b.0[k] <= x[k] && x[k] <= b.1[k])
}

/// Two distinct elements of a slice, mutably.
fn pair_mut<T>(s: &mut [T], a: usize, b: usize) -> (&mut T, &mut T) {
    assert_ne!(a, b);
    if a < b {
        let (lo, hi) = s.split_at_mut(b);
        (&mut lo[a], &mut hi[0])
    } else {
        let (lo, hi) = s.split_at_mut(a);
        (&mut hi[0], &mut lo[b])
    }
}
