//! Obstacles (plane, sphere, box, capsule, triangle mesh), static or moving along a prescribed rigid motion
//! ([`ObstacleMotion`]), and vertex contact with them.
//!
//! Contact is resolved per vertex after the base step (fepr-spec section 2, "contact"): a vertex found inside
//! an obstacle is put back outside, its normal velocity (relative to the obstacle's surface) is reflected with the
//! restitution coefficient and its tangential velocity is reduced by Coulomb friction (`|dv_t| <= mu |dv_n|`).
//! What the contact did to the velocities is what it reports: the kinetic energy it removed, or a moving obstacle
//! added (the step's energy budget), and the linear and
//! angular impulse (the momentum targets). The position correction is not physical work (it repairs the
//! base step's overshoot); FEPR restores the energy it changes.

use crate::error::{invalid, Result};
use crate::math::{add, cross, dot, norm, scale, sub, Mat3, Vec3};
use crate::model::{Model, State};

use super::{MeshCollider, Moving, ObstacleMotion, Placement};

/// Geometry of an obstacle (metres). The solid is where the signed distance is negative.
#[derive(Clone, Debug, PartialEq)]
pub enum Shape {
    /// Half-space below the plane through `point` with unit outward `normal`.
    Plane { point: Vec3, normal: Vec3 },
    /// Ball of `radius` about `center`.
    Sphere { center: Vec3, radius: f64 },
    /// Box of `half_extents` about `center`; the rows of `axes` are its local x, y, z axes (a rotation).
    Box {
        center: Vec3,
        half_extents: Vec3,
        axes: Mat3,
    },
    /// Points within `radius` of the segment `a`-`b`.
    Capsule { a: Vec3, b: Vec3, radius: f64 },
    /// A static triangle mesh, the solid behind its outward normals (closed, or open and one-sided).
    Mesh(MeshCollider),
}

/// An obstacle with its contact coefficients: static, or moving along a prescribed rigid motion
/// ([`Obstacle::with_motion`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Obstacle {
    /// The shape where the obstacle is at `t = 0`.
    pub shape: Shape,
    /// Coefficient of restitution in [0, 1]: the normal velocity after contact (relative to the obstacle's
    /// surface) is `-restitution` times the one before.
    pub restitution: f64,
    /// Coulomb friction coefficient (>= 0).
    pub friction: f64,
    /// The motion and where it has the obstacle over the current step (None: static).
    moving: Option<Box<Moving>>,
}

fn finite3(v: Vec3, what: &'static str) -> Result<()> {
    if v.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        Err(invalid(what, format!("must be finite, got {v:?}")))
    }
}

fn positive(x: f64, what: &'static str) -> Result<()> {
    if x.is_finite() && x > 0.0 {
        Ok(())
    } else {
        Err(invalid(
            what,
            format!("must be a positive length in m, got {x}"),
        ))
    }
}

/// Check contact coefficients: restitution in [0, 1], Coulomb friction finite and >= 0.
pub fn check_contact_coefficients(restitution: f64, friction: f64) -> Result<()> {
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
    Ok(())
}

impl Obstacle {
    /// Validate the geometry and coefficients (normalises a plane's normal).
    pub fn new(shape: Shape, restitution: f64, friction: f64) -> Result<Self> {
        check_contact_coefficients(restitution, friction)?;
        let shape = match shape {
            Shape::Plane { point, normal } => {
                finite3(point, "plane point")?;
                finite3(normal, "plane normal")?;
                let n = norm(normal);
                if n < 1e-12 {
                    return Err(invalid("plane normal", "must not be the zero vector"));
                }
                Shape::Plane {
                    point,
                    normal: scale(normal, 1.0 / n),
                }
            }
            Shape::Sphere { center, radius } => {
                finite3(center, "sphere center")?;
                positive(radius, "sphere radius")?;
                Shape::Sphere { center, radius }
            }
            Shape::Box {
                center,
                half_extents,
                axes,
            } => {
                finite3(center, "box center")?;
                for h in half_extents {
                    positive(h, "box half_extents")?;
                }
                for i in 0..3 {
                    for j in 0..3 {
                        let d = dot(axes[i], axes[j]) - if i == j { 1.0 } else { 0.0 };
                        if d.abs() >= 1e-6 || d.is_nan() {
                            return Err(invalid(
                                "box rotation",
                                format!(
                                    "must be a rotation matrix (orthonormal rows), got {axes:?}"
                                ),
                            ));
                        }
                    }
                }
                if crate::math::det(&axes) < 0.0 {
                    return Err(invalid(
                        "box rotation",
                        "must be a rotation (determinant +1), not a reflection",
                    ));
                }
                Shape::Box {
                    center,
                    half_extents,
                    axes,
                }
            }
            Shape::Capsule { a, b, radius } => {
                finite3(a, "capsule a")?;
                finite3(b, "capsule b")?;
                positive(radius, "capsule radius")?;
                Shape::Capsule { a, b, radius }
            }
            // Validated when it was built.
            Shape::Mesh(mesh) => Shape::Mesh(mesh),
        };
        Ok(Self {
            shape,
            restitution,
            friction,
            moving: None,
        })
    }

