//! Helpers shared by the benchmarks (each bench target includes this module).

use fepr_core::mesh::TetMesh;

/// TetGen `.node`/`.ele` reader for the benchmark meshes (0- or 1-based indices; `#` comments), renumbered in
/// the locality order the Python bindings run every simulation on (`renumber::VertexOrder`), so that these
/// benches time what `fepr bench` times. `None` when a file is missing or the mesh does not validate.
pub fn load_tetgen(stem: &std::path::Path) -> Option<TetMesh> {
    let read = |ext: &str| std::fs::read_to_string(format!("{}.{ext}", stem.display())).ok();
    let numbers = |text: &str| -> Vec<Vec<f64>> {
        text.lines()
            .map(|l| l.split('#').next().unwrap_or(""))
            .filter(|l| !l.trim().is_empty())
            .map(|l| {
                l.split_whitespace()
                    .filter_map(|w| w.parse().ok())
                    .collect()
            })
            .collect()
    };
    let nodes = numbers(&read("node")?);
    let eles = numbers(&read("ele")?);
    let base = nodes.get(1)?.first().copied()? as i64;
    let v: Vec<[f64; 3]> = nodes[1..].iter().map(|r| [r[1], r[2], r[3]]).collect();
    let t: Vec<[i64; 4]> = eles[1..]
        .iter()
        .map(|r| [1, 2, 3, 4].map(|c| r[c] as i64 - base))
        .collect();
    let (mesh, _) = TetMesh::new(v, &t).ok()?;
    Some(fepr_core::mesh::VertexOrder::locality(mesh.vertices()).mesh(&mesh))
}

/// The vertex adjacency of a mesh as a lower pattern (the Projective Dynamics m x m matrix).
#[allow(dead_code)] // not every bench target that includes this module uses it
pub fn vertex_pattern(model: &fepr_core::model::Model) -> fepr_core::math::LowerPattern {
    let m = model.num_vertices();
    let mut cols = vec![Vec::new(); m];
    for t in model.mesh.tets() {
        for &a in t {
            for &b in t {
                if a > b {
                    cols[b].push(a);
                }
            }
        }
    }
    fepr_core::math::LowerPattern::from_columns(m, cols)
}

/// The bench scenes' model (the bunny2 set-up): Neo-Hookean E = 1e3 Pa, nu = 0.3, 0.05 kg per node.
#[allow(dead_code)] // not every bench target that includes this module uses it
pub fn bench_model(mesh: TetMesh) -> fepr_core::model::Model {
    use fepr_core::material::{Material, NeoHookean};
    fepr_core::model::ModelBuilder::new(
        mesh,
        Material::NeoHookean(NeoHookean::new(1e3, 0.3).unwrap()),
    )
    .mass(fepr_core::mesh::MassSpec::NodeMass(0.05))
    .build()
    .unwrap()
}
