"""Running a scene (what ``fepr run`` does): build it, step it, measure it, write its outputs.

:func:`run_scene` builds the simulation of a :class:`fepr.scene.Scene` (:mod:`fepr.scene.build`), steps it in
chunks (reporting progress, exporting frames), catches a runaway instead of raising, summarises the run with
:mod:`fepr.report.metrics` (:class:`RunResult`) and writes ``diagnostics.csv`` and ``final_state.npz``.
"""

from __future__ import annotations

import re
import signal
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import ConfigError, SimulationError
from .schema import Scene

__all__ = ["RunResult", "StopRequest", "run_scene", "PROGRESS_S"]

#: Seconds between calls of :func:`run_scene`'s ``progress`` within a tenth of the run.
PROGRESS_S = 1.0


class StopRequest:
    """A request to stop a run at the next step boundary and keep its work, set by a signal handler.

    :meth:`install` (from the main thread) makes SIGINT and SIGTERM set it; a second signal while the run saves
    its work raises ``KeyboardInterrupt`` as usual (the files written so far stay complete: every file is written
    through a temporary name). Calling the object says whether a stop was requested (it is the step callback).
    """

    def __init__(self):
        self.signum: Optional[int] = None
        self._previous: Dict[int, Any] = {}

    def __call__(self, *_args) -> bool:
        return self.signum is not None

    def _handler(self, signum, frame) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum

    def install(self) -> StopRequest:
        """Handle SIGINT and SIGTERM by requesting the stop (no-op outside the main thread)."""
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def restore(self) -> None:
        """Put back the handlers :meth:`install` replaced."""
        for sig, h in self._previous.items():
            signal.signal(sig, h)
        self._previous.clear()



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
    #: The signal that stopped the run at a step boundary (``signal.SIGINT``, ``signal.SIGTERM``), or None.
    interrupted: Optional[int] = None
    #: The run's checkpoint (``DIR/checkpoint/state_<step>.npz``) and manifest (``DIR/run.json``), if written.
    checkpoint_path: Optional[Path] = None
    manifest_path: Optional[Path] = None
    #: The step a resumed run continued from.
    resumed_from: Optional[int] = None

    @property
    def status(self) -> str:
        """``complete``, ``interrupted`` (by a signal, work kept) or ``failed`` (a runaway)."""
        if self.runaway:
            return "failed"
        return "interrupted" if self.interrupted is not None else "complete"

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
    from ..report.metrics import simulation_history

    h = simulation_history(sim)
    start = max(rows_before - 1, 0)
    return {k: v[start:] for k, v in h.items()} if start else h


def _measure(result: RunResult, sim, rows_before: int, pinned: bool) -> None:
    """Fill in the summary of ``result`` (:func:`fepr.report.metrics.simulation_metrics`) and the fields that
    repeat it."""
    from ..report.metrics import simulation_metrics

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
    from ..report.metrics import RunProblemWarning

    text = None if result.metrics is None else result.metrics.warning_text(f"{result.scene}: the run")
    if text is None:
        return
    result.warnings.append(text)
    warnings.warn(text, RunProblemWarning, stacklevel=3)


def _projection_on(scene: Scene, override) -> bool:
    if override is not None:
        return override is not False
    return scene.projection.enabled


def _export_recorders(scene: Scene, sim, out_dir, export, export_every, **kw) -> list:
    """The :class:`fepr.export.Recorder` objects of a run (none when nothing is exported).

    One-body scene: one recorder in ``out_dir/export`` named after the scene. Multi-body scene (``sim`` a
    :class:`fepr.multibody.MultiBody`): one per body in ``out_dir/export/<body>``, named ``<scene>_<body>``,
    each with its own material (for the energy density field)."""
    from ..multibody import MultiBody

    if not isinstance(sim, MultiBody):
        rec = _export_recorder(scene, sim, out_dir, export, export_every, **kw)
        return [] if rec is None else [rec]
    recs = []
    for name, body in zip(sim.names, sim.bodies):
        rec = _export_recorder(scene, body, out_dir, export, export_every, body=name, **kw)
        if rec is None:
            return []
        recs.append(rec)
    return recs


