"""The summary of a run, computed only from its history columns: one module for every command.

``fepr run`` (:class:`fepr.scene.RunResult`), ``fepr compare`` (``summary.md``, ``summary.json``,
``report.html``), ``fepr demo`` (its tables and report) and the viewer all report the numbers of
:func:`compute_metrics`, formatted by :func:`format_value` / :meth:`RunMetrics.cell` and written as one line by
:meth:`RunMetrics.summary_line`, so the same run reads the same everywhere.

Inputs: the history columns ``h`` (``sim.history.as_dict()`` or the columns of ``diagnostics.csv``; row 0 the
initial state, rows 1.. the steps) and what the history cannot know: the total mass ``M`` (kg), gravity ``g``
(m/s^2), the rest shape's half bounding-box diagonal ``r`` (m), whether vertices are pinned, whether the
projection was on, and where a run ran away.

Definitions (``k`` runs over the rows):

- **energy scale** ``H_scale = |H_0|``, or ``E_0 = max(K_0 + |E_el,0| + |E_grav,0|, M |g| r)`` when ``|H_0|``
  is below ``1e-12 E_0`` (``M |g| r``: lifting the body by ``r``, for a body that starts with no energy at all).
- **energy error** (against the books) ``max_k |H_k - (H_0 + B_k)| / H_scale``, ``B_k = budget_total_k -
  budget_total_0``: the energy budget so far (damping, contact, pins, forces, and the unresolved energy); the
  final row's value is ``final_energy_error``. A non-finite energy counts as an infinite error.
- **unresolved** ``-sum_k work_unresolved_k / H_scale``: the energy the projection could not restore within its
  quality guard (booked in the budget, so the books still close), as a share of the energy scale; 0 without
  the column.
- **P drift** ``max_k |P_k - P_target,k| / p_scale``, **L drift** ``max_k |L_k - L_target,k| / l_scale`` (L about
  the centre of mass), with the running references ``px_target ... lz_target``: ``P_0`` plus every external
  impulse so far (gravity, contact, forces, damping), ``L_0`` plus the external angular impulses.
  ``p_scale = max(|P_0|, max_k |P_target,k|, sqrt(2 M (K_0 + |E_el,0|)))``, ``l_scale = max(|L_0|, r p_scale)``.
  Histories without the target columns (older ``diagnostics.csv``) use ``P_target = P_0 + M g (t - t_0)`` and
  ``L_target = L_0``. Both are ``None`` when vertices are pinned (the supports' impulses are not known).
- **min J** smallest volume ratio ``det F`` over all tets and rows; **inverted** the largest number of inverted
  tets in a row, **final_inverted** that of the last row.
- **unconverged** steps whose projection did not converge and did not stand down at resting contact
  (``proj_converged == 0`` and ``proj_stood_down == 0``; ``None`` without
  projection); **mean_iterations** / **max_iterations** of the projection over the steps.
- **substeps** the sum of ``base_substeps``; **ms_per_step** mean ``base_ms + proj_ms`` over the steps (the
  solver's own time); **base_unstable_step** the first step whose ``base_energy_error`` exceeded 1.
- ``final_h_ratio = H_last / H_0`` and ``max_dh = max_k |H_k - H_0| / H_scale`` (not against the books) are
  kept for reference only.

**Problems** (:meth:`RunMetrics.problems`): a runaway, inverted tets at the end, unconverged projections, and
unresolved energy above :data:`UNRESOLVED_LIMIT` of the energy scale (the share at which ``Simulation.step``
warns). These are what :func:`fepr.scene.run_scene` warns about at the end of a run (but the runaway, which its
result reports) and what ``--strict`` fails on. **Notes**
(:meth:`RunMetrics.notes`): tets inverted during the run but not at its end, and a base step that was unstable
while the projection kept the state bounded. Unresolved energy is always shown as its own number.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

__all__ = [
    "FIELDS",
    "LEGEND",
    "RunMetrics",
    "RunProblemWarning",
    "UNRESOLVED_LIMIT",
    "compute_metrics",
    "energy_error_series",
    "energy_scale",
    "format_value",
    "length_scale",
    "simulation_history",
    "simulation_metrics",
    "system_history",
]

_TINY = 1e-300

#: Unresolved energy (a share of the energy scale) above which a run has a problem: the same share at which
#: ``fepr.Simulation.step`` warns (``Simulation.UNRESOLVED_WARNING``).
UNRESOLVED_LIMIT = 1e-3

#: (key, header) of the summary numbers, in the order every table shows them.
FIELDS: Tuple[Tuple[str, str], ...] = (
    ("steps", "steps"),
    ("energy_error", "energy error"),
    ("unresolved", "unresolved"),
    ("p_drift", "P drift"),
    ("l_drift", "L drift"),
    ("min_j", "min J"),
    ("inverted", "inverted"),
    ("unconverged", "unconverged"),
    ("substeps", "substeps"),
    ("mean_iterations", "iters"),
    ("ms_per_step", "ms/step"),
)

#: What the columns mean (Markdown; the tables and the report show it under the numbers).
LEGEND: Tuple[str, ...] = (
    "- **energy error**: largest |H - (H0 + budget)| over the run, relative to |H0| (the books: the budget is "
    "the energy that damping, contact, pins, forces and unresolved restoration put in or took out); "
    "**unresolved**: the energy the projection could not restore within its quality guard, same scale.",
    "- **P drift**, **L drift**: largest |P - P_target| and |L - L_target| (L about the centre of mass), "
    "relative; the targets are P0 and L0 plus every external impulse so far (gravity, obstacles, forces, "
    "damping); n/a when vertices are pinned (the supports' impulses are not known).",
    "- **min J**: smallest volume ratio det F over all tets and steps (J <= 0: inverted); **inverted**: "
    "inverted tets at the end (the largest count during the run in parentheses when it differs).",
    "- **unconverged**: steps whose projection did not converge (- without projection); **substeps**: the base "
    "integrator's substeps in all; **iters**: mean FEPR iterations per step; **ms/step**: the base step's and "
    "the projection's own time per step.",
)

#: Keys formatted as ``1.23e-04``.
_SCI = frozenset({"energy_error", "final_energy_error", "unresolved", "p_drift", "l_drift", "max_dh"})


class RunProblemWarning(RuntimeWarning):
    """A run ended with inverted tets, had unconverged projections or left more than :data:`UNRESOLVED_LIMIT`
    of its energy unresolved (issued by :func:`fepr.scene.run_scene` at the end of the run)."""


def format_value(key: str, value: Any) -> str:
    """The text of one summary number (the same format in every command, table and report).

    ``None``: ``n/a`` for the drifts (pinned vertices), ``-`` otherwise (no projection)."""
    if value is None:
        return "n/a" if key in ("p_drift", "l_drift") else "-"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, str):
        return value
    if isinstance(value, (int, np.integer)) and key not in _SCI:
        return str(int(value))
    v = float(value)
    if not math.isfinite(v):
        return str(v)
    if key in _SCI:
        return f"{v:.2e}"
    if key == "final_h_ratio":
        return f"{v:.9f}" if abs(v) < 1e6 else f"{v:.3e}"
    if key == "mean_iterations":
        return f"{v:.2f}"
    if key == "ms_per_step":
        return f"{v:.3f}"
    return f"{v:.4g}"


def _plural(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


@dataclass(frozen=True)
class RunMetrics:
    """The summary of one run (see the module docstring for the definitions)."""

    steps: int
    runaway_step: Optional[int]
    energy_error: float
    final_energy_error: float
    unresolved: float
    p_drift: Optional[float]
    l_drift: Optional[float]
    min_j: float
    inverted: int
    final_inverted: int
    unconverged: Optional[int]
    mean_iterations: Optional[float]
    max_iterations: Optional[int]
    substeps: int
    ms_per_step: float
    base_unstable_step: Optional[int]
    projection: bool
    pinned: bool
    momentum_reference: str
    energy_scale: float
    final_h_ratio: float
    max_dh: float

    def as_dict(self) -> Dict[str, object]:
        return asdict(self)

    # ---- what went wrong --------------------------------------------------------------------------------
    def problems(self) -> List[str]:
        """Short phrases for what makes the run untrustworthy: a runaway, inverted tets at the end,
        unconverged projections, unresolved energy above :data:`UNRESOLVED_LIMIT` (empty: none). ``--strict``
        fails on any of them."""
        out = []
        if self.runaway_step is not None:
            out.append(f"runaway at step {self.runaway_step}")
        if self.final_inverted > 0:
            out.append(f"{_plural(self.final_inverted, 'inverted tet')} at the end")
        if self.unconverged:
            out.append(_plural(self.unconverged, "unconverged projection"))
        if self.unresolved_problem:
            out.append(f"unresolved energy {self.cell('unresolved')} (above {UNRESOLVED_LIMIT:g})")
        return out

    @property
    def unresolved_problem(self) -> bool:
        """The unresolved energy is above :data:`UNRESOLVED_LIMIT` of the energy scale (NaN counts)."""
        return not (self.unresolved <= UNRESOLVED_LIMIT)

    def notes(self) -> List[str]:
        """Short phrases for what a reader should know but does not fail the run."""
        out = []
        if self.inverted > 0 and self.final_inverted == 0:
            out.append(f"up to {_plural(self.inverted, 'inverted tet')} during the run")
        if self.projection and self.runaway_step is None and self.base_unstable_step is not None:
            out.append(f"base step unstable from step {self.base_unstable_step} (the projection kept it bounded)")
        return out

    @property
    def ok(self) -> bool:
        """No :meth:`problems`."""
        return not self.problems()

    # ---- text -------------------------------------------------------------------------------------------
    def cell(self, key: str) -> str:
        """The table cell of ``key`` (a key of :data:`FIELDS` or a field): ``steps`` with the runaway,
        ``inverted`` at the end with the largest count when it differs."""
        if key == "steps":
            if self.runaway_step is not None:
                return f"{self.steps} (runaway at {self.runaway_step})"
            return str(self.steps)
        if key == "inverted":
            if self.inverted != self.final_inverted:
                return f"{self.final_inverted} (max {self.inverted})"
            return str(self.final_inverted)
        return format_value(key, getattr(self, key))

    def summary_parts(self) -> List[str]:
        """The summary as ``name value`` phrases (what :meth:`summary_line` joins)."""
        if self.runaway_step is not None:
            steps = f"runaway at step {self.runaway_step} after {self.steps} steps"
        else:
            steps = _plural(self.steps, "step")
        p = self.cell("p_drift") + (" (pinned)" if self.p_drift is None else "")
        parts = [
            steps,
            f"energy error {self.cell('energy_error')} (end {self.cell('final_energy_error')})",
            f"unresolved {self.cell('unresolved')}",
            f"P drift {p}",
            f"L drift {self.cell('l_drift')}",
            f"min J {self.cell('min_j')}",
            f"inverted {self.cell('inverted')}",
        ]
        if self.projection:
            parts += [f"unconverged {self.cell('unconverged')}", f"iters {self.cell('mean_iterations')}"]
        else:
            parts.append("projection off")
        parts += [f"substeps {self.cell('substeps')}", f"{self.cell('ms_per_step')} ms/step"]
        return parts

    def summary_line(self, label: Optional[str] = None) -> str:
        """One line: ``label: steps, energy error, unresolved, P and L drift, min J, inverted, unconverged,
        iterations, substeps, ms/step``, then ``; problems: ...`` when there are any."""
        text = ", ".join(self.summary_parts())
        if label:
            text = f"{label}: {text}"
        problems = self.problems()
        if problems:
            text += "; problems: " + ", ".join(problems)
        return text

    def warning_text(self, label: str = "the run") -> Optional[str]:
        """The end-of-run warning (``None`` when the run neither ends with inverted tets, nor had unconverged
        projections, nor left more than :data:`UNRESOLVED_LIMIT` of its energy unresolved)."""
        parts = []
        if self.final_inverted > 0:
            parts.append(
                f"ends with {_plural(self.final_inverted, 'inverted tet')} (min J {self.cell('min_j')}, "
                "history column 'inverted')"
            )
        if self.unconverged:
            parts.append(
                f"had {self.unconverged} of {self.steps} projections unconverged (history column 'proj_converged')"
            )
        if self.unresolved_problem:
            parts.append(
                f"left {self.cell('unresolved')} of its energy scale unresolved, above {UNRESOLVED_LIMIT:g} "
                "(history column 'work_unresolved')"
            )
        if not parts:
            return None
        return f"{label} " + "; ".join(parts)


# --------------------------------------------------------------------------------------------------------
# Computing
# --------------------------------------------------------------------------------------------------------


def _columns(history) -> Dict[str, np.ndarray]:
    if hasattr(history, "as_dict"):
        history = history.as_dict()
    return {k: np.asarray(v, dtype=np.float64) for k, v in history.items()}


def _max(a: np.ndarray) -> float:
    """Largest value, a non-finite one counting as infinite (``0.0`` for no values)."""
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0:
        return 0.0
    return float(np.max(np.where(np.isfinite(a), a, np.inf)))


def _finite_max(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else float("nan")


def _vec(h: Mapping[str, np.ndarray], names: Sequence[str]) -> Optional[np.ndarray]:
    if not all(n in h for n in names):
        return None
    return np.stack([h[n] for n in names], axis=1)


def energy_scale(history, *, total_mass: float, gravity, length_scale: float) -> float:
    """``H_scale`` of the module docstring (J), from row 0 of ``history``."""
    h = _columns(history)
    h0 = float(h["total"][0])
    lift = float(total_mass) * float(np.linalg.norm(np.asarray(gravity, dtype=np.float64))) * float(length_scale)
    e0 = max(float(h["kinetic"][0] + abs(h["elastic"][0]) + abs(h["gravitational"][0])), lift)
    if math.isfinite(h0) and abs(h0) > 1e-12 * e0 and abs(h0) > _TINY:
        return abs(h0)
    return max(e0, _TINY)


def energy_error_series(history, *, total_mass: float, gravity, length_scale: float) -> np.ndarray:
    """``|H_k - (H_0 + B_k)| / H_scale`` for every row (the energy error against the books; non-finite
    energies give ``inf``)."""
    h = _columns(history)
    H = h["total"]
    scale = energy_scale(h, total_mass=total_mass, gravity=gravity, length_scale=length_scale)
    budget = h["budget_total"] - h["budget_total"][0] if "budget_total" in h else np.zeros_like(H)
    with np.errstate(all="ignore"):
        err = np.abs(H - H[0] - budget) / scale
    return np.where(np.isfinite(err), err, np.inf)


def compute_metrics(
    history,
    *,
    total_mass: float,
    gravity,
    length_scale: float,
    pinned: bool,
    projection: bool,
    runaway_step: Optional[int] = None,
) -> RunMetrics:
    """The summary of one run from its history columns (see the module docstring for the definitions).

    Parameters
    ----------
    history : mapping of column name to (rows,) float64, or a fepr.History
        ``sim.history.as_dict()`` or the columns of ``diagnostics.csv`` (row 0: the initial state).
    total_mass : float
        M, kg.
    gravity : (3,) float
        g, m/s^2.
    length_scale : float
        r, m: half the rest shape's bounding-box diagonal (:func:`length_scale`).
    pinned : bool
        Vertices are pinned (the momentum drifts are then ``None``).
    projection : bool
        FEPR was on (else ``unconverged`` and the iteration counts are ``None``).
    runaway_step : int, optional
        Where the run stopped, if it ran away.
    """
    h = _columns(history)
    rows = len(h["total"])
    steps = rows - 1
    H = h["total"]
    h0 = float(H[0])
    scale = energy_scale(h, total_mass=total_mass, gravity=gravity, length_scale=length_scale)
    err = energy_error_series(h, total_mass=total_mass, gravity=gravity, length_scale=length_scale)
    unresolved = 0.0
    if "work_unresolved" in h and steps > 0:
        unresolved = -float(np.nansum(h["work_unresolved"][1:])) / scale
        unresolved = unresolved + 0.0  # no -0.0
    with np.errstate(all="ignore"):
        final_ratio = float(H[-1] / h0) if h0 != 0 else float("nan")
        max_dh = _finite_max(np.abs(H - h0) / scale)
        p_drift = l_drift = None
        reference = "none"
        if not pinned:
            P = _vec(h, ("px", "py", "pz"))
            L = _vec(h, ("lx", "ly", "lz"))
            p_target = _vec(h, ("px_target", "py_target", "pz_target"))
            l_target = _vec(h, ("lx_target", "ly_target", "lz_target"))
            if p_target is not None and l_target is not None:
                reference = "targets"
            else:
                reference = "gravity"
                t = h["time"] - h["time"][0]
                p_target = P[0] + float(total_mass) * t[:, None] * np.asarray(gravity, dtype=np.float64)
                l_target = np.broadcast_to(L[0], L.shape)
            kinetic0 = float(h["kinetic"][0] + abs(h["elastic"][0]))
            p_scale = max(
                float(np.linalg.norm(P[0])),
                _finite_max(np.linalg.norm(p_target, axis=1)),
                math.sqrt(max(2.0 * float(total_mass) * kinetic0, 0.0)),
                _TINY,
            )
            l_scale = max(float(np.linalg.norm(L[0])), float(length_scale) * p_scale, _TINY)
            p_drift = _max(np.linalg.norm(P - p_target, axis=1) / p_scale)
            l_drift = _max(np.linalg.norm(L - l_target, axis=1) / l_scale)

    def count(name: str, last: bool = False) -> int:
        if name not in h or rows == 0:
            return 0
        a = h[name][-1:] if last else h[name]
        a = a[np.isfinite(a)]
        return int(a.max()) if a.size else 0

    unconverged = mean_it = max_it = None
    if projection:
        unconverged = 0
        if steps > 0 and "proj_converged" in h:
            # Steps on which the projection stood down at resting contact (by the stated rule) are not failures.
            stood = h["proj_stood_down"][1:] > 0.5 if "proj_stood_down" in h else False
            unconverged = int(np.sum(~(h["proj_converged"][1:] > 0.5) & ~stood))
        if steps > 0 and "proj_iterations" in h:
            it = h["proj_iterations"][1:]
            it = it[np.isfinite(it)]
            if it.size:
                mean_it, max_it = float(it.mean()), int(it.max())
    substeps = int(np.nansum(h["base_substeps"][1:])) if "base_substeps" in h and steps > 0 else 0
    if steps > 0 and "base_ms" in h and "proj_ms" in h:
        ms = float(np.mean(h["base_ms"][1:] + h["proj_ms"][1:]))
    else:
        ms = float("nan")
    unstable = None
    if steps > 0 and "base_energy_error" in h:
        flags = np.where(np.isfinite(h["base_energy_error"][1:]), h["base_energy_error"][1:], np.inf) > 1.0
        if np.any(flags):
            k = 1 + int(np.argmax(flags))
            unstable = int(h["step"][k]) if "step" in h else k
    min_j = h["min_j"][np.isfinite(h["min_j"])] if "min_j" in h else np.zeros(0)
    return RunMetrics(
        steps=steps,
        runaway_step=runaway_step,
        energy_error=_max(err),
        final_energy_error=float(err[-1]) if rows else float("nan"),
        unresolved=unresolved,
        p_drift=p_drift,
        l_drift=l_drift,
        min_j=float(min_j.min()) if min_j.size else float("nan"),
        inverted=count("inverted"),
        final_inverted=count("inverted", last=True),
        unconverged=unconverged,
        mean_iterations=mean_it,
        max_iterations=max_it,
        substeps=substeps,
        ms_per_step=ms,
        base_unstable_step=unstable,
        projection=bool(projection),
        pinned=bool(pinned),
        momentum_reference=reference,
        energy_scale=scale,
        final_h_ratio=final_ratio,
        max_dh=max_dh,
    )


def length_scale(rest_positions: np.ndarray) -> float:
    """Half the bounding-box diagonal of the rest shape, m (r in the module docstring)."""
    x = np.asarray(rest_positions, dtype=np.float64)
    return 0.5 * float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))


# --------------------------------------------------------------------------------------------------------
# Simulations and multi-body systems
# --------------------------------------------------------------------------------------------------------

#: Columns of a body's history that :func:`system_history` adds to ``MultiBody.history`` when it lacks them:
#: summed, largest and smallest over the bodies.
_ADD_SUM = ("work_unresolved", "base_substeps")
_ADD_MAX = ("proj_trials", "proj_metric_switched", "proj_quality_excess")
_ADD_MIN = ("proj_restored",)
_TARGETS = ("px_target", "py_target", "pz_target", "lx_target", "ly_target", "lz_target")


def system_history(system, start: int = 0, stop: Optional[int] = None) -> Dict[str, np.ndarray]:
    """The history of a :class:`fepr.multibody.MultiBody` for :func:`compute_metrics`.

    ``system.history`` (the totals), plus the columns it does not combine, from the bodies' histories: the
    momentum targets (``P_target = sum_b P_target,b``; about the system's centre of mass ``C``,
    ``L_target = sum_b [L_target,b + (c_b - C) x P_target,b]``, so that ``L - L_target`` is the sum of the bodies'
    drifts moved to ``C``), ``work_unresolved`` and ``base_substeps`` summed, the projection's trials, metric
    switches and quality excess the largest, the restored fraction the smallest. ``start`` and ``stop``: only those
    rows (a run writes its diagnostics as it goes).
    """
    h = system._history_slice(start, stop).as_dict()
    rows = len(h["step"])
    hists = [b.history for b in system.bodies]
    common = set(hists[0].columns)
    for b in hists[1:]:
        common &= set(b.columns)

    def stack(name: str) -> np.ndarray:
        return np.stack([np.asarray(b._slice(name, start, start + rows), dtype=np.float64) for b in hists])

    for name in _ADD_SUM:
        if name in common and name not in h:
            h[name] = stack(name).sum(axis=0)
    for name in _ADD_MAX:
        if name in common and name not in h:
            h[name] = stack(name).max(axis=0)
    for name in _ADD_MIN:
        if name in common and name not in h:
            h[name] = stack(name).min(axis=0)
    if set(_TARGETS) <= common and not set(_TARGETS) & set(h):
        pt = np.stack([stack("px_target"), stack("py_target"), stack("pz_target")], axis=-1)  # (bodies, rows, 3)
        lt = np.stack([stack("lx_target"), stack("ly_target"), stack("lz_target")], axis=-1)
        com = np.stack([stack("cx"), stack("cy"), stack("cz")], axis=-1)
        c_sys = np.stack([h["cx"], h["cy"], h["cz"]], axis=-1)[None]
        p_sys = pt.sum(axis=0)
        l_sys = (lt + np.cross(com - c_sys, pt)).sum(axis=0)
        for a, axis in enumerate("xyz"):
            h[f"p{axis}_target"] = p_sys[:, a]
        for a, axis in enumerate("xyz"):
            h[f"l{axis}_target"] = l_sys[:, a]
    return h


def _is_system(sim) -> bool:
    return hasattr(sim, "bodies") and hasattr(sim, "names")


#: The history columns :func:`compute_metrics` reads.
METRIC_COLUMNS = (
    "step", "time", "total", "kinetic", "elastic", "gravitational", "budget_total", "work_unresolved",
    "px", "py", "pz", "lx", "ly", "lz", "px_target", "py_target", "pz_target", "lx_target", "ly_target",
    "lz_target", "inverted", "proj_converged", "proj_stood_down", "proj_iterations", "base_substeps", "base_ms",
    "proj_ms", "base_energy_error", "min_j",
)  # fmt: skip


def simulation_history(sim) -> Dict[str, np.ndarray]:
    """The history columns of a :class:`fepr.Simulation` (those :func:`compute_metrics` reads) or
    (:func:`system_history`) a ``MultiBody``."""
    return system_history(sim) if _is_system(sim) else sim.history.as_dict(METRIC_COLUMNS)


def simulation_metrics(
    sim,
    *,
    projection: Optional[bool] = None,
    pinned: Optional[bool] = None,
    runaway_step: Optional[int] = None,
    history: Optional[Mapping[str, np.ndarray]] = None,
) -> RunMetrics:
    """:func:`compute_metrics` of a :class:`fepr.Simulation` or a :class:`fepr.multibody.MultiBody`, with the
    mass, gravity, length scale, pins and projection taken from it (``projection`` and ``pinned`` override;
    ``history`` replaces its history, e.g. rows from a later start)."""
    bodies = list(sim.bodies) if _is_system(sim) else [sim]
    if projection is None:
        projection = any(getattr(b, "projection", None) is not None for b in bodies)
    if pinned is None:
        pinned = any(bool(np.any(np.asarray(b.pinned))) for b in bodies)
    return compute_metrics(
        simulation_history(sim) if history is None else history,
        total_mass=float(sim.total_mass),
        gravity=np.asarray(bodies[0].gravity, dtype=np.float64),
        length_scale=length_scale(np.asarray(sim.rest_positions)),
        pinned=bool(pinned),
        projection=bool(projection),
        runaway_step=runaway_step,
    )
