"""Running a scene (what ``fepr run`` does): build it, step it, measure it, write its outputs.

:func:`run_scene` builds the simulation of a :class:`fepr.scene.Scene` (:mod:`fepr.scene.build`), steps it in
chunks (reporting progress, exporting frames), catches a runaway instead of raising, summarises the run with
:mod:`fepr.report.metrics` (:class:`RunResult`) and writes ``diagnostics.csv`` and ``final_state.npz``.
"""

from __future__ import annotations

import re
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import ConfigError, SimulationError
from .schema import Scene

__all__ = ["RunResult", "run_scene"]


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


def _write_diagnostics(sim, path: Path) -> None:
    """``diagnostics.csv``: the history of a simulation; for a multi-body system its totals with the momentum
    targets and the other columns :func:`fepr.report.metrics.system_history` adds (so that the summary can be
    recomputed from the file)."""
    from ..multibody import MultiBody

    if not isinstance(sim, MultiBody):
        sim.save_diagnostics(str(path))
        return
    from ..report.metrics import system_history
    from ..simulation import History

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
    from ..multibody import MultiBody

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
    start_steps = int(sim.num_steps)
    recorders = _export_recorders(scene, sim, out_dir, export, export_every)
    if progress is not None:
        progress(0, n, sim)
    t_start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        done = _step_and_record(sim, n, start_steps, recorders, progress, result)
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
        _write_outputs(result, scene, sim, Path(out_dir))
    _warn_problems(result)
    return result


def _step_and_record(sim, n: int, start_steps: int, recorders: list, progress, result: RunResult) -> int:
    """Step ``n`` steps in chunks of a tenth of the run (calling ``progress`` after each), stopping at every frame
    the recorders export; returns the steps done. A runaway (:class:`fepr.SimulationError`) is recorded in
    ``result`` instead of raised, and the recorders are closed either way."""
    chunk = max(1, n // 10)
    done = 0
    next_report = chunk
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
    return done


def _write_outputs(result: RunResult, scene: Scene, sim, out: Path) -> None:
    """``diagnostics.csv`` and ``final_state.npz`` in ``out`` (created if needed), and for a multi-body scene
    ``diagnostics_<body>.csv`` per body; their paths go into ``result``."""
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