def _export_recorder(scene: Scene, sim, out_dir, export, export_every, body: Optional[str] = None, **kw):
    """The :class:`fepr.export.Recorder` for ``out_dir/export`` (``out_dir/export/<body>`` for a body of a
    multi-body scene), or ``None`` when nothing is exported."""
    from ..export import parse_formats

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
    from ..export import Recorder

    name = re.sub(r"[^A-Za-z0-9_.\-]", "_", scene.name).strip(".") or "frame"
    folder = Path(out_dir) / "export"
    if body is not None:
        name, folder = f"{name}_{body}", folder / body
    return Recorder(sim, folder, formats, every=every, name=name, **kw)


def run_scene(
    scene: Scene,
    *,
    steps: Optional[int] = None,
    out_dir: Union[str, Path, None] = None,
    projection=None,
    progress: Optional[Callable[[int, int, Any], None]] = None,
    export: Union[str, Sequence[str], None] = None,
    export_every: Optional[int] = None,
    checkpoint_every: Optional[int] = None,
    overwrite: bool = False,
    resume: bool = False,
    stop: Optional[Callable[[], bool]] = None,
) -> RunResult:
    """Build and run a scene; optionally write its outputs to ``out_dir`` (see :mod:`fepr.scene.outputs`).

    Parameters
    ----------
    scene : Scene
        The validated scene.
    steps : int, optional
        Number of steps of the run (default: ``[run] steps``; for a resumed run, the number it was started with).
    out_dir : str or Path, optional
        Folder for ``diagnostics.csv`` (one row per step plus the initial row), ``final_state.npz`` and the
        manifest ``run.json``; created if needed and checked for writing before the first step. A folder that
        holds an earlier run's files is refused unless ``overwrite`` or ``resume``. Nothing is written when
        ``None``.
    projection : bool or fepr.Projection, optional
        Overrides ``[projection]`` (``False``: FEPR off).
    progress : callable, optional
        Called as ``progress(steps_done, steps_total, sim)`` before the first step, after every tenth of the
        run, and in between at most every :data:`PROGRESS_S` seconds (a long run's bar keeps its ETA current).
    export : str or sequence of str, optional
        Export formats (``"vtu,glb"``; :data:`fepr.export.FORMATS`), overriding ``[export] formats``. With
        formats from either and an ``out_dir``, every ``every``-th step (the initial state first) is written
        to ``out_dir/export`` by a :class:`fepr.export.Recorder` named after the scene; without ``out_dir``
        nothing is exported (an explicit ``export`` then raises :class:`fepr.ConfigError`).
    export_every : int, optional
        Overrides ``[export] every``.
    checkpoint_every : int, optional
        Write a checkpoint to ``out_dir/checkpoint`` every this many steps (the run can then be resumed with
        ``resume=True`` after a crash or a kill); an interrupted run writes one either way.
    overwrite : bool
        Replace an earlier run's files in ``out_dir`` (those its manifest lists).
    resume : bool
        Continue the run in ``out_dir`` from its last checkpoint, with the settings it was started with; the
        result is bit-identical to the uninterrupted run.
    stop : callable, optional
        Checked after every batch of steps (at most :attr:`fepr.Simulation.BATCH_SECONDS` apart): when it returns
        True the run stops at that step boundary and keeps its work (:class:`StopRequest` is one, set by
        SIGINT and SIGTERM). A ``KeyboardInterrupt`` during the steps is handled the same way.

    Returns
    -------
    RunResult
        Steps completed, whether and where the run ran away or was interrupted, conservation errors, iterations
        and timing. A runaway (:class:`fepr.SimulationError` from ``step``) does not raise: the files are written
        with the steps completed so far and the result says where it stopped.
    """
    from .._validate import integer
    from .outputs import RunFolder

    folder = None
    if out_dir is not None:
        folder = RunFolder(out_dir, overwrite=overwrite, resume=resume)
        folder.prepare()
    elif resume or checkpoint_every is not None:
        raise ConfigError("checkpoints and resume need an output folder (out_dir)")
    if checkpoint_every is not None:
        checkpoint_every = integer(checkpoint_every, "checkpoint_every", lo=1)
    earlier = folder.earlier if resume else None
    if earlier is not None:
        settings = earlier.get("settings", {})
        n = int(settings["steps"]) if steps is None else int(steps)
        export = settings.get("export") if export is None else export
        export_every = settings.get("export_every") if export_every is None else export_every
        if checkpoint_every is None:
            checkpoint_every = settings.get("checkpoint_every")
        projection_on = bool(settings.get("projection", True))
    else:
        n = scene.run.steps if steps is None else int(steps)
        projection_on = _projection_on(scene, projection)
    if n < 0:
        raise ConfigError(f"steps must be >= 0, got {n}")
    if earlier is not None:
        sim, start_steps = _resumed_simulation(scene, folder)
    else:
        sim = (
            scene.build_multibody(projection=projection) if scene.is_multibody else scene.build(projection=projection)
        )
        start_steps = int(sim.num_steps)
    # The supports' impulses are not known: no momentum drift to measure. (Obstacles, forces and air drag are
    # in the momentum targets of the history.)
    pinned = scene.has_supports()
    result = RunResult(
        scene=scene.name,
        projection=projection_on,
        steps_requested=n,
        steps_completed=0,
        wall_s=0.0,
        simulation=sim,
        bodies=tuple(sim.names) if scene.is_multibody else (),
        resumed_from=int(sim.num_steps) if earlier is not None else None,
    )
    recorders = _export_recorders(
        scene, sim, out_dir, export, export_every, start_step=start_steps, keep_frames=folder is not None
    )
    checkpoints = worker = diagnostics = None
    if folder is not None:
        from .outputs import OutputWorker

        worker = OutputWorker(backlog=2)
        diagnostics = _Diagnostics(folder, sim, worker)
        checkpoints = _Checkpoints(folder, sim, checkpoint_every, recorders, start_steps, diagnostics)
        if earlier is not None:
            checkpoints.resume_from(earlier["checkpoint"])
        else:
            diagnostics.open()
        formats = recorders[0].formats if recorders else ()
        folder.write_manifest(
            format="fepr-run",
            fepr=_fepr_version(),
            status="running",
            scene=_scene_entry(scene, earlier),
            settings={
                "steps": n,
                "projection": projection_on,
                "export": ",".join(formats) or None,
                "export_every": recorders[0].every if recorders else None,
                "checkpoint_every": checkpoint_every,
                "bodies": list(result.bodies),
            },
            start_step=start_steps,
            steps_completed=int(sim.num_steps) - start_steps,
            time=float(sim.time),
            started=(earlier or {}).get("started", time.strftime("%Y-%m-%dT%H:%M:%S%z")),
            resumed=[*(earlier or {}).get("resumed", []), int(sim.num_steps)] if earlier is not None else [],
            checkpoint=(earlier or {}).get("checkpoint"),
            files=[],
        )
    if progress is not None:
        progress(int(sim.num_steps) - start_steps, n, sim)
    stop = stop if stop is not None else (lambda: False)
    t_start = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _step_and_record(sim, n, start_steps, recorders, progress, result, checkpoints, stop, worker)
        result.wall_s = time.perf_counter() - t_start
        if folder is not None:
            if result.interrupted is not None or checkpoints.every is not None:
                checkpoints.write()
            _write_outputs(result, scene, sim, folder, diagnostics)
    finally:
        if worker is not None:
            worker.close()
    if recorders:  # the time spent writing exports is not simulation time
        result.wall_s = max(result.wall_s - sum(rec.write_s for rec in recorders), 0.0)
        result.export_dir = recorders[0].out_dir if len(recorders) == 1 else recorders[0].out_dir.parent
        result.export_frames = recorders[0].num_frames
        result.export_formats = recorders[0].formats
        result.export_fps = recorders[0].fps
    result.warnings = [str(w.message) for w in caught]
    result.steps_completed = int(sim.num_steps) - start_steps
    # The summary (fepr.report.metrics), as every command reports it; base_unstable_step is the first step whose
    # base energy error exceeded 100% of the energy scale, whether or not a converged projection rescued it.
    rows_before = 0 if earlier is not None else start_steps + 1
    _measure(result, sim, rows_before, bool(pinned))
    if folder is not None:
        result.checkpoint_path = checkpoints.state_path
        result.manifest_path = folder.path / "run.json"
        folder.write_manifest(
            status=result.status,
            steps_completed=result.steps_completed,
            time=float(sim.time),
            finished=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            interrupted_by=None if result.interrupted is None else signal.Signals(result.interrupted).name,
            runaway_step=result.runaway_step,
            summary=result.summary(),
            files=folder.file_entries(folder.all_files()),
        )
    _warn_problems(result)
    return result


