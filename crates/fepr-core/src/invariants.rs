//! The quantities FEPR conserves (fepr-spec section 1), measured sequentially: kinetic, elastic, gravitational
//! and total energy (J), centre of mass (m), linear momentum (kg m/s) and angular momentum about the centre of
//! mass (kg m^2/s).
//!
//! Who uses them: the simulation ([`measure`] for the initial row, the running references, the energy scale and
//! the diagnostics of steps without projection; [`center_of_mass`] for the targets), symplectic Euler's damping
//! report, the contact response, and the projection for the base step's `P*` and `L*` (the slack columns).
//!
//! The projection does **not** evaluate its constraints with these functions: its per-vertex pass
//! (`projection::vertex_moments`, in parallel over fixed chunks of vertices, combined in chunk order) sums the
//! kinetic and gravitational energy, P, L about the *target* centre of mass and C itself, by the same formulas,
//! together with the moments of its small system; the [`Invariants`] it returns (L converted to the actual
//! centre of mass) are those sums, and they become the diagnostics row of a projected step. They agree with
//! [`measure`] to round-off, not bit for bit. Both take the elastic energy from [`crate::elasticity`].

use crate::elasticity::{elastic_energy, ElasticSummary};
use crate::math::{add, cross, dot, scale, sub, Vec3};
use crate::model::{Model, State};

/// Everything measured about a state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Invariants {
    pub kinetic: f64,
    pub elastic: f64,
    pub gravitational: f64,
    /// `kinetic + elastic + gravitational`, J.
    pub total: f64,
    /// Linear momentum, kg m/s.
    pub momentum: Vec3,
    /// Angular momentum about the centre of mass, kg m^2/s.
    pub angular_momentum: Vec3,
    /// Centre of mass, m.
    pub center_of_mass: Vec3,
    /// Smallest `J = det F` over all tets.
    pub min_j: f64,
    /// Number of tets with `J <= 0`.
    pub inverted: usize,
}

/// Kinetic energy `1/2 sum m_i |v_i|^2`, J.
pub fn kinetic_energy(masses: &[f64], v: &[Vec3]) -> f64 {
    0.5 * masses
        .iter()
        .zip(v)
        .map(|(m, vi)| m * dot(*vi, *vi))
        .sum::<f64>()
}

/// Gravitational potential energy `-sum m_i g . x_i`, J.
pub fn gravitational_energy(masses: &[f64], gravity: Vec3, x: &[Vec3]) -> f64 {
    -masses
        .iter()
        .zip(x)
        .map(|(m, xi)| m * dot(gravity, *xi))
        .sum::<f64>()
}

/// Centre of mass, m.
pub fn center_of_mass(masses: &[f64], total_mass: f64, x: &[Vec3]) -> Vec3 {
    let s = masses
        .iter()
        .zip(x)
        .fold([0.0; 3], |acc, (m, xi)| add(acc, scale(*xi, *m)));
    scale(s, 1.0 / total_mass)
}

/// Linear momentum `sum m_i v_i`, kg m/s.
pub fn linear_momentum(masses: &[f64], v: &[Vec3]) -> Vec3 {
    masses
        .iter()
        .zip(v)
        .fold([0.0; 3], |acc, (m, vi)| add(acc, scale(*vi, *m)))
}

/// Angular momentum about the point `c`: `sum (x_i - c) x m_i v_i`, kg m^2/s.
pub fn angular_momentum(masses: &[f64], x: &[Vec3], v: &[Vec3], c: Vec3) -> Vec3 {
    masses
        .iter()
        .zip(x.iter().zip(v))
        .fold([0.0; 3], |acc, (m, (xi, vi))| {
            add(acc, scale(cross(sub(*xi, c), *vi), *m))
        })
}

/// Measure a state, evaluating the elastic energy.
pub fn measure(model: &Model, state: &State) -> Invariants {
    let el = elastic_energy(model, &state.x);
    measure_with_elastic(model, state, el)
}

/// Measure a state whose elastic energy summary is already known.
pub fn measure_with_elastic(model: &Model, state: &State, el: ElasticSummary) -> Invariants {
    let kinetic = kinetic_energy(&model.masses, &state.v);
    let gravitational = gravitational_energy(&model.masses, model.gravity, &state.x);
    let com = center_of_mass(&model.masses, model.total_mass, &state.x);
    Invariants {
        kinetic,
        elastic: el.energy,
        gravitational,
        total: kinetic + el.energy + gravitational,
        momentum: linear_momentum(&model.masses, &state.v),
        angular_momentum: angular_momentum(&model.masses, &state.x, &state.v, com),
        center_of_mass: com,
        min_j: el.min_j,
        inverted: el.inverted,
    }
}

/// The rigid motion that carries a state's linear and angular momentum: total mass, centre of mass, momentum,
/// angular momentum about the centre of mass, and the inverse inertia about it (`None` for a degenerate, e.g.
/// collinear, body).
#[derive(Clone, Copy, Debug)]
pub struct RigidMotion {
    pub mass: f64,
    pub center: Vec3,
    pub momentum: Vec3,
    pub angular_momentum: Vec3,
    pub inertia_inv: Option<crate::math::Mat3>,
}

/// [`RigidMotion`] of the vertices `x`, `v` with masses `masses` (sequential).
pub fn rigid_motion(masses: &[f64], x: &[Vec3], v: &[Vec3]) -> RigidMotion {
    let mass: f64 = masses.iter().sum();
    let center = center_of_mass(masses, mass, x);
    let momentum = linear_momentum(masses, v);
    let angular_momentum = angular_momentum(masses, x, v, center);
    let mut inertia = [[0.0; 3]; 3];
    for (m, xi) in masses.iter().zip(x) {
        let r = sub(*xi, center);
        let rr = dot(r, r);
        for a in 0..3 {
            for b in 0..3 {
                inertia[a][b] += m * (if a == b { rr } else { 0.0 } - r[a] * r[b]);
            }
        }
    }
    RigidMotion {
        mass,
        center,
        momentum,
        angular_momentum,
        inertia_inv: crate::math::inverse(&inertia),
    }
}
