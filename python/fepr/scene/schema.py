"""The scene format: sections, keys, their types, defaults and units, as dataclasses.

Each section of a scene file is one dataclass (:class:`MeshSettings`, ...; ``[[bodies]]`` tables are
:class:`BodySettings`, list entries :class:`ObstacleSettings` and :class:`KinematicPinSettings`) and a whole
scene is a :class:`Scene`. The key tables below (:data:`SCENE_KEYS`, ...) are what :mod:`fepr.scene.parse`
accepts; the dataclasses' docstrings document every key, its unit and default. Units are SI throughout.

The settings' ``make``/``build`` methods are part of the public API; they delegate to :mod:`fepr.scene.build`,
which reads these classes only for type hints, so the dependency runs one way (schema -> build).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np

from .. import _core
from ..errors import ConfigError
from . import build as _build

Vec3 = Tuple[float, float, float]

Vec3 = Tuple[float, float, float]

#: Sections of a scene file and the keys each accepts (in documentation order).
SCENE_KEYS: Dict[str, Tuple[str, ...]] = {
    "scene": ("name", "description"),
    "mesh": (
        "path",
        "builtin",
        "scale",
        "translate",
        "fit",
        "rotate",
        "up_axis",
        "center",
        "size",
        "resolution",
        "radius",
        "height",
    ),
    "material": ("model", "youngs_modulus", "poisson_ratio", "j0"),
    "mass": ("node_mass", "density"),
    "initial": (
        "scale",
        "scale_about",
        "translate",
        "velocity",
        "angular_velocity",
        "velocities",
        "alternating_velocity",
    ),
    "integrator": ("name", "dt", "tolerance", "max_iterations", "iterations", "substeps"),
    "projection": ("enabled", *_core.PROJECTION_KEYS),
    "world": (
        "gravity",
        "pinned",
        "pin_below",
        "damping",
        "air_damping",
        "rayleigh_damping",
        "force",
        "obstacles",
        "kinematic_pins",
        "self_contact",
    ),
    "run": ("steps", "threads"),
    "export": ("formats", "every"),
}

#: Keys of a ``[[bodies]]`` table (a multi-body scene); ``mesh``, ``material``, ``mass`` and ``initial`` are
#: tables with the keys of the sections of the same name.
BODY_KEYS: Tuple[str, ...] = (
    "name",
    "mesh",
    "material",
    "mass",
    "initial",
    "pinned",
    "pin_below",
    "kinematic_pins",
    "restitution",
    "friction",
    "self_contact",
)
#: Keys of a ``self_contact`` table (``[world]`` of a one-body scene, or a ``[[bodies]]`` table).
SELF_CONTACT_KEYS: Tuple[str, ...] = ("restitution", "friction")
#: Obstacle types of ``[[world.obstacles]]`` and the geometry keys of each (``box`` takes one of
#: ``half_extents`` and ``size``; ``rotate`` is optional).
OBSTACLE_KEYS: Dict[str, Tuple[str, ...]] = {
    "plane": ("point", "normal"),
    "sphere": ("center", "radius"),
    "box": ("center", "half_extents", "size", "rotate"),
    "capsule": ("a", "b", "radius"),
    "mesh": ("path", "terrain", "flip_normals"),
}
#: Keys of the ``terrain`` table of a mesh obstacle (the keyword arguments of :meth:`fepr.MeshObstacle.terrain`).
TERRAIN_KEYS: Tuple[str, ...] = ("size", "cells", "height", "wavelength", "center", "depth")
#: Keys every obstacle accepts.
OBSTACLE_COMMON_KEYS: Tuple[str, ...] = ("type", "restitution", "friction", "motion")
#: Keys of a ``[[world.kinematic_pins]]`` table.
KINEMATIC_PIN_KEYS: Tuple[str, ...] = (
    "vertices",
    "below",
    "motion",
    "amplitude",
    "frequency",
    "phase",
    "times",
    "offsets",
)
MOTIONS = {"sinusoidal": ("amplitude", "frequency", "phase"), "keyframes": ("times", "offsets")}
#: Keys of an obstacle's ``motion`` table: a translation path (``translation`` names its kind, ``MOTIONS`` its
#: keys), a constant spin and keyframed orientations about a pivot.
OBSTACLE_MOTION_KEYS: Tuple[str, ...] = (
    "translation",
    "amplitude",
    "frequency",
    "phase",
    "times",
    "offsets",
    "angular_velocity",
    "pivot",
    "orientation_times",
    "orientations",
)

#: Name lists, defined once in the core (``fepr._core``) and read here.
MATERIAL_MODELS: Tuple[str, ...] = tuple(_core.MATERIALS)
INTEGRATORS: Tuple[str, ...] = tuple(_core.INTEGRATORS)
PROJECTION_ROWS: Tuple[str, ...] = tuple(_core.PROJECTION_ROWS)
SLACK_MODES: Tuple[str, ...] = tuple(_core.SLACK_MODES)
METRICS: Tuple[str, ...] = tuple(_core.METRICS)
#: The ``[mesh]`` options each builtin mesh takes (its keyword arguments in :func:`fepr.meshes.builtin`).
_BUILTIN_OPTIONS = {
    "box": ("size", "resolution", "center"),
    "ell": ("size", "resolution"),
    "sphere": ("radius", "resolution", "center"),
    "cylinder": ("radius", "height", "resolution", "center"),
}
#: The axes ``pin_below`` and a kinematic pin's ``below`` accept.
_AXES = {"x": 0, "y": 1, "z": 2}


# --------------------------------------------------------------------------------------------------------
# Settings (one dataclass per section)
# --------------------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------------------
# Settings (one dataclass per section)
# --------------------------------------------------------------------------------------------------------


@dataclass
class MeshSettings:
    """``[mesh]``: where the rest shape comes from.

    Exactly one of ``path`` (a mesh file, resolved relative to the scene file) and ``builtin`` (a name for
    :func:`fepr.meshes.builtin`). The load options ``up_axis``, ``rotate``, ``scale`` or ``fit``, ``center``
    (``"bbox"`` / ``"centroid"``) and ``translate`` are applied in that order, as by :func:`fepr.load_mesh`.
    ``builtin_options`` holds ``size``, ``radius``, ``height``, ``resolution`` and ``center`` (a point) for
    a builtin mesh.
    """

    path: Optional[Path] = None
    builtin: Optional[str] = None
    builtin_options: Dict[str, Any] = field(default_factory=dict)
    scale: Optional[float] = None
    translate: Optional[Vec3] = None
    fit: Optional[float] = None
    rotate: Any = None
    up_axis: Optional[str] = None
    center: Optional[str] = None

    def load_options(self) -> Dict[str, Any]:
        """The load options that were given, as keyword arguments for :func:`fepr.load_mesh`."""
        names = ("scale", "translate", "fit", "rotate", "up_axis", "center")
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}


@dataclass
class MaterialSettings:
    """``[material]``: hyperelastic model and its parameters (Young's modulus in Pa, Poisson ratio)."""

    youngs_modulus: float
    poisson_ratio: float
    model: str = "neo_hookean"
    j0: Optional[float] = None


@dataclass
class MassSettings:
    """``[mass]``: exactly one of ``node_mass`` (kg per vertex) and ``density`` (kg/m^3, lumped)."""

    node_mass: Optional[float] = None
    density: Optional[float] = None


@dataclass
class InitialSettings:
    """``[initial]``: the initial state, derived from the rest shape.

    Positions are ``about + scale * (X - about)`` with ``about`` the origin, a point, or ``"centroid"``
    (the centre of mass of the rest shape). The initial velocity is the sum of the given terms: a uniform
    ``velocity`` (m/s), a rigid spin ``angular_velocity`` (rad/s) about the centre of mass of the initial
    positions, a per-vertex array file ``velocities`` (``.npy``, shape (m, 3), m/s) and
    ``alternating_velocity`` (applied to even-index vertices only, the seed's demo 1). Pinned vertices start
    at rest. ``translate`` (m) is added to the initial positions last (after ``scale``); the rest shape does not
    move, so a translated body starts undeformed, only elsewhere (e.g. a box dropped from a height).
    """

    scale: float = 1.0
    scale_about: Union[Vec3, str, None] = None
    velocity: Optional[Vec3] = None
    angular_velocity: Optional[Vec3] = None
    velocities: Optional[Path] = None
    alternating_velocity: Optional[Vec3] = None
    translate: Optional[Vec3] = None

    def is_rest(self) -> bool:
        """True if the initial state is the rest shape at rest."""
        return self.scale == 1.0 and not any(
            v is not None
            for v in (self.velocity, self.angular_velocity, self.velocities, self.alternating_velocity, self.translate)
        )

    def moves_positions(self) -> bool:
        """True if the initial positions differ from the rest positions (``scale`` or ``translate``)."""
        return self.scale != 1.0 or (self.translate is not None and any(c != 0.0 for c in self.translate))


@dataclass
class IntegratorSettings:
    """``[integrator]``: the base integrator and its time step ``dt`` (s)."""

    name: str = "symplectic_euler"
    dt: float = 1.0 / 30.0
    #: Newton settings (``implicit_euler``), local/global iterations (``projective_dynamics``), sweeps per
    #: substep and substeps (``xpbd``).
    tolerance: Optional[float] = None
    max_iterations: Optional[int] = None
    iterations: Optional[int] = None
    substeps: Optional[int] = None

    def make(self):
        """The integrator object with the given options (a ConfigError names an option the integrator lacks)."""
        return _build.make_integrator(self)


@dataclass
class ProjectionSettings:
    """``[projection]``: FEPR on or off and its options; ``None`` means the library default."""

    enabled: bool = True
    tolerance: Optional[float] = None
    max_iterations: Optional[int] = None
    rows: Optional[str] = None
    c_eps: Optional[float] = None
    regularization: Optional[float] = None
    max_halvings: Optional[int] = None
    impact_bound: Optional[float] = None
    slack: Optional[str] = None
    warm_start: Optional[float] = None
    metric: Optional[str] = None
    quality_guard: Optional[bool] = None
    quality_margin: Optional[float] = None

    def options(self) -> Dict[str, Any]:
        """The options that were given, as keyword arguments for :class:`fepr.Projection`."""
        names = [k for k in SCENE_KEYS["projection"] if k != "enabled"]
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}

    def make(self):
        """``False`` when disabled, else a :class:`fepr.Projection` with the given options."""
        return _build.make_projection(self)


