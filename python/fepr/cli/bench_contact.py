"""``fepr bench``'s contact scenes: the pile of bodies, a body on a triangle-mesh terrain, a body folding onto
itself, and how the cost of detecting contact between bodies grows with their number.

- ``pile``: ``examples/pile.toml`` (:func:`pile_scene`: eight bodies of 2-3k tets dropped into a bin,
  Projective Dynamics at dt = 1/60 with FEPR) over 2 s, the landing and the settling: milliseconds per step and
  steps per second, the same run without FEPR (the ratio is FEPR's cost), and the share of a step that detection
  between the bodies takes (one detection pass timed at the state after the run, against the mean step);
- ``terrain``: a 384-tet box dropped onto the built-in terrain (6,720 triangles) with backward Euler at dt = 1/60
  and FEPR, against the same drop onto a plane (the ratio is the terrain's cost);
- ``fold``: ``examples/fold.toml`` (:func:`fold_scene`: a 960-tet bar folded over a rod, its halves swinging into
  each other, Projective Dynamics at dt = 1/60 with FEPR) with self contact and without (the ratio is self
  contact's cost, impact substeps included);
- ``detection``: 1 to 64 boxes (384 tets each) in a touching grid; seconds per detection pass, and the growth
  exponent between the first and the last count (1 is linear).

Every figure is measured in this process, one run; speeds are to be compared as ratios within a run.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any, Dict, List, Tuple

import numpy as np

__all__ = ["contact_suite", "fold_scene", "format_contact", "pile_scene"]


def pile_scene() -> Dict[str, Any]:
    """The scene of ``examples/pile.toml`` as a dict (an installed package has no examples folder; a test holds
    the two equal): four balls and four boxes (Stable Neo-Hookean 1e5 / 0.4, 1000 kg/m^3, restitution 0.3,
    friction 0.4) in two layers above a 1 m bin (floor and four walls), Projective Dynamics at 1/60, FEPR."""
    grip = {"restitution": 0.3, "friction": 0.4}
    walls = [
        {"type": "box", "center": [cx, cy, 0.3], "half_extents": [hx, hy, 0.3], **grip}
        for cx, cy, hx, hy in [
            (-0.52, 0, 0.02, 0.54),
            (0.52, 0, 0.02, 0.54),
            (0, -0.52, 0.54, 0.02),
            (0, 0.52, 0.54, 0.02),
        ]
    ]
    bodies = []
    for layer, z in enumerate([0.35, 0.75]):
        shift = 0.03 if layer else -0.03
        for i, (x, y) in enumerate([(-0.2, -0.2), (0.2, -0.2), (-0.2, 0.2), (0.2, 0.2)]):
            k = 4 * layer + i + 1
            if (i + layer) % 2 == 0:
                name = f"ball{k}"
                mesh = {"builtin": "sphere", "radius": 0.15, "resolution": 8, "center": [round(x + shift, 2), y, z]}
            else:
                name = f"box{k}"
                mesh = {"builtin": "box", "size": 0.26, "resolution": 7, "center": [x, round(y + shift, 2), z]}
            bodies.append(
                {
                    "name": name,
                    "mesh": mesh,
                    "material": {"model": "stable_neo_hookean", "youngs_modulus": 1e5, "poisson_ratio": 0.4},
                    "mass": {"density": 1000.0},
                    **grip,
                }
            )
    return {
        "scene": {"name": "pile", "description": "eight soft bodies dropped into a bin"},
        "integrator": {"name": "projective_dynamics", "dt": 1 / 60},
        "world": {"gravity": [0.0, 0.0, -9.81], "obstacles": [{"type": "plane", **grip}] + walls},
        "bodies": bodies,
        "run": {"steps": 120},
    }


def _pile(steps: int) -> Dict[str, Any]:
    """The pile over ``steps`` steps with FEPR and again without (the same scene, projection off): ms per step
    of each, their ratio, and the run with FEPR's detection share, parts, convergence and books."""
    from .. import _core
    from ..scene import scene_from_dict

    def run(projection: bool):
        scene = pile_scene()
        if not projection:
            scene["projection"] = {"enabled": False}
        system = scene_from_dict(scene, ".").build_multibody()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            t0 = time.perf_counter()
            system.step(steps)
            wall = time.perf_counter() - t0
        return system, wall / steps

    system, per_step = run(True)
    _, off_per_step = run(False)
    detect = _core.bench_body_detection([b._sim for b in system.bodies], 5)
    h = [b.history for b in system.bodies]
    return {
        "bodies": len(system.bodies),
        "tets": int(sum(len(b.tets) for b in system.bodies)),
        "steps": steps,
        "ms_per_step": 1e3 * per_step,
        "steps_per_s": 1.0 / per_step,
        "off_ms_per_step": 1e3 * off_per_step,
        "ratio": per_step / off_per_step,
        "detection_ms": 1e3 * detect,
        "detection_share": detect / per_step,
        "max_parts": int(max(x["base_substeps"].max() for x in h)),
        "unconverged": int(sum((x["proj_converged"][1:] == 0).sum() for x in h)),
        "books": float(
            max(np.max(np.abs(x["total"] - x["total"][0] - x["budget_total"])) / abs(x["total"][0]) for x in h)
        ),
    }


