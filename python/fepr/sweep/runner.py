"""One run of a sweep, in whatever process runs it (a Ray worker, a pool process, the driver itself).

:func:`run_one` takes a :class:`RunTask` and leaves in the run's folder ``DIR/runs/<id>/``:

- ``scene.toml``: the run's scene; ``fepr run scene.toml`` runs it alone with the same results;
- ``diagnostics.csv`` (one row per step, as ``fepr run`` writes it; with ``[[bodies]]`` the totals, plus
  ``diagnostics_<body>.csv``) and ``final_state.npz`` (:meth:`fepr.Simulation.save_state`);
- with ``frames_every``: ``positions.npy``, ``velocities.npy`` (frames, m, 3) and ``frame_times.npy``
  (:mod:`fepr.sweep.frames`);
- ``status.json``: the run's manifest: id, parameters, status (``running``, ``interrupted``, ``complete``,
  ``runaway``, ``failed``), attempts (host, process id, where each resumed from), the checkpoint, the summary
  metrics, the files with their SHA-256 and the results' digest (:func:`result_digest`);
- while it runs, ``checkpoint/state.npz``, a :meth:`fepr.Simulation.save_checkpoint` with the history, written
  every ``checkpoint_every`` steps or about every ``checkpoint_seconds`` of wall time and removed at the end.

A run that finds a checkpoint of an earlier attempt (killed, interrupted, its worker lost) continues from it:
the results are bit-identical to a run that was never stopped. A run that is already complete (status and file
hashes) returns its record without running. The mesh (rest positions and tets) goes once per mesh to
``DIR/meshes/<mesh id>.npz``.

Failures: a runaway (:class:`fepr.SimulationError`) is a result (status ``runaway``; the files hold the steps
up to it); an invalid scene or mesh (:class:`fepr.FeprError`) fails the run at once (status ``failed``, no
retry: it would fail again); any other exception is recorded in ``status.json`` and raised, so that the
executor retries the run (:mod:`fepr.sweep.backends`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np

from ..errors import CheckpointError, ConfigError, FeprError, SimulationError
from ..io.atomic import atomic_path
from ..scene.outputs import file_sha256
from .frames import FrameStore, frame_count

__all__ = ["STATUS", "RunTask", "read_status", "result_digest", "run_one", "verify_files"]

STATUS = "status.json"
CHECKPOINT = Path("checkpoint") / "state.npz"
#: The statuses of a run that is finished (a runaway is a result too: running it again gives the same).
FINISHED = ("complete", "runaway")
#: History columns that are wall times (they differ from run to run; everything else is bit-identical).
_TIMING_SUFFIX = "_ms"


@dataclass(frozen=True)
class RunTask:
    """What a worker needs to run one run (plain data, sent to other processes and machines)."""

    run_id: str
    #: The run's folder and the sweep's (paths every worker sees: shared storage on a cluster).
    run_dir: str
    sweep_dir: str
    #: The run's scene file (TOML text), written to ``scene.toml`` and run from there.
    scene_text: str
    params: Dict[str, Any]
    steps: int
    frames_every: int
    frame_velocities: bool
    checkpoint_every: Optional[int]
    checkpoint_seconds: float
    #: Threads of the simulation: the CPUs the executor gives the run (results do not depend on it).
    threads: int
    #: The driver's fepr version (a worker with another one refuses, rather than mix results).
    fepr_version: str


def read_status(folder: Path) -> Optional[Dict[str, Any]]:
    """The run's ``status.json``, or None if there is none (or it cannot be read: the run starts again)."""
    try:
        return json.loads((Path(folder) / STATUS).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _write_status(folder: Path, status: Dict[str, Any]) -> None:
    status["updated"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    with atomic_path(Path(folder) / STATUS) as tmp:
        Path(tmp).write_text(json.dumps(status, indent=1, allow_nan=True) + "\n", encoding="utf-8")


def _file_entries(folder: Path, paths: List[Path]) -> List[Dict[str, Any]]:
    return [{"path": p.name, "size": p.stat().st_size, "sha256": file_sha256(p)} for p in paths]


def verify_files(folder: Path, status: Dict[str, Any]) -> bool:
    """True if every file ``status`` lists is in ``folder`` with its size and SHA-256."""
    files = status.get("files")
    if not files:
        return False
    for f in files:
        p = Path(folder) / f["path"]
        if not p.is_file() or p.stat().st_size != f["size"] or file_sha256(p) != f["sha256"]:
            return False
    return True


def _bodies(sim) -> list:
    from ..multibody import MultiBody

    return list(sim.bodies) if isinstance(sim, MultiBody) else [sim]


def result_digest(sim, frame_files: List[Path]) -> str:
    """SHA-256 of a run's results: the final positions and velocities, the frames, and every history column but
    the wall times (``*_ms``), in float64 bytes. Equal digests are bit-identical results."""
    h = hashlib.sha256()

    def add(name: str, a) -> None:
        h.update(name.encode("ascii"))
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())

    add("positions", sim.positions)
    add("velocities", sim.velocities)
    for k, body in enumerate(_bodies(sim)):
        hist = body.history
        for c in hist.columns:
            if not c.endswith(_TIMING_SUFFIX):
                add(f"history{k}.{c}", np.asarray(hist[c], dtype=np.float64))
    for p in frame_files:
        add(p.name, np.load(p, mmap_mode="r"))
    return h.hexdigest()


def _plain(value: Any) -> Any:
    """NumPy scalars as Python numbers (for JSON)."""
    if isinstance(value, np.generic):
        return value.item()
    return value


def _write_mesh(sweep_dir: Path, sim) -> str:
    """``DIR/meshes/<id>.npz`` (rest positions (m, 3) m, tets (k, 4); with bodies, their offsets and names), once
    per mesh; returns the mesh id (16 hex digits of :func:`fepr.checkpoint.mesh_hash`)."""
    from ..checkpoint import mesh_hash
    from ..io.npz import save_npz
    from ..multibody import MultiBody

    rest, tets = np.asarray(sim.rest_positions), np.asarray(sim.tets)
    mid = mesh_hash(rest, tets)[:16]
    path = sweep_dir / "meshes" / f"{mid}.npz"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"rest_positions": rest, "tets": tets.astype(np.int64)}
        if isinstance(sim, MultiBody):
            arrays["offsets"] = np.asarray(sim.offsets)
            arrays["names"] = np.array(list(sim.names))
        save_npz(path, arrays)  # atomic: two workers writing the same mesh leave one complete file
    return mid


