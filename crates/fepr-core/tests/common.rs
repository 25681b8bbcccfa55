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
/// The cells of an `n` x `n` x `n` block of unit cubes (for [`cubes_mesh`]).
pub fn block_cells(n: i64) -> Vec<[i64; 3]> {
    (0..n)
        .flat_map(|i| (0..n).flat_map(move |j| (0..n).map(move |k| [i, j, k])))
        .collect()
}

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

/// The procedural L stretched 1.3x about its centre of mass, spinning at 1 rad/s about z and drifting at
/// (0.5, 0.2, 0.1) m/s, run for `steps` steps of 1/30 s with `integrator`; returns the initial invariants and
/// the history.
pub fn spinning_ell_run(
    material: Material,
    integrator: Box<dyn fepr_core::integrators::Integrator>,
    project: bool,
    steps: usize,
) -> (
    fepr_core::invariants::Invariants,
    Vec<fepr_core::simulation::StepDiagnostics>,
) {
    let model = model(ell_mesh(), material, 5.0, [0.0; 3]);
    let mut state = State::at_rest(&model);
    let c = fepr_core::invariants::center_of_mass(&model.masses, model.total_mass, &state.x);
    scaled(&mut state, 1.3, c);
    for (x, v) in state.x.iter().zip(state.v.iter_mut()) {
        *v = [0.5 - (x[1] - c[1]), 0.2 + (x[0] - c[0]), 0.1];
    }
    let proj = project.then(|| Projector::new(ProjectionSettings::default()).unwrap());
    let mut sim = Simulation::new(model, state, integrator, 1.0 / 30.0, proj).unwrap();
    let d0 = sim.history()[0].invariants;
    for _ in 0..steps {
        sim.step().unwrap();
    }
    (d0, sim.history().to_vec())
}

/// Largest relative drifts of H, P and L over a history, asserting that every projection converged.
pub fn max_drifts(
    d0: &fepr_core::invariants::Invariants,
    hist: &[fepr_core::simulation::StepDiagnostics],
) -> (f64, f64, f64) {
    let (mut dh, mut dp, mut dl): (f64, f64, f64) = (0.0, 0.0, 0.0);
    for d in &hist[1..] {
        if let Some(p) = d.projection {
            assert!(p.converged, "step {}: {p:?}", d.step);
        }
        let i = &d.invariants;
        dh = dh.max(rel(i.total, d0.total));
        dp = dp.max(norm([0, 1, 2].map(|a| i.momentum[a] - d0.momentum[a])) / norm(d0.momentum));
        dl = dl.max(
            norm([0, 1, 2].map(|a| i.angular_momentum[a] - d0.angular_momentum[a]))
                / norm(d0.angular_momentum),
        );
    }
    (dh, dp, dl)
}

/// `f()` inside a fresh rayon pool of `threads` threads (the bit-identity tests run the same work in several).
pub fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}
