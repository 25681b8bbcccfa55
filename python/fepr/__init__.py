"""fepr: Fast Energy Projection (FEPR) for real-time deformable solids.

Tetrahedral finite elements with hyperelastic materials, a base integrator, and the FEPR projection
(Dinev et al., SIGGRAPH 2018) that keeps energy, linear and angular momentum where they belong after every
step. SI units; NumPy float64 arrays of shape (m, 3) for positions and velocities.

Quick example::

    import fepr
    mesh = fepr.meshes.ell()
    sim = fepr.Simulation(mesh, material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
                          node_mass=5.0, dt=1/30)
    sim.positions = 1.5 * sim.rest_positions
    sim.step(300)
    print(sim.energy().total, sim.last_projection)
"""

from . import meshes
from ._core import __version__
from .errors import ConfigError, FeprError, MeshError, SimulationError
from .io import load_mesh
from .materials import NeoHookean, StableNeoHookean
from .mesh import TetMesh
from .simulation import Energy, History, Projection, ProjectionReport, Simulation

__all__ = [
    "ConfigError",
    "Energy",
    "FeprError",
    "History",
    "MeshError",
    "NeoHookean",
    "Projection",
    "ProjectionReport",
    "Simulation",
    "SimulationError",
    "StableNeoHookean",
    "TetMesh",
    "__version__",
    "load_mesh",
    "meshes",
]