def _fepr_version() -> str:
    from .. import __version__

    return __version__


def _scene_entry(scene: Scene, earlier: Optional[dict]) -> dict:
    """What the manifest says of the scene: its name and, for a scene file, its path and SHA-256."""
    if earlier is not None and earlier.get("scene"):
        return earlier["scene"]
    entry: Dict[str, Any] = {"name": scene.name}
    src = getattr(scene, "source", None)
    if src:
        p = Path(src)
        if p.is_file():
            import hashlib

            entry["path"] = str(p.resolve())
            entry["sha256"] = hashlib.sha256(p.read_bytes()).hexdigest()
    return entry


def _bodies(sim) -> List[Tuple[str, Any]]:
    """``(name, Simulation)`` of each body (``"body"`` for a one-body run)."""
    from ..multibody import MultiBody

    if isinstance(sim, MultiBody):
        return list(zip(sim.names, sim.bodies))
    return [("body", sim)]


def _resumed_simulation(scene: Scene, folder):
    """The simulation of the run in ``folder`` at its last checkpoint (without its history, which the
    diagnostics files give back, :meth:`_Diagnostics.resume`); and the run's start step."""
    from ..errors import CheckpointError
    from ..multibody import MultiBody
    from ..simulation import Simulation

    earlier = folder.earlier
    ck = earlier.get("checkpoint")
    if not ck:
        raise ConfigError(f"--resume {folder.path}: the manifest records no checkpoint")
    if bool(earlier.get("settings", {}).get("bodies")) != scene.is_multibody:
        raise ConfigError(f"--resume {folder.path}: the scene given is not the scene of that run")
    loader = MultiBody if scene.is_multibody else Simulation
    try:
        sim = loader.load_checkpoint(folder.checkpoint_dir / ck["state"])
    except CheckpointError as exc:
        raise ConfigError(f"--resume {folder.path}: {exc}") from None
    folder.remove_stale(keep=[ck["state"], *ck.get("frames", [])])
    return sim, int(earlier.get("start_step", 0))