def _assigned_cpus(default: int) -> int:
    """The CPUs Ray gave this task (in a Ray worker), else ``default``: the simulation's threads."""
    import sys

    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        try:
            cpus = ray.get_runtime_context().get_assigned_resources().get("CPU")
        except Exception:  # not inside a task (the driver running a run itself)
            cpus = None
        if cpus:
            return max(1, int(round(cpus)))
    return default


def _check_worker(task: RunTask) -> None:
    """A worker that cannot see the sweep's folder, or has another fepr, refuses the run with a message saying
    what to fix (retrying would not help)."""
    from .. import __version__

    host = socket.gethostname()
    if not (Path(task.sweep_dir) / "sweep.json").is_file():
        raise ConfigError(
            f"the sweep folder {task.sweep_dir} is not visible on {host}: on a cluster, --out must be on storage "
            "every node mounts at the same path (NFS, a cluster file system); see docs/sweeps.md"
        )
    if __version__ != task.fepr_version:
        raise ConfigError(
            f"{host} has fepr {__version__}, the sweep was started with fepr {task.fepr_version}: install the same "
            "version on every node"
        )


def run_one(task: RunTask) -> Dict[str, Any]:
    """Run, resume or confirm one run of a sweep (see the module docs); returns its ``status.json`` content.

    Raises
    ------
    Exception
        Anything but a runaway or an invalid scene (recorded, not raised): the executor retries the run, which
        continues from its last checkpoint.
    """
    folder = Path(task.run_dir)
    try:
        _check_worker(task)
    except ConfigError as exc:  # nothing is written: the folder may not be this worker's to write
        return {
            "run_id": task.run_id,
            "params": task.params,
            "status": "failed",
            "error": str(exc),
            "attempts": 1,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "retry": False,
        }
    status = read_status(folder) or {}
    if status.get("run_id") == task.run_id and status.get("status") in FINISHED and verify_files(folder, status):
        return status
    folder.mkdir(parents=True, exist_ok=True)
    attempt = int(status.get("attempts", 0)) + 1 if status.get("run_id") == task.run_id else 1
    log = list(status.get("attempt_log", [])) if attempt > 1 else []
    log.append({"attempt": attempt, "host": socket.gethostname(), "pid": os.getpid(), "started": time.time()})
    status = {
        "format": "fepr-sweep-run",
        "version": 1,
        "run_id": task.run_id,
        "params": task.params,
        "status": "running",
        "attempts": attempt,
        "attempt_log": log,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "steps": task.steps,
        "checkpoint": status.get("checkpoint") if attempt > 1 else None,
        "error": None,
    }
    _write_status(folder, status)
    try:
        return _Run(task, folder, status).go()
    except FeprError as exc:
        if isinstance(exc, SimulationError):
            raise  # a runaway is handled while stepping; one raised later is unexpected: retried
        status.update(status="failed", error=f"{type(exc).__name__}: {exc}", retry=False)
        _write_status(folder, status)
        return status
    except Exception as exc:
        status.update(status="failed", error=f"{type(exc).__name__}: {exc}", retry=True)
        _write_status(folder, status)
        raise


