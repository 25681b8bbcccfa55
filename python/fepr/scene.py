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
    "initial": ("scale", "scale_about", "velocity", "angular_velocity", "velocities", "alternating_velocity"),
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
    ),
    "world": ("gravity", "pinned", "pin_below", "damping"),
    "run": ("steps", "threads"),
    "export": ("formats", "every"),
}

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
    at rest.
    """

    scale: float = 1.0
    scale_about: Union[Vec3, str, None] = None
    velocity: Optional[Vec3] = None
    angular_velocity: Optional[Vec3] = None
    velocities: Optional[Path] = None
    alternating_velocity: Optional[Vec3] = None

    def is_rest(self) -> bool:
        """True if the initial state is the rest shape at rest."""
        return self.scale == 1.0 and not any(
            v is not None for v in (self.velocity, self.angular_velocity, self.velocities, self.alternating_velocity)
        )


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
class WorldSettings:
    """``[world]``: gravity (m/s^2), pinned vertices, and damping."""

    gravity: Vec3 = (0.0, 0.0, 0.0)
    pinned: Tuple[int, ...] = ()
    pin_below: Optional[PinBelow] = None
    damping: float = 0.0


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

    ``source`` is the scene file (used in messages), ``base_dir`` the folder relative paths were resolved
    against.
    """

    name: str
    mesh: MeshSettings
    material: MaterialSettings
    mass: MassSettings
    initial: InitialSettings = field(default_factory=InitialSettings)
    integrator: IntegratorSettings = field(default_factory=IntegratorSettings)
    projection: ProjectionSettings = field(default_factory=ProjectionSettings)
    world: WorldSettings = field(default_factory=WorldSettings)
    run: RunSettings = field(default_factory=RunSettings)
    export: ExportSettings = field(default_factory=ExportSettings)
    description: str = ""
    source: Optional[str] = None
    base_dir: Path = field(default_factory=Path.cwd)

    # ---- building ------------------------------------------------------------------------------------

    def _where(self) -> str:
        return f"{self.source}: " if self.source else ""

    def load_mesh(self):
        """The rest mesh (:class:`fepr.TetMesh`) after the ``[mesh]`` load options."""
        import fepr

        m = self.mesh
        where = self._where()
        if m.path is not None:
            try:
                return fepr.load_mesh(str(m.path), **m.load_options())
            except MeshError as exc:
                msg = str(exc)
                if str(m.path) not in msg and m.path.name not in msg:
                    msg = f"{m.path}: {msg}"
                raise MeshError(f"{where}[mesh] {msg}") from None
        assert m.builtin is not None
        try:
            from . import meshes

            mesh = meshes.builtin(m.builtin, **m.builtin_options)
        except (ConfigError, MeshError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"{where}[mesh] builtin {m.builtin!r}: {exc}") from None
        if m.load_options():
            from .io import transform_mesh

            try:
                mesh = transform_mesh(mesh, **m.load_options())
            except ConfigError as exc:
                raise ConfigError(f"{where}[mesh] {exc}") from None
        return mesh

    def make_material(self):
        """The material object (:class:`fepr.NeoHookean`, :class:`fepr.StableNeoHookean`, ...)."""
        import fepr

        mat = self.material
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
            raise ConfigError(f"{self._where()}[material] {exc}") from None

    def pinned_indices(self, rest_vertices: np.ndarray) -> Optional[np.ndarray]:
        """Sorted indices of the pinned vertices (``[world] pinned`` and ``pin_below``), or ``None``."""
        where = self._where()
        m = len(rest_vertices)
        idx: List[int] = []
        for i in self.world.pinned:
            if not 0 <= i < m:
                raise ConfigError(f"{where}[world] pinned: vertex index {i} out of range (mesh has {m} vertices)")
            idx.append(i)
        pb = self.world.pin_below
        if pb is not None:
            coord = rest_vertices[:, _AXES[pb.axis]]
            below = np.flatnonzero(coord <= pb.value)
            if below.size == 0:
                raise ConfigError(
                    f"{where}[world] pin_below: no vertex has {pb.axis} <= {pb.value} "
                    f"(lowest {pb.axis} is {coord.min():.6g})"
                )
            idx.extend(int(i) for i in below)
        if not idx:
            return None
        return np.unique(np.asarray(idx, dtype=np.int64))

    def initial_state(
        self, rest_vertices: np.ndarray, masses: np.ndarray, pinned: Optional[np.ndarray] = None
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Initial positions and velocities, each (m, 3) float64, from the rest vertices and masses (kg)."""
        where = self._where()
        ini = self.initial
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
        return x, v

    def build(self, projection=None):
        """Build the :class:`fepr.Simulation` this scene describes, in its initial state.

        Parameters
        ----------
        projection : bool or fepr.Projection, optional
            Overrides ``[projection]`` (``False`` turns FEPR off, as ``fepr run --no-projection`` does).

        Raises
        ------
        ConfigError
            If a value is rejected (the message names the scene file and section).
        MeshError
            If the mesh file cannot be read or is invalid.
        """
        import fepr

        where = self._where()
        mesh = self.load_mesh()
        material = self.make_material()
        if projection is None:
            try:
                projection = self.projection.make()
            except ConfigError as exc:
                raise ConfigError(f"{where}[projection] {exc}") from None
        pinned = self.pinned_indices(np.asarray(mesh.vertices))
        kwargs: Dict[str, Any] = {}
        if self.mass.node_mass is not None:
            kwargs["node_mass"] = self.mass.node_mass
        else:
            kwargs["density"] = self.mass.density
        if self.run.threads is not None:
            kwargs["threads"] = self.run.threads
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
            raise ConfigError(f"{where}{exc}") from None
        if not self.initial.is_rest():
            x, v = self.initial_state(np.asarray(sim.rest_positions), np.asarray(sim.masses), pinned)
            if self.initial.scale != 1.0:
                sim.positions = x
            if np.any(v):
                sim.velocities = v
        return sim


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
        raise ConfigError(f"{where}[initial] velocities: cannot read {path}: {exc}") from None
    if not isinstance(arr, np.ndarray):
        raise ConfigError(f"{where}[initial] velocities: {path} must hold one array (a .npy file)")
    if arr.shape != (m, 3):
        raise ConfigError(f"{where}[initial] velocities: {path} has shape {arr.shape}, expected ({m}, 3)")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{where}[initial] velocities: {path} contains NaN or infinite values")
    return arr


# --------------------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------------------


class _Table:
    """One section of a scene: typed accessors that raise ConfigError naming the section and key."""

    def __init__(self, data: Mapping[str, Any], section: str, where: str):
        self.data = data
        self.section = section
        self.where = where
        known = SCENE_KEYS[section]
        for key in data:
            if key not in known:
                raise self.error(f"unknown key {key!r} (known: {', '.join(known)})")

    def error(self, msg: str) -> ConfigError:
        return ConfigError(f"{self.where}[{self.section}] {msg}")

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
        warm_start=t.number("warm_start", None, positive=True),
        metric=t.string("metric", None, choices=("auto", "mass", "stiffness")),
    )


def _parse_world(t: _Table) -> WorldSettings:
    w = WorldSettings(gravity=t.vec3("gravity", (0.0, 0.0, 0.0)), damping=t.number("damping", 0.0, nonnegative=True))
    if t.has("pinned"):
        raw = t.data["pinned"]
        ok = isinstance(raw, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in raw)
        if not ok:
            raise t.error(f"pinned must be a list of vertex indices (integers), got {raw!r}")
        if any(i < 0 for i in raw):
            raise t.error(f"pinned: vertex indices must be >= 0, got {raw!r}")
        w.pinned = tuple(raw)
    if t.has("pin_below"):
        raw = t.data["pin_below"]
        if not isinstance(raw, dict):
            raise t.error(f'pin_below must be a table {{axis = "z", value = 0.0}}, got {raw!r}')
        unknown = [k for k in raw if k not in ("axis", "value")]
        if unknown:
            raise t.error(f"pin_below: unknown key {unknown[0]!r} (known: axis, value)")
        axis = raw.get("axis", "z")
        if axis not in _AXES:
            raise t.error(f'pin_below.axis must be "x", "y" or "z", got {axis!r}')
        if "value" not in raw:
            raise t.error("pin_below: missing required key 'value'")
        value = raw["value"]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise t.error(f"pin_below.value must be a number, got {value!r}")
        w.pin_below = PinBelow(axis=axis, value=float(value))
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


def scene_from_dict(d: Mapping[str, Any], base_dir: Union[str, Path] = ".", *, source: Optional[str] = None) -> Scene:
    """Validate a scene given as a dict (the parsed TOML) into a :class:`Scene`.

    Parameters
    ----------
    d : mapping
        Sections (``mesh``, ``material``, ``mass``, ``initial``, ``integrator``, ``projection``, ``world``,
        ``run``, ``scene``), each a mapping of keys to values, as in a scene file.
    base_dir : str or Path
        Folder that relative paths (``[mesh] path``, ``[initial] velocities``) are resolved against.
    source : str, optional
        Name used at the start of error messages (the scene file).

    Raises
    ------
    ConfigError
        On an unknown section or key, a missing required key, or a value of the wrong type or out of range;
        the message names the section and the key.
    """
    where = f"{source}: " if source else ""
    base = Path(base_dir)
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where}a scene must be a table of sections, got {type(d).__name__}")
    for name, value in d.items():
        if name not in SCENE_KEYS:
            raise ConfigError(f"{where}unknown section [{name}] (known: {', '.join(SCENE_KEYS)})")
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}[{name}] must be a section (a table of keys), got {value!r}")
    for required in ("mesh", "material", "mass"):
        if required not in d:
            raise ConfigError(f"{where}missing section [{required}]")

    def table(name: str) -> _Table:
        return _Table(d.get(name, {}), name, where)

    meta = table("scene")
    default_name = Path(source).stem if source else "scene"
    name = meta.string("name", default_name)
    description = meta.string("description", "")

    integ = table("integrator")
    run = table("run")
    return Scene(
        name=name,
        description=description,
        mesh=_parse_mesh(table("mesh"), base),
        material=_parse_material(table("material")),
        mass=_parse_mass(table("mass")),
        initial=_parse_initial(table("initial"), base),
        integrator=IntegratorSettings(
            name=integ.string("name", "symplectic_euler", choices=_known_integrators()),
            dt=integ.number("dt", 1.0 / 30.0, positive=True),
            tolerance=integ.number("tolerance", None, positive=True),
            max_iterations=integ.integer("max_iterations", None, minimum=1),
            iterations=integ.integer("iterations", None, minimum=1),
            substeps=integ.integer("substeps", None, minimum=1),
        ),
        projection=_parse_projection(table("projection")),
        world=_parse_world(table("world")),
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
    """What :func:`run_scene` did, with the conservation measures of the run.

    Relative errors: energy ``|H - H0| / |H0|`` (``H0`` replaced by ``K0 + |E_el0| + |E_grav0|`` when it is
    near zero); momentum ``|P - P_expected| / p_scale`` with ``P_expected = P0 + m_tot g t`` and
    ``p_scale = max(|P_expected|, |P0|, sqrt(2 m_tot (K0 + |E_el0|)))``; angular momentum (about the centre of
    mass) ``|L - L0| / max(|L0|, r_g p_scale)`` with ``r_g`` the radius of gyration of the initial shape.
    Momentum errors are ``None`` when vertices are pinned (the supports exchange momentum with the body).
    ``base_unstable_step`` is the first step the simulation flagged as a runaway of the base integrator
    (its own energy error above 100%; with FEPR on, the projection may still keep the state bounded), and
    ``warnings`` the messages of the warnings issued while stepping. With exports, ``export_dir``,
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

    @property
    def ms_per_step(self) -> float:
        """Wall time per completed step, milliseconds."""
        return 1e3 * self.wall_s / self.steps_completed if self.steps_completed else float("nan")

    @property
    def runaway(self) -> bool:
        return self.runaway_step is not None

    def summary(self) -> str:
        """One line: steps, |H/H0-1|, |dP|, |dL|, mean projection iterations, ms per step."""
        head = (
            f"runaway at step {self.runaway_step} after {self.steps_completed} steps"
            if self.runaway
            else f"{self.steps_completed} steps"
        )
        iters = "projection off" if self.mean_iterations is None else f"{self.mean_iterations:.2f} proj. iters/step"
        energy = f"|H/H0-1| = {self.final_energy_error:.3g} (max {self.max_energy_error:.3g})"
        dp, dl = _fmt_opt(self.momentum_error), _fmt_opt(self.angular_momentum_error)
        fepr = "on" if self.projection else "off"
        return (
            f"{self.scene} (FEPR {fepr}): {head}, {energy}, |dP| = {dp}, |dL| = {dl} (relative), "
            f"{iters}, {self.ms_per_step:.3g} ms/step"
        )


def _fmt_opt(x: Optional[float]) -> str:
    return "n/a" if x is None else f"{x:.3g}"


def _column(hist, name: str) -> Optional[np.ndarray]:
    cols = list(hist.columns)
    if name not in cols:
        return None
    return np.asarray(hist[name], dtype=np.float64)


@dataclass
class _Snapshot:
    """The invariants of one state, measured directly (not from the history)."""

    time: float
    kinetic: float
    elastic: float
    gravitational: float
    total: float
    momentum: np.ndarray
    angular_momentum: np.ndarray


def _snapshot(sim) -> _Snapshot:
    e = sim.energy()
    return _Snapshot(
        time=float(sim.time),
        kinetic=float(e.kinetic),
        elastic=float(e.elastic),
        gravitational=float(e.gravitational),
        total=float(e.total),
        momentum=np.asarray(sim.linear_momentum(), dtype=np.float64),
        angular_momentum=np.asarray(sim.angular_momentum(), dtype=np.float64),
    )


def _measure(
    result: RunResult,
    sim,
    scene: Scene,
    x0: np.ndarray,
    first: _Snapshot,
    rows_before: int,
    pinned: bool,
    projection: bool,
) -> None:
    """Fill in the conservation errors of ``result`` from the initial snapshot, the new history rows and the
    final state."""
    tiny = 1e-300
    last = _snapshot(sim)
    hist = sim.history
    totals = [first.total, last.total]
    tot = _column(hist, "total")
    if tot is not None:
        totals[1:1] = list(tot[rows_before:])
    # A body that starts with zero energy (at rest, centre of mass at the origin) still has a physical energy
    # scale under gravity: m_tot |g| r, lifting it by its half bounding-box diagonal.
    rest = np.asarray(sim.rest_positions)
    r_half = 0.5 * float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    lift = float(sim.total_mass) * float(np.linalg.norm(scene.world.gravity)) * r_half
    e_scale = max(first.kinetic + abs(first.elastic) + abs(first.gravitational), lift)
    h_scale = abs(first.total)
    if h_scale < 1e-12 * e_scale or h_scale < tiny:
        h_scale = max(e_scale, tiny)
    with np.errstate(all="ignore"):
        err = np.abs(np.asarray(totals) - first.total) / h_scale
        finite = err[np.isfinite(err)]
        result.max_energy_error = float(finite.max()) if finite.size else float("inf")
        result.final_energy_error = float(err[-1])
        if not pinned:
            masses = _vertex_masses(np.asarray(sim.masses), len(x0))
            m_tot = float(masses.sum())
            g = np.asarray(scene.world.gravity, dtype=np.float64)
            p_exp = first.momentum + m_tot * g * (last.time - first.time)
            p_scale = max(
                float(np.linalg.norm(p_exp)),
                float(np.linalg.norm(first.momentum)),
                math.sqrt(max(2.0 * m_tot * (first.kinetic + abs(first.elastic)), 0.0)),
                tiny,
            )
            result.momentum_error = float(np.linalg.norm(last.momentum - p_exp) / p_scale)
            c = _centre_of_mass(x0, masses)
            r_g = math.sqrt(float((masses * ((x0 - c) ** 2).sum(axis=1)).sum()) / m_tot)
            l_scale = max(float(np.linalg.norm(first.angular_momentum)), r_g * p_scale, tiny)
            dl = last.angular_momentum - first.angular_momentum
            result.angular_momentum_error = float(np.linalg.norm(dl) / l_scale)
    it = _column(hist, "proj_iterations")
    if projection and it is not None and len(it) > rows_before:
        steps_it = it[rows_before:][np.isfinite(it[rows_before:])]
        if steps_it.size:
            result.mean_iterations = float(steps_it.mean())
            result.max_iterations = int(steps_it.max())


def _projection_on(scene: Scene, override) -> bool:
    if override is not None:
        return override is not False
    return scene.projection.enabled


def _export_recorder(scene: Scene, sim, out_dir, export, export_every):
    """The :class:`fepr.export.Recorder` for ``out_dir/export``, or ``None`` when nothing is exported."""
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
    return Recorder(sim, Path(out_dir) / "export", formats, every=every, name=name)


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
    sim = scene.build(projection=projection)
    x0 = np.array(sim.positions, dtype=np.float64)
    first = _snapshot(sim)
    rows_before = len(sim.history)
    pinned = scene.world.pinned or scene.world.pin_below is not None
    result = RunResult(
        scene=scene.name,
        projection=_projection_on(scene, projection),
        steps_requested=n,
        steps_completed=0,
        wall_s=0.0,
        simulation=sim,
    )
    chunk = max(1, n // 10)
    done = 0
    start_steps = int(sim.num_steps)
    recorder = _export_recorder(scene, sim, out_dir, export, export_every)
    next_report = chunk
    if progress is not None:
        progress(0, n, sim)
    t_start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if recorder is not None:
                recorder.record()
            while done < n:
                k = min(chunk, n - done)
                if recorder is not None:  # stop at every frame to export
                    k = min(k, recorder.steps_to_next())
                sim.step(k)
                done += k
                if recorder is not None:
                    recorder.record()
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
            if recorder is not None:
                recorder.close()
    result.wall_s = time.perf_counter() - t_start
    if recorder is not None:  # the time spent writing exports is not simulation time
        result.wall_s = max(result.wall_s - recorder.write_s, 0.0)
        result.export_dir = recorder.out_dir
        result.export_frames = recorder.num_frames
        result.export_formats = recorder.formats
        result.export_fps = recorder.fps
    result.warnings = [str(w.message) for w in caught]
    # The base step alone was unstable when its energy error exceeded 100% of the energy scale, whether or
    # not a converged projection rescued the step.
    flags = _column(sim.history, "base_energy_error")
    if flags is not None:
        flags = np.where(np.isfinite(flags), flags, np.inf) > 1.0
    if flags is not None and np.any(flags[rows_before:] > 0):
        first_flag = rows_before + int(np.argmax(flags[rows_before:] > 0))
        steps_col = _column(sim.history, "step")
        result.base_unstable_step = int(steps_col[first_flag]) if steps_col is not None else first_flag
    result.steps_completed = int(sim.num_steps) - start_steps if result.runaway else done
    _measure(result, sim, scene, x0, first, rows_before, bool(pinned), result.projection)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        result.diagnostics_path = out / "diagnostics.csv"
        result.state_path = out / "final_state.npz"
        sim.save_diagnostics(str(result.diagnostics_path))
        sim.save_state(str(result.state_path))
    return result