class _Diagnostics:
    """A run's diagnostics files, written as the run goes (:class:`fepr.scene.outputs.CsvStream` on the
    worker thread): ``diagnostics.csv`` (a body's history; for several bodies the system's totals, as
    :func:`fepr.report.metrics.system_history` gives them) and ``diagnostics_<body>.csv`` per body."""

    def __init__(self, folder, sim, worker):
        from ..history import History
        from ..multibody import MultiBody
        from .outputs import CsvStream

        self.sim, self.worker = sim, worker
        self.multi = isinstance(sim, MultiBody)
        self.streams: Dict[str, Any] = {}
        ints = History.INTEGER_COLUMNS
        if self.multi:
            from ..report.metrics import system_history

            names = list(system_history(sim, 0, 1))
            self.streams["diagnostics.csv"] = CsvStream(folder, "diagnostics.csv", names, [c in ints for c in names])
        for name, body in _bodies(sim):
            file = f"diagnostics_{name}.csv" if self.multi else "diagnostics.csv"
            cols = body._history.columns
            self.streams[file] = CsvStream(folder, file, cols, [c in ints for c in cols])
        self.rows = 0  # rows of every body's history handed to the streams

    #: Rows per job of the worker (about 40 ms of formatting).
    JOB_ROWS = 1500

    def open(self) -> None:
        for st in self.streams.values():
            st.open()

    def resume(self, marks: Dict[str, Dict[str, int]]) -> None:
        """Cut each file at the checkpoint's mark and give the bodies their history back from it."""
        for file, st in self.streams.items():
            if file not in marks:
                raise ConfigError(f"--resume: the checkpoint records no mark for {file}")
            table = st.resume(marks[file]["rows"], marks[file]["bytes"])
            if file == "diagnostics.csv" and self.multi:
                continue
            body = self.sim if not self.multi else self.sim[file[len("diagnostics_") : -len(".csv")]]
            body._history.clear()
            body._history.append(table)
            self.rows = len(table)

    def flush(self) -> None:
        """Hand the rows every body has and the streams do not to the worker."""
        for _, body in _bodies(self.sim):
            body._take_history()
        rows = min(len(b._history) for _, b in _bodies(self.sim))
        if rows <= self.rows:
            return
        start, self.rows = self.rows, rows
        jobs = []
        if self.multi:
            from ..report.metrics import system_history

            cols = system_history(self.sim, start, rows)
            st = self.streams["diagnostics.csv"]
            jobs.append((st, np.stack([cols[c] for c in st.columns], axis=1)))
        for name, body in _bodies(self.sim):
            st = self.streams[f"diagnostics_{name}.csv" if self.multi else "diagnostics.csv"]
            jobs.append((st, body._history.table(rows, start)))
        # Jobs of a bounded size, so that the worker's backlog (and what a stopped run waits for) stays short.
        for st, table in jobs:
            for k in range(0, len(table), self.JOB_ROWS):
                part = table[k : k + self.JOB_ROWS]
                self.worker.submit(lambda st=st, part=part: st.append(part))

    def marks(self) -> Dict[str, Dict[str, int]]:
        """Rows and bytes of each file, everything handed over written."""
        self.flush()
        self.worker.drain()
        return {file: st.mark() for file, st in self.streams.items()}

    def finish(self) -> List[Path]:
        self.flush()
        self.worker.drain()
        return [st.finish() for st in self.streams.values()]


