"""The built-in demo (``fepr demo``): short scenes on builtin meshes, each run with and without FEPR.

The scenes follow the reference results of the project's FEPR spec (section 7):

- ``seed_demo3_stretch``: the seed's demo 3 analogue. The builtin L, stretched 1.5x about the origin and
  released; Neo-Hookean E = 1e3 Pa, nu = 0.3, 5 kg per vertex, symplectic Euler, dt = 1/30 s, 300 steps, no
  gravity. Without projection the step is unstable and runs away; with it, H, P and L stay at their
  initial values.
- ``seed_demo1_wobble``: the seed's "wobbly" start on the builtin L: stretched 1.2x about its centre of mass and
  every other vertex pushed down at 2 m/s; symplectic Euler, dt = 1/30 s, no gravity. Without projection the
  energy wanders by about 20%; with it, H, P and L stay.
- ``spinning_l_gravity``: the L stretched 5% about its centre of mass, spinning at 1 rad/s about z and thrown
  at 1 m/s along x under gravity; dt = 1/100 s, 100 steps. P follows P0 + m g t, L (about the centre of mass)
  is conserved.
- ``dropped_box``: a box dropped from rest under gravity; dt = 1/60 s, 60 steps.
- ``wobbly_box``: a box pinned at its base, pushed sideways under gravity (Stable Neo-Hookean); energy is
  conserved, momenta are not (the pins exchange momentum with the body).
- ``implicit_ell``: the L stretched 1.3x, spinning and drifting, with backward Euler at dt = 1/30 s (the paper's
  headline): alone it damps the motion away; with FEPR H, P and L stay.
- ``implicit_cantilever``: a bar pinned at one end sagging under gravity, backward Euler at dt = 1/30 s: alone
  the oscillation dies out; with FEPR (energy row) it keeps swinging.
- ``box_on_ground``: a soft box dropped 0.5 m onto the ground (restitution 0.5, friction 0.3) with backward Euler,
  Projective Dynamics and XPBD at dt = 1/60 s: contact is held inside the implicit solve (no impact substeps);
  with FEPR the energy books (H0 + the contact's losses) close through the impacts and at rest.

The seed's three initial conditions on the L are ``seed_demo3_stretch``, ``seed_demo1_wobble`` and
``spinning_l_gravity``. ``implicit_ell`` and ``implicit_cantilever`` are also run with Projective Dynamics
(:data:`GALLERY`): every dissipative base integrator alone damps the motion out; with FEPR the energy is held.

``fepr demo`` (:func:`main`) runs the gallery through :func:`fepr.cli.compare.compare`, writes each scene's plots,
side-by-side video, summary and report under ``./fepr-demo/<scene>/`` with an index ``report.html``, and prints
a table. :func:`run_demos` runs the same scenes without any rendering (numbers only).
"""

from __future__ import annotations

import copy
import sys
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

from ..report.metrics import FIELDS, LEGEND
from ..scene import RunResult, Scene, run_scene, scene_from_dict

__all__ = [
    "DEMO_SCENES",
    "GALLERY",
    "GalleryItem",
    "demo_scenes",
    "format_gallery_table",
    "format_table",
    "main",
    "run_demos",
    "run_gallery",
]

G = [0.0, 0.0, -9.81]

