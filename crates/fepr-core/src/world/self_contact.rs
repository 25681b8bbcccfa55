//! Contact of a body with its own surface (a fold, a limb swung into the torso), after the base step, as contact
//! between bodies is for the integrators that do not hold it in their solve ([`super::resolve_body_contacts`]).
//!
//! What counts as a contact. Every surface point lies behind other parts of its own surface (across the body's
//! thickness), and a point beside a concave corner lies behind the corner's faces: so a vertex is not tested for
//! being inside the body, but for having crossed a face over the step. A surface vertex meets a triangle of its
//! surface when it ends the step behind the triangle's plane, over the inside of the triangle, having started in
//! front of the plane or at most [`START_BEHIND_EDGES`] mean edges behind it (the planes taken at the step's two
//! ends), and
//! - the triangle is not in the vertex's two-ring (the triangles around it or around a surface neighbour);
//! - no corner of the triangle was within [`REST_APART_EDGES`] mean edges of the vertex at rest: parts of the
//!   surface that close are one or two tets apart, and their crossing is the tets between them crushed (the
//!   material's business), as on a thin foot pressed on the ground, not two parts of the body meeting;
//! - the vertex's outward normal and the triangle's are opposed (parts that touch face each other; a flattened,
//!   wrinkled region crosses the planes of faces that look the same way);
//! - no tet around the vertex or the triangle's corners is inverted (the surface there is folded by the
//!   inversion; pushing the fold apart only strains it further).
//!
//! The earliest crossing along the vertex's path is answered as between bodies: the vertex and the triangle's
//! point are moved apart along the triangle's normal, in proportion to their inverse masses, to a small gap
//! in front of it (the centre of mass does not move), and an approaching relative velocity gets the impulse
//! `-(1 + e) u / K` with Coulomb friction (equal and opposite on the vertex and the triangle's point). The
//! impulses are internal: the body's momentum does not change, nor, up to the gap's lever arm, its angular
//! momentum (the projection keeps both to their targets); the kinetic energy they change is the contact's work.
//!
//! Cost. Detection is a BVH query per surface vertex within the step's relative motion (each vertex's
//! displacement less the surface's mean one, plus the largest such deviation: a body in free fall queries a
//! few triangles per vertex), in parallel over the vertices (each vertex's answer depends only on the state, so
//! the result is the same for any thread count); the answers are applied in vertex order. Moving a triangle's
//! corners can push them through another part of the surface, so detection runs again after the moves, up to
//! [`PASSES`] times.

use rayon::prelude::*;

use crate::math::{add, cross, dot, norm, scale, sub, Vec3};
use crate::mesh::signed_volume6;
use crate::model::{Model, State};

use super::body_contact::{contact_impulse, inverse_mass};
use super::{BodyExchange, BodySurface};

/// A vertex that ends behind a face counts if it started no more than this many mean edges behind the face's
/// plane: it crossed the face in the step, or it is still a little inside after the previous steps (the
/// elasticity pushed it back in, or it entered where the rules of the module comment held it off). Deeper
/// starts are the body's other side, across its thickness.
const START_BEHIND_EDGES: f64 = 0.3;

/// Self contact parts a vertex and the face it crossed to this many mean edges.
const GAP_EDGES: f64 = 2e-3;

/// A vertex and a face can meet only if every corner of the face was at least this many mean edges from the
/// vertex at rest.
pub const REST_APART_EDGES: f64 = 2.0;

/// Slack added to the query radius, in mean edges (the rotation of a face over a step).
const QUERY_SLACK_EDGES: f64 = 0.1;

/// At most this many detection passes per step.
pub const PASSES: usize = 4;

/// A body's self contact: its coefficients and what its detection keeps between steps.
#[derive(Clone, Debug)]
pub struct SelfContact {
    /// Coefficient of restitution in [0, 1].
    pub restitution: f64,
    /// Coulomb friction coefficient (>= 0).
    pub friction: f64,
    /// Per surface vertex (parallel to [`BodySurface::vertices`]): the triangles of its two-ring, increasing.
    /// Empty until the first step.
    near: Vec<Vec<u32>>,
    /// Per surface vertex: the triangles around it (its outward normal).
    around: Vec<Vec<u32>>,
    /// Per vertex of the body: whether a tet around it is inverted at the positions of the current pass.
    crushed: Vec<bool>,
}

/// A crossing found for one surface vertex: the triangle (its vertices), the barycentric weights of the point
/// under the vertex, the triangle's unit normal and the depth behind it (m), and when along the step (0..1).
#[derive(Clone, Copy, Debug)]
struct Crossing {
    triangle: [usize; 3],
    weights: [f64; 3],
    normal: Vec3,
    depth: f64,
    when: f64,
}

impl SelfContact {
    /// Self contact with these coefficients (validated by the caller).
    pub fn new(restitution: f64, friction: f64) -> Self {
        Self {
            restitution,
            friction,
            near: Vec::new(),
            around: Vec::new(),
            crushed: Vec::new(),
        }
    }

