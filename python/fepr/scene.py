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
their units and defaults are documented on the settings dataclasses below (:class:`MeshSettings`, ...);
:data:`SCENE_KEYS` lists the keys of every section.

Units are SI throughout: metres, kilograms, seconds, pascals.
"""

from __future__ import annotations

import math
import re
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from .errors import ConfigError, MeshError, SimulationError

if sys.version_info >= (3, 11):
    import tomllib as _toml
else:  # pragma: no cover - exercised on Python < 3.11 only
    import tomli as _toml

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
    "scene_from_dict",
]

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
    "projection": (
        "enabled",
        "tolerance",
        "max_iterations",
        "rows",
        "c_eps",
        "regularization",
        "max_halvings",
        "impact_bound",
        "slack",
        "warm_start",
        "metric",
        "quality_guard",
        "quality_margin",
    ),
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
    ),
    "run": ("steps", "threads"),
    "export": ("formats", "every"),
}

#: Keys of a ``[[bodies]]`` table (a multi-body scene); ``mesh``, ``material``, ``mass`` and ``initial`` are
#: tables with the keys of the sections of the same name.
BODY_KEYS: Tuple[str, ...] = ("name", "mesh", "material", "mass", "initial", "pinned", "pin_below", "kinematic_pins")
#: Obstacle types of ``[[world.obstacles]]`` and the geometry keys of each (``box`` takes one of
#: ``half_extents`` and ``size``; ``rotate`` is optional).
OBSTACLE_KEYS: Dict[str, Tuple[str, ...]] = {
    "plane": ("point", "normal"),
    "sphere": ("center", "radius"),
    "box": ("center", "half_extents", "size", "rotate"),
    "capsule": ("a", "b", "radius"),
}
#: Keys every obstacle accepts.
OBSTACLE_COMMON_KEYS: Tuple[str, ...] = ("type", "restitution", "friction")
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

MATERIAL_MODELS = ("neo_hookean", "stable_neo_hookean", "arap", "constraint_neo_hookean")
#: Integrator names planned by the design; the ones actually accepted come from the compiled core.
INTEGRATORS = ("symplectic_euler", "implicit_euler", "projective_dynamics", "xpbd")
PROJECTION_ROWS = ("auto", "energy", "energy_momentum", "all")
_BUILTIN_OPTIONS = {
    "box": ("size", "resolution", "center"),
    "ell": ("size", "resolution"),
    "sphere": ("radius", "resolution", "center"),
    "cylinder": ("radius", "height", "resolution", "center"),
}
_AXES = {"x": 0, "y": 1, "z": 2}
_MISSING = object()


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
        import fepr

        given = {
            k: getattr(self, k)
            for k in ("tolerance", "max_iterations", "iterations", "substeps")
            if getattr(self, k) is not None
        }
        allowed = {
            "implicit_euler": ("tolerance", "max_iterations"),
            "projective_dynamics": ("iterations",),
            "xpbd": ("iterations", "substeps"),
        }
        extra = sorted(set(given) - set(allowed.get(self.name, ())))
        if extra:
            raise ConfigError(f"[integrator] {', '.join(extra)} is not an option of {self.name!r}")
        types = {
            "implicit_euler": fepr.ImplicitEuler,
            "projective_dynamics": fepr.ProjectiveDynamics,
            "xpbd": fepr.Xpbd,
        }
        return types[self.name](**given) if self.name in types else self.name


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
        if not self.enabled:
            return False
        import fepr

        return fepr.Projection(**self.options())


@dataclass
class PinBelow:
    """Pin every vertex whose rest coordinate along ``axis`` is ``<= value`` (metres)."""

    axis: str
    value: float


@dataclass
class ObstacleSettings:
    """One ``[[world.obstacles]]`` entry: a fixed rigid obstacle the bodies' vertices collide with.

    ``type`` is ``"plane"``, ``"sphere"``, ``"box"`` or ``"capsule"``; ``geometry`` holds the keyword arguments
    of the matching :mod:`fepr.world` class (``point``/``normal``; ``center``/``radius``;
    ``center``/``half_extents``/``rotation`` (3x3, rows the box's axes in world coordinates, or ``None``);
    ``a``/``b``/``radius``; all in m).
    ``restitution`` is in [0, 1] (1: elastic), ``friction`` the Coulomb coefficient (>= 0). ``label`` names the
    entry in messages (``[[world.obstacles]] #2``).
    """

    type: str
    geometry: Dict[str, Any]
    restitution: float = 1.0
    friction: float = 0.0
    label: str = ""

    def make(self):
        """The obstacle object (:class:`fepr.Plane`, :class:`fepr.Sphere`, :class:`fepr.Box`, :class:`fepr.Capsule`)."""
        from . import world

        cls = {"plane": world.Plane, "sphere": world.Sphere, "box": world.Box, "capsule": world.Capsule}[self.type]
        try:
            return cls(**self.geometry, restitution=self.restitution, friction=self.friction)
        except (ConfigError, ValueError, TypeError) as exc:
            raise ConfigError(f"{self.label}: {exc}") from None


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
        m = len(rest_vertices)
        if self.vertices is not None:
            for i in self.vertices:
                if not 0 <= i < m:
                    raise ConfigError(f"{self.label}: vertices: vertex index {i} out of range (mesh has {m} vertices)")
            return np.unique(np.asarray(self.vertices, dtype=np.int64))
        assert self.below is not None
        return _vertices_below(rest_vertices, self.below, f"{self.label}: below")

    def make_motion(self):
        """The motion object (:class:`fepr.Sinusoid` or :class:`fepr.Keyframes`)."""
        from . import world

        try:
            if self.motion == "sinusoidal":
                return world.Sinusoid(amplitude=self.amplitude, frequency=self.frequency, phase=self.phase)
            return world.Keyframes(
                times=np.asarray(self.times, dtype=np.float64), offsets=np.asarray(self.offsets, dtype=np.float64)
            )
        except (ConfigError, ValueError, TypeError) as exc:
            raise ConfigError(f"{self.label}: {exc}") from None

    def make(self, rest_vertices: np.ndarray):
        """The :class:`fepr.KinematicPins` for a mesh with these rest vertices (m)."""
        idx = self.indices(rest_vertices)
        from . import world

        try:
            return world.KinematicPins(vertices=idx, motion=self.make_motion())
        except (ConfigError, ValueError, TypeError) as exc:
            raise ConfigError(f"{self.label}: {exc}") from None


@dataclass
class WorldSettings:
    """``[world]``: gravity (m/s^2), pinned vertices, damping, a constant force, obstacles, kinematic pins.

    ``damping`` is the per-step velocity factor ``v <- (1 - damping) v``; ``air_damping`` (1/s) the
    mass-proportional damping ``dv/dt = -a v``; ``rayleigh_damping`` (s) the stiffness-proportional damping
    force ``-b K v``. ``force`` (N) is the total constant force on the scene, spread over the free vertices of
    all bodies in proportion to their masses (a uniform acceleration ``force / m_free``). ``pinned``,
    ``pin_below`` and ``kinematic_pins`` belong to the single body of a one-body scene (a multi-body scene gives
    them per body).
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
        return f"{self.source}: " if self.source else ""

    def load_mesh(self):
        """The rest mesh (:class:`fepr.TetMesh`) after the ``[mesh]`` load options (one-body scenes)."""
        return self._load_body_mesh(self._single("load_mesh()"))

    def _load_body_mesh(self, body: BodySettings):
        import fepr

        m = body.mesh
        where = self._where()
        sec = body.section("mesh")
        if m.path is not None:
            try:
                return fepr.load_mesh(str(m.path), **m.load_options())
            except MeshError as exc:
                msg = str(exc)
                if str(m.path) not in msg and m.path.name not in msg:
                    msg = f"{m.path}: {msg}"
                raise MeshError(f"{where}{sec} {msg}") from None
        assert m.builtin is not None
        try:
            from . import meshes

            mesh = meshes.builtin(m.builtin, **m.builtin_options)
        except (ConfigError, MeshError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"{where}{sec} builtin {m.builtin!r}: {exc}") from None
        if m.load_options():
            from .io import transform_mesh

            try:
                mesh = transform_mesh(mesh, **m.load_options())
            except ConfigError as exc:
                raise ConfigError(f"{where}{sec} {exc}") from None
        return mesh

    def make_material(self):
        """The material object (:class:`fepr.NeoHookean`, :class:`fepr.StableNeoHookean`, ...), one-body scenes."""
        return self._make_body_material(self._single("make_material()"))

    def _make_body_material(self, body: BodySettings):
        import fepr

        mat = body.material
        try:
            if mat.model == "neo_hookean":
                kw: Dict[str, Any] = {}
                if mat.j0 is not None:
                    kw["j0"] = mat.j0
                return fepr.NeoHookean(youngs_modulus=mat.youngs_modulus, poisson_ratio=mat.poisson_ratio, **kw)
            types = {
                "stable_neo_hookean": fepr.StableNeoHookean,
                "arap": fepr.Arap,
                "constraint_neo_hookean": fepr.ConstraintNeoHookean,
            }
            return types[mat.model](youngs_modulus=mat.youngs_modulus, poisson_ratio=mat.poisson_ratio)
        except ConfigError as exc:
            raise ConfigError(f"{self._where()}{body.section('material')} {exc}") from None

    def pinned_indices(self, rest_vertices: np.ndarray) -> Optional[np.ndarray]:
        """Sorted indices of the pinned vertices (``[world] pinned`` and ``pin_below``), or ``None``."""
        return self._body_pinned(self._single("pinned_indices()"), rest_vertices)

    def _body_pinned(self, body: BodySettings, rest_vertices: np.ndarray) -> Optional[np.ndarray]:
        where = self._where()
        label = body.pins_label()
        m = len(rest_vertices)
        idx: List[int] = []
        for i in body.pinned:
            if not 0 <= i < m:
                raise ConfigError(f"{where}{label} pinned: vertex index {i} out of range (mesh has {m} vertices)")
            idx.append(i)
        if body.pin_below is not None:
            idx.extend(int(i) for i in _vertices_below(rest_vertices, body.pin_below, f"{where}{label} pin_below"))
        if not idx:
            return None
        return np.unique(np.asarray(idx, dtype=np.int64))

    def initial_state(
        self, rest_vertices: np.ndarray, masses: np.ndarray, pinned: Optional[np.ndarray] = None
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Initial positions and velocities, each (m, 3) float64, from the rest vertices and masses (kg)."""
        body = self._single("initial_state()")
        return _initial_state(body.initial, rest_vertices, masses, pinned, self._where() + body.section("initial"))

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
        from .multibody import MultiBody

        bodies = self.body_settings()
        return MultiBody(self.build_bodies(projection=projection), names=[b.name for b in bodies])

    def build_bodies(self, projection=None) -> list:
        """One :class:`fepr.Simulation` per body (:meth:`body_settings`), each in its initial state.

        The shared settings (integrator, projection, gravity, damping, obstacles, run threads) are the same for
        every body; ``[world] force`` is split over the free vertices of all bodies in proportion to mass.
        """
        import fepr

        where = self._where()
        if projection is None:
            try:
                projection = self.projection.make()
            except ConfigError as exc:
                raise ConfigError(f"{where}[projection] {exc}") from None
        obstacles = [o.make() for o in self.world.obstacles]
        sims = []
        free_masks = []
        for body in self.body_settings():
            mesh = self._load_body_mesh(body)
            material = self._make_body_material(body)
            rest = np.asarray(mesh.vertices, dtype=np.float64)
            pinned = self._body_pinned(body, rest)
            kin = []
            for kp in body.kinematic_pins:
                try:
                    kin.append(kp.make(rest))
                except ConfigError as exc:
                    raise ConfigError(f"{where}{exc}") from None
            kwargs: Dict[str, Any] = {}
            if body.mass.node_mass is not None:
                kwargs["node_mass"] = body.mass.node_mass
            else:
                kwargs["density"] = body.mass.density
            if self.run.threads is not None:
                kwargs["threads"] = self.run.threads
            # The world options are passed only when used, so scenes without them need nothing new.
            if obstacles:
                kwargs["obstacles"] = obstacles
            if kin:
                kwargs["kinematic_pins"] = kin
            if self.world.air_damping:
                kwargs["air_damping"] = self.world.air_damping
            if self.world.rayleigh_damping:
                kwargs["rayleigh_damping"] = self.world.rayleigh_damping
            try:
                sim = fepr.Simulation(
                    mesh,
                    material=material,
                    integrator=self.integrator.make(),
                    dt=self.integrator.dt,
                    projection=projection,
                    gravity=self.world.gravity,
                    pinned=pinned,
                    damping=self.world.damping,
                    **kwargs,
                )
            except ConfigError as exc:
                label = f"{body.label}: " if body.label else ""
                raise ConfigError(f"{where}{label}{exc}") from None
            if not body.initial.is_rest():
                x, v = _initial_state(
                    body.initial,
                    np.asarray(sim.rest_positions),
                    np.asarray(sim.masses),
                    pinned,
                    where + body.section("initial"),
                    kinematic=[np.asarray(k.vertices, dtype=np.int64) for k in kin],
                )
                if body.initial.moves_positions():
                    sim.positions = x
                if np.any(v):
                    sim.velocities = v
            free = np.ones(len(rest), dtype=bool)
            if pinned is not None:
                free[pinned] = False
            for k in kin:
                free[np.asarray(k.vertices, dtype=np.int64)] = False
            sims.append(sim)
            free_masks.append(free)
        if self.world.force is not None and any(c != 0.0 for c in self.world.force):
            for sim, f in zip(sims, _distribute_force(self.world.force, sims, free_masks)):
                sim.set_external_forces(f)
        return sims


def _distribute_force(force: Vec3, sims: Sequence[Any], free_masks: Sequence[np.ndarray]) -> list:
    """Per-body (m, 3) force arrays (N) that spread the total ``force`` (N) over the free vertices of all bodies
    in proportion to their masses: ``f_i = m_i force / m_free``."""
    masses = [_vertex_masses(np.asarray(s.masses), len(free)) for s, free in zip(sims, free_masks)]
    # > 0: fepr.Simulation rejects a body whose vertices are all pinned.
    m_free = float(sum(float(w[free].sum()) for w, free in zip(masses, free_masks)))
    a = np.asarray(force, dtype=np.float64) / m_free
    out = []
    for w, free in zip(masses, free_masks):
        f = np.zeros((len(free), 3))
        f[free] = w[free, None] * a
        out.append(f)
    return out


def _vertices_below(rest_vertices: np.ndarray, pb: PinBelow, label: str) -> np.ndarray:
    """Indices (int64) of the vertices whose rest coordinate along ``pb.axis`` is ``<= pb.value``; a ConfigError
    starting with ``label`` when there is none."""
    coord = np.asarray(rest_vertices)[:, _AXES[pb.axis]]
    below = np.flatnonzero(coord <= pb.value)
    if below.size == 0:
        raise ConfigError(f"{label}: no vertex has {pb.axis} <= {pb.value} (lowest {pb.axis} is {coord.min():.6g})")
    return below.astype(np.int64)


def _initial_state(
    ini: InitialSettings,
    rest_vertices: np.ndarray,
    masses: np.ndarray,
    pinned: Optional[np.ndarray],
    where: str,
    kinematic: Sequence[np.ndarray] = (),
) -> Tuple[np.ndarray, np.ndarray]:
    """Initial positions and velocities, each (m, 3) float64 (see :class:`InitialSettings`). Pinned and
    kinematically pinned vertices start at rest (a kinematic pin then moves them)."""
    rest = np.asarray(rest_vertices, dtype=np.float64)
    m = len(rest)
    w = _vertex_masses(masses, m)
    x = rest.copy()
    if ini.scale != 1.0:
        if ini.scale_about is None:
            about = np.zeros(3)
        elif isinstance(ini.scale_about, str):
            about = _centre_of_mass(rest, w)
        else:
            about = np.asarray(ini.scale_about, dtype=np.float64)
        x = about + ini.scale * (rest - about)
    if ini.translate is not None:
        x = x + np.asarray(ini.translate, dtype=np.float64)
    v = np.zeros_like(x)
    if ini.velocity is not None:
        v += np.asarray(ini.velocity, dtype=np.float64)
    if ini.angular_velocity is not None:
        c = _centre_of_mass(x, w)
        v += np.cross(np.asarray(ini.angular_velocity, dtype=np.float64), x - c)
    if ini.velocities is not None:
        v += _load_velocities(ini.velocities, m, where)
    if ini.alternating_velocity is not None:
        v[0::2] += np.asarray(ini.alternating_velocity, dtype=np.float64)
    if pinned is not None and len(pinned):
        v[pinned] = 0.0
    for k in kinematic:
        v[k] = 0.0
    return x, v


def _vertex_masses(masses: np.ndarray, m: int) -> np.ndarray:
    w = np.asarray(masses, dtype=np.float64)
    if w.ndim == 2:  # per-coordinate masses (m, 3)
        w = w[:, 0]
    if w.ndim == 0:
        w = np.full(m, float(w))
    return w


def _centre_of_mass(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    return (w[:, None] * x).sum(axis=0) / w.sum()


def _load_velocities(path: Path, m: int, where: str) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{where} velocities: cannot read {path}: {exc}") from None
    if not isinstance(arr, np.ndarray):
        raise ConfigError(f"{where} velocities: {path} must hold one array (a .npy file)")
    if arr.shape != (m, 3):
        raise ConfigError(f"{where} velocities: {path} has shape {arr.shape}, expected ({m}, 3)")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{where} velocities: {path} contains NaN or infinite values")
    return arr


# --------------------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------------------


class _Table:
    """One section of a scene: typed accessors that raise ConfigError naming the section and key."""

    def __init__(
        self,
        data: Mapping[str, Any],
        section: str,
        where: str,
        *,
        known: Optional[Sequence[str]] = None,
        label: Optional[str] = None,
    ):
        self.data = data
        self.section = section
        self.where = where
        #: How messages name this table: ``[mesh]``, ``[[bodies]] #2 [mesh]``, ``[[world.obstacles]] #1:``.
        self.label = label if label is not None else f"[{section}]"
        known = SCENE_KEYS[section] if known is None else known
        for key in data:
            if key not in known:
                raise self.error(f"unknown key {key!r} (known: {', '.join(known)})")

    def error(self, msg: str) -> ConfigError:
        return ConfigError(f"{self.where}{self.label} {msg}")

    def has(self, key: str) -> bool:
        return key in self.data

    def _get(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            raise self.error(f"missing required key {key!r}")
        return default

    def number(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        positive: bool = False,
        nonnegative: bool = False,
        lo: Optional[float] = None,
        hi: Optional[float] = None,
    ) -> Any:
        value = self._get(key, default)
        if key not in self.data:
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(f"{key} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(f"{key} must be finite, got {value!r}")
        if positive and value <= 0:
            raise self.error(f"{key} must be > 0, got {value!r}")
        if nonnegative and value < 0:
            raise self.error(f"{key} must be >= 0, got {value!r}")
        if lo is not None and hi is not None and not lo < value < hi:
            raise self.error(f"{key} must be in ({lo}, {hi}), got {value!r}")
        return value

    def integer(self, key: str, default: Any = _MISSING, *, minimum: Optional[int] = None) -> Any:
        value = self._get(key, default)
        if key not in self.data:
            return value
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(f"{key} must be an integer, got {value!r}")
        if minimum is not None and value < minimum:
            raise self.error(f"{key} must be >= {minimum}, got {value!r}")
        return value

    def boolean(self, key: str, default: Any = _MISSING) -> Any:
        value = self._get(key, default)
        if key in self.data and not isinstance(value, bool):
            raise self.error(f"{key} must be true or false, got {value!r}")
        return value

    def string(self, key: str, default: Any = _MISSING, *, choices: Optional[Sequence[str]] = None) -> Any:
        value = self._get(key, default)
        if key not in self.data:
            return value
        if not isinstance(value, str):
            raise self.error(f"{key} must be a string, got {value!r}")
        if choices is not None and value not in choices:
            raise self.error(f"{key} must be one of {', '.join(repr(c) for c in choices)}; got {value!r}")
        return value

    def vec3(self, key: str, default: Any = _MISSING) -> Any:
        value = self._get(key, default)
        if key not in self.data:
            return value
        return _as_vec3(value, lambda: self.error(f"{key} must be a list of 3 numbers, got {value!r}"))

    def path(self, key: str, base_dir: Path, default: Any = _MISSING) -> Any:
        value = self.string(key, default)
        if key not in self.data:
            return value
        if not value:
            raise self.error(f"{key} must not be empty")
        p = Path(value).expanduser()
        return p if p.is_absolute() else (base_dir / p)


def _is_number(c: Any) -> bool:
    return not isinstance(c, bool) and isinstance(c, (int, float)) and math.isfinite(c)


def _as_vec3(value: Any, err: Callable[[], ConfigError]) -> Vec3:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise err()
    out = []
    for c in value:
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not math.isfinite(c):
            raise err()
        out.append(float(c))
    return (out[0], out[1], out[2])


def _known_integrators() -> Tuple[str, ...]:
    """The integrators the compiled core provides (``fepr._core.INTEGRATORS``), else :data:`INTEGRATORS`."""
    try:
        from . import _core

        names = tuple(str(n) for n in _core.INTEGRATORS)
    except (ImportError, AttributeError):
        return INTEGRATORS
    return names or INTEGRATORS


def _mesh_file_exists(p: Path) -> bool:
    """A mesh file, or a TetGen basename whose ``.node``/``.ele`` files exist."""
    if p.is_file():
        return True
    return Path(str(p) + ".node").is_file() or Path(str(p) + ".ele").is_file()


def _parse_mesh(t: _Table, base_dir: Path) -> MeshSettings:
    has_path, has_builtin = t.has("path"), t.has("builtin")
    if has_path == has_builtin:
        raise t.error("give exactly one of 'path' (a mesh file) and 'builtin' (e.g. \"ell\", \"box\")")
    ms = MeshSettings(
        scale=t.number("scale", None, positive=True),
        translate=t.vec3("translate", None),
        fit=t.number("fit", None, positive=True),
        up_axis=t.string("up_axis", None, choices=("y", "z")),
    )
    if t.has("rotate"):
        raw = t.data["rotate"]
        ok = isinstance(raw, list) and len(raw) == 3
        if ok and all(isinstance(r, list) for r in raw):
            ok = all(len(r) == 3 and all(_is_number(c) for c in r) for r in raw)
            value: Any = tuple(tuple(float(c) for c in r) for r in raw)
        else:
            ok = ok and all(_is_number(c) for c in raw)
            value = tuple(float(c) for c in raw) if ok else None
        if not ok:
            raise t.error(f"rotate must be [ax, ay, az] (degrees about x, y, z) or a 3x3 rotation matrix, got {raw!r}")
        ms.rotate = value
    center_point = t.has("center") and isinstance(t.data["center"], list)
    if t.has("center") and not center_point:
        raw = t.data["center"]
        if raw is True:
            raw = "bbox"
        if raw is False:
            raw = None
        if raw is not None and raw not in ("bbox", "centroid"):
            raise t.error(f'center must be "bbox", "centroid", true, false or (builtins) [x, y, z], got {raw!r}')
        ms.center = raw
    from .io.transform import check_load_options

    try:
        check_load_options(**ms.load_options())
    except ConfigError as exc:
        raise t.error(str(exc)) from None
    if has_path:
        for opt in ("size", "resolution", "radius", "height"):
            if t.has(opt):
                raise t.error(f"{opt} applies to builtin meshes only (this scene gives 'path')")
        if center_point:
            raise t.error(
                'center = [x, y, z] applies to builtin meshes only; for a file use center = "bbox" or '
                '"centroid" (and translate)'
            )
        p = t.path("path", base_dir)
        if not _mesh_file_exists(p):
            raise t.error(f"path: mesh file not found: {p}")
        ms.path = p
        return ms
    name = t.string("builtin")
    from . import meshes

    known = getattr(meshes, "BUILTIN", None)
    if known is not None and name not in known:
        raise t.error(f"builtin: unknown built-in mesh {name!r} (known: {', '.join(sorted(known))})")
    ms.builtin = name
    allowed = _BUILTIN_OPTIONS.get(name)
    opts: Dict[str, Any] = {}
    for opt in ("size", "radius", "height", "resolution", "center"):
        if not t.has(opt) or (opt == "center" and not center_point):
            continue
        if allowed is not None and opt not in allowed:
            raise t.error(f"{opt} does not apply to builtin {name!r} (options: {', '.join(allowed)})")
        if opt == "resolution":
            raw = t.data[opt]
            if name == "box" and isinstance(raw, (list, tuple)):
                ok = len(raw) == 3 and all(isinstance(r, int) and not isinstance(r, bool) for r in raw)
                if not ok or min(raw) < 1:
                    raise t.error(f"resolution must be an integer >= 1 or 3 of them, got {raw!r}")
                opts[opt] = tuple(raw)
            else:
                opts[opt] = t.integer(opt, minimum=1)
        elif opt == "center":
            opts[opt] = t.vec3(opt)
        else:  # size: a number, or for a box also [sx, sy, sz]
            raw = t.data[opt]
            if name == "box" and isinstance(raw, (list, tuple)):
                size = t.vec3(opt)
                if min(size) <= 0:
                    raise t.error(f"size must be > 0, got {raw!r}")
                opts[opt] = size
            else:
                s = t.number(opt, positive=True)
                opts[opt] = (s, s, s) if name == "box" else s
    ms.builtin_options = opts
    return ms


def _parse_material(t: _Table) -> MaterialSettings:
    model = t.string("model", "neo_hookean", choices=MATERIAL_MODELS)
    mat = MaterialSettings(
        model=model,
        youngs_modulus=t.number("youngs_modulus", positive=True),
        poisson_ratio=t.number("poisson_ratio", lo=-1.0, hi=0.5),
        j0=t.number("j0", None, positive=True),
    )
    if mat.j0 is not None and model != "neo_hookean":
        raise t.error(f"j0 applies to model 'neo_hookean' only (this scene uses {model!r})")
    return mat


def _parse_mass(t: _Table) -> MassSettings:
    if t.has("node_mass") == t.has("density"):
        raise t.error("give exactly one of 'node_mass' (kg per vertex) and 'density' (kg/m^3)")
    return MassSettings(
        node_mass=t.number("node_mass", None, positive=True), density=t.number("density", None, positive=True)
    )


def _parse_initial(t: _Table, base_dir: Path) -> InitialSettings:
    ini = InitialSettings(
        scale=t.number("scale", 1.0, positive=True),
        translate=t.vec3("translate", None),
        velocity=t.vec3("velocity", None),
        angular_velocity=t.vec3("angular_velocity", None),
        alternating_velocity=t.vec3("alternating_velocity", None),
    )
    if t.has("scale_about"):
        raw = t.data["scale_about"]
        if isinstance(raw, str):
            if raw != "centroid":
                raise t.error(f'scale_about must be [x, y, z] or "centroid", got {raw!r}')
            ini.scale_about = "centroid"
        else:
            ini.scale_about = _as_vec3(
                raw, lambda: t.error(f'scale_about must be [x, y, z] or "centroid", got {raw!r}')
            )
    if t.has("velocities"):
        p = t.path("velocities", base_dir)
        if not p.is_file():
            raise t.error(f"velocities: file not found: {p}")
        ini.velocities = p
    return ini


def _parse_projection(t: _Table) -> ProjectionSettings:
    return ProjectionSettings(
        enabled=t.boolean("enabled", True),
        tolerance=t.number("tolerance", None, positive=True),
        max_iterations=t.integer("max_iterations", None, minimum=1),
        rows=t.string("rows", None, choices=PROJECTION_ROWS),
        c_eps=t.number("c_eps", None, positive=True),
        regularization=t.number("regularization", None),
        max_halvings=t.integer("max_halvings", None, minimum=0),
        impact_bound=t.number("impact_bound", None, positive=True),
        slack=t.string("slack", None, choices=("auto", "on", "off")),
        warm_start=t.number("warm_start", None, nonnegative=True),
        metric=t.string("metric", None, choices=("auto", "mass", "stiffness")),
        quality_guard=t.boolean("quality_guard", None),
        quality_margin=t.number("quality_margin", None, positive=True),
    )


def _parse_pinned(t: _Table, key: str = "pinned") -> Tuple[int, ...]:
    raw = t.data[key]
    ok = isinstance(raw, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in raw)
    if not ok:
        raise t.error(f"{key} must be a list of vertex indices (integers), got {raw!r}")
    if any(i < 0 for i in raw):
        raise t.error(f"{key}: vertex indices must be >= 0, got {raw!r}")
    return tuple(raw)


def _parse_pin_below(t: _Table, key: str = "pin_below") -> PinBelow:
    raw = t.data[key]
    if not isinstance(raw, Mapping):
        raise t.error(f'{key} must be a table {{axis = "z", value = 0.0}}, got {raw!r}')
    unknown = [k for k in raw if k not in ("axis", "value")]
    if unknown:
        raise t.error(f"{key}: unknown key {unknown[0]!r} (known: axis, value)")
    axis = raw.get("axis", "z")
    if axis not in _AXES:
        raise t.error(f'{key}.axis must be "x", "y" or "z", got {axis!r}')
    if "value" not in raw:
        raise t.error(f"{key}: missing required key 'value'")
    value = raw["value"]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise t.error(f"{key}.value must be a number, got {value!r}")
    return PinBelow(axis=axis, value=float(value))


def _list_of_tables(raw: Any, owner: str, key: str, toml_name: str) -> List[Mapping[str, Any]]:
    if not isinstance(raw, list) or not all(isinstance(item, Mapping) for item in raw):
        raise ConfigError(f"{owner} {key} must be a list of tables ([[{toml_name}]] entries), got {raw!r}")
    return list(raw)


def _parse_obstacles(raw: Any, where: str) -> Tuple[ObstacleSettings, ...]:
    items = _list_of_tables(raw, f"{where}[world]", "obstacles", "world.obstacles")
    out = []
    for k, item in enumerate(items, 1):
        label = f"[[world.obstacles]] #{k}"
        types = ", ".join(repr(n) for n in OBSTACLE_KEYS)
        if "type" not in item:
            raise ConfigError(f"{where}{label}: missing required key 'type' (one of {types})")
        kind = item["type"]
        if kind not in OBSTACLE_KEYS:
            raise ConfigError(f"{where}{label}: unknown obstacle type {kind!r} (known: {types})")
        t = _Table(item, "obstacle", where, known=OBSTACLE_COMMON_KEYS + OBSTACLE_KEYS[kind], label=f"{label}:")
        restitution = t.number("restitution", 1.0)
        if not 0.0 <= restitution <= 1.0:
            raise t.error(f"restitution must be in [0, 1], got {restitution!r}")
        friction = t.number("friction", 0.0, nonnegative=True)
        geometry: Dict[str, Any] = {}
        if kind == "plane":
            geometry["point"] = t.vec3("point", (0.0, 0.0, 0.0))
            normal = t.vec3("normal", (0.0, 0.0, 1.0))
            if not any(normal):
                raise t.error("normal must not be the zero vector")
            geometry["normal"] = normal
        elif kind == "sphere":
            geometry["center"] = t.vec3("center")
            geometry["radius"] = t.number("radius", positive=True)
        elif kind == "box":
            geometry["center"] = t.vec3("center")
            if t.has("half_extents") == t.has("size"):
                raise t.error(
                    "give exactly one of 'half_extents' (m, half the edge lengths) and 'size' (m, edge lengths)"
                )
            key = "half_extents" if t.has("half_extents") else "size"
            ext = t.vec3(key)
            if min(ext) <= 0:
                raise t.error(f"{key} must be > 0 in every component, got {list(ext)!r}")
            geometry["half_extents"] = ext if key == "half_extents" else tuple(0.5 * e for e in ext)
            rotation = None
            if t.has("rotate"):
                from .io.transform import _rotation

                try:
                    r = _rotation(t.data["rotate"])
                except ConfigError as exc:
                    raise t.error(str(exc)) from None
                # fepr.Box takes the box's local axes in world coordinates as rows: the columns of R.
                rotation = tuple(tuple(float(c) for c in row) for row in np.asarray(r).T)
            geometry["rotation"] = rotation
        else:  # capsule
            geometry["a"] = t.vec3("a")
            geometry["b"] = t.vec3("b")
            geometry["radius"] = t.number("radius", positive=True)
        out.append(
            ObstacleSettings(type=kind, geometry=geometry, restitution=restitution, friction=friction, label=label)
        )
    return tuple(out)


def _parse_kinematic_pins(
    raw: Any, where: str, owner: str, prefix: str, toml_name: str
) -> Tuple[KinematicPinSettings, ...]:
    """``owner`` names the table holding the list (``[world]``), ``prefix`` the list in messages
    (``[[world.kinematic_pins]]``), ``toml_name`` its TOML name (``world.kinematic_pins``)."""
    items = _list_of_tables(raw, f"{where}{owner}", "kinematic_pins", toml_name)
    out = []
    for k, item in enumerate(items, 1):
        label = f"{prefix} #{k}"
        t = _Table(item, "kinematic_pin", where, known=KINEMATIC_PIN_KEYS, label=f"{label}:")
        if t.has("vertices") == t.has("below"):
            raise t.error("give exactly one of 'vertices' (vertex indices) and 'below' ({axis, value})")
        kp = KinematicPinSettings(motion="", label=label)
        if t.has("vertices"):
            kp.vertices = _parse_pinned(t, "vertices")
            if not kp.vertices:
                raise t.error("vertices must not be empty")
        else:
            kp.below = _parse_pin_below(t, "below")
        kp.motion = t.string("motion", choices=tuple(MOTIONS))
        for other, keys in MOTIONS.items():
            if other == kp.motion:
                continue
            for key in keys:
                if t.has(key):
                    raise t.error(
                        f"{key} does not apply to motion {kp.motion!r} (its keys: {', '.join(MOTIONS[kp.motion])})"
                    )
        if kp.motion == "sinusoidal":
            kp.amplitude = t.vec3("amplitude")
            kp.frequency = t.number("frequency", positive=True)
            kp.phase = t.number("phase", 0.0)
        else:
            times = t.data.get("times", _MISSING)
            if times is _MISSING:
                raise t.error("missing required key 'times'")
            if not isinstance(times, list) or not times or not all(_is_number(c) for c in times):
                raise t.error(f"times must be a non-empty list of numbers (s), got {times!r}")
            if any(b <= a for a, b in zip(times, times[1:])):
                raise t.error(f"times must be strictly increasing, got {times!r}")
            offsets = t.data.get("offsets", _MISSING)
            if offsets is _MISSING:
                raise t.error("missing required key 'offsets'")
            if not isinstance(offsets, list):
                raise t.error(f"offsets must be a list of [x, y, z] vectors (m), got {offsets!r}")
            if len(offsets) != len(times):
                raise t.error(f"offsets has {len(offsets)} entries but times has {len(times)}")
            kp.times = tuple(float(c) for c in times)
            vecs = []
            for j, o in enumerate(offsets, 1):
                bad = t.error(f"offsets #{j} must be a list of 3 numbers (m), got {o!r}")
                vecs.append(_as_vec3(o, lambda bad=bad: bad))
            kp.offsets = tuple(vecs)
        out.append(kp)
    return tuple(out)


_BODY_PIN_KEYS = ("pinned", "pin_below", "kinematic_pins")


def _parse_world(t: _Table, multibody: bool = False) -> WorldSettings:
    w = WorldSettings(
        gravity=t.vec3("gravity", (0.0, 0.0, 0.0)),
        damping=t.number("damping", 0.0, nonnegative=True),
        air_damping=t.number("air_damping", 0.0, nonnegative=True),
        rayleigh_damping=t.number("rayleigh_damping", 0.0, nonnegative=True),
        force=t.vec3("force", None),
    )
    if multibody:
        for key in _BODY_PIN_KEYS:
            if t.has(key):
                raise t.error(f"{key} is per body in a scene with [[bodies]]: give it in the [[bodies]] tables")
    if t.has("pinned"):
        w.pinned = _parse_pinned(t)
    if t.has("pin_below"):
        w.pin_below = _parse_pin_below(t)
    if t.has("obstacles"):
        w.obstacles = _parse_obstacles(t.data["obstacles"], t.where)
    if t.has("kinematic_pins"):
        w.kinematic_pins = _parse_kinematic_pins(
            t.data["kinematic_pins"], t.where, "[world]", "[[world.kinematic_pins]]", "world.kinematic_pins"
        )
    return w


def _parse_export(t: _Table) -> ExportSettings:
    ex = ExportSettings(every=t.integer("every", 1, minimum=1))
    if t.has("formats"):
        raw = t.data["formats"]
        if not isinstance(raw, list) or not all(isinstance(f, str) for f in raw):
            raise t.error(f'formats must be a list of format names such as ["vtu", "glb"], got {raw!r}')
        from .export import parse_formats

        try:
            ex.formats = parse_formats(raw) if raw else ()
        except ConfigError as exc:
            raise t.error(f"formats: {exc}") from None
    return ex


_BODY_SECTIONS = ("mesh", "material", "mass", "initial")
_NAME_RE = re.compile(r"[A-Za-z0-9_.\-]+")


def _parse_bodies(raw: Any, where: str, base: Path) -> Tuple[BodySettings, ...]:
    if not isinstance(raw, list) or not raw or not all(isinstance(item, Mapping) for item in raw):
        raise ConfigError(f"{where}bodies must be a non-empty list of tables ([[bodies]] entries), got {raw!r}")
    items: List[Mapping[str, Any]] = list(raw)
    out = []
    seen: Dict[str, int] = {}
    for k, item in enumerate(items, 1):
        label = f"[[bodies]] #{k}"
        bt = _Table(item, "body", where, known=BODY_KEYS, label=f"{label}:")
        for sec in ("mesh", "material", "mass"):
            if sec not in item:
                raise bt.error(f"missing required table {sec!r} (e.g. {sec} = {{ ... }} or [bodies.{sec}])")
        for sec in _BODY_SECTIONS:
            if sec in item and not isinstance(item[sec], Mapping):
                raise bt.error(f"{sec} must be a table of keys, got {item[sec]!r}")

        def sub(sec: str, label: str = label, item: Mapping[str, Any] = item) -> _Table:
            return _Table(item.get(sec, {}), sec, where, label=f"{label} [{sec}]")

        name = bt.string("name", f"body{k}")
        if not _NAME_RE.fullmatch(name) or name in (".", ".."):
            raise bt.error(f"name must be letters, digits, '_', '-' or '.' (it names output files), got {name!r}")
        if name in seen:
            raise bt.error(f"name {name!r} is already used by [[bodies]] #{seen[name]}")
        seen[name] = k
        body = BodySettings(
            name=name,
            mesh=_parse_mesh(sub("mesh"), base),
            material=_parse_material(sub("material")),
            mass=_parse_mass(sub("mass")),
            initial=_parse_initial(sub("initial"), base),
            label=label,
        )
        if bt.has("pinned"):
            body.pinned = _parse_pinned(bt)
        if bt.has("pin_below"):
            body.pin_below = _parse_pin_below(bt)
        if bt.has("kinematic_pins"):
            body.kinematic_pins = _parse_kinematic_pins(
                item["kinematic_pins"], where, f"{label}:", f"{label} [[kinematic_pins]]", "bodies.kinematic_pins"
            )
        out.append(body)
    return tuple(out)


def scene_from_dict(d: Mapping[str, Any], base_dir: Union[str, Path] = ".", *, source: Optional[str] = None) -> Scene:
    """Validate a scene given as a dict (the parsed TOML) into a :class:`Scene`.

    Parameters
    ----------
    d : mapping
        Sections (``mesh``, ``material``, ``mass``, ``initial``, ``integrator``, ``projection``, ``world``,
        ``run``, ``export``, ``scene``), each a mapping of keys to values, as in a scene file; or, for several
        bodies, ``bodies``: a list of body tables (:data:`BODY_KEYS`) instead of ``mesh``, ``material``,
        ``mass`` and ``initial``.
    base_dir : str or Path
        Folder that relative paths (``[mesh] path``, ``[initial] velocities``) are resolved against.
    source : str, optional
        Name used at the start of error messages (the scene file).

    Raises
    ------
    ConfigError
        On an unknown section or key, a missing required key, or a value of the wrong type or out of range;
        the message names the section (and for list entries such as ``[[world.obstacles]] #2`` the position,
        counted from 1) and the key.
    """
    where = f"{source}: " if source else ""
    base = Path(base_dir)
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where}a scene must be a table of sections, got {type(d).__name__}")
    for name, value in d.items():
        if name == "bodies":
            continue
        if name not in SCENE_KEYS:
            known = ", ".join(list(SCENE_KEYS) + ["[bodies]"])
            raise ConfigError(f"{where}unknown section [{name}] (known: {known})")
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}[{name}] must be a section (a table of keys), got {value!r}")
    multibody = "bodies" in d
    if multibody:
        for sec in _BODY_SECTIONS:
            if sec in d:
                raise ConfigError(
                    f"{where}[{sec}] is not allowed in a scene with [[bodies]]: give {sec} in each [[bodies]] table"
                )
    else:
        for required in ("mesh", "material", "mass"):
            if required not in d:
                raise ConfigError(f"{where}missing section [{required}]")

    def table(name: str) -> _Table:
        return _Table(d.get(name, {}), name, where)

    meta = table("scene")
    default_name = Path(source).stem if source else "scene"
    name = meta.string("name", default_name)
    description = meta.string("description", "")

    if multibody:
        bodies = _parse_bodies(d["bodies"], where, base)
        one: Dict[str, Any] = {}
    else:
        bodies = ()
        one = {
            "mesh": _parse_mesh(table("mesh"), base),
            "material": _parse_material(table("material")),
            "mass": _parse_mass(table("mass")),
            "initial": _parse_initial(table("initial"), base),
        }
    integ = table("integrator")
    run = table("run")
    return Scene(
        name=name,
        description=description,
        bodies=bodies,
        **one,
        integrator=IntegratorSettings(
            name=integ.string("name", "symplectic_euler", choices=_known_integrators()),
            dt=integ.number("dt", 1.0 / 30.0, positive=True),
            tolerance=integ.number("tolerance", None, positive=True),
            max_iterations=integ.integer("max_iterations", None, minimum=1),
            iterations=integ.integer("iterations", None, minimum=1),
            substeps=integ.integer("substeps", None, minimum=1),
        ),
        projection=_parse_projection(table("projection")),
        world=_parse_world(table("world"), multibody=multibody),
        run=RunSettings(steps=run.integer("steps", 100, minimum=0), threads=run.integer("threads", None, minimum=1)),
        export=_parse_export(table("export")),
        source=source,
        base_dir=base,
    )


def load_scene(path: Union[str, Path]) -> Scene:
    """Read and validate a scene file (TOML). Relative paths inside it are relative to the file.

    Raises
    ------
    ConfigError
        If the file does not exist, is not valid TOML, or any entry is invalid (see :func:`scene_from_dict`).
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"scene file not found: {p}")
    try:
        with open(p, "rb") as fh:
            data = _toml.load(fh)
    except _toml.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: invalid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read scene file: {exc}") from None
    return scene_from_dict(data, p.resolve().parent, source=str(path))


# --------------------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------------------


@dataclass
class RunResult:
    """What :func:`run_scene` did, with the summary of the run (:mod:`fepr.report.metrics`).

    ``metrics`` is the full summary (:class:`fepr.report.metrics.RunMetrics`), computed from the run's history
    like every other command's; the fields below are filled from it. ``max_energy_error`` and
    ``final_energy_error``: the energy error against the books, ``|H - (H0 + budget_total)| / |H0|`` (``H0``
    replaced by ``K0 + |E_el0| + |E_grav0|``, or ``m_tot |g| r``, when it is near zero), the largest over the run
    and at its end. ``momentum_error`` and ``angular_momentum_error``: the largest drift over the run of ``P``
    and ``L`` (about the centre of mass) from their targets, ``P0`` and ``L0`` plus every external impulse so far
    (gravity, obstacles, forces, damping; history columns ``px_target ... lz_target``), relative to
    ``p_scale = max(|P0|, max |P_target|, sqrt(2 m_tot (K0 + |E_el0|)))`` and ``max(|L0|, r p_scale)``, ``r`` half
    the rest shape's bounding-box diagonal; ``None`` when vertices are pinned (the supports' impulses are not
    known). ``mean_iterations`` and ``max_iterations``: the projection's iterations per step.
    ``base_unstable_step`` is the first step the simulation flagged as a runaway of the base integrator
    (its own energy error above 100%; with FEPR on, the projection may still keep the state bounded), and
    ``warnings`` the messages of the warnings issued while stepping, plus the end-of-run warning when the run
    ends with inverted tets, had unconverged projections or left more than 1e-3 of its energy unresolved
    (:attr:`problems`). With exports, ``export_dir``,
    ``export_frames``, ``export_formats`` and ``export_fps`` (frames per simulated second) say what was
    written; ``wall_s`` leaves out the time spent writing them.
    """

    scene: str
    projection: bool
    steps_requested: int
    steps_completed: int
    wall_s: float
    runaway_step: Optional[int] = None
    runaway_message: Optional[str] = None
    max_energy_error: float = float("nan")
    final_energy_error: float = float("nan")
    momentum_error: Optional[float] = None
    angular_momentum_error: Optional[float] = None
    mean_iterations: Optional[float] = None
    max_iterations: Optional[int] = None
    base_unstable_step: Optional[int] = None
    warnings: List[str] = field(default_factory=list)
    diagnostics_path: Optional[Path] = None
    state_path: Optional[Path] = None
    simulation: Any = None
    export_dir: Optional[Path] = None
    export_frames: int = 0
    export_formats: Tuple[str, ...] = ()
    export_fps: Optional[float] = None
    bodies: Tuple[str, ...] = ()
    body_diagnostics_paths: Dict[str, Path] = field(default_factory=dict)
    metrics: Any = None  # fepr.report.metrics.RunMetrics

    @property
    def ms_per_step(self) -> float:
        """Wall time per completed step, milliseconds."""
        return 1e3 * self.wall_s / self.steps_completed if self.steps_completed else float("nan")

    @property
    def runaway(self) -> bool:
        return self.runaway_step is not None

    @property
    def problems(self) -> List[str]:
        """What makes the run untrustworthy, as short phrases: a runaway, inverted tets at the end, unconverged
        projections, unresolved energy above 1e-3 of the energy scale
        (:meth:`fepr.report.metrics.RunMetrics.problems`; empty: none)."""
        if self.metrics is None:
            return [f"runaway at step {self.runaway_step}"] if self.runaway else []
        return self.metrics.problems()

    def summary(self) -> str:
        """One line, the same as every command prints (:meth:`fepr.report.metrics.RunMetrics.summary_line`):
        steps, energy error against the books, unresolved energy, P and L drift against the targets, min J,
        inverted tets, unconverged projections, iterations, substeps, ms per step, then the problems."""
        label = f"{self.scene} (FEPR {'on' if self.projection else 'off'})"
        if self.metrics is None:
            return f"{label}: {self.steps_completed} steps"
        return self.metrics.summary_line(label)


def _history_from(sim, rows_before: int) -> Dict[str, np.ndarray]:
    """The history columns of ``sim`` (with the momentum targets of a multi-body system) from the row before
    the first new step, so that a run of an already stepped simulation is measured from where it started."""
    from .report.metrics import simulation_history

    h = simulation_history(sim)
    start = max(rows_before - 1, 0)
    return {k: v[start:] for k, v in h.items()} if start else h


def _measure(result: RunResult, sim, rows_before: int, pinned: bool) -> None:
    """Fill in the summary of ``result`` (:func:`fepr.report.metrics.simulation_metrics`) and the fields that
    repeat it."""
    from .report.metrics import simulation_metrics

    m = simulation_metrics(
        sim,
        projection=result.projection,
        pinned=pinned,
        runaway_step=result.runaway_step,
        history=_history_from(sim, rows_before),
    )
    result.metrics = m
    result.max_energy_error = m.energy_error
    result.final_energy_error = m.final_energy_error
    result.momentum_error = m.p_drift
    result.angular_momentum_error = m.l_drift
    result.mean_iterations = m.mean_iterations
    result.max_iterations = m.max_iterations
    result.base_unstable_step = m.base_unstable_step


def _warn_problems(result: RunResult) -> None:
    """Warn (and record in ``result.warnings``) when the run ends with inverted tets, had unconverged projections
    or left more than :data:`fepr.report.metrics.UNRESOLVED_LIMIT` of its energy unresolved."""
    from .report.metrics import RunProblemWarning

    text = None if result.metrics is None else result.metrics.warning_text(f"{result.scene}: the run")
    if text is None:
        return
    result.warnings.append(text)
    warnings.warn(text, RunProblemWarning, stacklevel=3)


def _write_diagnostics(sim, path: Path) -> None:
    """``diagnostics.csv``: the history of a simulation; for a multi-body system its totals with the momentum
    targets and the other columns :func:`fepr.report.metrics.system_history` adds (so that the summary can be
    recomputed from the file)."""
    from .multibody import MultiBody

    if not isinstance(sim, MultiBody):
        sim.save_diagnostics(str(path))
        return
    from .report.metrics import system_history
    from .simulation import History

    cols = system_history(sim)
    names = list(cols)
    data = np.stack([cols[c] for c in names], axis=1) if len(cols[names[0]]) else np.zeros((0, len(names)))
    History(data, names).to_csv(path)


def _projection_on(scene: Scene, override) -> bool:
    if override is not None:
        return override is not False
    return scene.projection.enabled


def _export_recorders(scene: Scene, sim, out_dir, export, export_every) -> list:
    """The :class:`fepr.export.Recorder` objects of a run (none when nothing is exported).

    One-body scene: one recorder in ``out_dir/export`` named after the scene. Multi-body scene (``sim`` a
    :class:`fepr.multibody.MultiBody`): one per body in ``out_dir/export/<body>``, named ``<scene>_<body>``,
    each with its own material (for the energy density field)."""
    from .multibody import MultiBody

    if not isinstance(sim, MultiBody):
        rec = _export_recorder(scene, sim, out_dir, export, export_every)
        return [] if rec is None else [rec]
    recs = []
    for name, body in zip(sim.names, sim.bodies):
        rec = _export_recorder(scene, body, out_dir, export, export_every, body=name)
        if rec is None:
            return []
        recs.append(rec)
    return recs


def _export_recorder(scene: Scene, sim, out_dir, export, export_every, body: Optional[str] = None):
    """The :class:`fepr.export.Recorder` for ``out_dir/export`` (``out_dir/export/<body>`` for a body of a
    multi-body scene), or ``None`` when nothing is exported."""
    from .export import parse_formats

    formats = scene.export.formats if export is None else parse_formats(export)
    every = scene.export.every if export_every is None else export_every
    if not formats:
        if export_every is not None:
            raise ConfigError("export_every needs export formats (--export or [export] formats)")
        return None
    if out_dir is None:
        if export is None:
            return None
        raise ConfigError("export needs an output folder (out_dir)")
    from .export import Recorder

    name = re.sub(r"[^A-Za-z0-9_.\-]", "_", scene.name).strip(".") or "frame"
    folder = Path(out_dir) / "export"
    if body is not None:
        name, folder = f"{name}_{body}", folder / body
    return Recorder(sim, folder, formats, every=every, name=name)


def run_scene(
    scene: Scene,
    *,
    steps: Optional[int] = None,
    out_dir: Union[str, Path, None] = None,
    projection=None,
    progress: Optional[Callable[[int, int, Any], None]] = None,
    export: Union[str, Sequence[str], None] = None,
    export_every: Optional[int] = None,
) -> RunResult:
    """Build and run a scene; optionally write ``diagnostics.csv`` and ``final_state.npz`` to ``out_dir``.

    Parameters
    ----------
    scene : Scene
        The validated scene.
    steps : int, optional
        Number of steps (default: ``[run] steps``).
    out_dir : str or Path, optional
        Folder for ``diagnostics.csv`` (one row per step plus the initial row) and ``final_state.npz``;
        created if needed. Nothing is written when ``None``.
    projection : bool or fepr.Projection, optional
        Overrides ``[projection]`` (``False``: FEPR off).
    progress : callable, optional
        Called as ``progress(steps_done, steps_total, sim)`` before the first step and after every tenth
        of the run.
    export : str or sequence of str, optional
        Export formats (``"vtu,glb"``; :data:`fepr.export.FORMATS`), overriding ``[export] formats``. With
        formats from either and an ``out_dir``, every ``every``-th step (the initial state first) is written
        to ``out_dir/export`` by a :class:`fepr.export.Recorder` named after the scene; without ``out_dir``
        nothing is exported (an explicit ``export`` then raises :class:`fepr.ConfigError`).
    export_every : int, optional
        Overrides ``[export] every``.

    Returns
    -------
    RunResult
        Steps completed, whether and where the run ran away, conservation errors, iterations and timing.
        A runaway (:class:`fepr.SimulationError` from ``step``) does not raise: the files are written with
        the steps completed so far and the result says where it stopped.
    """
    n = scene.run.steps if steps is None else int(steps)
    if n < 0:
        raise ConfigError(f"steps must be >= 0, got {n}")
    sim = scene.build_multibody(projection=projection) if scene.is_multibody else scene.build(projection=projection)
    rows_before = len(sim.history)
    # The supports' impulses are not known: no momentum drift to measure. (Obstacles, forces and air drag are
    # in the momentum targets of the history.)
    pinned = scene.has_supports()
    result = RunResult(
        scene=scene.name,
        projection=_projection_on(scene, projection),
        steps_requested=n,
        steps_completed=0,
        wall_s=0.0,
        simulation=sim,
        bodies=tuple(sim.names) if scene.is_multibody else (),
    )
    chunk = max(1, n // 10)
    done = 0
    start_steps = int(sim.num_steps)
    recorders = _export_recorders(scene, sim, out_dir, export, export_every)
    next_report = chunk
    if progress is not None:
        progress(0, n, sim)
    t_start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            for rec in recorders:
                rec.record()
            while done < n:
                k = min(chunk, n - done)
                if recorders:  # stop at every frame to export (the recorders share the same frames)
                    k = min(k, min(rec.steps_to_next() for rec in recorders))
                sim.step(k)
                done += k
                for rec in recorders:
                    rec.record()
                if progress is not None and (done >= next_report or done == n):
                    next_report = (done // chunk + 1) * chunk
                    progress(done, n, sim)
        except SimulationError as exc:
            completed = int(sim.num_steps) - start_steps
            step_attr = getattr(exc, "step", None)
            result.runaway_step = int(step_attr) if isinstance(step_attr, int) else int(sim.num_steps) + 1
            result.runaway_message = str(exc)
            done = completed
        finally:
            for rec in recorders:
                rec.close()
    result.wall_s = time.perf_counter() - t_start
    if recorders:  # the time spent writing exports is not simulation time
        result.wall_s = max(result.wall_s - sum(rec.write_s for rec in recorders), 0.0)
        result.export_dir = recorders[0].out_dir if len(recorders) == 1 else recorders[0].out_dir.parent
        result.export_frames = recorders[0].num_frames
        result.export_formats = recorders[0].formats
        result.export_fps = recorders[0].fps
    result.warnings = [str(w.message) for w in caught]
    result.steps_completed = int(sim.num_steps) - start_steps if result.runaway else done
    # The summary (fepr.report.metrics), as every command reports it; base_unstable_step is the first step whose
    # base energy error exceeded 100% of the energy scale, whether or not a converged projection rescued it.
    _measure(result, sim, rows_before, bool(pinned))
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        result.diagnostics_path = out / "diagnostics.csv"
        result.state_path = out / "final_state.npz"
        _write_diagnostics(sim, result.diagnostics_path)
        sim.save_state(str(result.state_path))
        if scene.is_multibody:
            for name, body in zip(sim.names, sim.bodies):
                path = out / f"diagnostics_{name}.csv"
                body.save_diagnostics(str(path))
                result.body_diagnostics_paths[name] = path
    _warn_problems(result)
    return result