@dataclass
class PinBelow:
    """Pin every vertex whose rest coordinate along ``axis`` is ``<= value`` (metres)."""

    axis: str
    value: float


@dataclass
class ObstacleSettings:
    """One ``[[world.obstacles]]`` entry: a rigid obstacle (static or moving) the bodies' vertices collide with.

    ``type`` is ``"plane"``, ``"sphere"``, ``"box"``, ``"capsule"`` or ``"mesh"``; ``geometry`` holds the keyword
    arguments of the matching :mod:`fepr.world` class (``point``/``normal``; ``center``/``radius``;
    ``center``/``half_extents``/``rotation`` (3x3, rows the box's axes in world coordinates, or ``None``);
    ``a``/``b``/``radius``; all in m); a mesh has ``path`` (a surface file, resolved against the scene's folder)
    or ``terrain`` (the keyword arguments of :meth:`fepr.MeshObstacle.terrain`), and ``flip_normals``.
    ``restitution`` is in [0, 1] (1: elastic), ``friction`` the Coulomb coefficient (>= 0). ``motion`` is None
    (static) or the keyword arguments of a :class:`fepr.ObstacleMotion` as read from the entry's ``motion`` table
    (``translation``: ``"sinusoidal"`` or ``"keyframes"`` or None, that path's keys, ``angular_velocity`` rad/s,
    ``pivot`` m, ``orientation_times`` s and ``orientations`` rotation vectors in rad). ``label`` names the entry
    in messages (``[[world.obstacles]] #2``).
    """

    type: str
    geometry: Dict[str, Any]
    restitution: float = 1.0
    friction: float = 0.0
    motion: Optional[Dict[str, Any]] = None
    #: Contact of the body with its own surface: ``(restitution, friction)``, or None (off).
    self_contact: Optional[Tuple[float, float]] = None
    label: str = ""

    def make(self):
        """The obstacle object (:class:`fepr.Plane`, :class:`fepr.Sphere`, :class:`fepr.Box`, :class:`fepr.Capsule`,
        :class:`fepr.MeshObstacle`)."""
        return _build.make_obstacle(self)