    /// The obstacle moving along `motion` (validated): at time `t` its shape as given is placed by
    /// [`ObstacleMotion::pose`]. It stands at its `t = 0` placement until [`Obstacle::place`] moves it.
    pub fn with_motion(mut self, motion: ObstacleMotion) -> Result<Self> {
        motion.validate()?;
        self.moving = Some(Box::new(Moving::new(motion)));
        Ok(self)
    }

    /// The prescribed motion, or None for a static obstacle.
    pub fn motion(&self) -> Option<&ObstacleMotion> {
        self.moving.as_deref().map(|m| &m.motion)
    }

    /// Place a moving obstacle for a step from `t` over `h` seconds: its queries answer for where it is at the
    /// step's end, [`Obstacle::first_crossing`] follows it from the step's start, and
    /// [`Obstacle::velocity_at`] gives its surface's velocity over the step (`h = 0`: standing at `t`, velocity
    /// 0). Nothing for a static obstacle.
    pub fn place(&mut self, t: f64, h: f64) {
        if let Some(m) = self.moving.as_deref_mut() {
            m.place(t, h);
        }
    }

    /// The velocity over the current step of the obstacle's surface point at `x` (m; where it is at the step's
    /// end), m/s: 0 for a static obstacle.
    pub fn velocity_at(&self, x: Vec3) -> Vec3 {
        self.moving
            .as_deref()
            .map_or([0.0; 3], |m| m.velocity_at(x))
    }

    /// Where the obstacle's point at `x` at the end of the current step was at its start (m): `x` itself for a
    /// static obstacle.
    pub fn point_at_start(&self, x: Vec3) -> Vec3 {
        self.moving.as_deref().map_or(x, |m| m.at_start(x))
    }

    /// [`Obstacle::signed_distance`] against the obstacle where it was at the start of the current step.
    pub fn signed_distance_at_start(&self, x: Vec3) -> (f64, Vec3) {
        self.placed_distance(x, |m| &m.start)
    }

    /// [`Obstacle::shape_distance`] of `x` against the shape where `at` places it (static: as given).
    fn placed_distance(&self, x: Vec3, at: impl Fn(&Moving) -> &Placement) -> (f64, Vec3) {
        match self.moving.as_deref() {
            None => self.shape_distance(x),
            Some(m) => {
                let (d, n) = self.shape_distance(at(m).to_given(x));
                (d, at(m).turn(n))
            }
        }
    }

    /// Where the obstacle's point at `x` at the start of the current step is at its end (m), and a direction
    /// `n` there turned with it: `(x, n)` for a static obstacle.
    pub fn carried_over_step(&self, x: Vec3, n: Vec3) -> (Vec3, Vec3) {
        match self.moving.as_deref() {
            None => (x, n),
            Some(m) => (m.at_end(x), m.end.turn(m.start.unturn(n))),
        }
    }

