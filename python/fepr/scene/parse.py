"""Scene files -> validated settings (:mod:`fepr.scene.schema`), with errors that name the file and the key.

:func:`load_scene` reads a TOML file and :func:`scene_from_dict` validates its tables. Every key is checked: an
unknown section or key, a missing required key, a value of the wrong type or out of range raises
:class:`fepr.ConfigError` naming the file, the section (for list entries such as ``[[world.obstacles]] #2`` its
position, counted from 1) and the key. Checks that need the mesh (vertex indices in range, a ``pin_below``
that pins something) happen when the scene is built (:mod:`fepr.scene.build`).
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from .._validate import PLAUSIBLE, check_magnitude, shown
from ..errors import ConfigError
from .schema import (
    _AXES,
    _BUILTIN_OPTIONS,
    BODY_KEYS,
    INTEGRATORS,
    KINEMATIC_PIN_KEYS,
    MATERIAL_MODELS,
    METRICS,
    MOTIONS,
    OBSTACLE_COMMON_KEYS,
    OBSTACLE_KEYS,
    OBSTACLE_MOTION_KEYS,
    PROJECTION_ROWS,
    SCENE_KEYS,
    SELF_CONTACT_KEYS,
    SLACK_MODES,
    TERRAIN_KEYS,
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

if sys.version_info >= (3, 11):
    import tomllib as _toml
else:  # pragma: no cover - exercised on Python < 3.11 only
    import tomli as _toml

__all__ = ["load_scene", "scene_from_dict"]

# A default that means "required": a missing key raises.
_MISSING = object()


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
            raise self.error(f"{key} must be a number, got {shown(value)}")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(f"{key} must be finite, got {shown(value)}")
        if positive and value <= 0:
            raise self.error(f"{key} must be > 0, got {shown(value)}")
        if nonnegative and value < 0:
            raise self.error(f"{key} must be >= 0, got {shown(value)}")
        if lo is not None and hi is not None and not lo < value < hi:
            raise self.error(f"{key} must be in ({lo}, {hi}), got {shown(value)}")
        if key in PLAUSIBLE:  # density, node_mass, youngs_modulus, dt: an error beyond what can be computed
            try:  # (the warning for implausible values comes when the scene is built, from the API)
                check_magnitude(value, key, warn=False)
            except ConfigError as exc:
                raise self.error(str(exc)) from None
        return value

    def integer(self, key: str, default: Any = _MISSING, *, minimum: Optional[int] = None) -> Any:
        value = self._get(key, default)
        if key not in self.data:
            return value
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(f"{key} must be an integer, got {shown(value)}")
        if minimum is not None and value < minimum:
            raise self.error(f"{key} must be >= {minimum}, got {shown(value)}")
        return value

    def boolean(self, key: str, default: Any = _MISSING) -> Any:
        value = self._get(key, default)
        if key in self.data and not isinstance(value, bool):
            raise self.error(f"{key} must be true or false, got {shown(value)}")
        return value

    def string(self, key: str, default: Any = _MISSING, *, choices: Optional[Sequence[str]] = None) -> Any:
        value = self._get(key, default)
        if key not in self.data:
            return value
        if not isinstance(value, str):
            raise self.error(f"{key} must be a string, got {shown(value)}")
        if choices is not None:
            # Names are case-insensitive, as in the Python API: "Y" is "y", "Implicit_Euler" is "implicit_euler".
            canonical = {c.lower(): c for c in choices}.get(value.strip().lower())
            if canonical is None:
                raise self.error(f"{key} must be one of {', '.join(repr(c) for c in choices)}; got {shown(value)}")
            return canonical
        return value

    def vec3(self, key: str, default: Any = _MISSING) -> Any:
        value = self._get(key, default)
        if key not in self.data:
            return value
        return _as_vec3(value, lambda: self.error(f"{key} must be a list of 3 numbers, got {shown(value)}"))

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
            raise t.error(
                f"rotate must be [ax, ay, az] (degrees about x, y, z) or a 3x3 rotation matrix, got {shown(raw)}"
            )
        ms.rotate = value
    center_point = t.has("center") and isinstance(t.data["center"], list)
    if t.has("center") and not center_point:
        raw = t.data["center"]
        if raw is True:
            raw = "bbox"
        if raw is False:
            raw = None
        if raw is not None and raw not in ("bbox", "centroid"):
            raise t.error(f'center must be "bbox", "centroid", true, false or (builtins) [x, y, z], got {shown(raw)}')
        ms.center = raw
    from ..io.transform import check_load_options

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
    from .. import meshes

    known = getattr(meshes, "BUILTIN", None)
    if known is not None and name not in known:
        raise t.error(f"builtin: unknown built-in mesh {name!r} (known: {', '.join(sorted(known))})")
    ms.builtin = name
    ms.builtin_options = _parse_builtin_options(t, name, center_point)
    return ms


def _parse_builtin_options(t: _Table, name: str, center_point: bool) -> Dict[str, Any]:
    """The keyword arguments of :func:`fepr.meshes.builtin` for builtin ``name`` (``center`` only when it is
    a point: a string ``center`` is a load option)."""
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
                    raise t.error(f"resolution must be an integer >= 1 or 3 of them, got {shown(raw)}")
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
                    raise t.error(f"size must be > 0, got {shown(raw)}")
                opts[opt] = size
            else:
                s = t.number(opt, positive=True)
                opts[opt] = (s, s, s) if name == "box" else s
    return opts


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
                raise t.error(f'scale_about must be [x, y, z] or "centroid", got {shown(raw)}')
            ini.scale_about = "centroid"
        else:
            ini.scale_about = _as_vec3(
                raw, lambda: t.error(f'scale_about must be [x, y, z] or "centroid", got {shown(raw)}')
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
        slack=t.string("slack", None, choices=SLACK_MODES),
        warm_start=t.number("warm_start", None, nonnegative=True),
        metric=t.string("metric", None, choices=METRICS),
        quality_guard=t.boolean("quality_guard", None),
        quality_margin=t.number("quality_margin", None, positive=True),
    )


def _parse_pinned(t: _Table, key: str = "pinned") -> Tuple[int, ...]:
    raw = t.data[key]
    ok = isinstance(raw, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in raw)
    if not ok:
        raise t.error(f"{key} must be a list of vertex indices (integers), got {shown(raw)}")
    if any(i < 0 for i in raw):
        raise t.error(f"{key}: vertex indices must be >= 0, got {shown(raw)}")
    return tuple(raw)


def _parse_pin_below(t: _Table, key: str = "pin_below") -> PinBelow:
    raw = t.data[key]
    if not isinstance(raw, Mapping):
        raise t.error(f'{key} must be a table {{axis = "z", value = 0.0}}, got {shown(raw)}')
    unknown = [k for k in raw if k not in ("axis", "value")]
    if unknown:
        raise t.error(f"{key}: unknown key {unknown[0]!r} (known: axis, value)")
    axis = raw.get("axis", "z")
    if axis not in _AXES:
        raise t.error(f'{key}.axis must be "x", "y" or "z", got {shown(axis)}')
    if "value" not in raw:
        raise t.error(f"{key}: missing required key 'value'")
    value = raw["value"]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise t.error(f"{key}.value must be a number, got {shown(value)}")
    return PinBelow(axis=axis, value=float(value))


def _list_of_tables(raw: Any, owner: str, key: str, toml_name: str) -> List[Mapping[str, Any]]:
    if not isinstance(raw, list) or not all(isinstance(item, Mapping) for item in raw):
        raise ConfigError(f"{owner} {key} must be a list of tables ([[{toml_name}]] entries), got {shown(raw)}")
    return list(raw)


def _parse_obstacles(raw: Any, where: str, base_dir: Path) -> Tuple[ObstacleSettings, ...]:
    items = _list_of_tables(raw, f"{where}[world]", "obstacles", "world.obstacles")
    out = []
    for k, item in enumerate(items, 1):
        label = f"[[world.obstacles]] #{k}"
        types = ", ".join(repr(n) for n in OBSTACLE_KEYS)
        if "type" not in item:
            raise ConfigError(f"{where}{label}: missing required key 'type' (one of {types})")
        kind = item["type"].strip().lower() if isinstance(item["type"], str) else item["type"]
        if kind not in OBSTACLE_KEYS:
            raise ConfigError(f"{where}{label}: unknown obstacle type {kind!r} (known: {types})")
        t = _Table(item, "obstacle", where, known=OBSTACLE_COMMON_KEYS + OBSTACLE_KEYS[kind], label=f"{label}:")
        restitution = t.number("restitution", 1.0)
        if not 0.0 <= restitution <= 1.0:
            raise t.error(f"restitution must be in [0, 1], got {shown(restitution)}")
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
                from ..io.transform import _rotation

                try:
                    r = _rotation(t.data["rotate"])
                except ConfigError as exc:
                    raise t.error(str(exc)) from None
                # fepr.Box takes the box's local axes in world coordinates as rows: the columns of R.
                rotation = tuple(tuple(float(c) for c in row) for row in np.asarray(r).T)
            geometry["rotation"] = rotation
        elif kind == "mesh":
            if t.has("path") == t.has("terrain"):
                raise t.error("give exactly one of 'path' (a surface file: OBJ, OFF, STL, PLY) and 'terrain' (a table)")
            if t.has("path"):
                geometry["path"] = t.path("path", base_dir)
            else:
                terrain = t.data["terrain"]
                if not isinstance(terrain, dict):
                    raise t.error(f"terrain must be a table (keys: {', '.join(TERRAIN_KEYS)}), got {shown(terrain)}")
                unknown = sorted(set(terrain) - set(TERRAIN_KEYS))
                if unknown:
                    raise t.error(f"terrain: unknown key {unknown[0]!r} (known: {', '.join(TERRAIN_KEYS)})")
                geometry["terrain"] = dict(terrain)
            geometry["flip_normals"] = t.boolean("flip_normals", False)
        else:  # capsule
            geometry["a"] = t.vec3("a")
            geometry["b"] = t.vec3("b")
            geometry["radius"] = t.number("radius", positive=True)
        motion = _parse_obstacle_motion(t.data["motion"], where, label) if t.has("motion") else None
        out.append(
            ObstacleSettings(
                type=kind,
                geometry=geometry,
                restitution=restitution,
                friction=friction,
                motion=motion,
                label=label,
            )
        )
    return tuple(out)


def _parse_path(t: _Table, kind: str, kind_key: str) -> Dict[str, Any]:
    """The keys of a displacement path of ``kind`` (a key of ``MOTIONS``, read from ``kind_key``) in ``t``:
    ``amplitude``, ``frequency``, ``phase`` for ``"sinusoidal"``; ``times``, ``offsets`` for ``"keyframes"``.
    A key of the other kind is an error naming it."""
    for other, keys in MOTIONS.items():
        if other == kind:
            continue
        for key in keys:
            if t.has(key):
                raise t.error(f"{key} does not apply to {kind_key} {kind!r} (its keys: {', '.join(MOTIONS[kind])})")
    if kind == "sinusoidal":
        return {
            "amplitude": t.vec3("amplitude"),
            "frequency": t.number("frequency", positive=True),
            "phase": t.number("phase", 0.0),
        }
    times = t.data.get("times", _MISSING)
    if times is _MISSING:
        raise t.error("missing required key 'times'")
    if not isinstance(times, list) or not times or not all(_is_number(c) for c in times):
        raise t.error(f"times must be a non-empty list of numbers (s), got {shown(times)}")
    if any(b <= a for a, b in zip(times, times[1:])):
        raise t.error(f"times must be strictly increasing, got {shown(times)}")
    offsets = t.data.get("offsets", _MISSING)
    if offsets is _MISSING:
        raise t.error("missing required key 'offsets'")
    if not isinstance(offsets, list):
        raise t.error(f"offsets must be a list of [x, y, z] vectors (m), got {shown(offsets)}")
    if len(offsets) != len(times):
        raise t.error(f"offsets has {len(offsets)} entries but times has {len(times)}")
    vecs = []
    for j, o in enumerate(offsets, 1):
        bad = t.error(f"offsets #{j} must be a list of 3 numbers (m), got {shown(o)}")
        vecs.append(_as_vec3(o, lambda bad=bad: bad))
    return {"times": tuple(float(c) for c in times), "offsets": tuple(vecs)}


def _parse_obstacle_motion(raw: Any, where: str, label: str) -> Dict[str, Any]:
    """An obstacle's ``motion`` table: ``translation`` (``"sinusoidal"`` or ``"keyframes"``, with that path's
    keys), ``angular_velocity`` (rad/s), ``orientation_times`` (s) with ``orientations`` (rotation vectors, rad)
    and ``pivot`` (m)."""
    if not isinstance(raw, dict):
        raise ConfigError(
            f"{where}{label} motion must be a table (keys: {', '.join(OBSTACLE_MOTION_KEYS)}), got {shown(raw)}"
        )
    t = _Table(raw, "obstacle_motion", where, known=OBSTACLE_MOTION_KEYS, label=f"{label} motion:")
    stray = [k for keys in MOTIONS.values() for k in keys if t.has(k)]
    if stray and not t.has("translation"):
        raise t.error(f"{stray[0]} needs 'translation' (one of {', '.join(repr(m) for m in MOTIONS)})")
    if not (t.has("translation") or t.has("angular_velocity") or t.has("orientations")):
        raise t.error(
            "give 'translation' (with its path's keys), 'angular_velocity' (rad/s) and/or 'orientations' "
            "(with 'orientation_times')"
        )
    motion: Dict[str, Any] = {"translation": t.string("translation", None, choices=tuple(MOTIONS))}
    if motion["translation"] is not None:
        motion.update(_parse_path(t, motion["translation"], "translation"))
    motion["angular_velocity"] = t.vec3("angular_velocity", (0.0, 0.0, 0.0))
    motion["pivot"] = t.vec3("pivot", (0.0, 0.0, 0.0))
    if t.has("orientations") != t.has("orientation_times"):
        raise t.error("give 'orientations' (rotation vectors, rad) and 'orientation_times' (s) together")
    times, turns = t.data.get("orientation_times", []), t.data.get("orientations", [])
    if not isinstance(times, list) or not all(_is_number(c) for c in times):
        raise t.error(f"orientation_times must be a list of numbers (s), got {shown(times)}")
    if any(b <= a for a, b in zip(times, times[1:])):
        raise t.error(f"orientation_times must be strictly increasing, got {shown(times)}")
    if not isinstance(turns, list) or len(turns) != len(times):
        raise t.error("orientations must be a list of as many [x, y, z] rotation vectors (rad) as orientation_times")
    vecs = []
    for j, r in enumerate(turns, 1):
        bad = t.error(f"orientations #{j} must be a list of 3 numbers (rad), got {shown(r)}")
        vecs.append(_as_vec3(r, lambda bad=bad: bad))
    motion["orientation_times"] = tuple(float(c) for c in times)
    motion["orientations"] = tuple(vecs)
    return motion


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
        for key, value in _parse_path(t, kp.motion, "motion").items():
            setattr(kp, key, value)
        out.append(kp)
    return tuple(out)


_BODY_PIN_KEYS = ("pinned", "pin_below", "kinematic_pins", "self_contact")


def _parse_world(t: _Table, base_dir: Path, multibody: bool = False) -> WorldSettings:
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
        w.obstacles = _parse_obstacles(t.data["obstacles"], t.where, base_dir)
    if t.has("kinematic_pins"):
        w.kinematic_pins = _parse_kinematic_pins(
            t.data["kinematic_pins"], t.where, "[world]", "[[world.kinematic_pins]]", "world.kinematic_pins"
        )
    w.self_contact = _parse_self_contact(t)
    return w


def _parse_self_contact(t: _Table) -> Optional[Tuple[float, float]]:
    """``self_contact``: ``true`` (restitution 1, no friction), ``false``, or a table of ``restitution`` in [0, 1]
    and ``friction`` >= 0; ``(restitution, friction)`` or None."""
    if not t.has("self_contact"):
        return None
    raw = t.data["self_contact"]
    if isinstance(raw, bool):
        return (1.0, 0.0) if raw else None
    if not isinstance(raw, Mapping):
        raise t.error(
            f"self_contact must be true, false or a table {{ restitution = ..., friction = ... }}, got {shown(raw)}"
        )
    c = _Table(raw, "self_contact", t.where, known=SELF_CONTACT_KEYS, label=f"{t.label} self_contact:")
    restitution = c.number("restitution", 1.0)
    if not 0.0 <= restitution <= 1.0:
        raise c.error(f"restitution must be in [0, 1], got {shown(restitution)}")
    return (restitution, c.number("friction", 0.0, nonnegative=True))


def _parse_export(t: _Table) -> ExportSettings:
    ex = ExportSettings(every=t.integer("every", 1, minimum=1))
    if t.has("formats"):
        raw = t.data["formats"]
        if not isinstance(raw, list) or not all(isinstance(f, str) for f in raw):
            raise t.error(f'formats must be a list of format names such as ["vtu", "glb"], got {shown(raw)}')
        from ..export import parse_formats

        try:
            ex.formats = parse_formats(raw) if raw else ()
        except ConfigError as exc:
            raise t.error(f"formats: {exc}") from None
    return ex


_BODY_SECTIONS = ("mesh", "material", "mass", "initial")
_NAME_RE = re.compile(r"[A-Za-z0-9_.\-]+")


def _parse_bodies(raw: Any, where: str, base: Path) -> Tuple[BodySettings, ...]:
    if not isinstance(raw, list) or not raw or not all(isinstance(item, Mapping) for item in raw):
        raise ConfigError(f"{where}bodies must be a non-empty list of tables ([[bodies]] entries), got {shown(raw)}")
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
                raise bt.error(f"{sec} must be a table of keys, got {shown(item[sec])}")

        def sub(sec: str, label: str = label, item: Mapping[str, Any] = item) -> _Table:
            return _Table(item.get(sec, {}), sec, where, label=f"{label} [{sec}]")

        name = bt.string("name", f"body{k}")
        if not _NAME_RE.fullmatch(name) or name in (".", ".."):
            raise bt.error(f"name must be letters, digits, '_', '-' or '.' (it names output files), got {shown(name)}")
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
        body.restitution = bt.number("restitution", 1.0)
        if not 0.0 <= body.restitution <= 1.0:
            raise bt.error(f"restitution must be in [0, 1], got {shown(body.restitution)}")
        body.friction = bt.number("friction", 0.0, nonnegative=True)
        if bt.has("pinned"):
            body.pinned = _parse_pinned(bt)
        if bt.has("pin_below"):
            body.pin_below = _parse_pin_below(bt)
        if bt.has("kinematic_pins"):
            body.kinematic_pins = _parse_kinematic_pins(
                item["kinematic_pins"], where, f"{label}:", f"{label} [[kinematic_pins]]", "bodies.kinematic_pins"
            )
        body.self_contact = _parse_self_contact(bt)
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
            raise ConfigError(f"{where}[{name}] must be a section (a table of keys), got {shown(value)}")
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
            name=integ.string("name", "symplectic_euler", choices=INTEGRATORS),
            dt=integ.number("dt", 1.0 / 30.0, positive=True),
            tolerance=integ.number("tolerance", None, positive=True),
            max_iterations=integ.integer("max_iterations", None, minimum=1),
            iterations=integ.integer("iterations", None, minimum=1),
            substeps=integ.integer("substeps", None, minimum=1),
        ),
        projection=_parse_projection(table("projection")),
        world=_parse_world(table("world"), base, multibody=multibody),
        run=RunSettings(steps=run.integer("steps", 100, minimum=0), threads=run.integer("threads", None, minimum=1)),
        export=_parse_export(table("export")),
        source=source,
        base_dir=base,
    )


def load_scene_from(source, base_dir: Union[str, Path, None] = None) -> Scene:
    """A :class:`Scene` from a scene file (``str`` or path), a dict of sections (relative paths against
    ``base_dir``, default the working folder) or a ``Scene`` (returned as it is)."""
    if isinstance(source, Scene):
        return source
    if isinstance(source, Mapping):
        return scene_from_dict(source, "." if base_dir is None else base_dir)
    if isinstance(source, (str, Path)) or hasattr(source, "__fspath__"):
        return load_scene(source)
    raise ConfigError(f"a scene must be a scene file path, a dict of sections or a fepr.scene.Scene, got {source!r}")


def load_scene(path: Union[str, Path]) -> Scene:
    """Read and validate a scene file (TOML). Relative paths inside it are relative to the file.

    The file must be UTF-8 (as TOML requires); a UTF-8 byte order mark at its start (as some Windows editors
    write) is skipped.

    Raises
    ------
    ConfigError
        If the file does not exist, is not UTF-8 text (the message names the byte offset, line and column of the
        first byte that is not), is not valid TOML, or any entry is invalid (see :func:`scene_from_dict`).
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"scene file not found: {p}")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read scene file: {exc.strerror or exc}") from None
    try:
        data = _toml.loads(_scene_text(raw, p))
    except _toml.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: invalid TOML: {exc}") from None
    return scene_from_dict(data, p.resolve().parent, source=str(path))