class _Checkpoints:
    """A run's checkpoints in ``folder/checkpoint``: every ``every`` steps (or only when asked), the diagnostics'
    marks, the frames exported since the last one (for the animation files written at the end), the simulation's
    state, then the manifest (the commit: a crash before it leaves the previous checkpoint in force)."""

    def __init__(self, folder, sim, every: Optional[int], recorders: list, start_steps: int, diagnostics):
        self.folder, self.sim, self.every, self.recorders = folder, sim, every, recorders
        self.start_steps, self.diagnostics = start_steps, diagnostics
        self.blocks: List[str] = []
        self.state_path: Optional[Path] = None
        self.last_step = int(sim.num_steps)

    def resume_from(self, ck: dict) -> None:
        """Continue after the checkpoint ``ck`` (the manifest's): the diagnostics cut there, the frames replayed."""
        self.diagnostics.resume(ck["diagnostics"])
        self.blocks = list(ck.get("frames", []))
        self.state_path = self.folder.checkpoint_dir / ck["state"]
        self.last_step = int(ck["step"])
        blocks = self.folder.read_blocks(self.blocks)
        for k, rec in enumerate(self.recorders):
            parts = [blocks.get(f"frames{k}.{x}", []) for x in ("steps", "times", "positions", "velocities")]
            if parts[0]:
                rec.replay(*(np.concatenate(p) for p in parts))

    def steps_to_next(self) -> Optional[int]:
        if self.every is None:
            return None
        done = int(self.sim.num_steps) - self.start_steps
        return self.every - done % self.every

    def due(self) -> bool:
        return (
            self.every is not None
            and (int(self.sim.num_steps) - self.start_steps) % self.every == 0
            and int(self.sim.num_steps) != self.last_step
        )

    def write(self) -> None:
        """A checkpoint of the current step (nothing if it is the last one's)."""
        step = int(self.sim.num_steps)
        if step == self.last_step and self.state_path is not None:
            return
        marks = self.diagnostics.marks()
        arrays: Dict[str, np.ndarray] = {}
        for k, rec in enumerate(self.recorders):
            for key, a in rec.take_frames().items():
                arrays[f"frames{k}.{key}"] = a
        if arrays:
            first = self.last_step + 1 if self.state_path is not None else 0
            self.blocks.append(self.folder.write_frames(first, step, arrays))
        state = self.folder.checkpoint_dir / f"state_{step:012d}.npz"
        self.folder.checkpoint_dir.mkdir(exist_ok=True)
        self.sim.save_checkpoint(state, history=False)
        previous = self.state_path
        self.state_path, self.last_step = state, step
        self.folder.write_manifest(
            checkpoint={"step": step, "state": state.name, "frames": list(self.blocks), "diagnostics": marks},
            steps_completed=step - self.start_steps,
            time=float(self.sim.time),
        )
        if previous is not None and previous != state and previous.exists():
            previous.unlink()


