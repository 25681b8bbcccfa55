//! # fepr-core
//!
//! The numerical core of fepr: tetrahedral finite elements with hyperelastic materials, base time
//! integrators, and FEPR (Fast Energy Projection, Dinev et al. 2018), which projects each step back onto
//! the manifold of constant energy, linear and angular momentum. No Python here; SI units throughout.
//!
//! ```
//! use fepr_core::{material::{Material, NeoHookean}, mesh::{MassSpec, TetMesh}, model::{ModelBuilder, State},
//!     integrators::SymplecticEuler, projection::{Projector, ProjectionSettings}, simulation::Simulation};
//! // One tet, stretched by 10% and released.
//! let (mesh, _) = TetMesh::new(vec![[0.,0.,0.],[1.,0.,0.],[0.,1.,0.],[0.,0.,1.]], &[[0, 1, 2, 3]]).unwrap();
//! let model = ModelBuilder::new(mesh, Material::NeoHookean(NeoHookean::new(1e3, 0.3).unwrap()))
//!     .mass(MassSpec::NodeMass(1.0)).build().unwrap();
//! let mut state = State::at_rest(&model);
//! for p in state.x.iter_mut() { for c in p.iter_mut() { *c *= 1.1; } }
//! let proj = Projector::new(ProjectionSettings::default()).unwrap();
//! let mut sim = Simulation::new(model, state, Box::new(SymplecticEuler::new()), 0.01, Some(proj)).unwrap();
//! let h0 = sim.history()[0].invariants.total;
//! for _ in 0..100 { sim.step().unwrap(); }
//! let h = sim.history().last().unwrap().invariants.total;
//! assert!(((h - h0) / h0).abs() < 1e-8);
//! ```

// Index loops mirror the tensor formulas (P_ij, dP_ij/dF_kl) and read better than iterator chains here.
#![allow(clippy::needless_range_loop)]

pub mod checkpoint;
pub mod elasticity;
pub mod error;
pub mod exec;
pub mod integrators;
pub mod invariants;
pub mod material;
pub mod math;
pub mod mesh;
pub mod model;
pub mod projection;
pub mod simulation;
pub mod world;

pub use error::{FeprError, Result};