    /// Each surface vertex's triangles and two-ring (once).
    fn prepare(&mut self, surface: &BodySurface) {
        if !self.near.is_empty() {
            return;
        }
        let triangles = surface.collider().triangles();
        let vertices = surface.vertices();
        let slot = |v: u32| vertices.binary_search(&v).expect("a surface vertex");
        let mut around: Vec<Vec<u32>> = vec![Vec::new(); vertices.len()];
        for (t, tri) in triangles.iter().enumerate() {
            for &v in tri {
                around[slot(v)].push(t as u32);
            }
        }
        self.near = (0..vertices.len())
            .map(|k| {
                let mut near: Vec<u32> = around[k]
                    .iter()
                    .flat_map(|&t| triangles[t as usize])
                    .flat_map(|v| around[slot(v)].iter().copied())
                    .collect();
                near.sort_unstable();
                near.dedup();
                near
            })
            .collect();
        self.around = around;
    }

    /// Mark the vertices of the tets of `model` inverted at the positions `x` (m).
    fn mark_crushed(&mut self, model: &Model, x: &[Vec3]) {
        self.crushed.clear();
        self.crushed.resize(x.len(), false);
        for t in model.mesh.tets() {
            if signed_volume6(x, t) <= 0.0 {
                for &v in t {
                    self.crushed[v] = true;
                }
            }
        }
    }

    /// Find and answer the body's contacts with its own surface over the step that went from `x_start` (m, all
    /// the body's vertices) to `state`; `surface` is the body's surface (it is moved to the positions);
    /// `mean_edge` (m) is the mesh's mean rest edge length. The exchange holds the contacts, their work (J), the
    /// vertices they touched and the deepest crossing (m); its impulse and moment are zero (internal).
    pub fn resolve(
        &mut self,
        model: &Model,
        state: &mut State,
        surface: &mut BodySurface,
        x_start: &[Vec3],
        mean_edge: f64,
    ) -> BodyExchange {
        self.prepare(surface);
        let mut out = BodyExchange::default();
        // The velocities of the vertices the contacts touch, before they touched them (for the work).
        let mut v_before: Vec<(u32, Vec3)> = Vec::new();
        for _ in 0..PASSES {
            surface.follow(&state.x);
            self.mark_crushed(model, &state.x);
            let crossings = self.detect(model, &state.x, surface, x_start, mean_edge);
            let mut found = 0;
            for (k, c) in crossings.into_iter().enumerate() {
                let Some(c) = c else { continue };
                let i = surface.vertices()[k] as usize;
                if self.answer(model, state, i, &c, mean_edge, &mut v_before) {
                    found += 1;
                    out.max_depth = out.max_depth.max(c.depth);
                }
            }
            out.contacts += found;
            if found == 0 {
                break;
            }
        }
        // The first velocity recorded for each vertex is the one before any contact touched it (a stable sort).
        v_before.sort_by_key(|&(j, _)| j);
        v_before.dedup_by_key(|&mut (j, _)| j);
        out.vertices = v_before.iter().map(|&(j, _)| j).collect();
        out.work = v_before
            .iter()
            .map(|&(j, v0)| {
                let v1 = state.v[j as usize];
                0.5 * model.masses[j as usize] * (dot(v1, v1) - dot(v0, v0))
            })
            .sum();
        out
    }

    /// The earliest crossing of each surface vertex (module comment), from the positions `x`, in parallel.
    fn detect(
        &self,
        model: &Model,
        x: &[Vec3],
        surface: &BodySurface,
        x_start: &[Vec3],
        mean_edge: f64,
    ) -> Vec<Option<Crossing>> {
        let vertices = surface.vertices();
        // The surface's mean displacement over the step and the largest deviation from it: a crossing is no
        // deeper than the vertex's deviation plus the face's.
        let mean_move = scale(
            vertices.iter().fold([0.0; 3], |s, &v| {
                add(s, sub(x[v as usize], x_start[v as usize]))
            }),
            1.0 / vertices.len().max(1) as f64,
        );
        let deviation = |v: usize| norm(sub(sub(x[v], x_start[v]), mean_move));
        let spread = vertices
            .iter()
            .map(|&v| deviation(v as usize))
            .fold(0.0, f64::max);
        let rest = model.mesh.vertices();
        let collider = surface.collider();
        let triangles = collider.triangles();
        (0..vertices.len())
            .into_par_iter()
            .map(|k| {
                let i = vertices[k] as usize;
                if self.crushed[i] {
                    return None;
                }
                let radius = deviation(i) + spread + QUERY_SLACK_EDGES * mean_edge;
                let mut best: Option<Crossing> = None;
                let mut facing: Option<Vec3> = None;
                for t in collider.triangles_near(x[i], radius) {
                    if self.near[k].binary_search(&t).is_ok() {
                        continue;
                    }
                    let idx = triangles[t as usize].map(|j| j as usize);
                    if idx.iter().any(|&j| {
                        self.crushed[j]
                            || norm(sub(rest[j], rest[i])) < REST_APART_EDGES * mean_edge
                    }) {
                        continue;
                    }
                    let (p0, n0) = plane(idx.map(|j| x_start[j]));
                    let c1 = idx.map(|j| x[j]);
                    let (p1, n1) = plane(c1);
                    let (s0, s1) = (dot(sub(x_start[i], p0), n0), dot(sub(x[i], p1), n1));
                    if s0 < -START_BEHIND_EDGES * mean_edge || s1 >= 0.0 {
                        continue;
                    }
                    let n_vertex =
                        *facing.get_or_insert_with(|| self.vertex_normal(k, x, triangles));
                    if dot(n_vertex, n1) >= 0.0 {
                        continue;
                    }
                    let Some(w) = barycentric(c1, sub(x[i], scale(n1, s1))) else {
                        continue;
                    };
                    if w.iter().any(|&b| b < 0.0) {
                        continue;
                    }
                    // When along the step it crossed the plane (0: it started behind it); among equals, the
                    // shallowest.
                    let when = (s0 / (s0 - s1)).max(0.0);
                    if best.is_none_or(|b| (when, -s1) < (b.when, b.depth)) {
                        best = Some(Crossing {
                            triangle: idx,
                            weights: w,
                            normal: n1,
                            depth: -s1,
                            when,
                        });
                    }
                }
                best
            })
            .collect()
    }

