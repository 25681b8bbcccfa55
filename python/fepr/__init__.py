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

from . import export, meshes, sweep
from ._core import __version__
from .errors import (
    CheckpointError,
    ConfigError,
    FeprError,
    ImplausibleValueWarning,
    MeshError,
    MissingDependencyError,
    SimulationError,
)
from .io import load_mesh
from .materials import Arap, ConstraintNeoHookean, NeoHookean, StableNeoHookean
from .mesh import TetMesh
from .mesh_report import MeshInfo, mesh_info
from .mesher import tetrahedralize
from .multibody import MultiBody
from .simulation import (
    Energy,
    History,
    ImplicitEuler,
    Projection,
    ProjectionReport,
    ProjectiveDynamics,
    Simulation,
    SymplecticEuler,
    Xpbd,
)
from .viewer import view
from .world import Box, Capsule, Keyframes, KinematicPins, MeshObstacle, ObstacleMotion, Plane, Sinusoid, Sphere

__all__ = [
    "Arap",
    "Box",
    "Capsule",
    "Keyframes",
    "KinematicPins",
    "MeshObstacle",
    "ObstacleMotion",
    "Plane",
    "Sinusoid",
    "Sphere",
    "ConstraintNeoHookean",
    "ProjectiveDynamics",
    "CheckpointError",
    "ConfigError",
    "Energy",
    "FeprError",
    "History",
    "ImplausibleValueWarning",
    "ImplicitEuler",
    "MeshError",
    "MeshInfo",
    "MissingDependencyError",
    "MultiBody",
    "NeoHookean",
    "Projection",
    "ProjectionReport",
    "Simulation",
    "SimulationError",
    "StableNeoHookean",
    "SymplecticEuler",
    "TetMesh",
    "Xpbd",
    "__version__",
    "export",
    "sweep",
    "load_mesh",
    "mesh_info",
    "meshes",
    "tetrahedralize",
    "view",
]
