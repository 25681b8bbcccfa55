"""Summary numbers of a run, computed only from its diagnostics columns (what ``diagnostics.csv`` holds).

Given the diagnostics ``h`` (row 0 the initial state, rows 1.. the steps), the total mass ``M`` (kg), gravity
``g`` (m/s^2) and the rest shape's half bounding-box diagonal ``R`` (m):

- ``final_h_ratio`` = ``H_last / H_0`` and ``max_dh`` = ``max_k |H_k - H_0| / H_scale`` with ``H_scale = |H_0|``
  (or ``K_0 + |E_el,0| + |E_grav,0|`` when ``H_0`` is zero).
- ``p_drift`` = ``max_k |P_k - P_0 - M g (t_k - t_0)| / P_scale``, ``P_scale = max(|P_0|, max_k |P_0 + M g t_k|,
  sqrt(2 M (K_0 + |E_el,0|)))``
  (kg m/s; momentum changed only by gravity).
- ``l_drift`` = ``max_k |L_k - L_0| / max(|L_0|, R P_scale)`` (L about the centre of mass).
  Both are ``None`` when vertices are pinned: the supports exchange momentum with the body.
- ``min_j``: smallest volume ratio J = det F over all tets and rows.
- ``mean_iterations``: mean FEPR iterations over the steps (``None`` without projection).
- ``ms_per_step``: mean of ``base_ms + proj_ms`` over the steps (the solver's own timing, ms).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Dict, Mapping, Optional

import numpy as np

__all__ = ["RunMetrics", "compute_metrics", "length_scale"]

_TINY = 1e-300


@dataclass(frozen=True)
class RunMetrics:
    """The summary of one run (see the module docstring for the definitions)."""

    steps: int
    runaway_step: Optional[int]
    final_h_ratio: float
    max_dh: float
    p_drift: Optional[float]
    l_drift: Optional[float]
    min_j: float
    mean_iterations: Optional[float]
    ms_per_step: float

    def as_dict(self) -> Dict[str, object]:
        return asdict(self)


def _finite_max(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(a.max()) if a.size else float("nan")


def compute_metrics(
    history: Mapping[str, np.ndarray],
    *,
    total_mass: float,
    gravity,
    length_scale: float,
    pinned: bool,
    projection: bool,
    runaway_step: Optional[int] = None,
) -> RunMetrics:
    """Summary numbers of one run from its diagnostics columns (each a (rows,) array, row 0 the initial state).

    Parameters
    ----------
    history : mapping of column name to (rows,) float64
        ``sim.history.as_dict()`` or the columns of ``diagnostics.csv``.
    total_mass : float
        M, kg.
    gravity : (3,) float
        g, m/s^2.
    length_scale : float
        R, m: half the rest shape's bounding-box diagonal.
    pinned : bool
        Vertices are pinned (momentum drifts are then ``None``).
    projection : bool
        FEPR was on (else ``mean_iterations`` is ``None``).
    runaway_step : int, optional
        Where the run stopped, if it ran away.
    """
    h = {k: np.asarray(v, dtype=np.float64) for k, v in history.items()}
    rows = len(h["total"])
    H = h["total"]
    h0 = float(H[0])
    e0 = float(h["kinetic"][0] + abs(h["elastic"][0]) + abs(h["gravitational"][0]))
    h_scale = abs(h0) if abs(h0) > 1e-12 * e0 else max(e0, _TINY)
    with np.errstate(all="ignore"):
        final_ratio = float(H[-1] / h0) if h0 != 0 else float("nan")
        max_dh = _finite_max(np.abs(H - h0) / h_scale)
        p_drift = l_drift = None
        if not pinned:
            t = h["time"] - h["time"][0]
            g = np.asarray(gravity, dtype=np.float64)
            P = np.stack([h["px"], h["py"], h["pz"]], axis=1)
            L = np.stack([h["lx"], h["ly"], h["lz"]], axis=1)
            p_exp = P[0] + total_mass * t[:, None] * g
            p_scale = max(
                float(np.linalg.norm(P[0])),
                _finite_max(np.linalg.norm(p_exp, axis=1)),
                math.sqrt(max(2.0 * total_mass * (h["kinetic"][0] + abs(h["elastic"][0])), 0.0)),
                _TINY,
            )
            p_drift = _finite_max(np.linalg.norm(P - p_exp, axis=1) / p_scale)
            l_scale = max(float(np.linalg.norm(L[0])), length_scale * p_scale, _TINY)
            l_drift = _finite_max(np.linalg.norm(L - L[0], axis=1) / l_scale)
    steps = rows - 1
    mean_it = None
    if projection and steps > 0:
        mean_it = float(np.mean(h["proj_iterations"][1:]))
    ms = float(np.mean(h["base_ms"][1:] + h["proj_ms"][1:])) if steps > 0 else float("nan")
    return RunMetrics(
        steps=steps,
        runaway_step=runaway_step,
        final_h_ratio=final_ratio,
        max_dh=max_dh,
        p_drift=p_drift,
        l_drift=l_drift,
        min_j=float(np.nanmin(h["min_j"])) if rows else float("nan"),
        mean_iterations=mean_it,
        ms_per_step=ms,
    )


def length_scale(rest_positions: np.ndarray) -> float:
    """Half the bounding-box diagonal of the rest shape, m (R in the module docstring)."""
    x = np.asarray(rest_positions, dtype=np.float64)
    return 0.5 * float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
