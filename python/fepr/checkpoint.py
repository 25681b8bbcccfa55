"""Checkpoints: a simulation (or a multi-body system) written to one ``.npz`` file and resumed bit for bit.

A checkpoint holds two things:

- the *recipe*: the arguments the simulation was built with (mesh, material, masses, integrator, projection,
  obstacles, pins, ...), encoded as JSON with their arrays beside it. Only fepr's own settings types are
  decoded (no pickle: a checkpoint from someone else cannot run code);
- the *carry*: what the core's next steps depend on besides those settings (``fepr._core.Simulation.carry``:
  the state, time and step count, the projection's running references, books and search memory, the kinematic
  pins' anchors, the forces and damping set since), and optionally the history so far.

Loading builds the simulation again from the recipe and puts the carry back, so the next steps are the saved
simulation's, bit for bit, for any thread count. A checkpoint is versioned (:data:`FORMAT_VERSION`); the core
also checks that the carry belongs to the rebuilt model (mesh, material, masses, pins) and time step. Files are
written atomically (a temporary name, renamed), so a checkpoint on disk is always complete.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import zipfile
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

import numpy as np

from .errors import CheckpointError, ConfigError

__all__ = ["FORMAT_VERSION", "save_simulation", "load_simulation", "save_multibody", "load_multibody", "mesh_hash"]

#: The checkpoint layout this fepr writes and reads.
FORMAT_VERSION = 1
_FORMAT = "fepr-checkpoint"


def mesh_hash(vertices: np.ndarray, tets: np.ndarray) -> str:
    """SHA-256 of a mesh's rest vertices (float64) and tets (int64), hex: names the mesh a checkpoint is of."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(tets, dtype=np.int64).tobytes())
    return h.hexdigest()


# --- the recipe's encoding -------------------------------------------------------------------------------------


def _types() -> Dict[str, type]:
    """The settings types a recipe may hold (decoding builds nothing else)."""
    from . import materials, simulation, world

    names = [
        (materials, "NeoHookean"),
        (materials, "StableNeoHookean"),
        (materials, "Arap"),
        (materials, "ConstraintNeoHookean"),
        (simulation, "Projection"),
        (simulation, "SymplecticEuler"),
        (simulation, "ImplicitEuler"),
        (simulation, "ProjectiveDynamics"),
        (simulation, "Xpbd"),
        (world, "Plane"),
        (world, "Sphere"),
        (world, "Box"),
        (world, "Capsule"),
        (world, "Sinusoid"),
        (world, "Keyframes"),
        (world, "ObstacleMotion"),
        (world, "KinematicPins"),
    ]
    return {n: getattr(mod, n) for mod, n in names}


