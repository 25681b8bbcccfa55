"""``fepr bench``'s real-time scenes for the implicit integrators, each with FEPR on and off (steps per second):

- ``bunny``: the 19,379-tet bunny of the main suite (0.5 m, Neo-Hookean 1e5 / 0.3, 1000 kg/m^3, released from a
  10% stretch, no gravity) at dt = 1/30 with backward Euler and with XPBD (20 substeps x 1 iteration);
- ``armadillo drop``: the 4,406-tet armadillo (fit to 1 m, Stable Neo-Hookean 1e5 / 0.4, 1000 kg/m^3) dropped
  from 0.3 m onto a plane (restitution 0, friction 0.5) at dt = 1/60 for 3 s, impacts included, with backward
  Euler and with Projective Dynamics.

Beside each speed: the Newton (or local/global) iterations per step, the impact substeps the simulation took,
the mesh quality (smallest J, most inverted tets on a step) and the energy books (``total - (H0 +
budget_total)`` relative to the run's largest energy), so that a speed is never read without what it bought.
Both meshes come from the shared meshes directory; without it the scenes are skipped. Every figure is one run
in this process: compare speeds as ratios within a run.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np

__all__ = ["format_implicit", "implicit_suite"]


def _summary(sim, steps: int, seconds: float) -> Dict[str, Any]:
    """What a timed run of ``steps`` steps bought: speed, solver work, quality and the books."""
    h = sim.history
    total, budget = np.asarray(h["total"]), np.asarray(h["budget_total"])
    scale = max(float(np.max(np.abs(total))), 1e-300)
    books = np.abs(total - (total[0] + budget)) / scale
    return {
        "steps": steps,
        "ms_per_step": 1e3 * seconds / steps,
        "steps_per_s": steps / seconds,
        "base_iterations": float(np.mean(h["base_iterations"][1:])),
        "substeps_max": int(np.max(h["base_substeps"])),
        "min_j": float(np.min(h["min_j"])),
        "inverted_max": int(np.max(h["inverted"])),
        "books": float(np.max(books)),
        "lowest_com": float(np.min(h["cz"])),
    }


def _bunny(meshes: Path, integrator: str, projection: bool, steps: int) -> Dict[str, Any]:
    from .bench import SCENES, _make_sim, load_scene_mesh

    scene = SCENES["bunny"]
    mesh, why = load_scene_mesh(scene, meshes)
    if mesh is None:
        return {"skipped": why}
    sim = _make_sim(scene, mesh, integrator, 1 / 30, None, projection=projection)
    sim.step(1)  # the first step builds the factorisation's analysis or the colouring
    t0 = time.perf_counter()
    sim.step(steps)
    return _summary(sim, steps, time.perf_counter() - t0)


def _armadillo_drop(meshes: Path, integrator: str, projection: bool, steps: int) -> Dict[str, Any]:
    import fepr

    path = meshes / "Armadillo_Tetra_4406.vtu"
    if not path.exists():
        return {"skipped": f"{path} is not present"}
    sim = fepr.Simulation(
        fepr.io.load_mesh(path, fit=1.0),
        material=fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4),
        density=1000.0,
        integrator=integrator,
        dt=1 / 60,
        projection=projection,
        gravity=(0.0, 0.0, -9.81),
        obstacles=[fepr.Plane((0, 0, 0), (0, 0, 1), restitution=0.0, friction=0.5)],
    )
    x0 = sim.positions
    sim.positions = x0 + np.array([0.0, 0.0, 0.3 - x0[:, 2].min()])
    t0 = time.perf_counter()
    sim.step(steps)
    return _summary(sim, steps, time.perf_counter() - t0)


def implicit_suite(quick: bool = False, meshes: Optional[Path] = None) -> Dict[str, Any]:
    """Every scene with FEPR on and off (see the module docs); ``quick``: a few steps each."""
    from .bench import shared_meshes_dir

    meshes = meshes if meshes is not None else shared_meshes_dir()
    if meshes is None:
        return {"skipped": "the shared meshes directory (../shared/meshes or $FEPR_SHARED_MESHES) is not present"}
    bunny_steps, drop_steps = (2, 10) if quick else (10, 180)
    out: Dict[str, Any] = {}
    with warnings.catch_warnings():
        # The bunny's released stretch at dt = 1/30 books energy the guard cannot restore (a warning says so).
        warnings.simplefilter("ignore", RuntimeWarning)
        for integrator in ("implicit_euler", "xpbd"):
            out[f"bunny/{integrator}"] = {
                ("fepr" if p else "plain"): _bunny(meshes, integrator, p, bunny_steps) for p in (True, False)
            }
        for integrator in ("implicit_euler", "projective_dynamics"):
            out[f"armadillo_drop/{integrator}"] = {
                ("fepr" if p else "plain"): _armadillo_drop(meshes, integrator, p, drop_steps) for p in (True, False)
            }
    return out


def format_implicit(suite: Dict[str, Any]) -> str:
    """Lines for the terminal: per scene and integrator, steps per second with FEPR and without."""
    if "skipped" in suite:
        return f"implicit scenes: skipped ({suite['skipped']})"
    lines = ["implicit scenes (one run; FEPR on / off):"]
    for name, runs in suite.items():
        on, off = runs["fepr"], runs["plain"]
        if "skipped" in on:
            lines.append(f"  {name}: skipped ({on['skipped']})")
            continue
        lines.append(
            f"  {name}: {on['steps_per_s']:.1f} / {off['steps_per_s']:.1f} steps/s "
            f"({on['ms_per_step']:.1f} / {off['ms_per_step']:.1f} ms per step, {on['steps']} steps), "
            f"iterations {on['base_iterations']:.1f} / {off['base_iterations']:.1f}, "
            f"substeps <= {on['substeps_max']}, min J {on['min_j']:.2f} / {off['min_j']:.2f}, "
            f"inverted <= {on['inverted_max']} / {off['inverted_max']}, books {on['books']:.1e}"
        )
    return "\n".join(lines)
