"""Bounces of a dropped box (issue 6): peak heights of the centre of mass and the energy, with and without FEPR.

A 0.2 m box of 1,080 tets (Neo-Hookean, E = 1e5 Pa, nu = 0.3, 1000 kg/m^3) is dropped with its centre at 0.5 m
onto the ground plane z = 0 (no friction). Run: ``python benchmarks/world/bounce.py``.
"""

import time

import numpy as np

import fepr

G = 9.81


def run(integrator, dt, restitution, projection, seconds=4.0):
    mesh = fepr.meshes.box(size=(0.2, 0.2, 0.2), resolution=(6, 6, 5), center=(0, 0, 0.5))
    sim = fepr.Simulation(
        mesh,
        material=fepr.NeoHookean(1e5, 0.3),
        density=1000.0,
        integrator=integrator,
        dt=dt,
        projection=projection,
        gravity=(0, 0, -G),
        obstacles=[fepr.Plane((0, 0, 0), (0, 0, 1), restitution=restitution)],
    )
    t0 = time.perf_counter()
    sim.step(round(seconds / dt))
    wall = time.perf_counter() - t0
    h = sim.history
    cz = h["cz"]
    # Peaks of the centre of mass between contacts (local maxima above the resting height).
    peaks = [k for k in range(1, len(cz) - 1) if cz[k] >= cz[k - 1] and cz[k] > cz[k + 1] and cz[k] > 0.11]
    bal = np.max(np.abs(h["total"] - h["total"][0] - h["budget_total"])) / h["total"][0]
    return {
        "peaks": [round(float(cz[k]), 4) for k in peaks][:6],
        "H_end/H0": float(h["total"][-1] / h["total"][0]),
        "max|H-H0-W|/H0": float(bal),
        "budget_total/H0": float(h["budget_total"][-1] / h["total"][0]),
        "max_penetration_m": float(h["penetration"].max()),
        "converged": float(np.mean(h["proj_converged"][1:])) if projection else None,
        "ms_per_step": 1e3 * wall / (len(h) - 1),
    }


if __name__ == "__main__":
    print(
        "| integrator | dt (s) | restitution | FEPR | CoM peak heights (m; drop from 0.5) | H_end/H0 | "
        "max abs(H-H0-W)/H0 | W_total/H0 | max penetration (m) | converged | ms/step |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for integ, dt, e, proj in [
        ("symplectic_euler", 2.5e-4, 1.0, True),
        ("symplectic_euler", 2.5e-4, 0.5, True),
        ("implicit_euler", 0.01, 1.0, True),
        ("implicit_euler", 0.01, 1.0, False),
    ]:
        r = run(integ, dt, e, proj)
        conv = "-" if r["converged"] is None else f"{r['converged']:.0%}"
        print(
            f"| {integ} | {dt:g} | {e} | {'on' if proj else 'off'} | {r['peaks']} | {r['H_end/H0']:.6f} | "
            f"{r['max|H-H0-W|/H0']:.1e} | {r['budget_total/H0']:.4f} | {r['max_penetration_m']:.1e} | "
            f"{conv} | {r['ms_per_step']:.2f} |"
        )
