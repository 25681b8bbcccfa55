"""The gauntlet: FEPR on real meshes, every base integrator, four scenarios, with and without the projection.

Meshes (``../shared/meshes``, or ``$FEPR_SHARED_MESHES``, or ``--meshes-dir``), each loaded with ``fit=0.3``,
``center="bbox"``, Stable Neo-Hookean E = 1e5 Pa, nu = 0.4, density 1000 kg/m^3:

- ``bunny2``: ``seed/bunny2.1.node`` (29,548 tets), ``bunny``: ``bunny.msh`` (19,379),
  ``armadillo``: ``Armadillo_Tetra_4406.vtu`` (4,406), ``little_elephant``: ``little-elephant.msh`` (24,953),
- ``elephant``: ``elephant.obj`` filled by ``fepr.tetrahedralize`` (TetGen). Its surface has 12,064 triangles, which
  sets the floor of the tet count (``max_volume`` only refines: TetGen's default radius-edge bound 2.0 gives
  32,687 tets with or without it); the bound 3.0 used here gives 25,545 tets (median quality 0.19).

Integrators: symplectic Euler at half its stability limit (``dt = 0.5 * 2 / omega_max`` with ``omega_max^2`` the
largest eigenvalue of ``M^-1 K`` at rest, by power iteration on finite-difference Hessian-vector products of the
elastic gradient), backward Euler, Projective Dynamics and XPBD at dt = 1/60 and 1/30 s.

Scenarios: ``stretch`` (10% about the centre of mass, at rest, no gravity), ``free_fall`` (at rest, gravity),
``spin`` (rigid 2 pi rad/s about (0.3, 0.2, 1), no gravity), ``drop`` (0.1 m above a plane, restitution and
friction 0.5, gravity; runs at least until 0.1 s after the ideal landing time).

Each case runs with and without FEPR; the FEPR run is judged against the same case without it:

- ``inversions``: no inverted tet where the base integrator alone has none;
- ``min_j``: min J over the run never more than 0.1 below the base run's;
- ``books``: ``max |H - (H0 + budget_total)| / E_scale <= 1e-8``;
- ``momentum``: P and L within 1e-10 (relative) of their values (stretch, spin: the initial ones; free fall: the
  targets, which include gravity; not judged for the drop);
- ``converged``: every projection converged;
- ``completed``: the FEPR run finished (no non-finite state).

Usage::

    fpy benchmarks/gauntlet.py --meshes armadillo --duration 0.2 --json out.json --out table.md

The module is also the library the tests use (``tests/test_gauntlet.py``): :func:`load_mesh`,
:func:`build_case`, :func:`run_case`, :func:`run_pair`, :func:`evaluate`, :func:`markdown_table`.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

import fepr

REPO = Path(__file__).resolve().parents[1]

MESH_FILES: Dict[str, str] = {
    "bunny2": "seed/bunny2.1.node",
    "bunny": "bunny.msh",
    "armadillo": "Armadillo_Tetra_4406.vtu",
    "little_elephant": "little-elephant.msh",
    "elephant": "elephant.obj",
}
MESHES: Tuple[str, ...] = tuple(MESH_FILES)
#: TetGen settings for the elephant surface (see the module docs).
ELEPHANT_TETGEN = {"quality": 3.0}
INTEGRATORS: Tuple[str, ...] = ("symplectic_euler", "implicit_euler", "projective_dynamics", "xpbd")
SCENARIOS: Tuple[str, ...] = ("stretch", "free_fall", "spin", "drop")
DTS: Tuple[float, ...] = (1 / 60, 1 / 30)

FIT = 0.3
YOUNGS_MODULUS = 1e5
POISSON_RATIO = 0.4
DENSITY = 1000.0
GRAVITY = (0.0, 0.0, -9.81)
STRETCH = 1.1
SPIN_RATE = 2 * math.pi
SPIN_AXIS = (0.3, 0.2, 1.0)
DROP_GAP = 0.1
DROP_AFTER_LANDING = 0.1
SE_SAFETY = 0.5

BOOKS_TOL = 1e-8
MOMENTUM_TOL = 1e-10
MIN_J_MARGIN = 0.1
CRITERIA = ("completed", "inversions", "min_j", "books", "momentum", "converged")


def material() -> fepr.StableNeoHookean:
    return fepr.StableNeoHookean(youngs_modulus=YOUNGS_MODULUS, poisson_ratio=POISSON_RATIO)


def plane() -> fepr.Plane:
    return fepr.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), restitution=0.5, friction=0.5)


# --- meshes --------------------------------------------------------------------------------------------------
def shared_meshes_dir(meshes_dir: Union[str, Path, None] = None) -> Optional[Path]:
    """The shared meshes folder: ``meshes_dir`` if given, else ``$FEPR_SHARED_MESHES``, else ``../shared/meshes``
    relative to the repository (the logic of ``tests/conftest.shared_meshes_dir``); None if absent."""
    if meshes_dir is not None:
        p = Path(meshes_dir)
        return p if p.is_dir() else None
    env = os.environ.get("FEPR_SHARED_MESHES")
    candidates = [Path(env)] if env else []
    candidates.append(REPO.parent / "shared" / "meshes")
    for c in candidates:
        if c.is_dir():
            return c
    return None


def _meshes_dir(meshes_dir) -> Path:
    d = shared_meshes_dir(meshes_dir)
    if d is None:
        raise FileNotFoundError("the shared meshes (../shared/meshes, $FEPR_SHARED_MESHES or --meshes-dir) are absent")
    return d


@functools.cache
def _load_mesh_cached(name: str, meshes_dir: str) -> fepr.TetMesh:
    path = Path(meshes_dir) / MESH_FILES[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # sliver warnings at load: the gauntlet measures what they do
        if name == "elephant":
            mesh = fepr.tetrahedralize(str(path), **ELEPHANT_TETGEN)
            return fepr.io.transform_mesh(mesh, fit=FIT, center="bbox")
        return fepr.load_mesh(str(path), fit=FIT, center="bbox")


def load_mesh(name: str, meshes_dir: Union[str, Path, None] = None) -> fepr.TetMesh:
    """The named gauntlet mesh, placed with ``fit=0.3, center="bbox"`` (cached per process)."""
    if name not in MESH_FILES:
        raise KeyError(f"unknown gauntlet mesh {name!r} (known: {', '.join(MESHES)})")
    return _load_mesh_cached(name, str(_meshes_dir(meshes_dir).resolve()))


def _simulation(mesh, integrator, dt, projection, threads=None, **kw) -> fepr.Simulation:
    if projection is True:
        projection = fepr.Projection()
    return fepr.Simulation(
        mesh,
        material=material(),
        density=DENSITY,
        integrator=integrator,
        dt=dt,
        projection=projection,
        threads=threads,
        **kw,
    )


def largest_frequency(sim: fepr.Simulation, *, max_iterations: int = 500, rtol: float = 1e-8, seed: int = 0):
    """omega_max (rad/s): sqrt of the largest eigenvalue of ``M^-1 K`` at the rest shape, by power iteration on
    ``M^-1/2 K M^-1/2`` with central finite-difference Hessian-vector products of the elastic gradient."""
    x0 = sim.rest_positions
    sq = np.sqrt(sim.masses)[:, None]
    r = 0.5 * float(np.linalg.norm(x0.max(axis=0) - x0.min(axis=0)))
    u = np.random.default_rng(seed).standard_normal(x0.shape)
    u /= np.linalg.norm(u)
    lam = 0.0
    for it in range(max_iterations):
        d = u / sq
        eps = 1e-7 * r / np.abs(d).max()
        gp = sim.elastic_energy_gradient(x0 + eps * d)[1]
        gm = sim.elastic_energy_gradient(x0 - eps * d)[1]
        ku = (gp - gm) / (2 * eps) / sq
        new = float(np.sum(u * ku))  # Rayleigh quotient
        u = ku / np.linalg.norm(ku)
        if it >= 20 and abs(new - lam) <= rtol * abs(new):
            lam = new
            break
        lam = new
    return math.sqrt(max(lam, 0.0))


@functools.cache
def _stable_dt_cached(name: str, meshes_dir: str) -> Tuple[float, float, float]:
    sim = _simulation(load_mesh(name, meshes_dir), "symplectic_euler", 1e-3, False, threads=None)
    omega = largest_frequency(sim)
    dt_crit = 2.0 / omega
    return SE_SAFETY * dt_crit, dt_crit, omega


def stable_dt(name: str, meshes_dir: Union[str, Path, None] = None) -> Tuple[float, float, float]:
    """``(dt, dt_crit, omega_max)`` for symplectic Euler on the named mesh: ``dt = 0.5 * dt_crit``,
    ``dt_crit = 2 / omega_max`` (cached per process)."""
    return _stable_dt_cached(name, str(_meshes_dir(meshes_dir).resolve()))


# --- cases -----------------------------------------------------------------------------------------------------
def dt_label(dt) -> str:
    if dt == "stable" or dt is None:
        return "stable"
    fr = Fraction(float(dt)).limit_denominator(10000)
    if fr.numerator == 1 and abs(float(fr) - float(dt)) < 1e-12:
        return f"1/{fr.denominator}"
    return f"{float(dt):.3g}"


def parse_dt(text: str):
    text = text.strip()
    if text == "stable":
        return "stable"
    if "/" in text:
        a, b = text.split("/")
        return float(a) / float(b)
    return float(text)


@dataclass
class Case:
    """A built simulation and what it is."""

    sim: fepr.Simulation
    mesh: str
    integrator: str
    dt: float
    dt_label: str
    scenario: str
    projection: bool
    dt_crit: Optional[float] = None  # symplectic Euler's stability limit (stable dt only)

    @property
    def key(self) -> str:
        return f"{self.mesh}/{self.integrator}/{self.dt_label}/{self.scenario}"


def build_case(
    mesh_name: str,
    integrator: str,
    dt,
    scenario: str,
    projection: Union[bool, fepr.Projection] = True,
    *,
    meshes_dir: Union[str, Path, None] = None,
    threads: Optional[int] = None,
) -> Case:
    """Build one gauntlet case. ``dt`` is a step size in s, or ``"stable"`` (or None) for symplectic Euler's
    ``0.5 * dt_crit``. ``projection``: True (default FEPR settings), False, or a :class:`fepr.Projection`."""
    if scenario not in SCENARIOS:
        raise KeyError(f"unknown scenario {scenario!r} (known: {', '.join(SCENARIOS)})")
    if integrator not in INTEGRATORS:
        raise KeyError(f"unknown integrator {integrator!r} (known: {', '.join(INTEGRATORS)})")
    mesh = load_mesh(mesh_name, meshes_dir)
    dt_crit = None
    label = dt_label(dt)
    if dt is None or dt == "stable":
        if integrator != "symplectic_euler":
            raise ValueError("dt='stable' is for symplectic Euler only")
        dt, dt_crit, _ = stable_dt(mesh_name, meshes_dir)
    dt = float(dt)
    kw: dict = {}
    if scenario in ("free_fall", "drop"):
        kw["gravity"] = GRAVITY
    if scenario == "drop":
        lift = DROP_GAP - float(mesh.vertices[:, 2].min())
        mesh = fepr.io.transform_mesh(mesh, translate=(0.0, 0.0, lift))
        kw["obstacles"] = [plane()]
    sim = _simulation(mesh, integrator, dt, projection, threads=threads, **kw)
    x = sim.rest_positions
    m = sim.masses
    c = (m[:, None] * x).sum(axis=0) / m.sum()
    if scenario == "stretch":
        sim.positions = c + STRETCH * (x - c)
    elif scenario == "spin":
        axis = np.asarray(SPIN_AXIS) / np.linalg.norm(SPIN_AXIS)
        sim.velocities = np.cross(SPIN_RATE * axis, x - c)
    return Case(sim, mesh_name, integrator, dt, label, scenario, projection is not False, dt_crit)


def case_duration(
    case: Case, duration: float, se_duration: Optional[float] = None, drop_after: float = DROP_AFTER_LANDING
) -> float:
    """The simulated time a case runs: ``duration`` (``se_duration`` for symplectic Euler when given); the drop
    runs at least until ``drop_after`` seconds after the ideal landing time."""
    d = duration
    if case.integrator == "symplectic_euler" and se_duration is not None:
        d = se_duration
    if case.scenario == "drop":
        d = max(d, math.sqrt(2 * DROP_GAP / abs(GRAVITY[2])) + drop_after)
    return d


# --- measuring -------------------------------------------------------------------------------------------------
def _fmax(a) -> float:
    """The largest value; NaN if empty or if any value is NaN (a NaN must not hide behind the others)."""
    a = np.asarray(a, dtype=float)
    return float(np.max(a)) if a.size else float("nan")


def run_case(
    case: Case, duration: float, se_duration: Optional[float] = None, drop_after: float = DROP_AFTER_LANDING
) -> dict:
    """Step a case for its duration (one step at a time, collecting each projection's base-step energy) and
    return the measurements as a JSON-friendly dict."""
    sim = case.sim
    dur = case_duration(case, duration, se_duration, drop_after)
    n = max(1, int(round(dur / case.dt)))
    base_energy: List[float] = []
    error = None
    runaway_warning = None
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(n):
            try:
                sim.step(1)
            except fepr.SimulationError as exc:
                error = str(exc)
                break
            if case.projection:
                rep = sim.last_projection
                base_energy.append(float(rep.base_energy) if rep is not None else float("nan"))
        for w in caught:
            if issubclass(w.category, RuntimeWarning) and "runaway" in str(w.message):
                runaway_warning = str(w.message)
    wall = time.perf_counter() - t0
    h = sim.history
    steps = len(h) - 1
    mtot = float(sim.total_mass)
    x0 = sim.rest_positions
    r = 0.5 * float(np.linalg.norm(x0.max(axis=0) - x0.min(axis=0)))
    g = float(np.linalg.norm(sim.gravity))
    total, budget = h["total"], h["budget_total"]
    H0, K0, El0, G0 = float(total[0]), float(h["kinetic"][0]), float(h["elastic"][0]), float(h["gravitational"][0])
    e_scale = max(abs(H0 - G0), K0 + abs(El0), mtot * g * r)
    books_dev = (total - (H0 + budget)) / e_scale
    books = _fmax(np.abs(books_dev[1:]))
    P = np.stack([h["px"], h["py"], h["pz"]], axis=1)
    L = np.stack([h["lx"], h["ly"], h["lz"]], axis=1)
    Pt = np.stack([h["px_target"], h["py_target"], h["pz_target"]], axis=1)
    Lt = np.stack([h["lx_target"], h["ly_target"], h["lz_target"]], axis=1)
    p_scale = max(float(np.linalg.norm(P[0])), math.sqrt(2 * mtot * e_scale))
    l_scale = r * p_scale
    p_drift = l_drift = None
    p_ref = "-"
    if case.scenario in ("stretch", "spin"):
        p_ref = "initial"
        p_drift = _fmax(np.linalg.norm(P[1:] - P[0], axis=1) / p_scale)
        l_drift = _fmax(np.linalg.norm(L[1:] - L[0], axis=1) / l_scale)
    target_error = None
    if case.scenario == "free_fall":
        p_ref = "target"
        p_drift = _fmax(np.linalg.norm(P[1:] - Pt[1:], axis=1) / p_scale)
        l_drift = _fmax(np.linalg.norm(L[1:] - Lt[1:], axis=1) / l_scale)
        # the targets themselves: P0 + M g t and L0 (uniform gravity has no torque about the centre of mass)
        p_exact = P[0] + mtot * np.outer(h["time"], sim.gravity)
        target_error = max(
            _fmax(np.linalg.norm(Pt[1:] - p_exact[1:], axis=1) / p_scale),
            _fmax(np.linalg.norm(Lt[1:] - L[0], axis=1) / l_scale),
        )
    # against the targets too, in every scenario (informational)
    p_target_drift = _fmax(np.linalg.norm(P[1:] - Pt[1:], axis=1) / p_scale)
    l_target_drift = _fmax(np.linalg.norm(L[1:] - Lt[1:], axis=1) / l_scale)
    out = {
        "key": case.key,
        "mesh": case.mesh,
        "tets": int(sim.mesh.num_tets),
        "integrator": case.integrator,
        "dt": case.dt,
        "dt_label": case.dt_label,
        "dt_crit": case.dt_crit,
        "scenario": case.scenario,
        "fepr": case.projection,
        "duration": steps * case.dt,
        "steps": steps,
        "steps_planned": n,
        "error": error,
        "runaway_warning": runaway_warning,
        "runaway_steps": int(np.nansum(h["runaway"][1:])),
        "E_scale": e_scale,
        "H0": H0,
        "min_j": float(np.min(h["min_j"])),
        "min_j_initial": float(h["min_j"][0]),
        "max_inverted": int(np.nanmax(h["inverted"])),
        "books": books,
        "books_end": float(books_dev[-1]) if steps else 0.0,
        "p_reference": p_ref,
        "p_drift": p_drift,
        "l_drift": l_drift,
        "target_error": target_error,
        "p_target_drift": p_target_drift,
        "l_target_drift": l_target_drift,
        "max_contacts": int(np.nanmax(h["contacts"])),
        "max_base_substeps": int(np.nanmax(h["base_substeps"])),
        "ms_per_step": float(np.mean(h["base_ms"][1:] + h["proj_ms"][1:])) if steps else float("nan"),
        "base_ms_per_step": float(np.mean(h["base_ms"][1:])) if steps else float("nan"),
        "proj_ms_per_step": float(np.mean(h["proj_ms"][1:])) if steps else float("nan"),
        "wall_s": wall,
        "threads": None,
    }
    if case.projection and steps:
        conv = h["proj_converged"][1:]
        unresolved_steps = -h["work_unresolved"][1:]
        # the step's target before its unresolved energy was booked
        h_target = H0 + budget[1:] - h["work_unresolved"][1:]
        hb = np.asarray(base_energy[:steps], dtype=float)
        lost = float(np.nansum(np.maximum(0.0, h_target[: hb.size] - hb)))
        gained = float(np.nansum(np.maximum(0.0, hb - h_target[: hb.size])))
        unresolved = float(np.nansum(unresolved_steps))
        out.update(
            {
                "converged_fraction": float(np.mean(conv == 1)),
                "unconverged": int(np.sum(conv != 1)),
                "fallbacks": int(np.nansum(h["proj_fallback"][1:])),
                "mean_trials": float(np.nanmean(h["proj_trials"][1:])),
                "mean_iterations": float(np.nanmean(h["proj_iterations"][1:])),
                "max_iterations": int(np.nanmax(h["proj_iterations"][1:])),
                "energy_lost": lost,
                "energy_gained": gained,
                "energy_unresolved": unresolved,
                # None where the base steps lost (next to) nothing: the fraction would be round-off
                "restored_fraction": (1.0 - unresolved / lost) if lost > 1e-12 * e_scale else None,
                "lost_over_scale": lost / e_scale,
            }
        )
    return out


def run_pair(
    mesh_name: str,
    integrator: str,
    dt,
    scenario: str,
    duration: float,
    *,
    se_duration: Optional[float] = None,
    meshes_dir=None,
    threads: Optional[int] = None,
    projection: Union[bool, fepr.Projection] = True,
    drop_after: float = DROP_AFTER_LANDING,
) -> dict:
    """Run one case without and with FEPR; returns ``{"base": ..., "fepr": ..., "criteria": ..., "breaks": [...]}``."""
    runs = {}
    for label, proj in (("base", False), ("fepr", projection)):
        case = build_case(mesh_name, integrator, dt, scenario, proj, meshes_dir=meshes_dir, threads=threads)
        runs[label] = run_case(case, duration, se_duration, drop_after)
        runs[label]["threads"] = threads
    crit = evaluate(runs["base"], runs["fepr"])
    return {
        "key": runs["fepr"]["key"],
        "base": runs["base"],
        "fepr": runs["fepr"],
        "criteria": crit,
        "breaks": [k for k, v in crit.items() if v["ok"] is False],
    }


def evaluate(base: dict, fe: dict) -> Dict[str, dict]:
    """The issue's criteria for a FEPR run against the same case without FEPR: ``{name: {"ok": True/False/None
    (not judged), "detail": str}}``."""
    c: Dict[str, dict] = {}
    if fe["error"] is None:
        c["completed"] = {"ok": True, "detail": "ok"}
    else:
        # FEPR does not make an unstable step size stable (fepr-spec section 5): not judged if the base stopped too
        c["completed"] = {
            "ok": False if base["error"] is None else None,
            "detail": f"stopped after {fe['steps']} steps (base: {base['steps']} of {base['steps_planned']}): "
            f"{fe['error'][:120]}",
        }
    if base["max_inverted"] == 0:
        c["inversions"] = {
            "ok": fe["max_inverted"] == 0,
            "detail": f"FEPR {fe['max_inverted']} inverted, base 0",
        }
    else:
        c["inversions"] = {"ok": None, "detail": f"base inverts {base['max_inverted']} (FEPR {fe['max_inverted']})"}
    ok_j = bool(np.isfinite(fe["min_j"]) and fe["min_j"] >= base["min_j"] - MIN_J_MARGIN)
    c["min_j"] = {"ok": ok_j, "detail": f"min J FEPR {fe['min_j']:.4g}, base {base['min_j']:.4g}"}
    c["books"] = {"ok": bool(fe["books"] <= BOOKS_TOL), "detail": f"books {fe['books']:.3g} (tol {BOOKS_TOL:g})"}
    if fe["p_drift"] is None:
        c["momentum"] = {"ok": None, "detail": "not judged (contact)"}
    else:
        ok_m = bool(fe["p_drift"] <= MOMENTUM_TOL and fe["l_drift"] <= MOMENTUM_TOL)
        detail = f"P {fe['p_drift']:.3g}, L {fe['l_drift']:.3g} vs {fe['p_reference']}"
        if fe.get("target_error") is not None:  # free fall: the targets must be P0 + M g t and L0
            ok_m = ok_m and bool(fe["target_error"] <= MOMENTUM_TOL)
            detail += f" (targets off by {fe['target_error']:.3g})"
        c["momentum"] = {"ok": ok_m, "detail": detail + f" (tol {MOMENTUM_TOL:g})"}
    unconv = fe.get("unconverged", 0)
    c["converged"] = {
        "ok": unconv == 0,
        "detail": f"{unconv} of {fe['steps']} unconverged ({fe.get('fallbacks', 0)} fallbacks)",
    }
    return c


# --- matrix and report -----------------------------------------------------------------------------------------
def matrix(meshes=MESHES, integrators=INTEGRATORS, dts=DTS, scenarios=SCENARIOS) -> List[Tuple[str, str, object, str]]:
    """The cases: symplectic Euler once per mesh and scenario at its stable dt, the others at every dt."""
    out = []
    for scenario in scenarios:
        for integ in integrators:
            for dt in ["stable"] if integ == "symplectic_euler" else list(dts):
                for mesh in meshes:
                    out.append((mesh, integ, dt, scenario))
    return out


#: Rough single-thread cost of a step pair (base + FEPR) per tet, s, measured on bunny2 and the elephant; an
#: implicit step in contact costs about 50 times more (impact substeps, more Newton iterations).
_COST_PER_TET = {"symplectic_euler": 1.8e-7, "implicit_euler": 3.5e-5, "projective_dynamics": 6e-6, "xpbd": 1.3e-5}
_APPROX_TETS = {"bunny2": 29548, "bunny": 19379, "armadillo": 4406, "little_elephant": 24953, "elephant": 25545}
_APPROX_SE_DT = {
    "bunny2": 3.3e-6,
    "bunny": 6.9e-6,
    "armadillo": 2.8e-5,
    "little_elephant": 1.04e-5,
    "elephant": 1.35e-5,
}


def estimated_cost(
    mesh: str, integrator: str, dt, scenario: str, duration: float, se_duration=None, drop_after=DROP_AFTER_LANDING
) -> float:
    """A rough wall-time estimate (s, one thread) of :func:`run_pair`, for ordering a run cheapest first."""
    d = se_duration if (integrator == "symplectic_euler" and se_duration is not None) else duration
    if scenario == "drop":
        d = max(d, math.sqrt(2 * DROP_GAP / abs(GRAVITY[2])) + drop_after)
    step = _APPROX_SE_DT.get(mesh, 1e-5) if dt == "stable" else float(dt)
    factor = 50.0 if (scenario == "drop" and integrator == "implicit_euler") else 1.0
    return _APPROX_TETS.get(mesh, 20000) * _COST_PER_TET[integrator] * factor * d / step


def order_cheapest_first(cases, duration: float, se_duration=None, drop_after=DROP_AFTER_LANDING):
    """Breadth first: the cheapest cases first, so a run with a time limit covers as many as it can."""
    return sorted(cases, key=lambda c: estimated_cost(*c, duration, se_duration, drop_after))


_INTEG_SHORT = {"symplectic_euler": "SE", "implicit_euler": "BE", "projective_dynamics": "PD", "xpbd": "XPBD"}


def _g(x, fmt=".2g") -> str:
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return "nan"
    return format(x, fmt)


def markdown_table(results: Sequence[dict]) -> str:
    """One row per case: the base run and the FEPR run side by side, and the criteria the FEPR run breaks."""
    head = (
        "| mesh | int. | dt | scenario | steps | base min J | base inv | base books | FEPR min J | FEPR inv | "
        "FEPR books | P drift | L drift | conv (unconv) | trials | lost/E | restored | ms/step base / FEPR | breaks |"
    )
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [head, sep]
    for res in results:
        b, f = res["base"], res["fepr"]
        dt = f["dt_label"] if f["dt_label"] != "stable" else f"{f['dt']:.2e}"
        breaks = res["breaks"]
        mark = "**" + ", ".join(breaks) + "**" if breaks else "ok"
        if b["error"]:
            mark += f" (base stopped at step {b['steps']})"
        conv = f"{_g(f.get('converged_fraction'), '.3f')} ({f.get('unconverged', '-')})"
        rf = f.get("restored_fraction")
        lines.append(
            "| "
            + " | ".join(
                [
                    f["mesh"],
                    _INTEG_SHORT.get(f["integrator"], f["integrator"]),
                    dt,
                    f["scenario"],
                    str(f["steps"]),
                    _g(b["min_j"], ".3g"),
                    str(b["max_inverted"]),
                    _g(b["books"]),
                    _g(f["min_j"], ".3g"),
                    str(f["max_inverted"]),
                    _g(f["books"]),
                    _g(f["p_drift"]),
                    _g(f["l_drift"]),
                    conv,
                    _g(f.get("mean_trials"), ".2f"),
                    _g(f.get("lost_over_scale"), ".2g"),
                    "-" if rf is None else f"{rf:.3f}",
                    f"{b['ms_per_step']:.3g} / {f['ms_per_step']:.3g}",
                    mark,
                ]
            )
            + " |"
        )
    return "\n".join(lines)


def summary(results: Sequence[dict]) -> str:
    """Counts of broken criteria and the mean restored fraction per mesh x integrator x dt."""
    lines = []
    n = len(results)
    broken = [r for r in results if r["breaks"]]
    lines.append(f"{n} cases, {len(broken)} break at least one criterion.")
    for c in CRITERIA:
        ks = [f"{r['key']} ({r['criteria'][c]['detail']})" for r in results if c in r["breaks"]]
        if ks:
            lines.append(f"- `{c}` broken in {len(ks)}: " + "; ".join(ks))
    groups: Dict[Tuple[str, str, str], Dict[str, float]] = {}
    for r in results:
        f = r["fepr"]
        k = (f["mesh"], f["integrator"], f["dt_label"])
        groups.setdefault(k, {})
        if f.get("restored_fraction") is not None:
            groups[k][f["scenario"]] = f["restored_fraction"]
    lines.append("")
    lines.append(
        "Restored fraction (1 - unresolved / lost) with FEPR: the mean over the scenarios whose base steps lost "
        "energy, and per scenario (-: no deficit, or not run)."
    )
    lines.append("")
    lines.append("| mesh | integrator | dt | mean | " + " | ".join(SCENARIOS) + " |")
    lines.append("|---|---|---|---|" + "---|" * len(SCENARIOS))
    for (mesh, integ, dt), v in groups.items():
        mean = f"{np.mean(list(v.values())):.3f}" if v else "-"
        per = " | ".join(f"{v[s]:.3f}" if s in v else "-" for s in SCENARIOS)
        lines.append(f"| {mesh} | {integ} | {dt} | {mean} | {per} |")
    return "\n".join(lines)


def _header(args, stable: Dict[str, Tuple[float, float, float]]) -> str:
    lines = [
        "# FEPR gauntlet",
        "",
        f"fepr {fepr.__version__} ({Path(fepr.__file__).parent}); SNH E = {YOUNGS_MODULUS:g} Pa, nu = {POISSON_RATIO}, "
        f"density {DENSITY:g} kg/m^3, fit {FIT} m; duration {args.duration} s"
        + (f" (symplectic Euler {args.se_duration} s)" if args.se_duration else "")
        + f"; drop runs >= {math.sqrt(2 * DROP_GAP / 9.81) + args.drop_after:.3f} s; threads {args.threads}.",
        "",
        "books = max |H - (H0 + budget_total)| / E_scale; P/L drift relative to p_scale, r p_scale (stretch, spin: "
        "vs the initial values; free fall: vs the targets; drop: not judged); lost/E = energy the base steps lost "
        "(sum of max(0, H_target - H_base)) over E_scale; restored = 1 - unresolved / lost.",
        "",
    ]
    if stable:
        lines.append("Symplectic Euler stable dt (0.5 * 2 / omega_max):")
        lines.append("")
        for mesh, (dt, crit, om) in stable.items():
            lines.append(f"- {mesh}: omega_max {om:.4g} rad/s, dt_crit {crit:.3e} s, dt {dt:.3e} s")
        lines.append("")
    return "\n".join(lines)


def _write_json(path, stable, results, skipped, header=None) -> None:
    doc = {"fepr": fepr.__version__, "header": header, "stable_dt": stable, "results": results, "skipped": skipped}
    Path(path).write_text(json.dumps(doc, indent=1))


def _sort_key(f: dict):
    return (
        MESHES.index(f["mesh"]) if f["mesh"] in MESHES else 99,
        SCENARIOS.index(f["scenario"]),
        INTEGRATORS.index(f["integrator"]),
        f["dt"],
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", nargs="+", default=list(MESHES), choices=MESHES)
    ap.add_argument("--integrators", nargs="+", default=list(INTEGRATORS), choices=INTEGRATORS)
    ap.add_argument("--dts", nargs="+", default=["1/60", "1/30"], help="step sizes for BE, PD, XPBD (e.g. 1/60)")
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=SCENARIOS)
    ap.add_argument("--duration", type=float, default=1.0, help="simulated seconds per case (default 1)")
    ap.add_argument("--se-duration", type=float, default=None, help="simulated seconds for symplectic Euler")
    ap.add_argument(
        "--drop-after", type=float, default=DROP_AFTER_LANDING, help="the drop runs this long after landing (s)"
    )
    ap.add_argument("--meshes-dir", default=None)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", default=None, help="write every result here (rewritten after each case)")
    ap.add_argument("--out", default=None, help="write the Markdown report here too")
    ap.add_argument("--max-seconds", type=float, default=None, help="start no new case after this wall time")
    ap.add_argument("--from-json", default=None, help="print the report of an earlier --json file; run nothing")
    args = ap.parse_args(argv)
    if args.from_json:
        doc = json.loads(Path(args.from_json).read_text())
        results = sorted(doc["results"], key=lambda r: _sort_key(r["fepr"]))
        for r in results:  # re-judge with this version's criteria
            r["criteria"] = evaluate(r["base"], r["fepr"])
            r["breaks"] = [k for k, v in r["criteria"].items() if v["ok"] is False]
        report = markdown_table(results) + "\n\n" + summary(results) + "\n"
        if doc.get("header"):
            report = doc["header"] + "\n" + report
        print(report)
        if args.out:
            Path(args.out).write_text(report)
        return 1 if any(r["breaks"] for r in results) else 0
    if shared_meshes_dir(args.meshes_dir) is None:
        print("the shared meshes are absent (use --meshes-dir)", file=sys.stderr)
        return 2
    dts = [parse_dt(d) for d in args.dts]
    cases = order_cheapest_first(
        matrix(args.meshes, args.integrators, dts, args.scenarios), args.duration, args.se_duration, args.drop_after
    )
    results: List[dict] = []
    stable: Dict[str, Tuple[float, float, float]] = {}
    t_start = time.perf_counter()
    skipped = []
    for i, (mesh, integ, dt, scen) in enumerate(cases):
        if args.max_seconds is not None and time.perf_counter() - t_start > args.max_seconds:
            skipped.append(f"{mesh}/{integ}/{dt_label(dt)}/{scen}")
            continue
        if integ == "symplectic_euler" and mesh not in stable:
            stable[mesh] = stable_dt(mesh, args.meshes_dir)
        t0 = time.perf_counter()
        res = run_pair(
            mesh,
            integ,
            dt,
            scen,
            args.duration,
            se_duration=args.se_duration,
            meshes_dir=args.meshes_dir,
            threads=args.threads,
            drop_after=args.drop_after,
        )
        results.append(res)
        print(
            f"[{i + 1}/{len(cases)}] {res['key']}: {', '.join(res['breaks']) or 'ok'} "
            f"({time.perf_counter() - t0:.1f} s)",
            file=sys.stderr,
            flush=True,
        )
        if args.json:
            _write_json(args.json, stable, results, skipped, _header(args, stable))
    results.sort(key=lambda r: _sort_key(r["fepr"]))
    report = _header(args, stable) + "\n" + markdown_table(results) + "\n\n" + summary(results) + "\n"
    if skipped:
        report += f"\nNot run (time limit): {len(skipped)} cases: " + ", ".join(skipped) + "\n"
    print(report)
    if args.out:
        Path(args.out).write_text(report)
    if args.json:
        _write_json(args.json, stable, results, skipped, _header(args, stable))
    return 1 if any(r["breaks"] for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
