"""Sweep files: a TOML description of many runs, validated into a :class:`SweepSpec`.

Example (``examples/sweeps/material_study.toml``)::

    [sweep]
    name = "material_study"
    scene = "../seed_demo3_stretch.toml"   # the base scene (relative to this file); or an inline [base] table
    steps = 300                            # steps per run (default: the scene's [run] steps)
    frames_every = 10                      # record positions and velocities every 10 steps (0: no frames)

    [grid]                                 # every combination of these values
    material.youngs_modulus = [1e3, 3e3, 1e4]     # Pa
    projection.enabled = [true, false]

    [random]                               # `samples` seeded draws at every grid point
    initial.scale = { uniform = [1.2, 1.5] }

Sections and keys (every key is checked: an unknown one, a wrong type or a value out of range raises
:class:`fepr.ConfigError` naming the file, the section and the key):

``[sweep]``
    ``name`` (default: the file's stem); ``scene``, a base scene file, relative to the sweep file (or give the
    base scene inline as ``[base]`` with the sections of a scene file: ``[base.mesh]``, ``[base.material]``, ...);
    ``steps`` per run (default: the scene's ``[run] steps``; a parameter ``run.steps`` overrides it per run);
    ``frames_every`` (steps between recorded frames, 0 for none; default 0); ``frame_velocities`` (record the
    velocities with the positions; default true); ``checkpoint_every`` (steps between a run's checkpoints;
    default: about every ``checkpoint_seconds`` of wall time, 30 s); ``retries`` (attempts after the first for a
    run whose process died or raised; default 2); ``cpus_per_run`` (CPUs, and threads, per run; default 1);
    ``seed`` (random samples; default 0); ``samples`` (random draws per grid point; required with ``[random]``).
``[grid]``
    parameter paths (:mod:`fepr.sweep.params`) to lists of values; the runs are every combination.
``[random]``
    parameter paths to distributions (:mod:`fepr.sweep.sampling`); ``samples`` draws at every grid point.
``[[cases]]``
    tables of parameter paths to single values, for values that go together (``integrator.dt`` with
    ``run.steps``); every case is crossed with the grid and the samples. A table in a case is read as more of
    the path (it sets keys; a whole table, such as a mesh from a list, is replaced from a list in ``[grid]``).
``[dataset]``
    ``split = [train, validation, test]`` fractions (default ``[0.8, 0.1, 0.1]``) and ``seed`` (default: the
    sweep's), used by ``fepr sweep --dataset``.

In ``[grid]``, ``[random]`` and ``[[cases]]`` a path is written as dotted TOML keys (``material.youngs_modulus =
...``, which TOML reads as nested tables) or quoted (``"world.obstacles.0.friction" = ...``); both mean the same.
"""

from __future__ import annotations

import copy
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple, Union

from .._validate import shown
from ..errors import ConfigError
from ..scene import scene_from_dict
from ..scene.outputs import file_sha256
from .params import ParamPath, check_path, parse_path, path_text
from .sampling import DISTRIBUTIONS, Distribution, parse_distribution

if sys.version_info >= (3, 11):
    import tomllib as _toml
else:  # pragma: no cover - exercised on Python < 3.11 only
    import tomli as _toml

__all__ = ["SWEEP_KEYS", "SweepSpec", "load_sweep", "sweep_from_dict"]

#: Sections of a sweep file and the keys each accepts (``grid``, ``random``, ``cases`` and ``base`` take
#: parameter paths or scene sections instead).
SWEEP_KEYS: Dict[str, Tuple[str, ...]] = {
    "sweep": (
        "name",
        "scene",
        "steps",
        "frames_every",
        "frame_velocities",
        "checkpoint_every",
        "checkpoint_seconds",
        "retries",
        "cpus_per_run",
        "seed",
        "samples",
    ),
    "dataset": ("split", "seed"),
}
_SECTIONS = ("sweep", "base", "grid", "random", "cases", "dataset")


