//! A static triangle mesh as an obstacle (a scanned floor, a bowl, a terrain): exact signed point-triangle
//! distances and segment crossings, for [`super::Shape::Mesh`].
//!
//! The bounding-volume hierarchy, the closest-triangle search and the ray casts are `parry3d-f64`'s (a
//! maintained collision library; its BVH answers a closest-point query in O(log n) triangles). What is ours is
//! the validation (each problem named by triangle or vertex), the orientation rule and the sign convention:
//! - the solid is on the side opposite the triangles' normals (right-hand rule on the listed vertex order);
//!   a closed mesh wound inside-out is turned outward (its signed volume says so), an open mesh is one-sided
//!   and its winding states the free side;
//! - the sign of a distance comes from the angle-weighted pseudo-normal of the nearest feature (face, edge or
//!   vertex; Baerentzen and Aanaes 2005), which is exact for a closed mesh and gives an open one a
//!   well-defined "below".

use parry3d_f64::math::{Vector, VectorExt};
use parry3d_f64::query::{PointQuery, PointQueryWithLocation, Ray, RayCast};
use parry3d_f64::shape::{TriMesh, TriMeshFlags, TrianglePointLocation};

use crate::error::{FeprError, Result};
use crate::math::{cross, dot, norm, scale, sub, Vec3};

fn to_parry(v: Vec3) -> Vector {
    Vector::new(v[0], v[1], v[2])
}

fn from_parry(v: Vector) -> Vec3 {
    [v.x, v.y, v.z]
}

/// A validated, outward-oriented triangle mesh with its BVH. Cheap to clone (shared).
#[derive(Clone)]
pub struct MeshCollider {
    mesh: std::sync::Arc<TriMesh>,
    around: std::sync::Arc<Around>,
    closed: bool,
    /// The diagonal of the vertices' bounding box at construction, m (a length scale).
    size: f64,
}

/// The triangles around each vertex and across each edge: the pseudo-normal of the feature a query lands on is
/// summed from them at query time, from the current positions. Why not parry's (`TriMeshFlags::ORIENTED`): it
/// recomputes every vertex's and edge's pseudo-normal, through two hash maps, on every refit, and a deforming
/// body's surface is refitted every iteration of a joint solve while its queries need a few (the refits were a
/// sixth of the pile's step). The sums run in parry's order (triangles in increasing order, angle-weighted unit
/// normals for a vertex, unit normals for an edge), so the values are the ones it would give.
#[derive(Clone, Debug)]
struct Around {
    /// Per vertex `v`, `corners[corner_start[v]..corner_start[v + 1]]`: `(triangle, corner)`, increasing.
    corner_start: Vec<u32>,
    corners: Vec<(u32, u8)>,
    /// Per triangle, the group of each edge (`0`: corners 0-1, `1`: 1-2, `2`: 2-0); a group's triangles are
    /// `edge_triangles[group_start[g]..group_start[g + 1]]`, increasing.
    edge_group: Vec<[u32; 3]>,
    group_start: Vec<u32>,
    edge_triangles: Vec<u32>,
}

impl Around {
    fn new(vertex_count: usize, triangles: &[[u32; 3]]) -> Self {
        let mut count = vec![0u32; vertex_count + 1];
        for t in triangles {
            for &v in t {
                count[v as usize + 1] += 1;
            }
        }
        for v in 0..vertex_count {
            count[v + 1] += count[v];
        }
        let corner_start = count.clone();
        let mut corners = vec![(0u32, 0u8); triangles.len() * 3];
        for (t, tri) in triangles.iter().enumerate() {
            for (c, &v) in tri.iter().enumerate() {
                corners[count[v as usize] as usize] = (t as u32, c as u8);
                count[v as usize] += 1;
            }
        }
        let mut edges: Vec<((u32, u32), u32, u8)> = triangles
            .iter()
            .enumerate()
            .flat_map(|(t, tri)| {
                (0..3).map(move |e| {
                    let (a, b) = (tri[e], tri[(e + 1) % 3]);
                    ((a.min(b), a.max(b)), t as u32, e as u8)
                })
            })
            .collect();
        edges.sort_unstable();
        let mut edge_group = vec![[0u32; 3]; triangles.len()];
        let mut group_start = vec![0u32];
        let mut edge_triangles = Vec::with_capacity(edges.len());
        for (k, &(pair, t, e)) in edges.iter().enumerate() {
            if k > 0 && edges[k - 1].0 != pair {
                group_start.push(edge_triangles.len() as u32);
            }
            edge_group[t as usize][e as usize] = group_start.len() as u32 - 1;
            edge_triangles.push(t);
        }
        group_start.push(edge_triangles.len() as u32);
        Self {
            corner_start,
            corners,
            edge_group,
            group_start,
            edge_triangles,
        }
    }
}

