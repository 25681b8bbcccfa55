"""XPBD on the integrators issue's bunny, alone and with FEPR.

The set-up of issue 3: ``bunny.msh`` scaled so that its largest extent is 0.5 m, E = 1e5 Pa, nu = 0.3,
1000 kg/m^3, no gravity, released from a uniform 1.1 stretch about the centre of mass, dt = 1/30 s. Prints, per
run: final and max |H/H0 - 1|, max |P| and |L|, min J over the run, inverted tets at the end, projection
iterations (mean / max), the fraction of converged projections and the base step's and the projection's wall
time per step. Needs the shared meshes (``../shared/meshes`` or ``$FEPR_SHARED_MESHES``).

    python benchmarks/integrators/xpbd_bunny.py [--steps 300] [--substeps 20] [--iterations 1] [--alone-steps 60]
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from pathlib import Path

import numpy as np

import fepr


def bunny_mesh() -> fepr.TetMesh:
    env = os.environ.get("FEPR_SHARED_MESHES")
    base = Path(env) if env else Path(__file__).resolve().parents[2] / ".." / "shared" / "meshes"
    mesh = fepr.load_mesh(base / "bunny.msh")
    v = mesh.vertices
    return fepr.TetMesh(v * 0.5 / (v.max(0) - v.min(0)).max(), mesh.tets)


def run(mesh, substeps, iterations, projection, steps):
    sim = fepr.Simulation(
        mesh,
        material=fepr.NeoHookean(youngs_modulus=1e5, poisson_ratio=0.3),
        density=1000.0,
        dt=1 / 30,
        integrator=fepr.Xpbd(substeps=substeps, iterations=iterations),
        projection=projection,
    )
    c = sim.center_of_mass()
    sim.positions = c + 1.1 * (sim.rest_positions - c)
    ended = "ran"
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            sim.step(steps)
        except fepr.SimulationError as exc:
            ended = f"stopped after step {sim.num_steps}: {exc}"
    wall = time.perf_counter() - t0
    return sim, ended, wall


def summary(sim, ended, wall, label):
    h = sim.history
    n = len(h) - 1
    rel = h["total"] / h["total"][0] - 1
    p = np.abs(np.stack([h["px"], h["py"], h["pz"]])).max()
    ang = np.abs(np.stack([h["lx"], h["ly"], h["lz"]])).max()
    it = h["proj_iterations"][1:]
    conv = h["proj_converged"][1:]
    print(
        f"{label}: {n} steps ({ended}); H/H0 final {h['total'][-1] / h['total'][0]:.4f}, "
        f"max |H/H0-1| {np.nanmax(np.abs(rel)):.2e}; max |P| {p:.1e} kg m/s, max |L| {ang:.1e} kg m^2/s; "
        f"min J {np.nanmin(h['min_j']):.4f}, inverted at end {h['inverted'][-1]:.0f}; "
        f"projection iterations {it.mean():.2f} mean / {it.max():.0f} max, converged {conv.mean():.1%}; "
        f"base {h['base_ms'][1:].mean():.1f} ms/step, projection {h['proj_ms'][1:].mean():.1f} ms/step, "
        f"wall {1e3 * wall / max(n, 1):.1f} ms/step"
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=300, help="steps of the XPBD + FEPR run (300 = 10 s)")
    ap.add_argument("--alone-steps", type=int, default=60, help="steps of the XPBD-alone run (0: skip)")
    ap.add_argument("--substeps", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=1)
    args = ap.parse_args()
    mesh = bunny_mesh()
    print(f"bunny: {mesh.num_vertices} vertices, {mesh.num_tets} tets; xpbd {args.substeps} x {args.iterations}")
    if args.alone_steps > 0:
        summary(*run(mesh, args.substeps, args.iterations, False, args.alone_steps), "XPBD alone")
    if args.steps > 0:
        summary(*run(mesh, args.substeps, args.iterations, True, args.steps), "XPBD + FEPR")


if __name__ == "__main__":
    main()
