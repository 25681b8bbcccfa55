"""A sweep's runs: every case x grid point x random sample, each a complete scene with a stable id.

:func:`plan_runs` expands a :class:`~fepr.sweep.spec.SweepSpec` into :class:`RunPlan` objects, in the order
cases, then grid points (the last grid parameter varying fastest), then samples. Each run's scene is the base
scene with the run's parameters set (:func:`fepr.sweep.params.set_path`), its steps in ``[run] steps``, and is
validated as a scene before anything runs, so a bad value is an error naming the run and its parameters.

The run id (:func:`run_id`) is the first 16 hex digits of the SHA-256 of the canonical JSON (sorted keys, no
spaces) of what determines the run's results: its scene (without ``[scene]``, which only names it, and without
threads, which do not change results), with every file path replaced by the SHA-256 of the file's bytes, and the
frame settings. So an id is the same on every machine and in every sweep that runs the same simulation, and a
changed mesh file or setting is a new run.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from ..errors import ConfigError
from ..scene import scene_from_dict
from .params import ParamPath, ordered, path_text, set_path
from .sampling import sample_value
from .spec import SweepSpec, absolute_paths, path_slots
from .toml_text import scene_toml

__all__ = ["RunPlan", "canonical_json", "plan_runs", "run_id"]

#: Bumped when what a run writes or how its id is made changes (old ids then do not match: runs are redone).
ID_VERSION = 1


@dataclass(frozen=True)
class RunPlan:
    """One run of a sweep: its id, position, parameters and scene (a dict of sections, paths absolute)."""

    run_id: str
    #: Position in the sweep, from 0 (the order of the index).
    number: int
    #: The varied parameters, path -> value, in the order cases, grid, random.
    params: Dict[str, Any]
    #: The random sample this run draws (None without ``[random]``).
    sample: Optional[int]
    scene: Dict[str, Any] = field(repr=False)
    steps: int = 0

    def scene_text(self, sweep_name: str) -> str:
        """The run's scene file (TOML), named ``<sweep>-<id>``; ``fepr run`` runs it alone, bit-identically."""
        named = {**self.scene.get("scene", {}), "name": f"{sweep_name}-{self.run_id}"}
        scene = {"scene": named, **{k: v for k, v in self.scene.items() if k != "scene"}}
        header = (
            f"Run {self.run_id} of the sweep {sweep_name!r}: {canonical_json(self.params)}\n"
            "Written by fepr sweep; `fepr run scene.toml --out DIR` runs it alone with the same results."
        )
        return scene_toml(scene, header)


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no spaces: the same text for the same data (floats in shortest round-trip)."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def _file_digest(path: str, cache: Dict[str, str]) -> str:
    """SHA-256 of a file's bytes (a TetGen basename: of its .node and .ele files), cached per path."""
    if path not in cache:
        p = Path(path)
        parts = [p] if p.is_file() else [Path(path + ext) for ext in (".node", ".ele") if Path(path + ext).is_file()]
        h = hashlib.sha256()
        for part in parts:
            with open(part, "rb") as fh:
                for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                    h.update(block)
        cache[path] = "sha256:" + h.hexdigest() if parts else "missing:" + path
    return cache[path]


def run_id(scene: Dict[str, Any], frames_every: int, frame_velocities: bool, cache: Optional[dict] = None) -> str:
    """The stable id of a run (see the module docs): 16 hex digits."""
    material = copy.deepcopy({k: v for k, v in scene.items() if k != "scene"})
    cache = {} if cache is None else cache
    for table, key in path_slots(material):
        table[key] = _file_digest(table[key], cache)
    material.get("run", {}).pop("threads", None)
    key = {
        "id_version": ID_VERSION,
        "scene": material,
        "frames_every": frames_every,
        "frame_velocities": bool(frame_velocities) if frames_every else None,
    }
    return hashlib.sha256(canonical_json(key).encode("ascii")).hexdigest()[:16]


def _grid_points(spec: SweepSpec) -> List[List[Tuple[ParamPath, Any]]]:
    paths = [p for p, _ in spec.grid]
    return [list(zip(paths, values)) for values in itertools.product(*(v for _, v in spec.grid))]


def _where(spec: SweepSpec) -> str:
    return f"{spec.source}: " if spec.source else ""


def plan_runs(spec: SweepSpec) -> List[RunPlan]:
    """The runs of a sweep (see the module docs).

    Raises
    ------
    ConfigError
        If a run's scene is invalid (the message names the run's parameters, then the section and key as scene
        errors do), or two runs are the same simulation (the same id: a value listed twice).
    """
    cases = spec.cases or [[]]
    samples: List[Optional[int]] = list(range(spec.samples)) if spec.random else [None]
    grid = _grid_points(spec)
    cache: Dict[str, str] = {}
    plans: List[RunPlan] = []
    seen: Dict[str, Dict[str, Any]] = {}
    for case, point, k in itertools.product(cases, grid, samples):
        assigned: List[Tuple[ParamPath, Any]] = [*case, *point]
        if k is not None:
            assigned += [(p, sample_value(d, spec.seed, k, path_text(p))) for p, d in spec.random]
        params = {path_text(p): v for p, v in assigned}
        scene = copy.deepcopy(spec.base)
        for path, value in ordered(assigned):
            set_path(scene, path, value)
        absolute_paths(scene, spec.sweep_dir)  # paths given as parameters are relative to the sweep file
        run = scene.setdefault("run", {})
        if ("run", "steps") not in {p for p, _ in assigned} and spec.steps is not None:
            run["steps"] = spec.steps
        run.pop("threads", None)
        try:
            parsed = scene_from_dict(scene, spec.sweep_dir)
        except ConfigError as exc:
            raise ConfigError(
                f"{_where(spec)}the run with {canonical_json(params)} (run {len(plans) + 1}): {exc}"
            ) from None
        run["steps"] = parsed.run.steps  # explicit, so the run's scene file says how far it goes
        if spec.frames_every > parsed.run.steps > 0:
            raise ConfigError(
                f"{_where(spec)}[sweep] frames_every ({spec.frames_every}) is more than the run's steps "
                f"({parsed.run.steps}) for the run with {canonical_json(params)}"
            )
        rid = run_id(scene, spec.frames_every, spec.frame_velocities, cache)
        if rid in seen:
            raise ConfigError(
                f"{_where(spec)}two runs are the same simulation (id {rid}): {canonical_json(seen[rid])} and "
                f"{canonical_json(params)}; is a value listed twice?"
            )
        seen[rid] = params
        plans.append(RunPlan(rid, len(plans), params, k, scene, int(parsed.run.steps)))
    return plans