impl std::fmt::Debug for MeshCollider {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "MeshCollider {{ vertices: {}, triangles: {}, closed: {} }}",
            self.mesh.vertices().len(),
            self.mesh.indices().len(),
            self.closed
        )
    }
}

impl PartialEq for MeshCollider {
    fn eq(&self, other: &Self) -> bool {
        self.closed == other.closed
            && self.mesh.vertices() == other.mesh.vertices()
            && self.mesh.indices() == other.mesh.indices()
    }
}

fn mesh_error(message: String) -> FeprError {
    FeprError::Mesh(format!("mesh obstacle: {message}"))
}

impl MeshCollider {
    /// Build from `vertices` (m) and `triangles` (indices into `vertices`). Errors name the problem: no
    /// triangles, a non-finite vertex, an index out of range, a triangle with a repeated vertex or no area.
    pub fn new(vertices: &[Vec3], triangles: &[[u32; 3]]) -> Result<Self> {
        if triangles.is_empty() {
            return Err(mesh_error("has no triangles".into()));
        }
        if let Some(i) = vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(mesh_error(format!(
                "vertex {i} is not finite: {:?}",
                vertices[i]
            )));
        }
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in vertices {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
        let diag = norm(sub(hi, lo));
        for (t, tri) in triangles.iter().enumerate() {
            if let Some(&bad) = tri.iter().find(|&&i| i as usize >= vertices.len()) {
                return Err(mesh_error(format!(
                    "triangle {t} refers to vertex {bad}, but there are {} vertices",
                    vertices.len()
                )));
            }
            if tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2] {
                return Err(mesh_error(format!(
                    "triangle {t} repeats a vertex: {tri:?}"
                )));
            }
            let [a, b, c] = tri.map(|i| vertices[i as usize]);
            let area2 = norm(cross(sub(b, a), sub(c, a)));
            if area2 <= 1e-14 * diag * diag {
                return Err(mesh_error(format!(
                    "triangle {t} {tri:?} has no area (its vertices are collinear)"
                )));
            }
        }
        let closed = every_edge_shared_twice(triangles);
        let mut tris = triangles.to_vec();
        if closed && signed_volume(vertices, triangles) < 0.0 {
            // Wound inside-out: the normals must point to the free side.
            for t in &mut tris {
                t.swap(1, 2);
            }
        }
        let points = vertices.iter().map(|&v| to_parry(v)).collect();
        let mesh = TriMesh::with_flags(points, tris, TriMeshFlags::empty())
            .map_err(|e| mesh_error(format!("cannot be indexed: {e}")))?;
        let around = Around::new(vertices.len(), mesh.indices());
        Ok(Self {
            mesh: std::sync::Arc::new(mesh),
            around: std::sync::Arc::new(around),
            closed,
            size: diag,
        })
    }

    /// Whether every edge is shared by exactly two triangles (a closed surface that bounds a solid).
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Vertices (m) and triangles, oriented outward.
    pub fn geometry(&self) -> (Vec<Vec3>, Vec<[u32; 3]>) {
        (
            self.mesh
                .vertices()
                .iter()
                .map(|&v| from_parry(v))
                .collect(),
            self.mesh.indices().to_vec(),
        )
    }

    /// Signed distance from `x` to the surface (m, negative on the solid side) and the unit outward normal
    /// at the nearest surface point, so that `x - d n` is that point.
    pub fn signed_distance(&self, x: Vec3) -> (f64, Vec3) {
        let (phi, n, _, _) = self.closest(x);
        (phi, n)
    }

    /// [`MeshCollider::signed_distance`] where it is below `below` (m), else `None`: what contact needs of most
    /// vertices, which lie far from the surface. On a closed mesh the search for the nearest triangle stops at
    /// `below` (a query from far above a large flat mesh otherwise visits much of its BVH: 45% of a Projective
    /// Dynamics step of the armadillo over the terrain), and a point farther than that is inside when a ray from it
    /// first meets a triangle from behind; then its exact distance is queried.
    pub fn signed_distance_below(&self, x: Vec3, below: f64) -> Option<(f64, Vec3)> {
        if !self.closed {
            let (phi, n) = self.signed_distance(x);
            return (phi < below).then_some((phi, n));
        }
        let p = to_parry(x);
        // Points on the surface (where a push-out left them) are signed by the pseudo-normals, as by
        // `signed_distance`, not by the ray: a ray from the surface may count its own triangle or not.
        let on_surface = 1e-9 * self.size;
        if let Some((proj, (tri, location))) = self
            .mesh
            .project_local_point_and_get_location_with_max_dist(p, false, below.max(on_surface))
        {
            let (phi, n, _, _) = self.signed_at(x, from_parry(proj.point), tri, location);
            return (phi < below).then_some((phi, n));
        }
        if !self.inside(x) {
            return None;
        }
        let (phi, n) = self.signed_distance(x);
        (phi < below).then_some((phi, n))
    }

    /// Whether `x` is inside a closed mesh: the first triangle a ray from it meets is met from behind.
    fn inside(&self, x: Vec3) -> bool {
        // An irrational-looking direction, so that the ray seldom grazes an edge of a grid-aligned mesh.
        let dir = Vector::new(0.231, 0.347, 0.909);
        let ray = Ray::new(to_parry(x), dir);
        self.mesh
            .cast_local_ray_and_get_normal(&ray, f64::MAX, false)
            .is_some_and(|hit| self.mesh.triangle(hit.subshape).scaled_normal().dot(dir) > 0.0)
    }

    /// [`MeshCollider::signed_distance`] with where it was measured: `(phi, n, triangle, barycentric
    /// coordinates of the nearest point in it)`.
    pub fn closest(&self, x: Vec3) -> (f64, Vec3, usize, [f64; 3]) {
        let (proj, (tri, location)) = self
            .mesh
            .project_local_point_and_get_location(to_parry(x), false);
        self.signed_at(x, from_parry(proj.point), tri, location)
    }

    /// `(phi, n, triangle, barycentric weights)` of `x`, whose nearest surface point `q` lies in triangle `tri`
    /// at `location`.
    fn signed_at(
        &self,
        x: Vec3,
        q: Vec3,
        tri: u32,
        location: TrianglePointLocation,
    ) -> (f64, Vec3, usize, [f64; 3]) {
        let pseudo = self.pseudo_normal(tri, location);
        let r = sub(x, q);
        let d = norm(r);
        let inside = dot(r, pseudo) < 0.0;
        let n = if d > 1e-14 * (1.0 + norm(x)) {
            // The gradient of the distance: away from the surface outside, towards it inside.
            scale(r, if inside { -1.0 / d } else { 1.0 / d })
        } else {
            scale(pseudo, 1.0 / norm(pseudo))
        };
        let bary = match location {
            TrianglePointLocation::OnVertex(i) => {
                let mut b = [0.0; 3];
                b[i as usize] = 1.0;
                b
            }
            TrianglePointLocation::OnEdge(i, [s, t]) => {
                // parry's edges: 0 = AB, 1 = BC, 2 = AC.
                let (a, b) = [(0, 1), (1, 2), (0, 2)][i as usize];
                let mut w = [0.0; 3];
                w[a] = s;
                w[b] = t;
                w
            }
            TrianglePointLocation::OnFace(_, b) => b,
            TrianglePointLocation::OnSolid => [1.0 / 3.0; 3],
        };
        (if inside { -d } else { d }, n, tri as usize, bary)
    }

    /// The triangles within `radius` (m) of `x` (exact point-triangle distances after the BVH's boxes), in the
    /// BVH's order (the same for the same mesh and positions).
    pub fn triangles_near(&self, x: Vec3, radius: f64) -> impl Iterator<Item = u32> + '_ {
        let p = to_parry(x);
        self.mesh
            .bvh()
            .leaves(move |node| node.aabb().distance_to_local_point(p, true) <= radius)
            .filter(move |&t| self.mesh.triangle(t).distance_to_local_point(p, true) <= radius)
    }

    /// Move the vertices (m; same count) and refit the BVH: a deforming body's surface.
    pub fn set_vertices(&mut self, vertices: &[Vec3]) {
        let points: Vec<Vector> = vertices.iter().map(|&v| to_parry(v)).collect();
        std::sync::Arc::make_mut(&mut self.mesh).set_vertices(&points);
    }

    /// The triangles' vertex indices (outward).
    pub fn triangles(&self) -> &[[u32; 3]] {
        self.mesh.indices()
    }

    /// Outward pseudo-normal (not unit) of the feature of triangle `tri` at `location`: the face's normal, the
    /// sum of the unit normals of an edge's triangles, or the angle-weighted sum of a vertex's.
    fn pseudo_normal(&self, tri: u32, location: TrianglePointLocation) -> Vec3 {
        let around = &*self.around;
        match location {
            TrianglePointLocation::OnEdge(i, _) => {
                // parry's edges: 0 = AB, 1 = BC, 2 = AC; ours: 0 = 0-1, 1 = 1-2, 2 = 2-0.
                let g = around.edge_group[tri as usize][i as usize] as usize;
                let range = around.group_start[g] as usize..around.group_start[g + 1] as usize;
                let sum = around.edge_triangles[range]
                    .iter()
                    .filter_map(|&t| self.mesh.triangle(t).normal())
                    .fold(Vector::ZERO, |s, n| s + n);
                from_parry(sum)
            }
            TrianglePointLocation::OnVertex(i) => {
                let v = self.mesh.indices()[tri as usize][i as usize] as usize;
                let range = around.corner_start[v] as usize..around.corner_start[v + 1] as usize;
                let sum = around.corners[range]
                    .iter()
                    .fold(Vector::ZERO, |s, &(t, corner)| {
                        let tri = self.mesh.triangle(t);
                        let Some(n) = tri.normal() else {
                            return s;
                        };
                        let angle = match corner {
                            0 => (tri.b - tri.a).angle(tri.c - tri.a),
                            1 => (tri.a - tri.b).angle(tri.c - tri.b),
                            _ => (tri.b - tri.c).angle(tri.a - tri.c),
                        };
                        s + n * angle
                    });
                from_parry(sum)
            }
            _ => from_parry(self.mesh.triangle(tri).scaled_normal()),
        }
    }

    /// Where the segment `p0 -> p1` (m), starting outside, first enters the solid: `(t, point, outward
    /// normal)`, `t` in [0, 1]. A ray cast against the triangles (exact for a static mesh); a segment that ends
    /// inside without crossing a front face (it came round an open mesh's edge) enters at the surface point
    /// nearest its end.
    pub fn first_crossing(&self, p0: Vec3, p1: Vec3) -> Option<(f64, Vec3, Vec3)> {
        let (d0, _) = self.signed_distance(p0);
        if d0 < 0.0 || norm(sub(p1, p0)) <= d0 {
            return None;
        }
        let (d1, n1) = self.signed_distance(p1);
        self.ray_entry(p0, p1, d1, n1)
    }

    /// [`MeshCollider::first_crossing`] for a segment known to start outside, given the signed distance `d1`
    /// (m) and normal `n1` at its end.
    pub fn ray_entry(&self, p0: Vec3, p1: Vec3, d1: f64, n1: Vec3) -> Option<(f64, Vec3, Vec3)> {
        let dir = sub(p1, p0);
        let ray = Ray::new(to_parry(p0), to_parry(dir));
        if let Some(hit) = self.mesh.cast_local_ray_and_get_normal(&ray, 1.0, false) {
            let n = from_parry(self.mesh.triangle(hit.subshape).scaled_normal());
            if dot(n, dir) < 0.0 {
                let t = hit.time_of_impact;
                let point = [0, 1, 2].map(|k| p0[k] + t * dir[k]);
                return Some((t, point, scale(n, 1.0 / norm(n))));
            }
        }
        (d1 <= 0.0).then(|| (1.0, sub(p1, scale(n1, d1)), n1))
    }
}