    /// Where the segment `p0 -> p1` (m) from outside the obstacle first touches it: `(t, point on the surface,
    /// outward normal there)` with `t` in [0, 1]; `None` when `p0` is inside or the segment stays outside.
    /// Both for a segment that ends inside (the entry point, not the surface point nearest `p1`, which for a thin
    /// obstacle can be on its far side) and for one that passed through within one step.
    ///
    /// Written here, not taken from a collision library: the analytic shapes are given by their exact signed
    /// distances, which are convex along any segment (each shape is convex), so the minimum along the segment is
    /// found by a golden-section search and the first crossing before it by bisection, to 1e-12 of the segment,
    /// for every analytic shape alike. A mesh ray-casts its triangles ([`MeshCollider::ray_entry`]).
    ///
    /// A segment that ends outside on the side it started, or on a side at right angles to it (the outward
    /// normals at its ends are not opposed), is not a crossing even where its chord dips into the solid: a vertex
    /// sliding over a bump or around a sphere ends its step on the surface, and only the straight line between
    /// its positions cuts the curve; one in the corner where a box stands on the floor slides along both.
    /// Passing through a thin obstacle ends on its far side, where the normal points the other way.
    ///
    /// A moving obstacle is followed over the step: the segment is taken in its own frame, from where `p0` was
    /// against its start placement to where `p1` is against its end placement, and the point and normal
    /// returned are where they are at the step's end.
    pub fn first_crossing(&self, p0: Vec3, p1: Vec3) -> Option<(f64, Vec3, Vec3)> {
        match self.moving.as_deref() {
            None => self.shape_crossing(p0, p1),
            Some(m) => {
                let (t, point, n) =
                    self.shape_crossing(m.start.to_given(p0), m.end.to_given(p1))?;
                Some((t, m.end.apply(point), m.end.turn(n)))
            }
        }
    }

    /// [`Obstacle::first_crossing`] against the shape where it is given.
    fn shape_crossing(&self, p0: Vec3, p1: Vec3) -> Option<(f64, Vec3, Vec3)> {
        let len = norm(sub(p1, p0));
        // The signed distance changes by at most the distance moved: a segment shorter than the clearance at
        // its start cannot reach the obstacle (most vertices stop here, after one query bounded at `len`).
        // A start on the surface (where the last push-out left the vertex) counts as outside.
        let (d0, n0) = self.shape_distance_below(p0, len)?;
        if d0 < 0.0 {
            return None;
        }
        let (d1, n1) = self.shape_distance(p1);
        if d1 >= 0.0 && (dot(n0, n1) > -0.5 || len <= d1) {
            return None;
        }
        if let Shape::Mesh(mesh) = &self.shape {
            // A mesh is not convex: its own ray cast finds the crossing.
            return mesh.ray_entry(p0, p1, d1, n1);
        }
        let phi = |t: f64| self.shape_distance(add(p0, scale(sub(p1, p0), t))).0;
        if d1 <= 0.0 {
            return Some(self.entry(p0, p1, 1.0));
        }
        let [(c, fc), (d, fd)] = crate::math::golden_section(phi, 1e-12, |v| v <= 0.0);
        let inside = if fc <= 0.0 {
            c
        } else if fd <= 0.0 {
            d
        } else {
            return None;
        };
        Some(self.entry(p0, p1, inside))
    }

    /// The first crossing of `p0 -> p1` before `t_inside`, by bisection (`p0` outside, `p(t_inside)` inside).
    fn entry(&self, p0: Vec3, p1: Vec3, t_inside: f64) -> (f64, Vec3, Vec3) {
        let at = |t: f64| add(p0, scale(sub(p1, p0), t));
        let (mut lo, mut hi) = (0.0, t_inside);
        while hi - lo > 1e-12 {
            let mid = 0.5 * (lo + hi);
            if self.shape_distance(at(mid)).0 >= 0.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let (dist, n) = self.shape_distance(at(lo));
        (lo, sub(at(lo), scale(n, dist)), n)
    }

    /// The shape's name as scene files write it: "plane", "sphere", "box", "capsule" or "mesh".
    pub fn kind_name(&self) -> &'static str {
        match self.shape {
            Shape::Plane { .. } => "plane",
            Shape::Sphere { .. } => "sphere",
            Shape::Box { .. } => "box",
            Shape::Capsule { .. } => "capsule",
            Shape::Mesh(_) => "mesh",
        }
    }