    /// Answer the crossing `c` of vertex `i` with the positions as they are now (an earlier answer may have moved
    /// them): apart to the gap, and the impulse. Whether it was still a contact.
    fn answer(
        &self,
        model: &Model,
        state: &mut State,
        i: usize,
        c: &Crossing,
        mean_edge: f64,
        v_before: &mut Vec<(u32, Vec3)>,
    ) -> bool {
        let (idx, w, n) = (c.triangle, c.weights, c.normal);
        let point = |x: &[Vec3]| (0..3).fold([0.0; 3], |s, k| add(s, scale(x[idx[k]], w[k])));
        let gap = GAP_EDGES * mean_edge;
        let apart = gap - dot(sub(state.x[i], point(&state.x)), n);
        let inv_i = inverse_mass(model, i);
        let inv_j = idx.map(|j| inverse_mass(model, j));
        let k_eff = inv_i + (0..3).map(|k| w[k] * w[k] * inv_j[k]).sum::<f64>();
        if apart <= 0.0 || k_eff <= 0.0 {
            return false;
        }
        v_before.push((i as u32, state.v[i]));
        v_before.extend(idx.iter().map(|&j| (j as u32, state.v[j])));
        state.x[i] = add(state.x[i], scale(n, apart * inv_i / k_eff));
        for k in 0..3 {
            state.x[idx[k]] = sub(state.x[idx[k]], scale(n, apart * w[k] * inv_j[k] / k_eff));
        }
        let rel = sub(state.v[i], point(&state.v));
        let impulse = contact_impulse(rel, n, k_eff, self.restitution, self.friction);
        state.v[i] = add(state.v[i], scale(impulse, inv_i));
        for k in 0..3 {
            state.v[idx[k]] = sub(state.v[idx[k]], scale(impulse, w[k] * inv_j[k]));
        }
        true
    }

    /// The outward unit normal at surface vertex `k` (position in the surface's vertices), the area-weighted mean
    /// of its triangles' normals at the positions `x` (m); zero when they cancel.
    fn vertex_normal(&self, k: usize, x: &[Vec3], triangles: &[[u32; 3]]) -> Vec3 {
        let n = self.around[k].iter().fold([0.0; 3], |s, &t| {
            let c = triangles[t as usize].map(|j| x[j as usize]);
            add(s, cross(sub(c[1], c[0]), sub(c[2], c[0])))
        });
        unit(n)
    }
}

/// A point of the triangle `c` and its unit normal (zero for a degenerate triangle).
fn plane(c: [Vec3; 3]) -> (Vec3, Vec3) {
    (c[0], unit(cross(sub(c[1], c[0]), sub(c[2], c[0]))))
}

fn unit(v: Vec3) -> Vec3 {
    let len = norm(v);
    if len > 0.0 {
        scale(v, 1.0 / len)
    } else {
        v
    }
}

/// Barycentric coordinates of `q` (m, in the triangle's plane) in the triangle `c`; `None` for a degenerate one.
fn barycentric(c: [Vec3; 3], q: Vec3) -> Option<[f64; 3]> {
    let (e1, e2, r) = (sub(c[1], c[0]), sub(c[2], c[0]), sub(q, c[0]));
    let (d11, d12, d22) = (dot(e1, e1), dot(e1, e2), dot(e2, e2));
    let (r1, r2) = (dot(r, e1), dot(r, e2));
    let det = d11 * d22 - d12 * d12;
    if det <= 1e-300 {
        return None;
    }
    let b1 = (d22 * r1 - d12 * r2) / det;
    let b2 = (d11 * r2 - d12 * r1) / det;
    Some([1.0 - b1 - b2, b1, b2])
}