@dataclass
class SweepSpec:
    """A validated sweep: the base scene, what varies, and how the runs are run and recorded (see the module
    docs for every key). Build the runs with :func:`fepr.sweep.plan_runs`; run them with
    :func:`fepr.sweep.run_sweep`."""

    name: str
    #: The base scene as a dict of sections (relative paths made absolute), and where it came from.
    base: Dict[str, Any]
    base_dir: Path
    base_source: Optional[str] = None
    base_sha256: Optional[str] = None
    steps: Optional[int] = None
    frames_every: int = 0
    frame_velocities: bool = True
    checkpoint_every: Optional[int] = None
    checkpoint_seconds: float = 30.0
    retries: int = 2
    cpus_per_run: int = 1
    seed: int = 0
    samples: int = 1
    grid: List[Tuple[ParamPath, List[Any]]] = field(default_factory=list)
    random: List[Tuple[ParamPath, Distribution]] = field(default_factory=list)
    cases: List[List[Tuple[ParamPath, Any]]] = field(default_factory=list)
    split: Tuple[float, float, float] = (0.8, 0.1, 0.1)
    split_seed: Optional[int] = None
    #: The sweep file (messages, the manifest), its folder (relative paths in parameters) and SHA-256.
    source: Optional[str] = None
    sweep_dir: Path = field(default_factory=Path.cwd)
    sha256: Optional[str] = None

    def describe(self) -> Dict[str, Any]:
        """The sweep as plain JSON data (for ``sweep.json``)."""
        return {
            "name": self.name,
            "source": {"path": str(Path(self.source).resolve()), "sha256": self.sha256} if self.source else None,
            "base_scene": {"path": self.base_source, "sha256": self.base_sha256} if self.base_source else "inline",
            "steps": self.steps,
            "frames_every": self.frames_every,
            "frame_velocities": self.frame_velocities,
            "checkpoint_every": self.checkpoint_every,
            "checkpoint_seconds": self.checkpoint_seconds,
            "retries": self.retries,
            "cpus_per_run": self.cpus_per_run,
            "seed": self.seed,
            "samples": self.samples,
            "grid": {path_text(p): v for p, v in self.grid},
            "random": {path_text(p): d.as_json() for p, d in self.random},
            "cases": [{path_text(p): v for p, v in case} for case in self.cases],
            "dataset": {"split": list(self.split), "seed": self.split_seed},
        }


class _Where:
    """Errors that start with the sweep file and the section."""

    def __init__(self, source: Optional[str]):
        self.prefix = f"{source}: " if source else ""

    def error(self, section: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.prefix}[{section}] {msg}")

    def at(self, section: str) -> Callable[[str], ConfigError]:
        return lambda msg: self.error(section, msg)


def _flatten(table: Mapping[str, Any], is_leaf: Callable[[Any], bool], prefix: str = "") -> List[Tuple[str, Any]]:
    """``{material: {youngs_modulus: [...]}}`` -> ``[("material.youngs_modulus", [...])]`` (TOML's dotted keys
    and nested tables both mean a path); a value ``is_leaf`` accepts ends a path."""
    out: List[Tuple[str, Any]] = []
    for key, value in table.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and not is_leaf(value):
            if not value:
                out.append((name, value))
            else:
                out.extend(_flatten(value, is_leaf, name + "."))
        else:
            out.append((name, value))
    return out


def _is_distribution(value: Mapping[str, Any]) -> bool:
    """A ``[random]`` entry ends where a table holds one key whose value is not a table: ``{ uniform = [1, 2] }``
    (or a misspelt distribution, which is then reported as one)."""
    return len(value) == 1 and not isinstance(next(iter(value.values())), Mapping)


def _integer(t: Mapping[str, Any], key: str, default: Any, err, minimum: int) -> Any:
    if key not in t:
        return default
    v = t[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise err(f"{key} must be an integer, got {shown(v)}")
    if v < minimum:
        raise err(f"{key} must be >= {minimum}, got {shown(v)}")
    return v


def _read_toml(path: Path, what: str) -> Dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"{what} not found: {path}")
    raw = path.read_bytes()
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    try:
        return _toml.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte offset {exc.start}); save it as UTF-8") from None
    except _toml.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None


# Keys of a scene whose values are file paths, relative to the scene file: (section, key) of a one-body scene;
# the same inside each [[bodies]] table; `path` of a mesh obstacle.
_PATH_KEYS = (("mesh", "path"), ("initial", "velocities"))


def path_slots(scene: Dict[str, Any]) -> List[Tuple[Dict[str, Any], str]]:
    """``(table, key)`` of every value of a scene dict that is a file path: ``[mesh] path`` and ``[initial]
    velocities`` (of the scene or of each ``[[bodies]]`` table) and ``path`` of a mesh obstacle."""
    out: List[Tuple[Dict[str, Any], str]] = []
    holders = [scene] + [b for b in scene.get("bodies", []) if isinstance(b, dict)]
    for h in holders:
        for sec, key in _PATH_KEYS:
            table = h.get(sec)
            if isinstance(table, dict) and isinstance(table.get(key), str) and table[key]:
                out.append((table, key))
    world = scene.get("world")
    if isinstance(world, dict) and isinstance(world.get("obstacles"), list):
        for ob in world["obstacles"]:
            if isinstance(ob, dict) and str(ob.get("type", "")).lower() == "mesh" and isinstance(ob.get("path"), str):
                out.append((ob, "path"))
    return out