def _step_and_record(
    sim, n: int, start_steps: int, recorders: list, progress, result: RunResult, checkpoints, stop, worker=None
) -> None:
    """Step until ``n`` steps after ``start_steps`` in chunks of a tenth of the run (calling ``progress`` after
    each), stopping at every frame the recorders export and every checkpoint. A runaway
    (:class:`fepr.SimulationError`) is recorded in ``result`` instead of raised, and so is a stop request or a
    ``KeyboardInterrupt`` (``result.interrupted``); the recorders are closed either way."""
    chunk = max(1, n // 10)
    next_report = (int(sim.num_steps) - start_steps) // chunk * chunk + chunk
    diagnostics = checkpoints.diagnostics if checkpoints is not None else None

    last_progress = [time.perf_counter()]

    def after_batch(_sim) -> bool:
        if diagnostics is not None:
            diagnostics.flush()  # the rows go to the files while the next batch steps
        if progress is not None and time.perf_counter() - last_progress[0] >= PROGRESS_S:
            last_progress[0] = time.perf_counter()
            progress(int(sim.num_steps) - start_steps, n, sim)
        return stop()

    def record() -> None:
        for rec in recorders:
            if rec.record() and worker is not None:
                for path in rec.frame_files():  # hashed for the manifest while the run goes on
                    worker.submit(lambda path=path: checkpoints.folder.note_hash(path))

    try:
        record()
        while int(sim.num_steps) - start_steps < n and not stop():
            done = int(sim.num_steps) - start_steps
            k = min(chunk, n - done)
            if recorders:  # stop at every frame to export (the recorders share the same frames)
                k = min(k, min(rec.steps_to_next() for rec in recorders))
            if checkpoints is not None and checkpoints.steps_to_next() is not None:
                k = min(k, checkpoints.steps_to_next())
            sim.step(k, after_batch)
            record()
            if checkpoints is not None and checkpoints.due():
                checkpoints.write()
            done = int(sim.num_steps) - start_steps
            if progress is not None and (done >= next_report or done == n):
                next_report = (done // chunk + 1) * chunk
                progress(done, n, sim)
        if stop() and int(sim.num_steps) - start_steps < n:
            result.interrupted = getattr(stop, "signum", None) or signal.SIGINT
    except SimulationError as exc:
        step_attr = getattr(exc, "step", None)
        result.runaway_step = int(step_attr) if isinstance(step_attr, int) else int(sim.num_steps) + 1
        result.runaway_message = str(exc)
    except KeyboardInterrupt:
        result.interrupted = signal.SIGINT
    finally:
        for rec in recorders:
            rec.close()


def _write_outputs(result: RunResult, scene: Scene, sim, folder, diagnostics: _Diagnostics) -> None:
    """The diagnostics files finished (renamed from their temporary names) and ``final_state.npz`` (through a
    temporary name) in the run's folder; their paths go into ``result``."""
    out = folder.path
    diagnostics.finish()
    result.diagnostics_path = out / "diagnostics.csv"
    result.state_path = out / "final_state.npz"
    sim.save_state(result.state_path)  # atomic (fepr.io.npz.save_npz)
    folder.note_hash(result.state_path)
    if scene.is_multibody:
        for name in sim.names:
            result.body_diagnostics_paths[name] = out / f"diagnostics_{name}.csv"


