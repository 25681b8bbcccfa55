//! Tetrahedral meshes: validation, rest shapes, and the cache-friendly renumbering of vertices and tets.

mod renumber;
mod tet_mesh;

pub use renumber::*;
pub use tet_mesh::*;