def absolute_paths(scene: Dict[str, Any], base_dir: Path) -> None:
    """Make the file paths of a scene dict absolute (relative ones are taken against ``base_dir``), in place, so
    that the scene reads the same files from any folder (each run's own, a worker's)."""
    for table, key in path_slots(scene):
        p = Path(table[key]).expanduser()
        table[key] = str(p if p.is_absolute() else (base_dir / p).resolve())


def load_sweep(path: Union[str, Path]) -> SweepSpec:
    """Read and validate a sweep file (TOML); relative paths in it are relative to the file.

    Raises
    ------
    ConfigError
        If the file is missing or not TOML, or any entry is invalid (see :func:`sweep_from_dict`).
    """
    p = Path(path)
    data = _read_toml(p, "sweep file")
    spec = sweep_from_dict(data, p.resolve().parent, source=str(path), default_name=p.stem)
    spec.sha256 = file_sha256(p)
    return spec


def sweep_from_dict(
    d: Mapping[str, Any],
    base_dir: Union[str, Path] = ".",
    *,
    source: Optional[str] = None,
    default_name: str = "sweep",
) -> SweepSpec:
    """Validate a sweep given as a dict (the parsed TOML: ``sweep``, ``base``, ``grid``, ``random``, ``cases``,
    ``dataset``) into a :class:`SweepSpec`. ``base_dir`` is the folder relative paths are taken against.

    Raises
    ------
    ConfigError
        On an unknown section or key, a wrong type or a value out of range, a parameter path the base scene does
        not have (``material.youngs_modulu``), a base scene that is invalid; the message names the sweep file, the
        section and the key.
    """
    w = _Where(source)
    sweep_dir = Path(base_dir).resolve()
    if not isinstance(d, Mapping):
        raise ConfigError(f"{w.prefix}a sweep must be a table of sections, got {type(d).__name__}")
    for name, value in d.items():
        if name not in _SECTIONS:
            raise ConfigError(f"{w.prefix}unknown section [{name}] (known: {', '.join(_SECTIONS)})")
        if name == "cases":
            if not isinstance(value, list) or not all(isinstance(c, Mapping) for c in value):
                raise ConfigError(f"{w.prefix}cases must be [[cases]] tables, got {shown(value)}")
        elif not isinstance(value, Mapping):
            raise ConfigError(f"{w.prefix}[{name}] must be a section (a table of keys), got {shown(value)}")
    t = d.get("sweep", {})
    err = w.at("sweep")
    for key in t:
        if key not in SWEEP_KEYS["sweep"]:
            raise err(f"unknown key {key!r} (known: {', '.join(SWEEP_KEYS['sweep'])})")

    name = t.get("name", default_name)
    if not isinstance(name, str) or not name.strip():
        raise err(f"name must be a non-empty string, got {shown(name)}")
    spec = SweepSpec(name=name, base={}, base_dir=sweep_dir, source=source, sweep_dir=sweep_dir)
    _read_base(spec, t, d, w, sweep_dir)

    spec.steps = _integer(t, "steps", None, err, 0)
    spec.frames_every = _integer(t, "frames_every", 0, err, 0)
    if "frame_velocities" in t:
        if not isinstance(t["frame_velocities"], bool):
            raise err(f"frame_velocities must be true or false, got {shown(t['frame_velocities'])}")
        spec.frame_velocities = t["frame_velocities"]
    spec.checkpoint_every = _integer(t, "checkpoint_every", None, err, 1)
    if "checkpoint_seconds" in t:
        v = t["checkpoint_seconds"]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v > 0 and math.isfinite(v)):
            raise err(f"checkpoint_seconds must be a number > 0, got {shown(v)}")
        spec.checkpoint_seconds = float(v)
    spec.retries = _integer(t, "retries", 2, err, 0)
    spec.cpus_per_run = _integer(t, "cpus_per_run", 1, err, 1)
    spec.seed = _integer(t, "seed", 0, err, 0)

    seen: Dict[ParamPath, str] = {}

    def param(section: str, text: str, perr: Callable[[str], ConfigError], case: Optional[set] = None) -> ParamPath:
        path = parse_path(text, perr)
        check_path(path, spec.base, perr)
        where = seen.get(path)
        if where is not None and where != section:
            raise perr(f"parameter {text!r} is varied in [{where}] too; vary it in one place")
        repeated = path in case if case is not None else where == section
        if repeated:
            raise perr(f"parameter {text!r} is given twice (as a dotted and a quoted key?)")
        seen[path] = section
        if case is not None:
            case.add(path)
        return path

    for text, values in _flatten(d.get("grid", {}), lambda v: False):
        path = param("grid", text, w.at("grid"))
        if not isinstance(values, list) or not values:
            raise w.error("grid", f"{text} must be a non-empty list of values, got {shown(values)}")
        spec.grid.append((path, list(values)))
    for text, raw in _flatten(d.get("random", {}), _is_distribution):
        kind = next(iter(raw)) if isinstance(raw, Mapping) and raw else None
        if kind is not None and kind not in DISTRIBUTIONS:
            try:  # `x.y = [1, 2]` in [random]: a list of values where a distribution belongs
                check_path(parse_path(f"{text}.{kind}", w.at("random")), spec.base, w.at("random"))
            except ConfigError:
                pass
            else:
                raise w.error(
                    "random",
                    f"{text}.{kind} must be a distribution such as {{ uniform = [lo, hi] }} (lists of "
                    f"values go in [grid]), got {shown(raw[kind])}",
                )
        path = param("random", text, w.at("random"))
        spec.random.append((path, parse_distribution(raw, lambda m, text=text: w.error("random", f"{text}: {m}"))))
    for k, case in enumerate(d.get("cases", []), 1):
        label = f"{w.prefix}[[cases]] #{k}"
        items, given = [], set()
        # Tables are read as paths here (TOML gives `mesh = { builtin = "box" }` and `mesh.builtin = "box"` the
        # same shape): a case sets keys; a whole table is replaced from a list in [grid].
        for text, value in _flatten(case, lambda v: False):
            path = param("cases", text, lambda m, label=label: ConfigError(f"{label} {m}"), given)
            items.append((path, value))
        if not items:
            raise ConfigError(f"{label} is empty; give parameter = value pairs")
        spec.cases.append(items)

    if spec.random:
        if "samples" not in t:
            raise err("samples is required with [random]: the number of random draws at every grid point")
        spec.samples = _integer(t, "samples", 1, err, 1)
    elif "samples" in t:
        raise err("samples needs a [random] table of distributions to draw from")
    _read_dataset(spec, d.get("dataset", {}), w)
    return spec


