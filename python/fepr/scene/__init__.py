"""Scene files: a TOML description of a simulation, validated into a :class:`Scene`.

A scene names a mesh, a material, the masses, the initial state, the integrator, the projection, the world
(gravity, pins, damping) and how long to run. :func:`load_scene` reads and validates a file;
:meth:`Scene.build` turns it into a :class:`fepr.Simulation`; :func:`run_scene` runs it and writes the
diagnostics, which is what ``fepr run`` does.

Example (``examples/seed_demo3_stretch.toml``)::

    [mesh]
    builtin = "ell"

    [material]
    model = "neo_hookean"
    youngs_modulus = 1e3      # Pa
    poisson_ratio = 0.3

    [mass]
    node_mass = 5.0           # kg per vertex

    [initial]
    scale = 1.5               # stretch the rest shape 1.5x about the origin

    [integrator]
    name = "symplectic_euler"
    dt = 0.0333333333         # s

    [run]
    steps = 300

Every key is validated: an unknown key, a value of the wrong type or out of range raises
:class:`fepr.ConfigError` with a message naming the file, the section and the key. The full list of keys,
their units and defaults are documented on the settings dataclasses (:class:`MeshSettings`, ...);
:data:`SCENE_KEYS` lists the keys of every section.

Units are SI throughout: metres, kilograms, seconds, pascals.

The package has one module per job: :mod:`~fepr.scene.schema` (the keys, the settings dataclasses, their
defaults and docs), :mod:`~fepr.scene.parse` (TOML -> validated settings, errors naming file and key),
:mod:`~fepr.scene.build` (settings -> simulations, materials, world objects) and :mod:`~fepr.scene.run`
(running a scene, its outputs). The names below are the public API; import them from ``fepr.scene``.
"""

from .parse import load_scene, load_scene_from, scene_from_dict
from .run import RunResult, StopRequest, run_scene
from .schema import (
    BODY_KEYS,
    INTEGRATORS,
    KINEMATIC_PIN_KEYS,
    MATERIAL_MODELS,
    MOTIONS,
    OBSTACLE_COMMON_KEYS,
    OBSTACLE_KEYS,
    PROJECTION_ROWS,
    SCENE_KEYS,
    BodySettings,
    ExportSettings,
    InitialSettings,
    IntegratorSettings,
    KinematicPinSettings,
    MassSettings,
    MaterialSettings,
    MeshSettings,
    ObstacleSettings,
    PinBelow,
    ProjectionSettings,
    RunSettings,
    Scene,
    Vec3,
    WorldSettings,
)

# The old single-module ``fepr.scene`` listed the first group in ``__all__``; the second group was importable
# from it too (documented in docs/scenes.md) and is listed now so that every public name is in one place.
__all__ = [
    "SCENE_KEYS",
    "InitialSettings",
    "IntegratorSettings",
    "MassSettings",
    "MaterialSettings",
    "MeshSettings",
    "PinBelow",
    "ProjectionSettings",
    "RunResult",
    "ExportSettings",
    "RunSettings",
    "Scene",
    "WorldSettings",
    "load_scene",
    "run_scene",
    "load_scene_from",
    "StopRequest",
    "scene_from_dict",
    # also public in the single module
    "BODY_KEYS",
    "INTEGRATORS",
    "KINEMATIC_PIN_KEYS",
    "MATERIAL_MODELS",
    "MOTIONS",
    "OBSTACLE_COMMON_KEYS",
    "OBSTACLE_KEYS",
    "PROJECTION_ROWS",
    "BodySettings",
    "KinematicPinSettings",
    "ObstacleSettings",
    "Vec3",
]
