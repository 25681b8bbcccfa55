//! A prescribed rigid motion of an obstacle (a moving platform, a piston, a turning drum or paddle): where the
//! obstacle is at any time, and so where it is at the start and the end of a step.
//!
//! The obstacle's shape is given where it is at `t = 0`; at time `t` a point `p` of it is at
//! `R(omega t) Q(t) (p - pivot) + pivot + d(t)`, with `d` a translation path ([`PinMotion`]: keyframes or a
//! sinusoid, `d(0) = 0` for a sinusoid), `Q` keyframed orientations (slerp between them) and `omega` a constant
//! angular velocity, both about `pivot` (which travels with `d`).
//! A query at `x` is answered in the obstacle's own frame (`x` mapped back by the inverse pose), so every shape,
//! the triangle meshes included, moves without rebuilding anything (a mesh's BVH stays as built). The rotations
//! and poses are `parry3d-f64`'s (glam quaternions), the library the mesh queries already use.

use parry3d_f64::math::{Pose, Rotation, Vector};

use super::PinMotion;
use crate::error::{invalid, Result};
use crate::math::{scale, sub, Vec3};

fn to_parry(v: Vec3) -> Vector {
    Vector::new(v[0], v[1], v[2])
}

fn from_parry(v: Vector) -> Vec3 {
    [v.x, v.y, v.z]
}

/// A rigid motion prescribed over time (see the module comment).
#[derive(Clone, Debug, PartialEq)]
pub struct ObstacleMotion {
    /// The translation `d(t)`, m.
    pub translation: PinMotion,
    /// Constant angular velocity, rad/s (its direction is the axis, right-hand rule).
    pub angular_velocity: Vec3,
    /// The point the obstacle turns about at `t = 0`, m.
    pub pivot: Vec3,
    /// Keyframed orientations about the pivot: `(times (s), rotation vectors (rad))`, interpolated by slerp and
    /// held before the first and after the last; composed before the spin. Empty: none.
    pub orientations: (Vec<f64>, Vec<Vec3>),
}

impl ObstacleMotion {
    /// Checks the translation path and that the angular velocity and pivot are finite.
    pub fn validate(&self) -> Result<()> {
        self.translation.validate()?;
        if !self.angular_velocity.iter().all(|c| c.is_finite()) {
            return Err(invalid(
                "angular_velocity",
                format!("must be finite (rad/s), got {:?}", self.angular_velocity),
            ));
        }
        let (times, turns) = &self.orientations;
        if times.len() != turns.len() {
            return Err(invalid(
                "orientations",
                format!(
                    "need as many rotations as times, got {} times and {} rotations",
                    times.len(),
                    turns.len()
                ),
            ));
        }
        super::check_key_times(times, "orientations")?;
        if let Some(k) = turns.iter().position(|r| !r.iter().all(|c| c.is_finite())) {
            return Err(invalid(
                "orientations",
                format!("rotation {k} is not finite: {:?}", turns[k]),
            ));
        }
        if !self.pivot.iter().all(|c| c.is_finite()) {
            return Err(invalid(
                "pivot",
                format!("must be finite (m), got {:?}", self.pivot),
            ));
        }
        Ok(())
    }

    /// The pose at time `t` (s): the map from the obstacle as given to where it is.
    pub fn pose(&self, t: f64) -> Placement {
        let rotation =
            Rotation::from_scaled_axis(to_parry(self.angular_velocity) * t) * self.orientation(t);
        let c = to_parry(self.pivot);
        let d = to_parry(self.translation.displacement(t));
        Placement(Pose::from_parts(c + d - rotation * c, rotation))
    }
}

impl ObstacleMotion {
    /// The keyframed orientation at time `t` (identity without keyframes).
    fn orientation(&self, t: f64) -> Rotation {
        let (times, turns) = &self.orientations;
        let at = |k: usize| Rotation::from_scaled_axis(to_parry(turns[k]));
        match times.len() {
            0 => Rotation::IDENTITY,
            _ if t <= times[0] => at(0),
            n if t >= times[n - 1] => at(n - 1),
            _ => {
                let k = times.partition_point(|tk| *tk <= t) - 1;
                let s = (t - times[k]) / (times[k + 1] - times[k]);
                at(k).slerp(at(k + 1), s)
            }
        }
    }
}

/// A rigid placement of an obstacle: its shape as given mapped to where it is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement(Pose);

impl Placement {
    /// The placement that leaves the obstacle where it was given.
    pub fn identity() -> Self {
        Self(Pose::identity())
    }

    /// Where the point `p` of the obstacle as given is, m.
    pub fn apply(&self, p: Vec3) -> Vec3 {
        from_parry(self.0.transform_point(to_parry(p)))
    }

    /// The point of the obstacle as given that is at `x` (m).
    pub fn to_given(&self, x: Vec3) -> Vec3 {
        from_parry(self.0.inverse_transform_point(to_parry(x)))
    }

    /// A direction of the obstacle as given, turned with it.
    pub fn turn(&self, n: Vec3) -> Vec3 {
        from_parry(self.0.transform_vector(to_parry(n)))
    }

    /// A direction at the obstacle's placement, in the obstacle as given.
    pub fn unturn(&self, n: Vec3) -> Vec3 {
        from_parry(self.0.inverse_transform_vector(to_parry(n)))
    }
}

/// Where a moving obstacle is over the current step: its placements at the step's start and end, and the
/// step's length.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Moving {
    pub motion: ObstacleMotion,
    pub start: Placement,
    pub end: Placement,
    /// The step's length, s (0: no step under way; the obstacle stands at `end`).
    pub h: f64,
}