#: The demo scenes, as scene-file dicts (the same content as the files in ``examples/``).
DEMO_SCENES: Dict[str, Dict[str, Any]] = {
    "seed_demo3_stretch": {
        "scene": {"description": "the L stretched 1.5x and released (seed demo 3), no gravity"},
        "mesh": {"builtin": "ell"},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 5.0},
        "initial": {"scale": 1.5},
        "integrator": {"name": "symplectic_euler", "dt": 1.0 / 30.0},
        "projection": {"enabled": True},
        "world": {"gravity": [0.0, 0.0, 0.0]},
        "run": {"steps": 300},
    },
    "seed_demo1_wobble": {
        "scene": {"description": "the L stretched 1.2x, every other vertex pushed down at 2 m/s, no gravity"},
        "mesh": {"builtin": "ell"},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 5.0},
        "initial": {"scale": 1.2, "scale_about": "centroid", "alternating_velocity": [0.0, 0.0, -2.0]},
        "integrator": {"name": "symplectic_euler", "dt": 1.0 / 30.0},
        "projection": {"enabled": True},
        "world": {"gravity": [0.0, 0.0, 0.0]},
        "run": {"steps": 240},
    },
    "spinning_l_gravity": {
        "scene": {"description": "the L stretched 5%, spinning 1 rad/s about z, thrown at 1 m/s, gravity"},
        "mesh": {"builtin": "ell"},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 5.0},
        "initial": {
            "scale": 1.05,
            "scale_about": "centroid",
            "angular_velocity": [0.0, 0.0, 1.0],
            "velocity": [1.0, 0.0, 0.0],
        },
        "integrator": {"name": "symplectic_euler", "dt": 0.01},
        "projection": {"enabled": True},
        "world": {"gravity": G},
        "run": {"steps": 100},
    },
    "dropped_box": {
        "scene": {"description": "a box dropped from rest under gravity"},
        "mesh": {"builtin": "box", "size": [1.0, 1.0, 1.0], "resolution": 2, "center": [0.0, 0.0, 1.0]},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e4, "poisson_ratio": 0.3},
        "mass": {"density": 100.0},
        "integrator": {"name": "symplectic_euler", "dt": 1.0 / 60.0},
        "projection": {"enabled": True},
        "world": {"gravity": G},
        "run": {"steps": 60},
    },
    "box_on_ground": {
        "scene": {"description": "a soft box dropped 0.5 m onto the ground, contact inside the implicit solve"},
        "mesh": {"builtin": "box", "size": [0.5, 0.5, 0.5], "resolution": 4, "center": [0.0, 0.0, 0.75]},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e5, "poisson_ratio": 0.3},
        "mass": {"density": 1000.0},
        "integrator": {"name": "implicit_euler", "dt": 1.0 / 60.0},
        "projection": {"enabled": True},
        "world": {
            "gravity": G,
            "obstacles": [
                {
                    "type": "plane",
                    "point": [0.0, 0.0, 0.0],
                    "normal": [0.0, 0.0, 1.0],
                    "restitution": 0.5,
                    "friction": 0.3,
                }
            ],
        },
        "run": {"steps": 120},
    },
    "wobbly_box": {
        "scene": {"description": "a box pinned at its base, pushed sideways, under gravity"},
        "mesh": {"builtin": "box", "size": [1.0, 1.0, 1.0], "resolution": 3, "center": [0.0, 0.0, 0.5]},
        "material": {"model": "stable_neo_hookean", "youngs_modulus": 2e4, "poisson_ratio": 0.3},
        "mass": {"density": 100.0},
        "initial": {"velocity": [1.0, 0.0, 0.0]},
        "integrator": {"name": "symplectic_euler", "dt": 1.0 / 120.0},
        "projection": {"enabled": True, "rows": "auto"},
        "world": {"gravity": G, "pin_below": {"axis": "z", "value": 1e-6}},
        "run": {"steps": 240},
    },
    "implicit_ell": {
        "scene": {"description": "the L stretched 1.3x, spinning and drifting, backward Euler"},
        "mesh": {"builtin": "ell"},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 5.0},
        "initial": {
            "scale": 1.3,
            "scale_about": "centroid",
            "angular_velocity": [0.0, 0.0, 1.0],
            "velocity": [0.5, 0.2, 0.1],
        },
        "integrator": {"name": "implicit_euler", "dt": 1.0 / 30.0},
        "projection": {"enabled": True},
        "world": {"gravity": [0.0, 0.0, 0.0]},
        "run": {"steps": 150},
    },
    "implicit_cantilever": {
        "scene": {"description": "a bar pinned at one end sagging under gravity, backward Euler"},
        "mesh": {"builtin": "box", "size": [1.0, 0.1, 0.1], "resolution": [20, 2, 2], "center": [0.5, 0.0, 1.0]},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e7, "poisson_ratio": 0.3},
        "mass": {"density": 1000.0},
        "integrator": {"name": "implicit_euler", "dt": 1.0 / 30.0},
        "projection": {"enabled": True},
        "world": {"gravity": G, "pin_below": {"axis": "x", "value": 1e-9}},
        "run": {"steps": 150},
    },
}


def demo_scenes() -> List[Scene]:
    """The demo scenes, validated (see :data:`DEMO_SCENES`)."""
    scenes = []
    for name, d in DEMO_SCENES.items():
        d = copy.deepcopy(d)
        d.setdefault("scene", {})["name"] = name
        scenes.append(scene_from_dict(d, ".", source=f"demo:{name}"))
    return scenes


def run_demos(
    *,
    steps: Optional[int] = None,
    out_dir: Union[str, Path, None] = None,
    on_result: Optional[Callable[[RunResult], None]] = None,
) -> List[RunResult]:
    """Run every demo scene with and without projection.

    Parameters
    ----------
    steps : int, optional
        Steps per run (default: each scene's own).
    out_dir : str or Path, optional
        If given, each run writes ``diagnostics.csv`` and ``final_state.npz`` to
        ``out_dir/<scene>/fepr`` or ``out_dir/<scene>/plain``.
    on_result : callable, optional
        Called with each :class:`RunResult` as soon as it is available.
    """
    results = []
    for scene in demo_scenes():
        for projection in (True, False):
            sub = None
            if out_dir is not None:
                sub = Path(out_dir) / scene.name / ("fepr" if projection else "plain")
            res = run_scene(scene, steps=steps, out_dir=sub, projection=None if projection else False)
            res.simulation = None  # do not keep the simulations alive
            results.append(res)
            if on_result is not None:
                on_result(res)
    return results


