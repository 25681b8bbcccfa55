//! `Model`: everything that does not change during a run (rest mesh, rest shape, masses, material, pins,
//! gravity, damping). Integrators and the projection read it and mutate only a `State`.

mod blocks;
mod corners;

pub use blocks::*;
pub(crate) use corners::*;

use crate::error::{invalid, Result};
use crate::material::Material;
use crate::math::Vec3;
use crate::mesh::{lumped_masses, MassSpec, RestShape, TetMesh};
use crate::model::CornerSums;

/// The fixed part of a simulation. Build it with [`ModelBuilder`].
///
/// The material, masses, pins, gravity and damping are public fields and may be changed between steps (keep
/// `total_mass` the sum of `masses`): the integrators, the projection and the world read them at every step, and
/// the data they build from the model once (sparsity patterns, factorisations, colourings, the stiffness metric)
/// is keyed on [`Model::key`], [`Model::structure_key`] or [`Model::elastic_key`] and rebuilt when its key
/// changes. What [`crate::simulation::Simulation`] validated when it was built or set (a nonzero `damping` only
/// with symplectic Euler, kinematic pins on pinned vertices) is not checked again. The mesh and the rest volumes
/// are derived data: build a new model for another mesh.
#[derive(Clone, Debug)]
pub struct Model {
    /// The rest mesh. Not to be replaced after [`ModelBuilder::build`] (the rest data and internal orders
    /// are derived from it): build a new model instead.
    pub mesh: TetMesh,
    /// Rest volume of every tet, m^3, derived from the mesh (not to be changed). (`D_m^-1` lives in the SIMD
    /// blocks only: [`Model::dm_inv`].)
    pub rest_volume: Vec<f64>,
    pub material: Material,
    /// Lumped vertex masses, kg.
    pub masses: Vec<f64>,
    /// Sum of all masses, kg.
    pub total_mass: f64,
    /// Gravitational acceleration, m/s^2 (enters the potential energy `-sum m_i g . x_i`).
    pub gravity: Vec3,
    /// `pinned[i]`: vertex i is held at its position (zero velocity).
    pub pinned: Vec<bool>,
    /// Velocity damping factor per step in [0, 1): `v <- (1 - damping) v` (the seed's 0.999 is 0.001).
    pub damping: f64,
    /// Half diagonal of the rest bounding box, metres (the length scale r of fepr-spec section 2).
    pub length_scale: f64,
    /// Vertex rank (`kernel_rank`) -> (4 * block position + corner) incidence (CSR offsets and slots,
    /// ascending per vertex; see `tet_at`), for the deterministic gathers of per-tet values in block order
    /// (PD's right-hand side, XPBD's colouring; the elastic gradient sums its corners per chunk instead:
    /// `corner_sums`). A slot's user tet is `tet_at[slot / 4]`; user vertex `v`'s slots start at
    /// `incidence_offsets[kernel_rank[v]]`.
    pub(crate) incidence_offsets: Vec<usize>,
    pub(crate) incidence_slots: Vec<u32>,
    /// User vertex -> rank in the internal vertex order (invisible to users): the Morton (Z-curve) order of
    /// the rest positions (ties by index). It orders the tets (`tet_at`), so that a chunk of consecutive
    /// tets is spatially compact, and the incidence lists.
    pub(crate) kernel_rank: Vec<u32>,
    /// The internal tet order of the blocks: position -> user tet (tets sorted stably by their smallest
    /// vertex rank).
    pub(crate) tet_at: Vec<u32>,
    /// User tet -> position in the blocks (the inverse of `tet_at`).
    pub(crate) tet_position: Vec<u32>,
    /// Rest data in SIMD-friendly blocks for the per-tet kernels (88 bytes per tet), in the internal tet
    /// order, with every corner's local index in its chunk (`corner_sums`); the only copy of `D_m^-1`.
    pub(crate) tet_blocks: TetBlocks,
    /// The chunks' local vertex numbering: how the per-tet passes' chunks gather their positions and sum
    /// their corners into vertices (the blocks hold the local indices).
    pub(crate) corner_sums: CornerSums,
    /// Hash of the rest mesh (vertex coordinates and tets), computed once by the builder (see [`ModelKey`]).
    mesh_hash: u64,
}

impl Model {
    /// Inverse rest edge matrix `D_m^-1` of tet `e`, 1/m.
    #[inline]
    pub fn dm_inv(&self, e: usize) -> crate::math::Mat3 {
        self.tet_blocks.dm_inv_at(self.tet_position[e] as usize)
    }