impl Moving {
    pub fn new(motion: ObstacleMotion) -> Self {
        let at = motion.pose(0.0);
        Self {
            motion,
            start: at,
            end: at,
            h: 0.0,
        }
    }

    /// Place the obstacle for a step from `t` over `h` seconds (`h = 0`: standing at `t`).
    pub fn place(&mut self, t: f64, h: f64) {
        self.start = self.motion.pose(t);
        self.end = if h > 0.0 {
            self.motion.pose(t + h)
        } else {
            self.start
        };
        self.h = h;
    }

    /// The velocity over the step of the obstacle's material point at `x` at the step's end (m/s): its
    /// displacement over the step divided by the step's length; zero when no step is under way.
    pub fn velocity_at(&self, x: Vec3) -> Vec3 {
        if self.h <= 0.0 {
            return [0.0; 3];
        }
        let from = self.start.apply(self.end.to_given(x));
        scale(sub(x, from), 1.0 / self.h)
    }

    /// Where the obstacle's material point at `x` at the step's end was at its start, m.
    pub fn at_start(&self, x: Vec3) -> Vec3 {
        self.start.apply(self.end.to_given(x))
    }

    /// Where the obstacle's material point at `x` at the step's start is at its end, m.
    pub fn at_end(&self, x: Vec3) -> Vec3 {
        self.end.apply(self.start.to_given(x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{add, norm};

    fn spin_and_slide() -> ObstacleMotion {
        ObstacleMotion {
            translation: PinMotion::Keyframes {
                times: vec![0.0, 2.0],
                offsets: vec![[0.0; 3], [1.0, 0.0, 0.5]],
            },
            angular_velocity: [0.0, 0.0, 0.7],
            pivot: [1.0, 2.0, 0.0],
            orientations: (Vec::new(), Vec::new()),
        }
    }

    #[test]
    fn keyframed_orientations_turn_about_the_pivot_and_are_held_outside() {
        let m = ObstacleMotion {
            translation: PinMotion::Keyframes {
                times: vec![0.0],
                offsets: vec![[0.0; 3]],
            },
            angular_velocity: [0.0; 3],
            pivot: [1.0, 0.0, 0.0],
            orientations: (
                vec![1.0, 3.0],
                vec![[0.0; 3], [0.0, 0.0, std::f64::consts::FRAC_PI_2]],
            ),
        };
        m.validate().unwrap();
        let p = [2.0, 0.0, 0.0];
        // Half way between the keyframes: an eighth of a turn about z, through the pivot.
        let q = m.pose(2.0).apply(p);
        let a = std::f64::consts::FRAC_PI_4;
        assert!(norm(sub(q, [1.0 + a.cos(), a.sin(), 0.0])) < 1e-12, "{q:?}");
        assert!(norm(sub(m.pose(0.0).apply(p), p)) < 1e-15);
        assert!(norm(sub(m.pose(5.0).apply(p), [1.0, 1.0, 0.0])) < 1e-12);
        let mut bad = m.clone();
        bad.orientations.0 = vec![1.0, 1.0];
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("orientations"));
    }

    #[test]
    fn the_pivot_travels_with_the_translation_and_points_turn_about_it() {
        let m = spin_and_slide();
        let t = 1.0;
        let pose = m.pose(t);
        let d = m.translation.displacement(t);
        // The pivot only translates.
        let c = pose.apply(m.pivot);
        assert!(norm(sub(c, add(m.pivot, d))) < 1e-14);
        // A point one metre along x from the pivot turns by 0.7 rad about z.
        let p = pose.apply(add(m.pivot, [1.0, 0.0, 0.0]));
        let expected = add(add(m.pivot, d), [0.7f64.cos(), 0.7f64.sin(), 0.0]);
        assert!(norm(sub(p, expected)) < 1e-14, "{p:?} {expected:?}");
        // The inverse maps back.
        assert!(norm(sub(pose.to_given(p), add(m.pivot, [1.0, 0.0, 0.0]))) < 1e-14);
        let n = pose.turn([1.0, 0.0, 0.0]);
        assert!(norm(sub(pose.unturn(n), [1.0, 0.0, 0.0])) < 1e-15);
    }

    #[test]
    fn a_material_points_step_velocity_is_its_displacement_over_the_step() {
        let mut moving = Moving::new(spin_and_slide());
        assert_eq!(moving.velocity_at([3.0, 1.0, 0.0]), [0.0; 3]);
        let (t, h) = (0.5, 1e-3);
        moving.place(t, h);
        let p = [2.0, 2.0, 0.3];
        let x_end = moving.motion.pose(t + h).apply(p);
        let v = moving.velocity_at(x_end);
        // Translation 0.5 m/s along x, 0.25 m/s along z; the point 1 m from the pivot along x turns at 0.7 m/s
        // along y (at the step's middle, to first order in h).
        let expected = [
            0.5 - 0.7 * (0.7 * (t + 0.5 * h)).sin(),
            0.7 * (0.7 * (t + 0.5 * h)).cos(),
            0.25,
        ];
        assert!(norm(sub(v, expected)) < 1e-6, "{v:?} {expected:?}");
        assert!(norm(sub(moving.at_start(x_end), moving.motion.pose(t).apply(p))) < 1e-14);
        assert!(norm(sub(add(moving.at_start(x_end), scale(v, h)), x_end)) < 1e-14);
    }

    #[test]
    fn a_non_finite_spin_or_pivot_is_named() {
        let mut m = spin_and_slide();
        m.angular_velocity[1] = f64::NAN;
        assert!(m
            .validate()
            .unwrap_err()
            .to_string()
            .contains("angular_velocity"));
        let mut m = spin_and_slide();
        m.pivot[0] = f64::INFINITY;
        assert!(m.validate().unwrap_err().to_string().contains("pivot"));
    }
}