#: The columns of the demo tables: the scene, FEPR on/off, then the summary numbers of
#: :data:`fepr.report.metrics.FIELDS` (the same headers and cells as ``summary.md``).
HEADER = ("scene", "FEPR") + tuple(h for _, h in FIELDS)


def format_row(r: RunResult) -> List[str]:
    """The table cells for one run (:meth:`fepr.report.metrics.RunMetrics.cell`)."""
    return [r.scene, "on" if r.projection else "off"] + [r.metrics.cell(k) for k, _ in FIELDS]


def _legend() -> List[str]:
    return [textwrap.fill(line[2:].replace("**", ""), width=110, subsequent_indent="  ") for line in LEGEND]


def _aligned(rows: List[List[str]], left: int) -> List[str]:
    """Rows as text columns (the first ``left`` left-aligned), a rule under the header."""
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = []
    for k, row in enumerate(rows):
        cells = [c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))]
        lines.append("  ".join(cells).rstrip())
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    return lines


def _flags(items: Sequence[Tuple[str, Any]]) -> List[str]:
    """``problems:`` and ``notes:`` blocks for (name, RunMetrics) pairs, empty when there are none."""
    lines: List[str] = []
    problems = [f"  {name}: {'; '.join(m.problems())}" for name, m in items if m.problems()]
    notes = [f"  {name}: {'; '.join(m.notes())}" for name, m in items if m.notes()]
    if problems:
        lines += ["", "problems:"] + problems
    if notes:
        lines += ["", "notes:"] + notes
    return lines


def format_table(results: List[RunResult]) -> str:
    """A plain-text table of demo results, one line per run, with the runs' problems and notes and a legend."""
    lines = _aligned([list(HEADER)] + [format_row(r) for r in results], left=3)
    lines += _flags([(f"{r.scene} (FEPR {'on' if r.projection else 'off'})", r.metrics) for r in results])
    lines += [""] + _legend()
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------
# The gallery: every demo scene as a side-by-side comparison (plots, video, summary, report)
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GalleryItem:
    """One scene of ``fepr demo``: its name in :data:`DEMO_SCENES`, the integrators to compare (``None``: the
    scene's own) and an optional shorter run for the video."""

    name: str
    integrators: Optional[Tuple[str, ...]] = None
    steps: Optional[int] = None


#: What ``fepr demo`` shows, in order. Integrators that the installed extension lacks are left out.
GALLERY: Tuple[GalleryItem, ...] = (
    GalleryItem("seed_demo3_stretch", steps=150),
    GalleryItem("seed_demo1_wobble", steps=150),
    GalleryItem("spinning_l_gravity"),
    GalleryItem("dropped_box"),
    GalleryItem("wobbly_box"),
    GalleryItem("implicit_ell", integrators=("implicit_euler", "projective_dynamics", "xpbd"), steps=120),
    GalleryItem("implicit_cantilever", integrators=("implicit_euler", "projective_dynamics"), steps=90),
    GalleryItem("box_on_ground", integrators=("implicit_euler", "projective_dynamics", "xpbd"), steps=120),
)

#: Video settings of the demo: frames per scene, panel size (pixels), frames per second.
DEMO_FRAMES = 30
DEMO_SIZE = (480, 352)
DEMO_FPS = 15.0


def _gallery_scene(item: GalleryItem) -> Scene:
    d = copy.deepcopy(DEMO_SCENES[item.name])
    d.setdefault("scene", {})["name"] = item.name
    return scene_from_dict(d, ".", source=f"demo:{item.name}")


def _integrators(item: GalleryItem) -> Optional[List[str]]:
    if item.integrators is None:
        return None
    from .. import _core

    names = [n for n in item.integrators if n in _core.INTEGRATORS]
    return names or None


def run_gallery(
    out_dir: Union[str, Path],
    *,
    steps: Optional[int] = None,
    frames: int = DEMO_FRAMES,
    size: Tuple[int, int] = DEMO_SIZE,
    video: bool = True,
    quiet: bool = False,
    on_result: Optional[Callable[[Any], None]] = None,
) -> List[Any]:
    """Run every :data:`GALLERY` scene through :func:`fepr.cli.compare.compare` into ``out_dir/<scene>/``.

    Returns the :class:`fepr.cli.compare.CompareResult` of each scene. ``steps`` overrides every scene's length.
    """
    from .compare import compare
    from .progress import progress_bar

    results = []
    out = Path(out_dir)
    with progress_bar(len(GALLERY), desc="fepr demo", unit="scene", quiet=quiet) as bar:
        for item in GALLERY:
            bar.set_description(f"fepr demo: {item.name}")
            res = compare(
                _gallery_scene(item),
                out / item.name,
                integrators=_integrators(item),
                steps=item.steps if steps is None else steps,
                frames=frames,
                size=size,
                fps=DEMO_FPS,
                video=video,
                quiet=True,
            )
            for run in res.runs:  # the recorded frames are no longer needed
                run.frames = run.frames[:0]
            results.append(res)
            bar.update(1)
            if on_result is not None:
                on_result(res)
    return results


