//! Shared builders for the integration tests.
#![allow(dead_code)]

use fepr_core::integrators::SymplecticEuler;
use fepr_core::material::{Material, NeoHookean};
use fepr_core::mesh::{MassSpec, TetMesh};
use fepr_core::model::{Model, ModelBuilder, State};
use fepr_core::projection::{ProjectionSettings, Projector};
use fepr_core::simulation::Simulation;

/// A union of unit cubes (given by their integer corners), each cut into 6 tets around its main diagonal,
/// with shared vertices: conforming.
pub fn cubes_mesh(cells: &[[i64; 3]], size: f64) -> TetMesh {
    let cube_tets = [
        [0, 1, 3, 7],
        [0, 3, 2, 7],
        [0, 2, 6, 7],
        [0, 6, 4, 7],
        [0, 4, 5, 7],
        [0, 5, 1, 7],
    ];
    let mut index = std::collections::BTreeMap::new();
    let mut verts = Vec::new();
    let mut tets = Vec::new();
    for c in cells {
        let mut corner = [0i64; 8];
        for (k, slot) in corner.iter_mut().enumerate() {
            let p = [
                c[0] + (k as i64 & 1),
                c[1] + ((k as i64 >> 1) & 1),
                c[2] + ((k as i64 >> 2) & 1),
            ];
            let n = index.len() as i64;
            *slot = *index.entry(p).or_insert_with(|| {
                verts.push([p[0] as f64 * size, p[1] as f64 * size, p[2] as f64 * size]);
                n
            });
        }
        for t in cube_tets {
            tets.push([corner[t[0]], corner[t[1]], corner[t[2]], corner[t[3]]]);
        }
    }
    TetMesh::new(verts, &tets).unwrap().0
}

/// The seed's "L": 2x2 footprint minus one corner, height 1, plus a 1x1x2 column on top.
pub fn ell_mesh() -> TetMesh {
    cubes_mesh(
        &[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 2]],
        1.0,
    )
}

pub fn neo_hookean(e: f64, nu: f64) -> Material {
    Material::NeoHookean(NeoHookean::new(e, nu).unwrap())
}

pub fn model(mesh: TetMesh, material: Material, node_mass: f64, gravity: [f64; 3]) -> Model {
    ModelBuilder::new(mesh, material)
        .mass(MassSpec::NodeMass(node_mass))
        .gravity(gravity)
        .build()
        .unwrap()
}

/// Scale positions about a point.
pub fn scaled(state: &mut State, factor: f64, about: [f64; 3]) {
    for p in state.x.iter_mut() {
        for a in 0..3 {
            p[a] = about[a] + factor * (p[a] - about[a]);
        }
    }
}

pub fn simulation(model: Model, state: State, dt: f64, project: bool) -> Simulation {
    let proj = project.then(|| Projector::new(ProjectionSettings::default()).unwrap());
    Simulation::new(model, state, Box::new(SymplecticEuler::new()), dt, proj).unwrap()
}

pub fn rel(a: f64, b: f64) -> f64 {
    ((a - b) / b).abs()
}

pub fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}
