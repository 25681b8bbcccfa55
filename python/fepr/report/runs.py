"""Recording runs of a scene for a comparison: one :class:`RecordedRun` per (integrator, projection) pair.

A run is built from a validated :class:`fepr.scene.Scene` with its integrator swapped and FEPR on or off,
stepped to the frame steps (positions are kept for the video), and its diagnostics and final state are written
to ``out_dir/<folder>/diagnostics.csv`` and ``final_state.npz``, exactly as ``fepr run`` writes them.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np

from .. import _core
from ..errors import ConfigError, SimulationError
from .style import run_color, run_label

__all__ = ["RecordedRun", "RunSpec", "available_integrators", "frame_steps", "parse_integrators", "record_run"]


def available_integrators() -> List[str]:
    """Names of the base integrators the extension provides (``fepr._core.INTEGRATORS``)."""
    return list(_core.INTEGRATORS)


def parse_integrators(text: Optional[str], default: str) -> List[str]:
    """Parse ``"a,b"`` into integrator names, checked against :func:`available_integrators`.

    ``None`` or an empty string gives ``[default]``. Raises :class:`fepr.ConfigError` naming an unknown entry.
    """
    if text is None or not text.strip():
        return [default]
    names = [t.strip() for t in text.split(",") if t.strip()]
    known = available_integrators()
    for n in names:
        if n not in known:
            raise ConfigError(f"unknown integrator {n!r} in --integrators (known: {', '.join(known)})")
    return list(dict.fromkeys(names))


def frame_steps(steps: int, frames: int) -> np.ndarray:
    """Steps at which video frames are taken: ``min(frames, steps + 1)`` evenly spaced steps from 0 to ``steps``.

    Returns a strictly increasing (F,) int64 array that starts at 0 and ends at ``steps``.
    """
    if steps < 0 or frames < 1:
        raise ConfigError(f"need steps >= 0 and frames >= 1, got steps={steps}, frames={frames}")
    n = min(frames, steps + 1)
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    return np.round(np.linspace(0, steps, n)).astype(np.int64)


@dataclass(frozen=True)
class RunSpec:
    """One run of a comparison: the base integrator's name, FEPR on or off, and its place in the figures."""

    integrator: str
    projection: bool
    index: int = 0  # position of the integrator in the comparison (picks the colour shade)
    default: bool = True  # the scene's own integrator (its runs are written to ``fepr/`` and ``plain/``)

    @property
    def label(self) -> str:
        return run_label(self.integrator, self.projection)

    @property
    def color(self) -> str:
        return run_color(self.projection, self.index)

    @property
    def folder(self) -> str:
        """Sub-folder of the comparison's output for this run's diagnostics."""
        tag = "fepr" if self.projection else "plain"
        return tag if self.default else f"{self.integrator}-{tag}"


@dataclass
class RecordedRun:
    """A finished run: diagnostics, the positions at the frame steps, and where the files went.

    Attributes
    ----------
    frames : (F, m, 3) float64
        Positions (m) at ``frame_steps``; after a runaway the last finite state is repeated.
    frame_steps : (F,) int64
        The step of each frame.
    history : dict of str to (rows,) float64
        The diagnostics columns (row 0: the initial state), as in ``diagnostics.csv``.
    runaway_step : int or None
        The step at which the state became non-finite (the run stopped there).
    wall_s : float
        Wall time spent in ``Simulation.step``, s.
    """

    spec: RunSpec
    scene: str
    steps_requested: int
    frames: np.ndarray
    frame_steps: np.ndarray
    history: Dict[str, np.ndarray]
    runaway_step: Optional[int]
    wall_s: float
    rest_positions: np.ndarray
    tets: np.ndarray
    masses: np.ndarray
    pinned: bool
    gravity: np.ndarray
    material: object
    diagnostics_path: Optional[Path] = None
    state_path: Optional[Path] = None

    @property
    def steps_completed(self) -> int:
        return len(self.history["step"]) - 1

    @property
    def total_mass(self) -> float:
        return float(np.sum(self.masses))


