//! A locality order of a mesh's vertices, and the renumbering between the user's vertex numbering and it.
//!
//! The per-tet passes cut the tets into spatially compact chunks, and the per-vertex passes cut the vertex
//! arrays into contiguous tasks; with two threads, each thread runs about half of both. When the vertex
//! numbering follows space (a Z-curve), a thread's vertex tasks hold mostly the vertices of its own tet chunks,
//! so the positions it writes and the gradients it sums stay in its own core's cache. A mesher's numbering
//! (TetGen's Steiner points are appended at the end) scatters them: half of every chunk's rows then come from
//! the other core. Measured on two threads (symplectic Euler + FEPR, alternated runs): the same meshes
//! renumbered by [`VertexOrder::locality`] took 15-40% less time per projected step on the bunny, bunny2 and
//! armadillo; on one thread the two orders run at the same speed.
//!
//! The Python bindings renumber every simulation's mesh this way and translate every per-vertex array at the
//! API boundary, so users see their own numbering. Rust users may do the same with [`VertexOrder::mesh`],
//! [`VertexOrder::to_internal`] and [`VertexOrder::to_user`].

use crate::math::Vec3;
use crate::mesh::TetMesh;

/// A permutation of a mesh's vertices: internal vertex `i` is user vertex `user_of(i)`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VertexOrder {
    /// Internal index -> user index.
    user_of: Vec<u32>,
    /// User index -> internal index.
    internal_of: Vec<u32>,
}

impl VertexOrder {
    /// The Z-curve (Morton) order of `vertices` (ties by index): shape (m, 3), metres.
    pub fn locality(vertices: &[Vec3]) -> Self {
        let m = vertices.len();
        u32::try_from(m).expect("vertex indices fit in u32");
        let code = morton_codes(vertices);
        let mut user_of: Vec<u32> = (0..m as u32).collect();
        // Stable: ties keep index order, so an already ordered mesh gets the identity.
        user_of.sort_by_key(|&v| code[v as usize]);
        let mut internal_of = vec![0u32; m];
        for (i, &u) in user_of.iter().enumerate() {
            internal_of[u as usize] = i as u32;
        }
        Self {
            user_of,
            internal_of,
        }
    }

    /// Number of vertices.
    pub fn len(&self) -> usize {
        self.user_of.len()
    }

    /// True for an order of no vertices.
    pub fn is_empty(&self) -> bool {
        self.user_of.is_empty()
    }

    /// True when the internal numbering is the user's.
    pub fn is_identity(&self) -> bool {
        self.user_of
            .iter()
            .enumerate()
            .all(|(i, &u)| u as usize == i)
    }

    /// The internal index of user vertex `user` (`user < len()`).
    pub fn internal(&self, user: usize) -> usize {
        self.internal_of[user] as usize
    }

    /// The internal index of user vertex `user`, or `user` itself when it is out of range (so that a later
    /// range check names the index the user gave).
    pub fn internal_or_same(&self, user: usize) -> usize {
        if user < self.len() {
            self.internal(user)
        } else {
            user
        }
    }

    /// User index -> internal index, for every vertex (the order's own table, handed over).
    pub(crate) fn into_internal_indices(self) -> Vec<u32> {
        self.internal_of
    }

    /// The user index of internal vertex `internal` (`internal < len()`).
    pub fn user(&self, internal: usize) -> usize {
        self.user_of[internal] as usize
    }

    /// Per-vertex rows in the user's numbering, shape (m, ...), renumbered to the internal one.
    pub fn to_internal<T: Copy>(&self, user_rows: &[T]) -> Vec<T> {
        assert_eq!(user_rows.len(), self.len(), "one row per vertex");
        self.user_of
            .iter()
            .map(|&u| user_rows[u as usize])
            .collect()
    }

    /// Per-vertex rows in the internal numbering, shape (m, ...), renumbered to the user's.
    pub fn to_user<T: Copy>(&self, internal_rows: &[T]) -> Vec<T> {
        assert_eq!(internal_rows.len(), self.len(), "one row per vertex");
        self.internal_of
            .iter()
            .map(|&i| internal_rows[i as usize])
            .collect()
    }

    /// `mesh` in the internal numbering: its vertices renumbered, its tets in the same order with their
    /// corners renamed (tet `e` is still the user's tet `e`, with the same orientation).
    pub fn mesh(&self, mesh: &TetMesh) -> TetMesh {
        assert_eq!(mesh.num_vertices(), self.len(), "one entry per vertex");
        let tets = mesh
            .tets()
            .iter()
            .map(|t| t.map(|v| self.internal_of[v] as usize))
            .collect();
        // Renaming vertices keeps every tet's shape and orientation: a valid mesh stays valid (no second check,
        // and no second copy of the tets on the way).
        TetMesh::from_valid_parts(self.to_internal(mesh.vertices()), tets)
    }
}