GALLERY_HEADER = ("scene", "integrator", "FEPR") + tuple(h for _, h in FIELDS)


def _gallery_name(res: Any, run: Any) -> str:
    return res.scene if run.spec.default else f"{res.scene}/{run.spec.integrator}"


def gallery_rows(results: Sequence[Any]) -> List[List[str]]:
    """Table cells, one row per run; runs of an integrator other than the scene's own are named
    ``scene/integrator``."""
    rows = []
    for res in results:
        for run, m in zip(res.runs, res.metrics):
            head = [_gallery_name(res, run), run.spec.integrator, "on" if run.spec.projection else "off"]
            rows.append(head + [m.cell(k) for k, _ in FIELDS])
    return rows


def format_gallery_table(results: Sequence[Any]) -> str:
    """The plain-text table of ``fepr demo``: one line per run, the runs' problems and notes, and a legend."""
    lines = _aligned([list(GALLERY_HEADER)] + gallery_rows(results), left=4)
    items = [
        (f"{_gallery_name(res, run)} ({run.spec.label})", m) for res in results for run, m in zip(res.runs, res.metrics)
    ]
    lines += _flags(items)
    lines += [""] + _legend()
    return "\n".join(lines)


def _write_index(out: Path, results: Sequence[Any]) -> Path:
    from ..report.html import report_page
    from .compare import _section

    sections = []
    for res in results:
        setup = ""
        summary = res.out_dir / "summary.json"
        if summary.is_file():
            import json

            info = json.loads(summary.read_text())["setup"]
            setup = f"{info['steps']} steps of dt = {info['dt']:.4g} s; total mass {info['total_mass']:.4g} kg."
        description = DEMO_SCENES[res.scene].get("scene", {}).get("description", "")
        sections.append(_section(res, res.scene, description, setup, prefix=f"{res.scene}/"))
    intro = (
        "Each scene runs with FEPR (warm colours) and without it (cool colours), side by side with the same "
        "camera. Without projection, symplectic Euler drifts or runs away, and backward Euler and Projective "
        "Dynamics damp the motion out; with FEPR the energy, linear and angular momentum are held."
    )
    path = out / "report.html"
    path.write_text(report_page("fepr demo", sections, intro=intro))
    return path


def main(
    steps: Optional[int] = None,
    out_dir: Union[str, Path, None] = None,
    quiet: bool = False,
    *,
    frames: int = DEMO_FRAMES,
    size: Tuple[int, int] = DEMO_SIZE,
    video: bool = True,
    strict: bool = False,
) -> int:
    """Run the gallery, write ``out_dir`` (default ``./fepr-demo``), print the table (what ``fepr demo`` does).

    Returns 0; with ``strict``, 3 when a run with FEPR has a problem (a runaway, inverted tets at the end,
    unconverged projections, unresolved energy above 1e-3; :meth:`fepr.cli.compare.CompareResult.problems`).
    """
    out = Path("fepr-demo") if out_dir is None else Path(out_dir)
    start = time.perf_counter()

    def report(res) -> None:
        if not quiet:
            print(f"  {res.summary_line()}", flush=True)

    if not quiet:
        print(f"fepr demo: {len(GALLERY)} scenes, each with FEPR on and off -> {out}", flush=True)
    results = run_gallery(out, steps=steps, frames=frames, size=size, video=video, quiet=quiet, on_result=report)
    index = _write_index(out, results)
    if not quiet:
        print()
    print(format_gallery_table(results))
    notes = sorted({r.video_error for r in results if r.video_error} | {r.plot_error for r in results if r.plot_error})
    for note in notes:
        print(f"note: {note}", file=sys.stderr, flush=True)
    runs = sum(len(r.runs) for r in results)
    print(
        f"\nfepr demo: {len(results)} scenes, {runs} runs in {time.perf_counter() - start:.1f} s; report: {index}",
        flush=True,
    )
    problems = [f"{r.scene}: {p}" for r in results for p in r.problems()]
    if strict and problems:
        print(f"fepr: --strict: {'; '.join(problems)}", file=sys.stderr, flush=True)
        return 3
    return 0
