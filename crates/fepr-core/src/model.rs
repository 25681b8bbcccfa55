//! `Model`: everything that does not change during a run (rest mesh, rest shape, masses, material, pins,
//! gravity, damping). Integrators and the projection read it and mutate only a `State`.

use crate::elasticity::TetBlocks;
use crate::error::{invalid, Result};
use crate::linalg::Vec3;
use crate::material::Material;
use crate::mesh::{lumped_masses, MassSpec, RestShape, TetMesh};

/// The fixed part of a simulation. Build it with [`ModelBuilder`].
#[derive(Clone, Debug)]
pub struct Model {
    pub mesh: TetMesh,
    /// Rest volume of every tet, m^3. (`D_m^-1` lives in the SIMD blocks only: [`Model::dm_inv`].)
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
    /// Vertex -> (tet * 4 + corner) incidence (CSR offsets and slots), for deterministic gathers.
    pub(crate) incidence_offsets: Vec<usize>,
    pub(crate) incidence_slots: Vec<u32>,
    /// Rest data in SIMD-friendly blocks for the Neo-Hookean kernel (96 bytes per tet); the only copy of
    /// `D_m^-1`.
    pub(crate) tet_blocks: TetBlocks,
}

impl Model {
    /// Inverse rest edge matrix `D_m^-1` of tet `e`, 1/m.
    #[inline]
    pub fn dm_inv(&self, e: usize) -> crate::linalg::Mat3 {
        self.tet_blocks.dm_inv(e)
    }

    pub fn num_vertices(&self) -> usize {
        self.mesh.num_vertices()
    }
    pub fn num_tets(&self) -> usize {
        self.mesh.num_tets()
    }
    pub fn num_pinned(&self) -> usize {
        self.pinned.iter().filter(|p| **p).count()
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
        let (incidence_offsets, incidence_slots) = self.mesh.vertex_incidence();
        let tet_blocks = TetBlocks::new(self.mesh.tets(), &rest);
        // D_m^-1 is kept in the blocks only (72 bytes per tet not held twice).
        let RestShape { volume, .. } = rest;
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
            tet_blocks,
        })
    }
}

/// What changes during a run: positions (m), velocities (m/s) and time (s).
#[derive(Clone, Debug, PartialEq)]
pub struct State {
    pub x: Vec<Vec3>,
    pub v: Vec<Vec3>,
    pub time: f64,
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
    /// True when every coordinate and velocity is finite.
    pub fn is_finite(&self) -> bool {
        self.x
            .iter()
            .chain(&self.v)
            .all(|p| p.iter().all(|c| c.is_finite()))
    }
}