    /// [`Obstacle::signed_distance`] where it is below `below` (m), else `None`; for a closed mesh without
    /// searching farther than needed ([`MeshCollider::signed_distance_below`]).
    pub fn signed_distance_below(&self, x: Vec3, below: f64) -> Option<(f64, Vec3)> {
        match self.moving.as_deref() {
            None => self.shape_distance_below(x, below),
            Some(m) => {
                let (d, n) = self.shape_distance_below(m.end.to_given(x), below)?;
                Some((d, m.end.turn(n)))
            }
        }
    }

    /// [`Obstacle::signed_distance_below`] against the shape where it is given.
    fn shape_distance_below(&self, x: Vec3, below: f64) -> Option<(f64, Vec3)> {
        if let Shape::Mesh(mesh) = &self.shape {
            return mesh.signed_distance_below(x, below);
        }
        let (phi, n) = self.shape_distance(x);
        (phi < below).then_some((phi, n))
    }

    /// Signed distance from `x` to the obstacle's surface (m, negative inside) and the unit outward normal
    /// of the nearest surface point. Exact for every shape, so `x - d n` lies on the surface. A moving
    /// obstacle answers for where it is at the end of the current step ([`Obstacle::place`]).
    pub fn signed_distance(&self, x: Vec3) -> (f64, Vec3) {
        self.placed_distance(x, |m| &m.end)
    }