class _Encoder:
    """Recipe values to JSON, with arrays set aside under generated names."""

    def __init__(self, prefix: str):
        self.prefix = prefix
        self.arrays: Dict[str, np.ndarray] = {}

    def array(self, a: np.ndarray) -> dict:
        name = f"{self.prefix}array{len(self.arrays)}"
        self.arrays[name] = np.asarray(a)
        return {"array": name}

    def __call__(self, obj: Any) -> Any:
        from .mesh import TetMesh
        from .world import MeshObstacle

        if obj is None or isinstance(obj, (bool, str)):
            return obj
        if isinstance(obj, (int, np.integer)):
            return int(obj)
        if isinstance(obj, (float, np.floating)):
            return float(obj)
        if isinstance(obj, np.ndarray):
            return self.array(obj)
        if isinstance(obj, (list, tuple)):
            return {"list": [self(x) for x in obj], "tuple": isinstance(obj, tuple)}
        if isinstance(obj, TetMesh):
            return {"type": "TetMesh", "vertices": self.array(obj.vertices), "tets": self.array(obj.tets)}
        if isinstance(obj, MeshObstacle):
            # The triangles as stored (already flipped where flip_normals was asked for).
            return {
                "type": "MeshObstacle",
                "vertices": self.array(obj.vertices),
                "triangles": self.array(obj.triangles),
                "restitution": float(obj.restitution),
                "friction": float(obj.friction),
                "motion": self(obj.motion),
            }
        name = type(obj).__name__
        if dataclasses.is_dataclass(obj) and _types().get(name) is type(obj):
            fields = {f.name: self(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
            return {"type": name, "fields": fields}
        raise ConfigError(f"a checkpoint cannot hold a {name} ({obj!r})")


def _decode(obj: Any, arrays: Dict[str, np.ndarray], where: str) -> Any:
    from .mesh import TetMesh
    from .world import MeshObstacle

    if not isinstance(obj, dict):
        return obj
    if "array" in obj:
        try:
            return arrays[obj["array"]]
        except KeyError:
            raise CheckpointError(f"{where}: the recipe refers to a missing array {obj['array']!r}") from None
    if "list" in obj:
        items = [_decode(x, arrays, where) for x in obj["list"]]
        return tuple(items) if obj.get("tuple") else items
    kind = obj.get("type")
    if kind == "TetMesh":
        return TetMesh(_decode(obj["vertices"], arrays, where), _decode(obj["tets"], arrays, where))
    if kind == "MeshObstacle":
        return MeshObstacle(
            (_decode(obj["vertices"], arrays, where), _decode(obj["triangles"], arrays, where)),
            restitution=obj["restitution"],
            friction=obj["friction"],
            motion=_decode(obj["motion"], arrays, where),
        )
    cls = _types().get(kind)
    if cls is None:
        raise CheckpointError(f"{where}: the recipe holds an unknown type {kind!r}")
    fields = {k: _decode(v, arrays, where) for k, v in obj.get("fields", {}).items()}
    try:
        return cls(**fields)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{where}: cannot rebuild {kind}: {exc}") from None


# --- files ---------------------------------------------------------------------------------------------------


def _write(path: Union[str, Path], meta: dict, arrays: Dict[str, np.ndarray]) -> None:
    from .io.npz import save_npz

    save_npz(path, {"meta": np.array(json.dumps(meta, allow_nan=True)), **arrays})


def _read(path: Union[str, Path]) -> Tuple[dict, Dict[str, np.ndarray]]:
    p = Path(path)
    if not p.is_file():
        raise CheckpointError(f"{p}: no such checkpoint file")
    try:
        with np.load(p, allow_pickle=False) as z:
            if "meta" not in z.files:
                raise CheckpointError(f"{p}: not a fepr checkpoint (no 'meta' entry)")
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k != "meta"}
    except CheckpointError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError) as exc:
        raise CheckpointError(f"{p}: not a readable checkpoint ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
        raise CheckpointError(f"{p}: not a fepr checkpoint")
    if meta.get("version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{p}: checkpoint version {meta.get('version')!r} (written by fepr {meta.get('fepr', '?')}); this fepr "
            f"reads version {FORMAT_VERSION}"
        )
    return meta, arrays


# --- one simulation ------------------------------------------------------------------------------------------


def _simulation_parts(sim, prefix: str, history: bool) -> Tuple[dict, Dict[str, np.ndarray]]:
    """A simulation's meta entry and arrays, under ``prefix``."""
    from . import __version__

    enc = _Encoder(prefix)
    recipe = {k: enc(v) for k, v in sim._recipe.items()}
    arrays = dict(enc.arrays)
    carry = sim._sim.carry()
    for name, values in carry.items():
        arrays[f"{prefix}carry/{name}"] = np.asarray(values, dtype=np.float64)
    if history:
        arrays[f"{prefix}history"] = sim._history.table()
    meta = {
        "recipe": recipe,
        "carry": sorted(carry),
        "history_columns": list(sim._history.columns) if history else None,
        "steps": int(sim.num_steps),
        "time": float(sim.time),
        "mesh_sha256": mesh_hash(sim.mesh.vertices, sim.mesh.tets),
        "warned": [sim._warned_runaway, sim._warned_unconverged, sim._warned_unresolved],
        "fepr": __version__,
    }
    return meta, arrays


def _build_simulation(meta: dict, arrays: Dict[str, np.ndarray], prefix: str, where: str, threads):
    from .simulation import Simulation

    try:
        recipe = {k: _decode(v, arrays, where) for k, v in meta["recipe"].items()}
        sim = Simulation(**recipe, threads=threads)
    except (ConfigError, TypeError, KeyError) as exc:
        raise CheckpointError(f"{where}: cannot rebuild the simulation: {exc}") from None
    if mesh_hash(sim.mesh.vertices, sim.mesh.tets) != meta.get("mesh_sha256"):
        raise CheckpointError(f"{where}: the mesh in the checkpoint does not match its recorded hash (damaged file)")
    carry = {}
    for name in meta["carry"]:
        key = f"{prefix}carry/{name}"
        if key not in arrays:
            raise CheckpointError(f"{where}: the checkpoint lacks {key!r} (damaged file)")
        carry[name] = arrays[key].astype(np.float64).ravel().tolist()
    try:
        sim._sim.resume(carry)
    except ValueError as exc:
        raise CheckpointError(f"{where}: {exc}") from None
    sim._history.clear()
    table = arrays.get(f"{prefix}history")
    if table is not None:
        if meta.get("history_columns") != list(sim._history.columns):
            raise CheckpointError(
                f"{where}: the checkpoint's history has other columns than this fepr's (written by fepr "
                f"{meta.get('fepr', '?')})"
            )
        sim._history.append(table)
    else:
        # Without the history: the store starts at the checkpoint's step (its row is the core's last row).
        sim._take_history()
    sim._warned_runaway, sim._warned_unconverged, sim._warned_unresolved = (bool(w) for w in meta["warned"])
    return sim


def save_simulation(sim, path: Union[str, Path], *, history: bool = True) -> None:
    """Write ``sim`` (a :class:`fepr.Simulation`) to ``path`` (see the module docs)."""
    from . import __version__

    meta, arrays = _simulation_parts(sim, "", history)
    _write(path, {"format": _FORMAT, "version": FORMAT_VERSION, "kind": "simulation", "fepr": __version__,
                  "body": meta}, arrays)


def load_simulation(path: Union[str, Path], *, threads: Optional[int] = None):
    """The :class:`fepr.Simulation` saved in ``path``, resumed."""
    meta, arrays = _read(path)
    if meta.get("kind") != "simulation":
        raise CheckpointError(
            f"{path}: holds a {meta.get('kind')!r} checkpoint; use fepr.MultiBody.load_checkpoint for a multi-body one"
        )
    return _build_simulation(meta["body"], arrays, "", str(path), threads)


# --- several bodies ------------------------------------------------------------------------------------------


def save_multibody(system, path: Union[str, Path], *, history: bool = True) -> None:
    """Write ``system`` (a :class:`fepr.MultiBody`) to ``path``: each body as :func:`save_simulation` writes one,
    and the system's names, contact switch and coefficients."""
    from . import __version__

    bodies, arrays = [], {}
    for k, b in enumerate(system.bodies):
        meta, a = _simulation_parts(b, f"body{k}/", history)
        bodies.append(meta)
        arrays.update(a)
    meta = {
        "format": _FORMAT,
        "version": FORMAT_VERSION,
        "kind": "multibody",
        "fepr": __version__,
        "names": list(system.names),
        "contact": bool(system.contact),
        "coefficients": [list(map(float, c)) for c in system.coefficients],
        "bodies": bodies,
    }
    _write(path, meta, arrays)


def load_multibody(path: Union[str, Path], *, threads: Optional[int] = None):
    """The :class:`fepr.MultiBody` saved in ``path``, resumed."""
    from .multibody import MultiBody

    meta, arrays = _read(path)
    if meta.get("kind") != "multibody":
        raise CheckpointError(
            f"{path}: holds a {meta.get('kind')!r} checkpoint; use fepr.Simulation.load_checkpoint for one body"
        )
    names = meta["names"]
    bodies = [
        _build_simulation(b, arrays, f"body{k}/", f"{path} (body {names[k]!r})", threads)
        for k, b in enumerate(meta["bodies"])
    ]
    coefficients = meta["coefficients"]
    return MultiBody(
        bodies,
        names=names,
        contact=meta["contact"],
        restitution=[c[0] for c in coefficients],
        friction=[c[1] for c in coefficients],
    )