@dataclass
class KinematicPinSettings:
    """One ``[[world.kinematic_pins]]`` entry: vertices that follow a prescribed motion.

    The vertices are ``vertices`` (indices) or every vertex whose rest coordinate along ``below.axis`` is
    ``<= below.value`` (m). ``motion`` is ``"sinusoidal"`` (``amplitude`` (3,) m, ``frequency`` Hz, ``phase``
    rad: displacement ``amplitude (sin(2 pi f t + phase) - sin(phase))``) or ``"keyframes"`` (``times`` (k,) s,
    strictly increasing, ``offsets`` (k, 3) m: piecewise-linear displacement, held outside the keyframes).
    Each vertex follows its initial position plus the displacement (see :class:`fepr.KinematicPins`).
    """

    motion: str
    vertices: Optional[Tuple[int, ...]] = None
    below: Optional[PinBelow] = None
    amplitude: Optional[Vec3] = None
    frequency: Optional[float] = None
    phase: float = 0.0
    times: Optional[Tuple[float, ...]] = None
    offsets: Optional[Tuple[Vec3, ...]] = None
    label: str = ""

    def indices(self, rest_vertices: np.ndarray) -> np.ndarray:
        """Sorted vertex indices (int64) of this pin for a mesh with these rest vertices (m)."""
        return _build.kinematic_pin_indices(self, rest_vertices)

    def make_motion(self):
        """The motion object (:class:`fepr.Sinusoid` or :class:`fepr.Keyframes`)."""
        return _build.make_motion(self)

    def make(self, rest_vertices: np.ndarray):
        """The :class:`fepr.KinematicPins` for a mesh with these rest vertices (m)."""
        return _build.make_kinematic_pins(self, rest_vertices)