def scene_with_integrator(scene, integrator: str):
    """A copy of ``scene`` whose base integrator is ``integrator``, at the same ``dt``.

    The scene's integrator options (Newton tolerance, PD iterations, ...) are kept when the name is the scene's
    own and dropped otherwise (each integrator then uses its defaults).
    """
    current = scene.integrator
    if integrator == current.name:
        return scene
    reset = {
        f.name: f.default
        for f in dataclasses.fields(current)
        if f.name not in ("name", "dt") and f.default is not dataclasses.MISSING
    }
    return dataclasses.replace(scene, integrator=dataclasses.replace(current, name=integrator, **reset))


def record_run(
    scene,
    spec: RunSpec,
    steps: int,
    frames_at: Sequence[int],
    *,
    out_dir: Optional[Path] = None,
    on_steps: Optional[Callable[[int], None]] = None,
) -> RecordedRun:
    """Run ``scene`` with ``spec`` for ``steps`` steps, keeping positions at the steps ``frames_at``.

    Parameters
    ----------
    scene : fepr.scene.Scene
        The validated scene (its integrator is replaced by ``spec.integrator``).
    spec : RunSpec
        Integrator and projection.
    steps : int
        Steps to run.
    frames_at : sequence of int
        Increasing steps in ``[0, steps]`` at which to keep the positions.
    out_dir : Path, optional
        The comparison's folder; the run writes ``out_dir/<spec.folder>/diagnostics.csv`` and ``final_state.npz``.
    on_steps : callable, optional
        Called with the number of steps just done (for progress bars).
    """
    variant = scene_with_integrator(scene, spec.integrator)
    build = variant.build_multibody if variant.is_multibody else variant.build
    sim = build(projection=None if spec.projection else False)
    first = sim.bodies[0] if variant.is_multibody else sim
    if spec.projection and first.projection is None:
        sim = build(projection=True)  # the scene disables FEPR; the "on" run turns it on with defaults
        first = sim.bodies[0] if variant.is_multibody else sim
    frames_at = [int(s) for s in frames_at]
    frames: List[np.ndarray] = []
    runaway: Optional[int] = None
    wall = 0.0
    done = 0
    keep = set(frames_at)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # runaways are reported in the summary instead
        for target in sorted(keep | {int(steps)}):
            if target > done:
                if runaway is None:
                    t0 = time.perf_counter()
                    try:
                        sim.step(target - done)
                    except SimulationError as exc:
                        step_attr = getattr(exc, "step", None)
                        runaway = int(step_attr) if isinstance(step_attr, int) else int(sim.num_steps) + 1
                    wall += time.perf_counter() - t0
                if on_steps is not None:
                    on_steps(target - done)
                done = target
            if target in keep:
                frames.append(np.array(sim.positions, dtype=np.float64))
    hist = sim.history
    run = RecordedRun(
        spec=spec,
        scene=scene.name,
        steps_requested=int(steps),
        frames=np.stack(frames) if frames else np.zeros((0,) + sim.positions.shape),
        frame_steps=np.asarray(frames_at, dtype=np.int64),
        history=hist.as_dict(),
        runaway_step=runaway,
        wall_s=wall,
        rest_positions=np.array(sim.rest_positions),
        tets=np.array(sim.tets),
        masses=np.array(sim.masses),
        pinned=bool(any(np.any(b.pinned) for b in getattr(sim, "bodies", [sim]))),
        gravity=np.array(first.gravity, dtype=np.float64),
        material=first.material,
    )
    if out_dir is not None:
        folder = Path(out_dir) / spec.folder
        folder.mkdir(parents=True, exist_ok=True)
        run.diagnostics_path = folder / "diagnostics.csv"
        run.state_path = folder / "final_state.npz"
        sim.save_diagnostics(run.diagnostics_path)
        sim.save_state(run.state_path)
    return run