    pub fn num_vertices(&self) -> usize {
        self.mesh.num_vertices()
    }
    pub fn num_tets(&self) -> usize {
        self.mesh.num_tets()
    }
    /// Mean length of the tets' edges in the rest shape, m (each edge counted once per tet).
    pub fn mean_rest_edge(&self) -> f64 {
        let x = self.mesh.vertices();
        let mut sum = 0.0;
        for t in self.mesh.tets() {
            for (a, b) in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] {
                sum += crate::math::norm(crate::math::sub(x[t[a]], x[t[b]]));
            }
        }
        sum / (6.0 * self.num_tets().max(1) as f64)
    }
    /// Tets per chunk of the per-tet passes ([`crate::exec::tet_chunk_for`] the tet count): chunk `c`
    /// holds the block positions `c * tet_chunk() ..`.
    #[inline]
    pub(crate) fn tet_chunk(&self) -> usize {
        self.corner_sums.chunk()
    }
    pub fn num_pinned(&self) -> usize {
        self.pinned.iter().filter(|p| **p).count()
    }
    /// Speed of a pressure (longitudinal) wave in the material at rest, m/s: `sqrt(M / rho)` with the P-wave
    /// modulus `M = d^2 Psi / d eps^2` of a uniaxial strain `F = diag(1 + eps, 1, 1)` at rest (`lambda + 2 mu`
    /// for the Neo-Hookean family; measured from the material's energy, so every material gets it the same way)
    /// and the mean density `rho` (total mass over rest volume).
    pub fn pressure_wave_speed(&self) -> f64 {
        use crate::material::Hyperelastic;
        let psi = |e: f64| {
            self.material
                .energy_density(&[[1.0 + e, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        };
        let eps = 1e-4;
        let modulus = (psi(eps) - 2.0 * psi(0.0) + psi(-eps)) / (eps * eps);
        let volume: f64 = self.rest_volume.iter().sum();
        (modulus.max(0.0) * volume / self.total_mass).sqrt()
    }

    /// Mass of the vertices that are not pinned, kg.
    pub fn free_mass(&self) -> f64 {
        self.masses
            .iter()
            .zip(&self.pinned)
            .filter(|(_, p)| !**p)
            .map(|(m, _)| m)
            .sum()
    }
}

/// Builder for [`Model`] with documented defaults: node mass 1 kg, no gravity, no pins, no damping.
#[derive(Clone, Debug)]
pub struct ModelBuilder {
    mesh: TetMesh,
    material: Material,
    mass: MassSpec,
    gravity: Vec3,
    pinned: Vec<usize>,
    damping: f64,
}

impl ModelBuilder {
    pub fn new(mesh: TetMesh, material: Material) -> Self {
        Self {
            mesh,
            material,
            mass: MassSpec::NodeMass(1.0),
            gravity: [0.0; 3],
            pinned: Vec::new(),
            damping: 0.0,
        }
    }
    /// How masses are given (density in kg/m^3 or node masses in kg).
    pub fn mass(mut self, mass: MassSpec) -> Self {
        self.mass = mass;
        self
    }
    /// Gravitational acceleration in m/s^2.
    pub fn gravity(mut self, g: Vec3) -> Self {
        self.gravity = g;
        self
    }
    /// Indices of pinned vertices.
    pub fn pinned(mut self, pinned: Vec<usize>) -> Self {
        self.pinned = pinned;
        self
    }
    /// Velocity damping factor per step, in [0, 1).
    pub fn damping(mut self, damping: f64) -> Self {
        self.damping = damping;
        self
    }

    pub fn build(self) -> Result<Model> {
        let rest = self.mesh.rest_shape();
        let masses = lumped_masses(&self.mesh, &rest, &self.mass)?;
        if !self.gravity.iter().all(|g| g.is_finite()) {
            return Err(invalid(
                "gravity",
                format!("must be finite, got {:?}", self.gravity),
            ));
        }
        if !(self.damping.is_finite() && (0.0..1.0).contains(&self.damping)) {
            return Err(invalid(
                "damping",
                format!("must satisfy 0 <= damping < 1, got {}", self.damping),
            ));
        }
        let m = self.mesh.num_vertices();
        let mut pinned = vec![false; m];
        for &p in &self.pinned {
            if p >= m {
                return Err(invalid(
                    "pinned",
                    format!("vertex {p} is out of range: the mesh has {m} vertices"),
                ));
            }
            pinned[p] = true;
        }
        if pinned.iter().all(|p| *p) {
            return Err(invalid(
                "pinned",
                "every vertex is pinned: nothing can move",
            ));
        }
        let total_mass = masses.iter().sum();
        let length_scale = self.mesh.half_diagonal();
        let order = KernelOrder::new(&self.mesh);
        let (incidence_offsets, incidence_slots) = order.incidence(&self.mesh);
        let (corner_sums, local) = CornerSums::new(self.mesh.tets(), &order.tet_at, m);
        let tet_blocks = TetBlocks::new(&rest, &order.tet_at, &local);
        // D_m^-1 is kept in the blocks only (72 bytes per tet not held twice).
        let RestShape { volume, .. } = rest;
        let mesh_hash = hash_mesh(&self.mesh);
        Ok(Model {
            mesh: self.mesh,
            rest_volume: volume,
            material: self.material,
            masses,
            total_mass,
            gravity: self.gravity,
            pinned,
            damping: self.damping,
            length_scale,
            incidence_offsets,
            incidence_slots,
            kernel_rank: order.rank,
            tet_at: order.tet_at,
            tet_position: order.tet_position,
            tet_blocks,
            corner_sums,
            mesh_hash,
        })
    }
}

/// A fingerprint of the parts of a [`Model`] that integrators, the projection and the world build cached data
/// from (see [`Model::key`], [`Model::structure_key`], [`Model::elastic_key`]). Equal keys of one model at two
/// times mean that those parts did not change (up to a 64-bit hash collision; a change of a single value is
/// always detected). Keys are for comparison within one process only.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ModelKey(u64);

impl ModelKey {
    /// The key's bits (for a checkpoint that must be resumed on the same model).
    pub fn bits(self) -> u64 {
        self.0
    }
}

impl Model {
    /// Key of everything the elastic energy depends on besides the positions: the rest mesh and the material.
    /// O(1) (the mesh's hash is computed once, by the builder).
    pub fn elastic_key(&self) -> ModelKey {
        let mut h = KeyHasher::new(1);
        h.word(self.mesh_hash);
        let (tag, params) = match self.material {
            Material::NeoHookean(m) => (1, [m.mu, m.lambda, m.j0, 0.0]),
            Material::StableNeoHookean(m) => (2, [m.mu, m.lambda, m.alpha, m.rest_offset]),
            Material::Arap(m) => (3, [m.mu, 0.0, 0.0, 0.0]),
            Material::ConstraintNeoHookean(m) => (4, [m.mu, m.lambda, m.alpha, 0.0]),
        };
        h.word(tag);
        for p in params {
            h.word(p.to_bits());
        }
        ModelKey(h.finish())
    }

    /// Key of the sparsity structure over the free degrees of freedom: the rest mesh and the pin set.
    /// O(vertices / 64).
    pub fn structure_key(&self) -> ModelKey {
        let mut h = KeyHasher::new(2);
        h.word(self.mesh_hash);
        hash_pins(&mut h, &self.pinned);
        ModelKey(h.finish())
    }

    /// Key of the rest mesh, the material, the pin set and the masses: what the Projective Dynamics factor,
    /// the XPBD compliances and the projection's stiffness metric are built from. O(vertices).
    pub fn key(&self) -> ModelKey {
        let mut h = KeyHasher::new(3);
        h.word(self.elastic_key().0);
        hash_pins(&mut h, &self.pinned);
        h.word(self.masses.len() as u64);
        for m in &self.masses {
            h.word(m.to_bits());
        }
        ModelKey(h.finish())
    }
}

/// A 64-bit hash over a sequence of words. Each step `s <- rotl((s ^ w) * K, 29)` is a bijection of the state
/// for a given word, so two sequences of equal length that differ in one word always hash differently.
struct KeyHasher(u64);

impl KeyHasher {
    fn new(domain: u64) -> Self {
        let mut h = Self(0x243f_6a88_85a3_08d3);
        h.word(domain);
        h
    }
    #[inline]
    fn word(&mut self, w: u64) {
        self.0 = (self.0 ^ w)
            .wrapping_mul(0x9e37_79b9_7f4a_7c15)
            .rotate_left(29);
    }
    fn finish(self) -> u64 {
        let mut z = self.0;
        z ^= z >> 31;
        z = z.wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z ^ (z >> 29)
    }
}

/// The pin mask, 64 vertices per word.
fn hash_pins(h: &mut KeyHasher, pinned: &[bool]) {
    h.word(pinned.len() as u64);
    for chunk in pinned.chunks(64) {
        h.word(
            chunk
                .iter()
                .enumerate()
                .fold(0u64, |w, (i, &p)| w | (u64::from(p) << i)),
        );
    }
}

/// Hash of a mesh's vertex coordinates and tets.
fn hash_mesh(mesh: &TetMesh) -> u64 {
    let mut h = KeyHasher::new(0);
    h.word(mesh.num_vertices() as u64);
    for p in mesh.vertices() {
        for c in p {
            h.word(c.to_bits());
        }
    }
    h.word(mesh.num_tets() as u64);
    for t in mesh.tets() {
        for &v in t {
            h.word(v as u64);
        }
    }
    h.finish()
}

/// The internal orders of a mesh's vertices and tets (see [`Model::kernel_rank`]).
struct KernelOrder {
    /// User vertex -> rank.
    rank: Vec<u32>,
    /// Position -> user tet.
    tet_at: Vec<u32>,
    /// User tet -> position.
    tet_position: Vec<u32>,
}

impl KernelOrder {
    fn new(mesh: &TetMesh) -> Self {
        let verts = mesh.vertices();
        let tets = mesh.tets();
        let m = verts.len();
        u32::try_from(m).expect("vertex indices fit in u32");
        u32::try_from(4 * tets.len()).expect("incidence slots fit in u32");
        let rank = crate::mesh::VertexOrder::locality(verts).into_internal_indices();
        let mut tet_at: Vec<u32> = (0..tets.len() as u32).collect();
        tet_at.sort_by_key(|&e| tets[e as usize].iter().map(|&v| rank[v]).min().unwrap_or(0));
        let mut tet_position = vec![0u32; tets.len()];
        for (p, &e) in tet_at.iter().enumerate() {
            tet_position[e as usize] = p as u32;
        }
        Self {
            rank,
            tet_at,
            tet_position,
        }
    }

    /// Vertex rank -> (4 * position + corner) slots, ascending per vertex.
    fn incidence(&self, mesh: &TetMesh) -> (Vec<usize>, Vec<u32>) {
        let (m, tets) = (mesh.num_vertices(), mesh.tets());
        let mut offsets = vec![0usize; m + 1];
        for t in tets {
            for &v in t {
                offsets[self.rank[v] as usize + 1] += 1;
            }
        }
        for i in 0..m {
            offsets[i + 1] += offsets[i];
        }
        let mut fill = offsets.clone();
        let mut slots = vec![0u32; 4 * tets.len()];
        for (p, &e) in self.tet_at.iter().enumerate() {
            for (c, &v) in tets[e as usize].iter().enumerate() {
                let r = self.rank[v] as usize;
                slots[fill[r]] = (4 * p + c) as u32;
                fill[r] += 1;
            }
        }
        (offsets, slots)
    }
}

/// What changes during a run: positions (m), velocities (m/s) and time (s).
#[derive(Debug, PartialEq)]
pub struct State {
    pub x: Vec<Vec3>,
    pub v: Vec<Vec3>,
    pub time: f64,
}

impl Clone for State {
    fn clone(&self) -> Self {
        Self {
            x: self.x.clone(),
            v: self.v.clone(),
            time: self.time,
        }
    }

    /// Copies into the existing buffers (no allocation once they are large enough): a simulation keeps the
    /// previous step's state this way every step (the derived `clone_from` allocated two new arrays).
    fn clone_from(&mut self, source: &Self) {
        self.x.clone_from(&source.x);
        self.v.clone_from(&source.v);
        self.time = source.time;
    }
}

impl State {
    /// The rest state of a model: rest positions, zero velocity, time 0.
    pub fn at_rest(model: &Model) -> Self {
        let m = model.num_vertices();
        Self {
            x: model.mesh.vertices().to_vec(),
            v: vec![[0.0; 3]; m],
            time: 0.0,
        }
    }
    /// True when every coordinate and velocity is finite (and there are as many velocities as positions). In
    /// the vertex tasks of [`crate::exec::all_rows`]: a step checks its state after the base step.
    pub fn is_finite(&self) -> bool {
        let finite = |rows: &[Vec3]| rows.iter().all(|p| p.iter().all(|c| c.is_finite()));
        self.x.len() == self.v.len()
            && crate::exec::all_rows(self.x.len(), |r| {
                finite(&self.x[r.clone()]) && finite(&self.v[r])
            })
    }
}