@dataclass
class WorldSettings:
    """``[world]``: gravity (m/s^2), pinned vertices, damping, a constant force, obstacles, kinematic pins.

    ``damping`` is the per-step velocity factor ``v <- (1 - damping) v``; ``air_damping`` (1/s) the
    mass-proportional damping ``dv/dt = -a v``; ``rayleigh_damping`` (s) the stiffness-proportional damping
    force ``-b K v``. ``force`` (N) is the total constant force on the scene, spread over the free vertices of
    all bodies in proportion to their masses (a uniform acceleration ``force / m_free``). ``pinned``,
    ``pin_below``, ``kinematic_pins`` and ``self_contact`` belong to the single body of a one-body scene (a
    multi-body scene gives them per body).
    """

    gravity: Vec3 = (0.0, 0.0, 0.0)
    pinned: Tuple[int, ...] = ()
    pin_below: Optional[PinBelow] = None
    damping: float = 0.0
    air_damping: float = 0.0
    rayleigh_damping: float = 0.0
    force: Optional[Vec3] = None
    obstacles: Tuple[ObstacleSettings, ...] = ()
    kinematic_pins: Tuple[KinematicPinSettings, ...] = ()
    self_contact: Optional[Tuple[float, float]] = None

    def make_obstacles(self) -> list:
        """The obstacle objects of :mod:`fepr.world`, in file order."""
        return [o.make() for o in self.obstacles]


@dataclass
class BodySettings:
    """One body: its mesh, material, masses, initial state and pins.

    In a multi-body scene each ``[[bodies]]`` table is one; a one-body scene's top-level ``[mesh]``,
    ``[material]``, ``[mass]``, ``[initial]`` and the pins of ``[world]`` make the single one
    (:meth:`Scene.body_settings`). ``label`` names the body in messages (``[[bodies]] #2``; empty for the
    top-level body).
    """

    name: str
    mesh: MeshSettings
    material: MaterialSettings
    mass: MassSettings
    initial: InitialSettings = field(default_factory=InitialSettings)
    pinned: Tuple[int, ...] = ()
    pin_below: Optional[PinBelow] = None
    kinematic_pins: Tuple[KinematicPinSettings, ...] = ()
    #: Contact with the other bodies: restitution in [0, 1] and Coulomb friction (a pair uses the smaller
    #: restitution and the geometric mean of the frictions).
    restitution: float = 1.0
    friction: float = 0.0
    #: Contact of the body with its own surface: ``(restitution, friction)``, or None (off).
    self_contact: Optional[Tuple[float, float]] = None
    label: str = ""

    def section(self, name: str) -> str:
        """How messages name a section of this body: ``[mesh]`` or ``[[bodies]] #2 [mesh]``."""
        return f"[{name}]" if not self.label else f"{self.label} [{name}]"

    def pins_label(self) -> str:
        """How messages name this body's pin keys: ``[world]`` or ``[[bodies]] #2:``."""
        return "[world]" if not self.label else f"{self.label}:"


@dataclass
class RunSettings:
    """``[run]``: number of steps, and worker threads (``None``: the library's default)."""

    steps: int = 100
    threads: Optional[int] = None


@dataclass
class ExportSettings:
    """``[export]``: formats written by :func:`run_scene` into ``out_dir/export`` (none by default), every
    ``every``-th step (see :class:`fepr.export.Recorder`)."""

    formats: Tuple[str, ...] = ()
    every: int = 1


