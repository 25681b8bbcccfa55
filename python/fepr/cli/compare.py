"""Side-by-side comparisons (``fepr compare``): one scene with and without FEPR, for one or more integrators.

:func:`compare` runs every (integrator, projection) pair, then writes to the output folder::

    energy.png, momentum.png        plots, one curve per run (matplotlib)
    side_by_side.mp4, .gif          the runs next to each other, same camera (polyscope off-screen on EGL)
    summary.md, summary.json        the table (fepr.report.metrics): energy error against the books, unresolved
                                    energy, P and L drift against the targets, min J, inverted tets,
                                    unconverged projections, substeps, iterations, ms/step; each run's problems
    report.html                     all of the above on one page
    fepr/, plain/, <integrator>-fepr/, ...   each run's diagnostics.csv and final_state.npz

Example::

    from fepr.cli.compare import compare
    result = compare("examples/seed_demo3_stretch.toml", "out/cmp", integrators=["symplectic_euler"], steps=120)
    print(result.summary_line())
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import ConfigError, MissingDependencyError
from ..report.metrics import RunMetrics, compute_metrics, format_value, length_scale
from ..report.runs import RecordedRun, RunSpec, available_integrators, frame_steps, record_run
from .progress import progress_bar

__all__ = ["CompareResult", "compare", "parse_size"]

#: Default frames of the video, panel size (pixels) and frame rate (1/s).
DEFAULT_FRAMES = 48
DEFAULT_SIZE = (640, 480)
DEFAULT_FPS = 24.0


def parse_size(text: str) -> Tuple[int, int]:
    """``"640x480"`` as ``(640, 480)``; sizes are rounded down to multiples of 16 when rendering."""
    try:
        w, h = (int(t) for t in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"size must look like 640x480, got {text!r}") from None
    if not (64 <= w <= 4096 and 64 <= h <= 4096):
        raise ConfigError(f"panel size must be between 64 and 4096 pixels per side, got {text!r}")
    return w, h


@dataclass
class CompareResult:
    """What :func:`compare` did: the runs, their metrics, the files written and the timings (s)."""

    scene: str
    out_dir: Path
    runs: List[RecordedRun]
    metrics: List[RunMetrics]
    rows: List[Dict[str, str]]
    files: Dict[str, Path] = field(default_factory=dict)
    video_frames: int = 0
    video_size: Optional[Tuple[int, int]] = None
    ms_per_frame: Optional[float] = None
    video_error: Optional[str] = None
    plot_error: Optional[str] = None
    run_s: float = 0.0
    render_s: float = 0.0
    wall_s: float = 0.0

    @property
    def report(self) -> Path:
        return self.out_dir / "report.html"

    def run_lines(self) -> List[str]:
        """One summary line per run (:meth:`fepr.report.metrics.RunMetrics.summary_line`, labelled by run)."""
        return [m.summary_line(r.spec.label) for r, m in zip(self.runs, self.metrics)]

    def problems(self, projected_only: bool = True) -> List[str]:
        """``"label: problem"`` for every problem of the runs with FEPR (of every run with
        ``projected_only=False``): what ``--strict`` fails on. The runs without FEPR are there to show what
        goes wrong without it."""
        return [
            f"{r.spec.label}: {p}"
            for r, m in zip(self.runs, self.metrics)
            if r.spec.projection or not projected_only
            for p in m.problems()
        ]

    def summary_line(self) -> str:
        """One line: the scene, the runs, the largest energy error (against the books) with and without FEPR,
        the problems of the runs with FEPR, the time, the report."""
        on = [m.energy_error for r, m in zip(self.runs, self.metrics) if r.spec.projection]
        off = [m.energy_error for r, m in zip(self.runs, self.metrics) if not r.spec.projection]
        parts = [f"{self.scene}: {len(self.runs)} runs"]
        if on:
            parts.append(f"energy error {format_value('energy_error', max(on))} with FEPR")
        if off:
            parts.append(f"{format_value('energy_error', max(off))} without")
        problems = self.problems()
        if problems:
            word = "problem" if len(problems) == 1 else "problems"
            parts.append(f"{len(problems)} {word} with FEPR ({'; '.join(problems)})")
        video = (
            f"{self.video_frames} frames {self.video_size[0]}x{self.video_size[1]}" if self.video_size else "no video"
        )
        parts.append(video)
        parts.append(f"{self.wall_s:.1f} s")
        return ", ".join(parts) + f" -> {self.report}"


def _load(scene):
    from ..scene import Scene, load_scene

    if isinstance(scene, Scene):
        return scene
    path = Path(scene)
    if not path.is_file():
        raise ConfigError(f"scene file not found: {path}")
    return load_scene(path)


def _check_integrators(integrators: Optional[Sequence[str]], default: str) -> List[str]:
    if not integrators:
        return [default]
    known = available_integrators()
    names = list(dict.fromkeys(str(n) for n in integrators))
    for n in names:
        if n not in known:
            raise ConfigError(f"unknown integrator {n!r} (known: {', '.join(known)})")
    return names


def _setup_text(scene, run: RecordedRun, steps: int, dt: float) -> str:
    g = np.asarray(scene.world.gravity, dtype=np.float64)
    grav = "no gravity" if not np.any(g) else f"gravity {np.linalg.norm(g):.3g} m/s²"
    pins = ", pinned vertices" if run.pinned else ""
    return (
        f"{len(run.rest_positions)} vertices, {len(run.tets)} tets; {steps} steps of dt = {dt:.4g} s "
        f"({steps * dt:.3g} s); total mass {run.total_mass:.4g} kg; {grav}{pins}."
    )


def compare(
    scene,
    out_dir: Union[str, Path],
    *,
    integrators: Optional[Sequence[str]] = None,
    steps: Optional[int] = None,
    frames: int = DEFAULT_FRAMES,
    size: Tuple[int, int] = DEFAULT_SIZE,
    fps: float = DEFAULT_FPS,
    video: bool = True,
    gif: bool = True,
    plots: bool = True,
    html_report: bool = True,
    quiet: bool = True,
    title: Optional[str] = None,
) -> CompareResult:
    """Run ``scene`` with and without FEPR for each integrator and write plots, videos and the report.

    Parameters
    ----------
    scene : fepr.scene.Scene or path
        The scene (a TOML file or a validated scene).
    out_dir : str or Path
        Output folder (created).
    integrators : sequence of str, optional
        Base integrators (default: the scene's own); names from ``fepr._core.INTEGRATORS``.
    steps : int, optional
        Steps per run (default: ``[run] steps``).
    frames : int
        Video frames, evenly spaced over the run (at most ``steps + 1``).
    size : (int, int)
        Panel size in pixels (width, height).
    fps : float
        Video frame rate, frames per second.
    video, gif, plots, html_report : bool
        What to write besides the runs' diagnostics and ``summary.md``.
    quiet : bool
        No progress bars.

    Returns
    -------
    CompareResult
        When the video cannot be rendered here (no polyscope or no EGL), ``video_error`` says why and the rest
        is still written; the same holds for the plots and ``plot_error``.
    """
    t_start = time.perf_counter()
    sc = _load(scene)
    names = _check_integrators(integrators, sc.integrator.name)
    n = sc.run.steps if steps is None else int(steps)
    if n < 0:
        raise ConfigError(f"steps must be >= 0, got {n}")
    if int(frames) < 1:
        raise ConfigError(f"frames must be >= 1, got {frames}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    at = frame_steps(n, int(frames))
    specs = [
        RunSpec(name, proj, index=i, default=(name == sc.integrator.name))
        for i, name in enumerate(names)
        for proj in (True, False)
    ]
    runs: List[RecordedRun] = []
    with progress_bar(n * len(specs), desc=f"{sc.name}: simulate", unit="step", quiet=quiet) as bar:
        for spec in specs:
            runs.append(record_run(sc, spec, n, at, out_dir=out, on_steps=bar.update))
    run_s = time.perf_counter() - t_start
    metrics = [
        compute_metrics(
            r.history,
            total_mass=r.total_mass,
            gravity=r.gravity,
            length_scale=length_scale(r.rest_positions),
            pinned=r.pinned,
            projection=r.spec.projection,
            runaway_step=r.runaway_step,
        )
        for r in runs
    ]
    from ..report.summary import summary_markdown, table_rows

    rows = table_rows(runs, metrics)
    result = CompareResult(scene=sc.name, out_dir=out, runs=runs, metrics=metrics, rows=rows, run_s=run_s)
    setup = _setup_text(sc, runs[0], n, float(sc.integrator.dt))
    heading = title or f"{sc.name}: with and without FEPR"
    (out / "summary.md").write_text(summary_markdown(heading, sc.description, setup, rows))
    result.files["summary.md"] = out / "summary.md"
    if plots:
        _write_plots(result, sc.name)
    t_render = time.perf_counter()
    if video:
        _write_video(result, sc.name, len(at), size=size, fps=fps, gif=gif, quiet=quiet, ground=_ground_height(sc))
    result.render_s = time.perf_counter() - t_render
    _write_summary_json(result, sc, n, at, fps)
    if html_report:
        from ..report.html import report_page

        section = _section(result, heading, sc.description, setup)
        (out / "report.html").write_text(report_page(heading, [section]))
        result.files["report.html"] = out / "report.html"
    result.wall_s = time.perf_counter() - t_start
    return result


def _write_plots(result: CompareResult, name: str) -> None:
    """``energy.png`` and ``momentum.png``; without matplotlib, ``plot_error`` says why."""
    from ..report.plots import energy_plot, momentum_plot

    out, runs = result.out_dir, result.runs
    try:
        result.files["energy.png"] = energy_plot(runs, out / "energy.png", title=f"{name}: energy")
        result.files["momentum.png"] = momentum_plot(runs, out / "momentum.png", title=f"{name}: momentum")
    except MissingDependencyError as exc:
        result.plot_error = str(exc)


def _ground_height(scene) -> Optional[float]:
    """The height (m) of the scene's ground, a plane obstacle facing up (+z), or None: the video draws a floor
    only where the scene has one."""
    for ob in scene.world.obstacles:
        if ob.type == "plane" and ob.motion is None:
            n = np.asarray(ob.geometry.get("normal", (0.0, 0.0, 1.0)), dtype=np.float64)
            if np.linalg.norm(n) > 0 and n[2] / np.linalg.norm(n) > 1.0 - 1e-9:
                return float(np.asarray(ob.geometry.get("point", (0.0, 0.0, 0.0)), dtype=np.float64)[2])
    return None


def _write_video(
    result: CompareResult,
    name: str,
    frames: int,
    *,
    size: Tuple[int, int],
    fps: float,
    gif: bool,
    quiet: bool,
    ground: Optional[float] = None,
) -> None:
    """``side_by_side.mp4`` (and ``.gif``) of the recorded frames; where it cannot be rendered (no polyscope or
    no EGL), ``video_error`` says why."""
    from ..report.render import RenderUnavailable, render_video

    try:
        with progress_bar(frames, desc=f"{name}: render", unit="frame", quiet=quiet) as bar:
            v = render_video(
                result.runs, result.out_dir, size=size, fps=fps, gif=gif, on_frame=bar.update, ground=ground
            )
        result.files["side_by_side.mp4"] = v.mp4
        if gif:
            result.files["side_by_side.gif"] = v.gif
        result.video_frames, result.video_size, result.ms_per_frame = v.frames, v.size, v.ms_per_frame
    except (RenderUnavailable, MissingDependencyError) as exc:
        result.video_error = str(exc)


def _write_summary_json(result: CompareResult, sc, n: int, at, fps: float) -> None:
    """``summary.json``: the setup, every run's metrics and the video's size and speed."""
    from ..report.summary import summary_json

    runs = result.runs
    summary_json(
        result.out_dir / "summary.json",
        scene=sc.name,
        setup={
            "description": sc.description,
            "steps": n,
            "dt": float(sc.integrator.dt),
            "total_mass": runs[0].total_mass,
            "gravity": [float(g) for g in runs[0].gravity],
            "length_scale": length_scale(runs[0].rest_positions),
            "pinned": runs[0].pinned,
            "frame_steps": [int(s) for s in at],
        },
        runs=runs,
        metrics=result.metrics,
        video=None
        if result.video_size is None
        else {
            "frames": result.video_frames,
            "width": result.video_size[0],
            "height": result.video_size[1],
            "fps": fps,
            "ms_per_frame": result.ms_per_frame,
        },
    )
    result.files["summary.json"] = result.out_dir / "summary.json"


def _section(result: CompareResult, heading: str, description: str, setup: str, prefix: str = "") -> str:
    from ..report.html import report_section

    note = None
    if result.video_error:
        note = f"No video: {result.video_error}"
    return report_section(
        heading,
        description=description,
        setup=setup,
        rows=result.rows,
        colors=[r.spec.color for r in result.runs],
        prefix=prefix,
        video=result.video_size is not None,
        diagnostics=[f"{r.spec.folder}/diagnostics.csv" for r in result.runs],
        note=note,
    )