_UTF8_BOM = b"\xef\xbb\xbf"


def _scene_text(raw: bytes, p: Path) -> str:
    """The text of a scene file: UTF-8 without a leading byte order mark; a ConfigError naming the first byte
    that is not UTF-8 (offset, line, column)."""
    if raw.startswith(_UTF8_BOM):
        raw = raw[len(_UTF8_BOM) :]
    elif raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise ConfigError(
            f"{p}: the file is UTF-16 text (it starts with a UTF-16 byte order mark); scene files must be UTF-8: "
            "save it as UTF-8"
        )
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        at = exc.start
        line = raw.count(b"\n", 0, at) + 1
        column = at - (raw.rfind(b"\n", 0, at) + 1) + 1
        bad = raw[at : min(exc.end, at + 4)]
        shown = " ".join(f"0x{b:02x}" for b in bad)
        text = raw[raw.rfind(b"\n", 0, at) + 1 : at].decode("utf-8", "replace")[-40:]
        after = f" after {text!r}" if text.strip() else ""
        raise ConfigError(
            f"{p} line {line}, column {column} (byte offset {at}): not UTF-8 text: byte {shown}{after} "
            f"({exc.reason}); scene files must be UTF-8 (TOML requires it): save the file as UTF-8 (a file saved as "
            "Latin-1 or Windows-1252 shows this for accented letters)"
        ) from None


# --------------------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------------------
