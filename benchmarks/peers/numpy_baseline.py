"""The plain NumPy baseline: the same explicit step as fepr's symplectic Euler (Neo-Hookean with the log
volumetric term, lumped masses), vectorised with einsum and bincount. Single process; NumPy's element-wise
kernels run on one thread."""

from __future__ import annotations

import time

import numpy as np


class NumpyNeoHookean:
    """Energy + gradient and a symplectic Euler step of ``Psi = mu/2 (I_C - 3) - mu log J + lambda/2 log^2 J``."""

    def __init__(self, rest: np.ndarray, tets: np.ndarray, mu: float, lam: float, masses: np.ndarray):
        self.tets = np.ascontiguousarray(tets, dtype=np.int64)
        self.m = len(rest)
        dm = (rest[self.tets[:, 1:]] - rest[self.tets[:, [0]]]).transpose(0, 2, 1)  # columns = edges
        self.dm_inv = np.linalg.inv(dm)
        self.vol = np.abs(np.linalg.det(dm)) / 6.0
        self.mu, self.lam = mu, lam
        self.inv_m = 1.0 / masses
        self.flat = self.tets.ravel()

    def energy_gradient(self, x: np.ndarray):
        t = self.tets
        ds = (x[t[:, 1:]] - x[t[:, [0]]]).transpose(0, 2, 1)
        f = ds @ self.dm_inv
        j = np.linalg.det(f)
        f_inv_t = np.linalg.inv(f).transpose(0, 2, 1)
        logj = np.log(j)
        ic = np.einsum("kij,kij->k", f, f)
        psi = 0.5 * self.mu * (ic - 3.0) - self.mu * logj + 0.5 * self.lam * logj**2
        p = self.mu * f + (self.lam * logj - self.mu)[:, None, None] * f_inv_t
        h = self.vol[:, None, None] * (p @ self.dm_inv.transpose(0, 2, 1))  # columns: corners 1..3
        g = np.empty((len(t), 4, 3))
        g[:, 1:, :] = h.transpose(0, 2, 1)
        g[:, 0, :] = -h.sum(axis=2)
        grad = np.stack(
            [np.bincount(self.flat, weights=g[:, :, a].ravel(), minlength=self.m) for a in range(3)], axis=1
        )
        return float(np.dot(self.vol, psi)), grad

    def step(self, x: np.ndarray, v: np.ndarray, dt: float) -> None:
        _, grad = self.energy_gradient(x)
        v -= dt * grad * self.inv_m[:, None]
        x += dt * v


def time_step(rest, tets, mu, lam, masses, x0, dt, budget_s=1.0, min_steps=3):
    """Seconds per explicit step (after one warm-up step)."""
    sim = NumpyNeoHookean(rest, tets, mu, lam, masses)
    x, v = x0.copy(), np.zeros_like(x0)
    sim.step(x, v, dt)
    n, t0 = 0, time.perf_counter()
    while n < min_steps or time.perf_counter() - t0 < budget_s:
        sim.step(x, v, dt)
        n += 1
    return (time.perf_counter() - t0) / n, sim