def _read_base(spec: SweepSpec, t: Mapping[str, Any], d: Mapping[str, Any], w: _Where, sweep_dir: Path) -> None:
    """The base scene: ``[sweep] scene`` (a file) or ``[base]`` (inline), validated as a scene."""
    if ("scene" in t) == ("base" in d):
        raise w.error("sweep", 'give exactly one base scene: scene = "file.toml" in [sweep], or a [base] table')
    if "scene" in t:
        if not isinstance(t["scene"], str) or not t["scene"]:
            raise w.error("sweep", f"scene must be a scene file path, got {shown(t['scene'])}")
        p = Path(t["scene"]).expanduser()
        p = p if p.is_absolute() else sweep_dir / p
        if not p.is_file():
            raise w.error("sweep", f"scene: file not found: {p}")
        base = _read_toml(p, "scene file")
        spec.base_dir, spec.base_source, spec.base_sha256 = p.resolve().parent, str(p.resolve()), file_sha256(p)
        scene_from_dict(base, spec.base_dir, source=str(p))  # errors name the scene file, section and key
    else:
        base = copy.deepcopy(dict(d["base"]))
        spec.base_dir = sweep_dir
        try:
            scene_from_dict(base, spec.base_dir)
        except ConfigError as exc:
            raise ConfigError(f"{w.prefix}[base] {exc}") from None
    base.pop("export", None)  # the sweep records its own frames (frames_every)
    absolute_paths(base, spec.base_dir)
    spec.base = base


def _read_dataset(spec: SweepSpec, t: Mapping[str, Any], w: _Where) -> None:
    err = w.at("dataset")
    for key in t:
        if key not in SWEEP_KEYS["dataset"]:
            raise err(f"unknown key {key!r} (known: {', '.join(SWEEP_KEYS['dataset'])})")
    if "split" in t:
        s = t["split"]
        ok = (
            isinstance(s, list)
            and len(s) == 3
            and all(not isinstance(x, bool) and isinstance(x, (int, float)) and x >= 0 for x in s)
        )
        if not ok or abs(sum(s) - 1.0) > 1e-9:
            raise err(f"split must be [train, validation, test], fractions >= 0 that sum to 1, got {shown(s)}")
        spec.split = (float(s[0]), float(s[1]), float(s[2]))
    spec.split_seed = _integer(t, "seed", None, err, 0)