def _timed_run(sim, steps: int) -> Tuple[float, float]:
    """Run ``steps`` steps of ``sim`` (its warnings silenced): milliseconds per step and the worst books, relative
    to the first step's energy."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        t0 = time.perf_counter()
        sim.step(steps)
        ms = 1e3 * (time.perf_counter() - t0) / steps
    h = sim.history
    return ms, float(np.max(np.abs(h["total"] - h["total"][0] - h["budget_total"])) / abs(h["total"][0]))


def _terrain(steps: int) -> Dict[str, Any]:
    import fepr

    out: Dict[str, Any] = {}
    grounds = {
        "terrain": fepr.MeshObstacle.terrain(
            size=3.0, cells=40, height=0.08, wavelength=0.8, restitution=0.5, friction=0.3
        ),
        "plane": fepr.Plane(restitution=0.5, friction=0.3),
    }
    for name, ground in grounds.items():
        sim = fepr.Simulation(
            fepr.meshes.box(size=0.4, resolution=4, center=(0.1, 0.05, 0.5)),
            material=fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4),
            density=1000.0,
            dt=1 / 60,
            integrator="implicit_euler",
            gravity=(0.0, 0.0, -9.81),
            obstacles=[ground],
        )
        out[f"{name}_ms_per_step"], out[f"{name}_books"] = _timed_run(sim, steps)
    out["ratio"] = out["terrain_ms_per_step"] / out["plane_ms_per_step"]
    return out


def fold_scene(self_contact: bool = True) -> Dict[str, Any]:
    """The scene of ``examples/fold.toml`` as a dict (a test holds the two equal): a 1.6 m bar (8 cm square,
    960 tets, Stable Neo-Hookean 1e5 / 0.4, 1000 kg/m^3) dropped across a rod at 1 m, over a floor, Projective
    Dynamics at 1/60, FEPR; with self contact (restitution 0.2, friction 0.5) or without."""
    grip = {"restitution": 0.2, "friction": 0.8}
    world: Dict[str, Any] = {
        "gravity": [0.0, 0.0, -9.81],
        "obstacles": [
            {"type": "capsule", "a": [0.0, -0.5, 1.0], "b": [0.0, 0.5, 1.0], "radius": 0.03, **grip},
            {"type": "plane", **grip},
        ],
    }
    if self_contact:
        world["self_contact"] = {"restitution": 0.2, "friction": 0.5}
    return {
        "scene": {"name": "fold", "description": "a long bar folds over a rod and its halves swing into each other"},
        "mesh": {"builtin": "box", "size": [1.6, 0.08, 0.08], "resolution": [40, 2, 2], "center": [0.0, 0.0, 1.1]},
        "material": {"model": "stable_neo_hookean", "youngs_modulus": 1e5, "poisson_ratio": 0.4},
        "mass": {"density": 1000.0},
        "integrator": {"name": "projective_dynamics", "dt": 1 / 60},
        "world": world,
        "run": {"steps": 120},
    }


def _fold(steps: int) -> Dict[str, Any]:
    from ..scene import scene_from_dict

    out: Dict[str, Any] = {}
    for name, self_contact in (("self", True), ("none", False)):
        sim = scene_from_dict(fold_scene(self_contact), ".").build()
        out[f"{name}_ms_per_step"], out[f"{name}_books"] = _timed_run(sim, steps)
        out[f"{name}_max_parts"] = int(sim.history["base_substeps"].max())
    out["ratio"] = out["self_ms_per_step"] / out["none_ms_per_step"]
    return out


def _detection(counts: List[int]) -> Dict[str, Any]:
    import fepr

    from .. import _core

    mat = fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4)
    seconds = []
    for n in counts:
        side = math.ceil(n ** (1 / 3))
        sims = []
        for k in range(n):
            i, j, m = k % side, (k // side) % side, k // (side * side)
            # 0.3 m boxes 0.29 m apart: neighbours overlap by 1 cm, so every pair of neighbours is queried.
            center = (0.29 * i, 0.29 * j, 0.29 * m)
            sims.append(
                fepr.Simulation(
                    fepr.meshes.box(size=0.3, resolution=4, center=center), material=mat, density=1000.0, dt=1e-3
                )
            )
        seconds.append(_core.bench_body_detection([s._sim for s in sims], 5))
    exponent = (
        math.log(seconds[-1] / seconds[0]) / math.log(counts[-1] / counts[0]) if len(counts) > 1 else float("nan")
    )
    return {"bodies": counts, "seconds": seconds, "exponent": exponent}


def contact_suite(quick: bool = False) -> Dict[str, Any]:
    """The contact scenes (see the module docstring); ``quick``: a few steps and up to 8 bodies (CI)."""
    return {
        "pile": _pile(2 if quick else 120),   # 2 s: the landing and the settling
        "terrain": _terrain(5 if quick else 60),
        "fold": _fold(40 if quick else 120),
        "detection": _detection([1, 2, 4, 8] if quick else [1, 2, 4, 8, 16, 32, 64]),
    }


def format_contact(c: Dict[str, Any]) -> str:
    """The contact scenes as text lines."""
    lines = ["contact scenes"]
    p = c["pile"]
    lines.append(
        f"  pile ({p['bodies']} bodies, {p['tets']} tets, PD 1/60 + FEPR, {p['steps']} steps): "
        f"{p['ms_per_step']:.1f} ms/step ({p['steps_per_s']:.1f} steps/s; without FEPR {p['off_ms_per_step']:.1f}, "
        f"{p['ratio']:.2f}x), detection {p['detection_ms']:.2f} ms = {100 * p['detection_share']:.1f}% "
        f"of a step, impact parts up to {p['max_parts']}, {p['unconverged']} unconverged projections, "
        f"books {p['books']:.1e}"
    )
    t = c["terrain"]
    lines.append(
        f"  terrain (384-tet box, BE 1/60 + FEPR): {t['terrain_ms_per_step']:.2f} ms/step on the terrain, "
        f"{t['plane_ms_per_step']:.2f} on a plane ({t['ratio']:.2f}x); books {t['terrain_books']:.1e}"
    )
    f = c["fold"]
    lines.append(
        f"  fold (960-tet bar, PD 1/60 + FEPR): {f['self_ms_per_step']:.2f} ms/step with self contact, "
        f"{f['none_ms_per_step']:.2f} without ({f['ratio']:.2f}x; impact parts up to {f['self_max_parts']}); "
        f"books {f['self_books']:.1e}"
    )
    d = c["detection"]
    pairs = ", ".join(f"{n}: {1e3 * s:.2f} ms" for n, s in zip(d["bodies"], d["seconds"]))
    lines.append(f"  detection between bodies ({pairs}): grows as n^{d['exponent']:.2f}")
    return "\n".join(lines)