@dataclass
class Scene:
    """A validated scene. Build a simulation with :meth:`build`; run it with :func:`run_scene`.

    A one-body scene has ``mesh``, ``material``, ``mass`` and ``initial`` (and its pins in ``world``); a
    multi-body scene has them per body in ``bodies`` (one :class:`BodySettings` per ``[[bodies]]`` table) and
    ``mesh``, ``material`` and ``mass`` are ``None``. :meth:`body_settings` gives the bodies either way.
    ``source`` is the scene file (used in messages), ``base_dir`` the folder relative paths were resolved
    against.
    """

    name: str
    mesh: Optional[MeshSettings] = None
    material: Optional[MaterialSettings] = None
    mass: Optional[MassSettings] = None
    initial: InitialSettings = field(default_factory=InitialSettings)
    integrator: IntegratorSettings = field(default_factory=IntegratorSettings)
    projection: ProjectionSettings = field(default_factory=ProjectionSettings)
    world: WorldSettings = field(default_factory=WorldSettings)
    run: RunSettings = field(default_factory=RunSettings)
    export: ExportSettings = field(default_factory=ExportSettings)
    description: str = ""
    source: Optional[str] = None
    base_dir: Path = field(default_factory=Path.cwd)
    bodies: Tuple[BodySettings, ...] = ()

    # ---- bodies --------------------------------------------------------------------------------------

    @property
    def is_multibody(self) -> bool:
        """True for a scene with ``[[bodies]]`` tables (even a single one)."""
        return bool(self.bodies)

    def body_settings(self) -> List[BodySettings]:
        """The bodies of the scene: the ``[[bodies]]`` tables, or the single top-level body."""
        if self.bodies:
            return list(self.bodies)
        if self.mesh is None or self.material is None or self.mass is None:
            raise ConfigError(f"{self._where()}a scene needs [mesh], [material] and [mass], or [[bodies]] tables")
        return [
            BodySettings(
                name=self.name,
                mesh=self.mesh,
                material=self.material,
                mass=self.mass,
                initial=self.initial,
                pinned=self.world.pinned,
                pin_below=self.world.pin_below,
                kinematic_pins=self.world.kinematic_pins,
                self_contact=self.world.self_contact,
            )
        ]

    def _single(self, what: str) -> BodySettings:
        if self.bodies:
            raise ConfigError(
                f"{self._where()}{what} needs a one-body scene; this scene has {len(self.bodies)} [[bodies]] "
                "(use build_bodies() or build_multibody())"
            )
        return self.body_settings()[0]

    def has_supports(self) -> bool:
        """True if any body has pinned or kinematically pinned vertices."""
        return any(b.pinned or b.pin_below is not None or b.kinematic_pins for b in self.body_settings())

    # ---- building ------------------------------------------------------------------------------------

    def _where(self) -> str:
        """How messages start: the scene file, or nothing for a scene given as a dict without a source."""
        return f"{self.source}: " if self.source else ""

    def load_mesh(self):
        """The rest mesh (:class:`fepr.TetMesh`) after the ``[mesh]`` load options (one-body scenes)."""
        return _build.load_body_mesh(self, self._single("load_mesh()"))

    def make_material(self):
        """The material object (:class:`fepr.NeoHookean`, :class:`fepr.StableNeoHookean`, ...), one-body scenes."""
        return _build.make_body_material(self, self._single("make_material()"))

    def pinned_indices(self, rest_vertices: np.ndarray) -> Optional[np.ndarray]:
        """Sorted indices of the pinned vertices (``[world] pinned`` and ``pin_below``), or ``None``."""
        return _build.body_pinned(self, self._single("pinned_indices()"), rest_vertices)

    def initial_state(
        self, rest_vertices: np.ndarray, masses: np.ndarray, pinned: Optional[np.ndarray] = None
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Initial positions and velocities, each (m, 3) float64, from the rest vertices and masses (kg)."""
        body = self._single("initial_state()")
        return _build.initial_state(
            body.initial, rest_vertices, masses, pinned, self._where() + body.section("initial")
        )

    def build(self, projection=None):
        """Build the :class:`fepr.Simulation` this (one-body) scene describes, in its initial state.

        Parameters
        ----------
        projection : bool or fepr.Projection, optional
            Overrides ``[projection]`` (``False`` turns FEPR off, as ``fepr run --no-projection`` does).

        Raises
        ------
        ConfigError
            If a value is rejected (the message names the scene file and section), or for a multi-body scene
            (use :meth:`build_multibody`).
        MeshError
            If the mesh file cannot be read or is invalid.
        """
        self._single("build()")
        return self.build_bodies(projection=projection)[0]

    def build_multibody(self, projection=None):
        """A :class:`fepr.multibody.MultiBody` of :meth:`build_bodies`, named after the bodies."""
        return _build.build_multibody(self, projection)

    def build_bodies(self, projection=None) -> list:
        """One :class:`fepr.Simulation` per body (:meth:`body_settings`), each in its initial state.

        The shared settings (integrator, projection, gravity, damping, obstacles, run threads) are the same for
        every body; ``[world] force`` is split over the free vertices of all bodies in proportion to mass.
        """
        return _build.build_bodies(self, projection)
