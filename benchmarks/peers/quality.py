"""Mesh quality of a peer's state, computed the same way for every solver (fepr included) with NumPy: the
deformation gradient's determinant J = det(F) = det(Ds) / det(Dm) per tet (Dm, Ds: the edge matrices of the rest
and current positions), the smallest J and the number of inverted tets (J <= 0), and the centre of mass."""

from __future__ import annotations

import time

import numpy as np


def edge_dets(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """det of each tet's edge matrix [x1 - x0, x2 - x0, x3 - x0] (six times its signed volume)."""
    a = x[tets[:, 0]]
    return np.einsum("ij,ij->i", np.cross(x[tets[:, 1]] - a, x[tets[:, 2]] - a), x[tets[:, 3]] - a)


class Quality:
    """J of a state against the rest shape, and the worst J / inverted count over the states it has seen."""

    def __init__(self, rest: np.ndarray, tets: np.ndarray, masses: np.ndarray | None = None, ref=None):
        self.tets = np.asarray(tets, dtype=np.int64)
        self.rest_det = edge_dets(np.asarray(rest, dtype=np.float64), self.tets)
        if np.any(self.rest_det <= 0):
            raise ValueError("rest shape has inverted or flat tets")
        self.masses = None if masses is None else np.asarray(masses, dtype=np.float64)
        self.min_j_worst = np.inf
        self.inverted_worst = 0
        self.com_z_min = np.inf
        self.finite = True
        self.samples = 0
        self.ref = None if ref is None else np.asarray(ref, dtype=np.float64)
        self.max_disp = 0.0  # largest |x - ref| seen (a blow-up test)

    def jacobians(self, x: np.ndarray) -> np.ndarray:
        return edge_dets(np.asarray(x, dtype=np.float64), self.tets) / self.rest_det

    def com(self, x: np.ndarray) -> np.ndarray:
        if self.masses is None:
            return np.asarray(x, dtype=np.float64).mean(axis=0)
        return (self.masses[:, None] * x).sum(axis=0) / self.masses.sum()

    def observe(self, x: np.ndarray, up: int = 2) -> dict:
        """J and centre of mass of state ``x``; updates the worst-over-run figures."""
        x = np.asarray(x, dtype=np.float64)
        finite = bool(np.all(np.isfinite(x)))
        self.finite &= finite
        self.samples += 1
        if not finite:
            self.min_j_worst = -np.inf
            return {"finite": False, "min_j": None, "inverted": None, "com": None}
        if self.ref is not None:
            self.max_disp = max(self.max_disp, float(np.abs(x - self.ref).max()))
        j = self.jacobians(x)
        min_j, inv = float(j.min()), int(np.sum(j <= 0.0))
        c = self.com(x)
        self.min_j_worst = min(self.min_j_worst, min_j)
        self.inverted_worst = max(self.inverted_worst, inv)
        self.com_z_min = min(self.com_z_min, float(c[up]))
        return {"finite": True, "min_j": min_j, "inverted": inv, "com": c.tolist()}

    def summary(self, x_end: np.ndarray, up: int = 2) -> dict:
        """The end state's figures and the worst over every observed state (``x_end`` included)."""
        end = self.observe(x_end, up)
        return {
            "finite": self.finite,
            "min_j_end": end["min_j"],
            "inverted_end": end["inverted"],
            "min_j_worst": None if not np.isfinite(self.min_j_worst) else float(self.min_j_worst),
            "inverted_worst": int(self.inverted_worst),
            "com_end": end["com"],
            "com_up_min": None if not np.isfinite(self.com_z_min) else float(self.com_z_min),
            "lowest_end": None if not end["finite"] else float(np.asarray(x_end)[:, up].min()),
            "quality_samples": self.samples,
            "max_displacement": None if self.ref is None else self.max_disp,
        }


def timed_run(step, positions, quality, *, steps, every, wall_budget_s=None):
    """Time ``steps`` calls of ``step(n)`` (n steps at once, ``every`` between quality samples; the sampling is
    not timed), sampling ``positions()`` into ``quality``; stops early on non-finite positions or past
    ``wall_budget_s`` seconds of stepping. Returns (seconds of stepping, steps done)."""
    t_steps, done = 0.0, 0
    while done < steps:
        n = min(every, steps - done)
        t0 = time.perf_counter()
        step(n)
        t_steps += time.perf_counter() - t0
        done += n
        x = positions()
        if done < steps:
            quality.observe(x)
        if not np.all(np.isfinite(x)):
            break
        if wall_budget_s is not None and t_steps > wall_budget_s:
            break
    return t_steps, done