fn every_edge_shared_twice(triangles: &[[u32; 3]]) -> bool {
    let mut edges: Vec<(u32, u32)> = triangles
        .iter()
        .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
        .map(|(a, b)| (a.min(b), a.max(b)))
        .collect();
    edges.sort_unstable();
    let mut k = 0;
    while k < edges.len() {
        let mut j = k;
        while j < edges.len() && edges[j] == edges[k] {
            j += 1;
        }
        if j - k != 2 {
            return false;
        }
        k = j;
    }
    true
}

/// Signed volume enclosed by the triangles (m^3), positive when they are wound outward.
fn signed_volume(vertices: &[Vec3], triangles: &[[u32; 3]]) -> f64 {
    triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| vertices[i as usize]);
            dot(a, cross(b, c)) / 6.0
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The unit cube [0, 1]^3 as 12 triangles, wound outward unless `inward`.
    fn cube(inward: bool) -> (Vec<Vec3>, Vec<[u32; 3]>) {
        let v: Vec<Vec3> = (0..8)
            .map(|i| [(i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64])
            .collect();
        let quads = [
            [0, 2, 3, 1], // z = 0, normal -z
            [4, 5, 7, 6], // z = 1, normal +z
            [0, 1, 5, 4], // y = 0, normal -y
            [2, 6, 7, 3], // y = 1, normal +y
            [0, 4, 6, 2], // x = 0, normal -x
            [1, 3, 7, 5], // x = 1, normal +x
        ];
        let mut t = Vec::new();
        for q in quads {
            t.push([q[0], q[1], q[2]]);
            t.push([q[0], q[2], q[3]]);
        }
        if inward {
            for tri in &mut t {
                tri.swap(1, 2);
            }
        }
        (v, t)
    }

    /// Two triangles of the square [-1, 1]^2 at z = 0, normals +z.
    fn sheet() -> MeshCollider {
        let v = [
            [-1.0, -1.0, 0.0],
            [1.0, -1.0, 0.0],
            [1.0, 1.0, 0.0],
            [-1.0, 1.0, 0.0],
        ];
        MeshCollider::new(&v, &[[0, 1, 2], [0, 2, 3]]).unwrap()
    }

    #[test]
    fn a_closed_cube_gives_exact_signed_distances_whichever_way_it_is_wound() {
        for inward in [false, true] {
            let (v, t) = cube(inward);
            let m = MeshCollider::new(&v, &t).unwrap();
            assert!(m.is_closed());
            // Inside, nearest face x = 1.
            let (d, n) = m.signed_distance([0.9, 0.5, 0.45]);
            assert!((d + 0.1).abs() < 1e-12, "{d}");
            assert!((n[0] - 1.0).abs() < 1e-12);
            // Outside a corner: distance to the corner (1, 1, 1), normal along the diagonal.
            let (d, n) = m.signed_distance([2.0, 2.0, 2.0]);
            assert!((d - 3f64.sqrt()).abs() < 1e-12);
            assert!((n[0] - 1.0 / 3f64.sqrt()).abs() < 1e-12);
            // Outside an edge.
            let (d, _) = m.signed_distance([1.5, -0.5, 0.5]);
            assert!((d - 0.5 * 2f64.sqrt()).abs() < 1e-12);
            // On the surface: the normal is the face's.
            let (d, n) = m.signed_distance([0.3, 0.4, 1.0]);
            assert!(d.abs() < 1e-12 && (n[2] - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn a_bounded_query_answers_exactly_where_the_distance_is_below_the_bound() {
        let (v, t) = cube(false);
        let m = MeshCollider::new(&v, &t).unwrap();
        let points = [
            [0.9, 0.5, 0.45], // inside, 0.1 from a face
            [0.5, 0.5, 0.5],  // inside, deepest
            [2.0, 2.0, 2.0],  // far outside a corner
            [1.05, 0.5, 0.5], // just outside
            [0.3, 0.4, 1.0],  // on the surface
            [0.5, -3.0, 0.5], // far outside, level with the cube
        ];
        for x in points {
            let exact = m.signed_distance(x);
            for below in [-0.3, -0.05, 0.0, 0.01, 0.2, 5.0] {
                let got = m.signed_distance_below(x, below);
                if exact.0 < below {
                    assert_eq!(got, Some(exact), "{x:?} below {below}");
                } else {
                    assert_eq!(got, None, "{x:?} below {below}");
                }
            }
        }
    }

    #[test]
    fn the_nearest_point_is_the_barycentric_combination_reported() {
        let (v, t) = cube(false);
        let m = MeshCollider::new(&v, &t).unwrap();
        for x in [
            [0.9, 0.5, 0.45],
            [2.0, 2.0, 2.0],
            [1.5, -0.5, 0.5],
            [0.5, -0.3, 1.2],
            [-0.2, 0.4, -0.1],
            [0.2, 0.7, 0.5],
        ] {
            let (phi, n, tri, w) = m.closest(x);
            let idx = m.triangles()[tri];
            let mut q = [0.0; 3];
            for (k, &j) in idx.iter().enumerate() {
                q = crate::math::add(q, scale(v[j as usize], w[k]));
            }
            // x = q + phi n, and the weights sum to 1.
            let back = crate::math::add(q, scale(n, phi));
            assert!(norm(sub(back, x)) < 1e-12, "{x:?}: {back:?}");
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn an_open_sheet_is_one_sided_with_the_solid_behind_its_normals() {
        let m = sheet();
        assert!(!m.is_closed());
        assert!((m.signed_distance([0.2, 0.1, 0.3]).0 - 0.3).abs() < 1e-12);
        let (d, n) = m.signed_distance([0.2, 0.1, -0.3]);
        assert!((d + 0.3).abs() < 1e-12 && (n[2] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn a_segment_through_a_thin_sheet_is_caught_where_it_crosses() {
        let m = sheet();
        let (t, p, n) = m.first_crossing([0.1, 0.2, 0.5], [0.1, 0.2, -1.5]).unwrap();
        assert!((t - 0.25).abs() < 1e-12 && p[2].abs() < 1e-12 && (n[2] - 1.0).abs() < 1e-12);
        // Passing beside the sheet, and moving away from it, cross nothing.
        assert!(m.first_crossing([3.0, 0.0, 0.5], [3.0, 0.0, 0.4]).is_none());
        assert!(m.first_crossing([0.0, 0.0, 0.5], [0.0, 0.0, 0.9]).is_none());
    }

    #[test]
    fn bad_meshes_are_named_errors() {
        let v = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let msg = |r: Result<MeshCollider>| r.unwrap_err().to_string();
        assert!(msg(MeshCollider::new(&v, &[])).contains("no triangles"));
        assert!(msg(MeshCollider::new(&v, &[[0, 1, 3]])).contains("triangle 0 refers to vertex 3"));
        assert!(msg(MeshCollider::new(&v, &[[0, 1, 1]])).contains("repeats a vertex"));
        let line = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
        assert!(msg(MeshCollider::new(&line, &[[0, 1, 2]])).contains("no area"));
        let nan = vec![[0.0, 0.0, 0.0], [f64::NAN, 0.0, 0.0], [0.0, 1.0, 0.0]];
        assert!(msg(MeshCollider::new(&nan, &[[0, 1, 2]])).contains("vertex 1 is not finite"));
    }
}