class _Run:
    """The steps of one attempt: build or resume, step with frames and checkpoints, write the outputs."""

    def __init__(self, task: RunTask, folder: Path, status: Dict[str, Any]):
        self.task, self.folder, self.status = task, folder, status
        self.ck = folder / CHECKPOINT

    def _scene(self):
        from ..scene import load_scene

        path = self.folder / "scene.toml"
        if not path.is_file() or path.read_text(encoding="utf-8") != self.task.scene_text:
            with atomic_path(path) as tmp:
                Path(tmp).write_text(self.task.scene_text, encoding="utf-8")
        return load_scene(path)

    def _start(self, scene, threads: int):
        """The simulation at the last checkpoint (and the frames up to it), or built from the scene."""
        from ..multibody import MultiBody
        from ..simulation import Simulation

        task = self.task
        nframes = frame_count(task.steps, task.frames_every)
        if self.ck.is_file():
            loader = MultiBody if scene.is_multibody else Simulation
            try:
                sim = loader.load_checkpoint(self.ck, threads=threads)
            except CheckpointError:
                sim = None  # damaged or of another version: start again
            if sim is not None:
                frames = FrameStore(self.folder, nframes, len(sim.rest_positions), task.frame_velocities)
                if not nframes or frames.reopen():
                    return sim, frames, int(sim.num_steps)
        if self.ck.parent.is_dir():
            shutil.rmtree(self.ck.parent)
        scene.run.threads = threads
        sim = scene.build_multibody() if scene.is_multibody else scene.build()
        frames = FrameStore(self.folder, nframes, len(sim.rest_positions), task.frame_velocities)
        frames.discard()
        if nframes:
            frames.create()
        self.status["checkpoint"] = None
        return sim, frames, None

    def go(self) -> Dict[str, Any]:
        from ..report.metrics import simulation_metrics

        task, status = self.task, self.status
        scene = self._scene()
        threads = _assigned_cpus(task.threads)
        sim, frames, resumed_from = self._start(scene, threads)
        status["attempt_log"][-1]["resumed_from"] = resumed_from
        status["threads"] = threads
        every = task.frames_every
        wall = float((status.get("checkpoint") or {}).get("wall_s", 0.0)) if resumed_from is not None else 0.0
        recorded = (int(sim.num_steps) // every + 1) if every else 0
        if every and resumed_from is None:
            frames.record(0, sim.positions, sim.velocities, float(sim.time))
        runaway_step = runaway_message = None
        last_ck = time.perf_counter()

        def checkpoint_due(_sim=None) -> bool:
            return time.perf_counter() - last_ck >= task.checkpoint_seconds

        def checkpoint() -> None:
            nonlocal last_ck
            frames.flush()  # the frames up to here are on disk before the checkpoint that counts on them
            self.ck.parent.mkdir(exist_ok=True)
            sim.save_checkpoint(self.ck)
            status["checkpoint"] = {"step": int(sim.num_steps), "wall_s": wall + time.perf_counter() - t0}
            _write_status(self.folder, status)
            last_ck = time.perf_counter()

        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                while int(sim.num_steps) < task.steps:
                    done = int(sim.num_steps)
                    target = task.steps
                    if every:
                        target = min(target, (done // every + 1) * every)
                    if task.checkpoint_every:
                        target = min(target, (done // task.checkpoint_every + 1) * task.checkpoint_every)
                    # Without a checkpoint cadence in steps, stepping stops (at a batch boundary) when a checkpoint
                    # is due by the clock; where it stops does not change the results.
                    sim.step(target - done, None if task.checkpoint_every else checkpoint_due)
                    done = int(sim.num_steps)
                    if every and done % every == 0 and done // every == recorded:
                        frames.record(recorded, sim.positions, sim.velocities, float(sim.time))
                        recorded += 1
                    by_steps = task.checkpoint_every and done % task.checkpoint_every == 0
                    if done < task.steps and (by_steps or (not task.checkpoint_every and checkpoint_due())):
                        checkpoint()
            except SimulationError as exc:
                step_attr = getattr(exc, "step", None)
                runaway_step = int(step_attr) if isinstance(step_attr, int) else int(sim.num_steps) + 1
                runaway_message = str(exc)
            except KeyboardInterrupt:
                checkpoint()
                status.update(status="interrupted", steps_completed=int(sim.num_steps))
                _write_status(self.folder, status)
                raise
        wall += time.perf_counter() - t0
        metrics = simulation_metrics(
            sim, projection=scene.projection.enabled, pinned=scene.has_supports(), runaway_step=runaway_step
        )
        messages = sorted({str(x.message) for x in caught})[:10]
        return self._finish(scene, sim, frames, recorded, wall, runaway_step, runaway_message, messages, metrics)

    def _finish(self, scene, sim, frames, recorded, wall, runaway_step, runaway_message, messages, metrics):
        task, folder, status = self.task, self.folder, self.status
        outputs = [folder / "diagnostics.csv"]
        sim.save_diagnostics(outputs[0])
        if scene.is_multibody:
            for name, body in zip(sim.names, sim.bodies):
                outputs.append(folder / f"diagnostics_{name}.csv")
                body.save_diagnostics(outputs[-1])
        outputs.append(folder / "final_state.npz")
        sim.save_state(outputs[-1])
        frame_files = frames.finish(recorded) if task.frames_every else []
        status.update(
            status="runaway" if runaway_step is not None else "complete",
            steps_completed=int(sim.num_steps),
            runaway_step=runaway_step,
            error=runaway_message,
            frames=recorded,
            mesh_id=_write_mesh(Path(task.sweep_dir), sim),
            vertices=int(len(sim.rest_positions)),
            tets=int(len(sim.tets)),
            wall_s=wall,
            metrics={k: _plain(v) for k, v in metrics.as_dict().items()},
            problems=metrics.problems(),
            warnings=messages,
            result_sha256=result_digest(sim, frame_files),
            files=_file_entries(folder, outputs + frame_files),
            finished=time.time(),
        )
        status["attempt_log"][-1]["finished"] = status["finished"]
        _write_status(folder, status)
        if self.ck.parent.is_dir():
            shutil.rmtree(self.ck.parent)
        return status