    /// [`Obstacle::signed_distance`] against the shape where it is given.
    fn shape_distance(&self, x: Vec3) -> (f64, Vec3) {
        match &self.shape {
            Shape::Plane { point, normal } => (dot(sub(x, *point), *normal), *normal),
            Shape::Sphere { center, radius } => {
                let r = sub(x, *center);
                let d = norm(r);
                (d - radius, unit_or_up(r, d))
            }
            Shape::Capsule { a, b, radius } => {
                let ab = sub(*b, *a);
                let len2 = dot(ab, ab);
                let t = if len2 > 0.0 {
                    (dot(sub(x, *a), ab) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let r = sub(x, add(*a, scale(ab, t)));
                let d = norm(r);
                (d - radius, unit_or_up(r, d))
            }
            Shape::Box {
                center,
                half_extents,
                axes,
            } => {
                let rel = sub(x, *center);
                let p = [dot(axes[0], rel), dot(axes[1], rel), dot(axes[2], rel)];
                let q = [0, 1, 2].map(|k| p[k].abs() - half_extents[k]);
                let outside = [0, 1, 2].map(|k| q[k].max(0.0));
                let d_out = norm(outside);
                let local = if d_out > 0.0 {
                    [0, 1, 2].map(|k| outside[k].copysign(p[k]) / d_out)
                } else {
                    // Inside: the nearest face is the one with the largest q.
                    let k = (0..3)
                        .max_by(|&i, &j| q[i].total_cmp(&q[j]))
                        .expect("three axes");
                    let mut n = [0.0; 3];
                    n[k] = 1.0f64.copysign(p[k]);
                    n
                };
                let d = if d_out > 0.0 {
                    d_out
                } else {
                    q[0].max(q[1]).max(q[2])
                };
                let n = add(
                    add(scale(axes[0], local[0]), scale(axes[1], local[1])),
                    scale(axes[2], local[2]),
                );
                (d, n)
            }
            Shape::Mesh(mesh) => mesh.signed_distance(x),
        }
    }
}

/// `r / d`, or +z when `x` sits exactly on the centre (any direction is a nearest one).
fn unit_or_up(r: Vec3, d: f64) -> Vec3 {
    if d > 0.0 {
        scale(r, 1.0 / d)
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// What the contacts of one step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ContactReport {
    /// Vertex-obstacle contacts resolved.
    pub contacts: usize,
    /// Kinetic energy change of the velocity corrections, J (<= 0 against static obstacles; a moving obstacle's
    /// work on the body is included).
    pub work: f64,
    /// Linear impulse of the contacts, kg m/s.
    pub impulse: Vec3,
    /// Angular impulse about the centre of mass after the contacts, kg m^2/s.
    pub angular_impulse: Vec3,
    /// Deepest penetration resolved, m.
    pub max_depth: f64,
}

/// Resolve contacts of the free vertices of `state` (the base step's result for step size `h`) with the
/// obstacles. Each vertex found inside an obstacle is moved out along the normal onto the surface, its
/// normal velocity relative to the surface (a moving obstacle's surface velocity over the step,
/// [`Obstacle::velocity_at`]) is reflected with the restitution, and Coulomb friction reduces its relative
/// tangential velocity by at most `friction` times the normal velocity change (static friction stops it); the
/// tangential position follows the corrected velocity over the step. The work reported is the kinetic energy
/// the velocity changes made: against a static obstacle never positive, against a moving one it includes the
/// obstacle's work on the body (the impulse times the surface's velocity). The indices of the vertices touched
/// are appended to `touched`.
///
/// `x_start` (m, (m, 3); empty: not checked) are the positions at the start of the step: a vertex that ends
/// outside every obstacle but whose straight path from there passed through one (a thin plate crossed within one
/// step) is put back where the path first touched it ([`Obstacle::first_crossing`]) and its velocity answered
/// there, as for a vertex found inside; its depth is the distance it is put back.
#[allow(clippy::too_many_arguments)]
pub fn resolve_contacts(
    obstacles: &[Obstacle],
    model: &Model,
    state: &mut State,
    x_start: &[Vec3],
    h: f64,
    touched: &mut Vec<u32>,
    dv: &mut Vec<(u32, Vec3)>,
) -> ContactReport {
    let mut report = ContactReport::default();
    if obstacles.is_empty() {
        return report;
    }
    dv.clear();
    for i in 0..model.num_vertices() {
        if model.pinned[i] {
            continue;
        }
        let v_before = state.v[i];
        let mut hit = false;
        for ob in obstacles {
            // `Some` for a vertex inside (a distance query bounded at the surface: most vertices are far out).
            let inside = ob.signed_distance_below(state.x[i], 0.0);
            // Where the vertex goes back to: onto the surface along the normal, or, when its path crossed the
            // obstacle, to where the path first touched it.
            // The crossing test applies where the nearest surface would be wrong: a vertex that ends outside
            // but passed through, or one that ends inside nearer the far side than the side it came in by (its
            // nearest surface's normal points along its motion and away from the normal where it started).
            // Elsewhere (resting, sliding over a bump, ordinary impacts) the nearest surface point is the answer.
            // (The motion relative to the obstacle: from where `x0` would be carried by a moving one.)
            let far_side = inside.is_some_and(|(_, n)| {
                x_start.get(i).is_some_and(|&x0| {
                    let (carried, _) = ob.carried_over_step(x0, n);
                    dot(n, sub(state.x[i], carried)) > 0.0
                        && dot(n, ob.signed_distance_at_start(x0).1) < 0.0
                })
            });
            let crossing = if inside.is_none() || far_side {
                x_start
                    .get(i)
                    .and_then(|&x0| ob.first_crossing(x0, state.x[i]))
            } else {
                None
            };
            let (n, surface, depth) = if let Some((_, point, n_hit)) = crossing {
                (n_hit, point, norm(sub(state.x[i], point)))
            } else if let Some((phi, n)) = inside {
                (n, sub(state.x[i], scale(n, phi)), -phi)
            } else {
                continue;
            };
            hit = true;
            report.contacts += 1;
            report.max_depth = report.max_depth.max(depth);
            // Velocities relative to the obstacle's surface (a moving obstacle's), which the contact answers.
            let v_surface = ob.velocity_at(surface);
            let v = sub(state.v[i], v_surface);
            let vn = dot(v, n);
            let vt = sub(v, scale(n, vn));
            let dvn = if vn < 0.0 {
                -(1.0 + ob.restitution) * vn
            } else {
                0.0
            };
            let vt_len = norm(vt);
            let vt_new = if ob.friction > 0.0 && vt_len > 0.0 {
                let cut = ob.friction * dvn;
                if vt_len <= cut {
                    [0.0; 3]
                } else {
                    scale(vt, 1.0 - cut / vt_len)
                }
            } else {
                vt
            };
            state.v[i] = add(v_surface, add(scale(n, vn + dvn), vt_new));
            // Out of the solid, onto the surface. (Mirroring the penetration, a free particle's exact bounce,
            // moves a vertex by twice the depth; at the large steps of implicit integrators that is a large
            // fraction of an element and puts spikes of elastic energy into the body.)
            let mut x = add(surface, scale(sub(vt_new, vt), h));
            // The tangential move can re-enter a curved or corner surface: put it back on the surface.
            let (phi2, n2) = ob.signed_distance(x);
            if phi2 < 0.0 {
                x = sub(x, scale(n2, phi2));
            }
            state.x[i] = x;
        }
        if hit {
            touched.push(i as u32);
            let d = sub(state.v[i], v_before);
            let m = model.masses[i];
            report.work += 0.5 * m * (dot(state.v[i], state.v[i]) - dot(v_before, v_before));
            report.impulse = add(report.impulse, scale(d, m));
            dv.push((i as u32, d));
        }
    }
    if !dv.is_empty() {
        let c = crate::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
        for &(i, d) in dv.iter() {
            let i = i as usize;
            report.angular_impulse = add(
                report.angular_impulse,
                scale(cross(sub(state.x[i], c), d), model.masses[i]),
            );
        }
    }
    report
}

/// Append to `out` the free vertices not already in it (sorted) that lie within a thousandth of the body's
/// size of an obstacle: the projection freezes their positions too, so that its (small) position correction
/// cannot push a vertex that touches the surface into the obstacle. Vertices further out are left free: the
/// next step's contact resolution catches them, and freezing a whole approaching face would leave the
/// projection too few positions to work with.
pub fn near_obstacles(obstacles: &[Obstacle], model: &Model, state: &State, out: &mut Vec<u32>) {
    if obstacles.is_empty() {
        return;
    }
    let n_touched = out.len();
    let floor = 1e-3 * model.length_scale;
    for i in 0..model.num_vertices() {
        if model.pinned[i] || out[..n_touched].binary_search(&(i as u32)).is_ok() {
            continue;
        }
        if obstacles
            .iter()
            .any(|ob| ob.signed_distance_below(state.x[i], floor).is_some())
        {
            out.push(i as u32);
        }
    }
}

/// Deepest penetration of a free vertex into any obstacle, m (0 when none penetrates).
pub fn max_penetration(obstacles: &[Obstacle], model: &Model, x: &[Vec3]) -> f64 {
    let mut worst = 0.0f64;
    for (i, xi) in x.iter().enumerate() {
        if model.pinned[i] {
            continue;
        }
        for ob in obstacles {
            if let Some((phi, _)) = ob.signed_distance_below(*xi, 0.0) {
                worst = worst.max(-phi);
            }
        }
    }
    worst
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn a_path_through_a_thin_obstacle_is_caught_where_it_enters() {
        let plate = Obstacle::new(
            Shape::Box {
                center: [0.0, 0.0, 0.0],
                half_extents: [1.0, 1.0, 0.005],
                axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            },
            0.5,
            0.0,
        )
        .unwrap();
        // Straight through, 16.7 cm in one step (10 m/s at dt = 1/60): caught at the top face.
        let (t, p, n) = plate
            .first_crossing([0.1, 0.2, 0.1], [0.1, 0.2, -0.0667])
            .expect("crosses");
        assert!((p[2] - 0.005).abs() < 1e-9 && close(n[2], 1.0));
        assert!((t - 0.095 / 0.1667).abs() < 1e-6);
        // Ending in the lower half: the entry point on the top, not the nearer bottom face.
        let (_, p, n) = plate
            .first_crossing([0.0, 0.0, 0.02], [0.0, 0.0, -0.003])
            .unwrap();
        assert!((p[2] - 0.005).abs() < 1e-9 && close(n[2], 1.0));
        // Beside it, or stopping short: nothing.
        assert!(plate
            .first_crossing([1.5, 0.0, 0.1], [1.5, 0.0, -0.1])
            .is_none());
        assert!(plate
            .first_crossing([0.0, 0.0, 0.1], [0.0, 0.0, 0.01])
            .is_none());
        // A ball grazed along a chord: the entry point lies on the sphere.
        let ball = Obstacle::new(
            Shape::Sphere {
                center: [0.0, 0.0, 0.0],
                radius: 0.1,
            },
            1.0,
            0.0,
        )
        .unwrap();
        let (_, p, _) = ball
            .first_crossing([-1.0, 0.05, 0.0], [1.0, 0.05, 0.0])
            .unwrap();
        assert!((norm(p) - 0.1).abs() < 1e-9 && p[0] < 0.0);
        assert!(ball
            .first_crossing([-1.0, 0.2, 0.0], [1.0, 0.2, 0.0])
            .is_none());
    }

    #[test]
    fn signed_distances_are_exact_for_every_shape() {
        let plane = Obstacle::new(
            Shape::Plane {
                point: [0.0, 0.0, 1.0],
                normal: [0.0, 0.0, 2.0],
            },
            1.0,
            0.0,
        )
        .unwrap();
        let (d, n) = plane.signed_distance([3.0, 4.0, 0.5]);
        assert!(close(d, -0.5) && n == [0.0, 0.0, 1.0]);
        let sphere = Obstacle::new(
            Shape::Sphere {
                center: [1.0, 0.0, 0.0],
                radius: 0.5,
            },
            1.0,
            0.0,
        )
        .unwrap();
        let (d, n) = sphere.signed_distance([1.0, 0.2, 0.0]);
        assert!(close(d, -0.3) && close(n[1], 1.0));
        let capsule = Obstacle::new(
            Shape::Capsule {
                a: [0.0; 3],
                b: [2.0, 0.0, 0.0],
                radius: 0.1,
            },
            1.0,
            0.0,
        )
        .unwrap();
        assert!(close(capsule.signed_distance([1.0, 0.0, 0.3]).0, 0.2));
        assert!(close(capsule.signed_distance([3.0, 0.0, 0.0]).0, 0.9));
        // A box turned 90 degrees about z: local x is world y.
        let bx = Obstacle::new(
            Shape::Box {
                center: [0.0; 3],
                half_extents: [1.0, 2.0, 3.0],
                axes: [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            },
            1.0,
            0.0,
        )
        .unwrap();
        let (d, n) = bx.signed_distance([0.0, 0.9, 0.0]);
        assert!(close(d, -0.1) && close(n[1], 1.0));
        let (d, _) = bx.signed_distance([3.0, 2.0, 0.0]);
        assert!(close(d, (1.0f64 + 1.0).sqrt()));
        // On every shape, x - d n lands on the surface.
        for ob in [&plane, &sphere, &capsule, &bx] {
            for x in [[0.3, -0.2, 0.7], [1.1, 0.05, -0.02], [2.5, 1.5, 0.4]] {
                let (d, n) = ob.signed_distance(x);
                let on = sub(x, scale(n, d));
                assert!(ob.signed_distance(on).0.abs() < 1e-12, "{ob:?} at {x:?}");
            }
        }
    }

    #[test]
    fn bad_coefficients_and_geometry_are_named_errors() {
        let plane = || Shape::Plane {
            point: [0.0; 3],
            normal: [0.0, 0.0, 1.0],
        };
        let e = Obstacle::new(plane(), -0.5, 0.0).unwrap_err().to_string();
        assert!(e.contains("restitution"), "{e}");
        let e = Obstacle::new(plane(), 0.5, -1.0).unwrap_err().to_string();
        assert!(e.contains("friction"), "{e}");
        let e = Obstacle::new(
            Shape::Plane {
                point: [0.0; 3],
                normal: [0.0; 3],
            },
            0.5,
            0.0,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("normal"), "{e}");
        let e = Obstacle::new(
            Shape::Sphere {
                center: [0.0; 3],
                radius: f64::NAN,
            },
            0.5,
            0.0,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("radius"), "{e}");
        let e = Obstacle::new(
            Shape::Box {
                center: [0.0; 3],
                half_extents: [1.0; 3],
                axes: [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            },
            0.5,
            0.0,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("rotation"), "{e}");
    }
}