/// Morton (Z-curve) codes of points: 21 bits per axis over the bounding box (the same scale on every axis).
pub(crate) fn morton_codes(points: &[Vec3]) -> Vec<u64> {
    const BITS: u32 = 21;
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0f64, f64::max);
    let top = ((1u64 << BITS) - 1) as f64;
    let s = if extent > 0.0 && extent.is_finite() {
        top / extent
    } else {
        0.0
    };
    // Spread the low 21 bits of `v` to every third bit.
    let spread = |v: u64| {
        let mut v = v & 0x1f_ffff;
        v = (v | (v << 32)) & 0x001f_0000_0000_ffff;
        v = (v | (v << 16)) & 0x001f_0000_ff00_00ff;
        v = (v | (v << 8)) & 0x100f_00f0_0f00_f00f;
        v = (v | (v << 4)) & 0x10c3_0c30_c30c_30c3;
        v = (v | (v << 2)) & 0x1249_2492_4924_9249;
        v
    };
    points
        .iter()
        .map(|p| {
            let mut code = 0u64;
            for a in 0..3 {
                let q = ((p[a] - lo[a]) * s).clamp(0.0, top) as u64;
                code |= spread(q) << a;
            }
            code
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elasticity::{elastic_energy_gradient, ElasticWorkspace};
    use crate::material::{Material, NeoHookean};
    use crate::mesh::MassSpec;
    use crate::model::ModelBuilder;

    /// An `n^3` block of cubes (6 tets each) with its vertices numbered in a scrambled order.
    fn scrambled_block(n: usize) -> TetMesh {
        let model = crate::elasticity::tests::grid_model(
            n,
            Material::NeoHookean(NeoHookean::new(1e4, 0.3).unwrap()),
        );
        let m = model.num_vertices();
        // A fixed scramble: multiplication by a unit modulo m (7919 is prime, m is not a multiple of it).
        let new_of = |v: usize| (v * 7919 + 13) % m;
        let mut vertices = vec![[0.0; 3]; m];
        for (v, p) in model.mesh.vertices().iter().enumerate() {
            vertices[new_of(v)] = *p;
        }
        let tets: Vec<[i64; 4]> = model
            .mesh
            .tets()
            .iter()
            .map(|t| t.map(|v| new_of(v) as i64))
            .collect();
        TetMesh::new(vertices, &tets).unwrap().0
    }

    #[test]
    fn renumbering_round_trips_and_an_ordered_mesh_keeps_its_numbering() {
        let mesh = scrambled_block(4);
        let order = VertexOrder::locality(mesh.vertices());
        assert!(!order.is_identity());
        let rows: Vec<usize> = (0..mesh.num_vertices()).collect();
        assert_eq!(order.to_user(&order.to_internal(&rows)), rows);
        for u in 0..order.len() {
            assert_eq!(order.user(order.internal(u)), u);
            assert_eq!(order.internal_or_same(u), order.internal(u));
        }
        assert_eq!(order.internal_or_same(order.len() + 3), order.len() + 3);
        let inner = order.mesh(&mesh);
        for (e, (t, ti)) in mesh.tets().iter().zip(inner.tets()).enumerate() {
            assert_eq!(t.map(|v| order.internal(v)), *ti, "tet {e}");
        }
        assert!(VertexOrder::locality(inner.vertices()).is_identity());
    }

    #[test]
    fn renumbered_mesh_gives_the_same_energy_and_gradient_rows() {
        let mesh = scrambled_block(5);
        let order = VertexOrder::locality(mesh.vertices());
        let material = Material::NeoHookean(NeoHookean::new(1e4, 0.3).unwrap());
        let build = |mesh: TetMesh| {
            ModelBuilder::new(mesh, material)
                .mass(MassSpec::Density(1e3))
                .build()
                .unwrap()
        };
        let (user, inner) = (build(mesh.clone()), build(order.mesh(&mesh)));
        let x_user = crate::elasticity::tests::deformed(&user, 3);
        let x_inner = order.to_internal(&x_user);
        let (mut g_user, mut g_inner) =
            (vec![[0.0; 3]; x_user.len()], vec![[0.0; 3]; x_user.len()]);
        let mut ws = ElasticWorkspace::default();
        let e_user = elastic_energy_gradient(&user, &x_user, &mut ws, &mut g_user).energy;
        let e_inner = elastic_energy_gradient(&inner, &x_inner, &mut ws, &mut g_inner).energy;
        // Summed in other orders: equal to rounding.
        assert!((e_user - e_inner).abs() <= 1e-12 * e_user.abs());
        let scale = g_user.iter().flatten().fold(0.0f64, |a, g| a.max(g.abs()));
        for (a, b) in g_user.iter().zip(order.to_user(&g_inner)) {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() <= 1e-12 * scale);
            }
        }
        assert_eq!(order.to_user(&inner.masses), user.masses);
    }
}
