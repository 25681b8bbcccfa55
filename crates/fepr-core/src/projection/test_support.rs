//! Shared fixtures of the projection's unit tests.

use crate::material::{Material, NeoHookean};
use crate::math::{dot, Vec3};
use crate::mesh::{tests::cube, MassSpec, TetMesh};
use crate::model::ModelBuilder;
use crate::model::{Model, State};
use crate::projection::Targets;

/// The test cube with unequal vertex masses (1 + 0.1 i kg), Neo-Hookean with Young's modulus `youngs` (Pa)
/// and Poisson ratio 0.3, under `gravity` (m/s^2).
pub(super) fn cube_model(youngs: f64, gravity: Vec3) -> Model {
    let (v, t) = cube();
    let (mesh, _) = TetMesh::new(v, &t).unwrap();
    let masses: Vec<f64> = (0..mesh.num_vertices())
        .map(|i| 1.0 + 0.1 * i as f64)
        .collect();
    ModelBuilder::new(
        mesh,
        Material::NeoHookean(NeoHookean::new(youngs, 0.3).unwrap()),
    )
    .mass(MassSpec::PerVertex(masses))
    .gravity(gravity)
    .build()
    .unwrap()
}

/// `model`'s rest shape stretched 10% about a point and moving, with targets 10% below its energy and at
/// its momenta: far enough from the manifold for a few iterations.
pub(super) fn stretched_and_moving(model: &Model) -> (State, Targets) {
    let x: Vec<Vec3> = (model.mesh.vertices().iter())
        .map(|p| [0, 1, 2].map(|a| 0.5 + 1.1 * (p[a] - 0.5)))
        .collect();
    let v: Vec<Vec3> = (0..x.len())
        .map(|i| [0.1 * (i as f64).sin(), -0.05, 0.02 * (i as f64).cos()])
        .collect();
    let state = State { x, v, time: 0.0 };
    let inv = crate::invariants::measure(model, &state);
    let targets = Targets {
        energy: 0.9 * inv.total,
        momentum: inv.momentum,
        angular_momentum: inv.angular_momentum,
        center_of_mass: inv.center_of_mass,
        energy_scale: inv.total.abs(),
        uncertain_impulses: false,
    };
    (state, targets)
}

pub(super) fn norm3(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}
