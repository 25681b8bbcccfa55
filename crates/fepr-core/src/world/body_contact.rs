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
//! they change, as for obstacles. Vertex-triangle proximity only: an edge of one body can still cross an edge of
//! the other without a vertex entering (fine meshes against each other make this rare). A body against its own
//! surface: [`super::self_contact`].

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
}

impl BodySurface {
    /// The boundary of the model's mesh, at its rest positions.
    pub fn new(model: &Model) -> Result<Self> {
        let triangles = model.mesh.boundary_triangles();
        let collider = MeshCollider::new(model.mesh.vertices(), &triangles)?;
        let mut vertices: Vec<u32> = triangles.iter().flatten().copied().collect();
        vertices.sort_unstable();
        vertices.dedup();
        Ok(Self { collider, vertices })
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

/// Find and answer the contacts between every pair of `bodies` (see the module comment); one exchange per body,
/// in order. Deterministic: pairs in index order, vertices in increasing order.
pub fn resolve_body_contacts(bodies: &mut [BodyInContact]) -> Vec<BodyExchange> {
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
                let idx = bb.surface.collider.triangles()[tri].map(|j| j as usize);
                let inv_i = inverse_mass(ba.model, i);
                let inv_j = idx.map(|j| inverse_mass(bb.model, j));
                let k_eff = inv_i + (0..3).map(|c| w[c] * w[c] * inv_j[c]).sum::<f64>();
                if k_eff <= 0.0 {
                    continue;
                }
                let depth = -phi;
                for (k, body) in [(a, &*ba), (b, &*bb)] {
                    v_before[k].get_or_insert_with(|| body.state.v.clone());
                }
                ba.state.x[i] = add(x, scale(n, depth * inv_i / k_eff));
                for c in 0..3 {
                    let j = idx[c];
                    bb.state.x[j] = sub(bb.state.x[j], scale(n, depth * w[c] * inv_j[c] / k_eff));
                }
                if friction > 0.0 && !ba.start.is_empty() && !bb.start.is_empty() {
                    // Coulomb friction on the sliding within the step (the displacement of the vertex relative
                    // to its point on the face, tangential part), within the cone of the push-out's depth: a
                    // body resting on another under its weight sinks a little each step and is pushed back; the
                    // velocity impulse below stops its sliding velocity but not the sliding already done, which
                    // adds up to millimetres of creep over seconds.
                    let moved = |st: &State, start: &[Vec3], j: usize| sub(st.x[j], start[j]);
                    let d_p = (0..3).fold([0.0; 3], |s, c| {
                        add(s, scale(moved(bb.state, bb.start, idx[c]), w[c]))
                    });
                    let rel = sub(moved(ba.state, ba.start, i), d_p);
                    let slide = sub(rel, scale(n, dot(rel, n)));
                    let len = norm(slide);
                    if len > 0.0 {
                        let undo = scale(slide, (friction * depth / len).min(1.0) / k_eff);
                        ba.state.x[i] = sub(ba.state.x[i], scale(undo, inv_i));
                        for c in 0..3 {
                            let j = idx[c];
                            bb.state.x[j] = add(bb.state.x[j], scale(undo, w[c] * inv_j[c]));
                        }
                    }
                }
                let v_p = (0..3).fold([0.0; 3], |s, c| add(s, scale(bb.state.v[idx[c]], w[c])));
                let rel = sub(ba.state.v[i], v_p);
                let u = dot(rel, n);
                let impulse = contact_impulse(rel, n, k_eff, restitution, friction);
                ba.state.v[i] = add(ba.state.v[i], scale(impulse, inv_i));
                for c in 0..3 {
                    let j = idx[c];
                    bb.state.v[j] = sub(bb.state.v[j], scale(impulse, w[c] * inv_j[c]));
                }
                // Each side's impulse as it reaches the free vertices; the moment at the contact point.
                let got_a = if inv_i > 0.0 { impulse } else { [0.0; 3] };
                let share_b: f64 = (0..3).filter(|&c| inv_j[c] > 0.0).map(|c| w[c]).sum();
                let got_b = scale(impulse, -share_b);
                let point = ba.state.x[i];
                let (ea, eb) = pair_mut(&mut out, a, b);
                for (e, got, verts) in [(ea, got_a, &[i][..]), (eb, got_b, &idx[..])] {
                    e.contacts += 1;
                    e.impulse = add(e.impulse, got);
                    e.moment = add(e.moment, cross(point, got));
                    e.vertices.extend(verts.iter().map(|&v| v as u32));
                    e.max_depth = e.max_depth.max(depth);
                    e.max_approach = e.max_approach.max(-u);
                }
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
