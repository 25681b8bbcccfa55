"""The seed project's three demos at the seed's time steps, per base integrator, with and without FEPR.

Prints a Markdown table: final H/H0, max |H/H0 - 1|, min J, mean and max projection iterations, and how the run
ended. Needs the seed meshes (``../shared/meshes/seed`` or ``$FEPR_SHARED_MESHES/seed``).

    python benchmarks/integrators/seed_demos.py [--steps 300] [--integrators implicit_euler,projective_dynamics]
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from pathlib import Path

import numpy as np

import fepr

# (name, mesh, position scale, dt in s, alternating initial z velocity in m/s): the seed's set-ups
# (seed/README: 5 kg per node, E = 1e3 Pa, nu = 0.3, no gravity, no damping).
DEMOS = [
    ("demo 1 (wobbly L)", "ellell.1", 1.5, 1 / 20, -5.0),
    ("demo 2 (T pose)", "test_mesh.1", 1.1, 1 / 30, None),
    ("demo 3 (stretched L)", "ellell.1", 1.5, 1 / 30, None),
]


def meshes_dir() -> Path:
    env = os.environ.get("FEPR_SHARED_MESHES")
    base = Path(env) if env else Path(__file__).resolve().parents[2] / ".." / "shared" / "meshes"
    return base / "seed"


def run(mesh_name, scale, dt, vz, integrator, projection, steps):
    mesh = fepr.load_mesh(meshes_dir() / mesh_name)
    sim = fepr.Simulation(
        mesh,
        material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
        node_mass=5.0,
        dt=dt,
        integrator=integrator,
        projection=projection,
    )
    sim.positions = scale * sim.rest_positions
    if vz is not None:
        v = np.zeros((mesh.num_vertices, 3))
        v[::2, 2] = vz
        sim.velocities = v
    t0 = time.perf_counter()
    ended = "ran"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            sim.step(steps)
        except fepr.SimulationError:
            ended = f"non-finite after step {sim.num_steps}"
    h = sim.history
    runaway = np.flatnonzero(h["runaway"] == 1)
    if runaway.size and ended == "ran":
        ended = f"runaway flagged at step {int(runaway[0])}"
    ratio = h["total"] / h["total"][0]
    it = h["proj_iterations"][1:]
    return {
        "final": ratio[-1],
        "max_dh": np.abs(ratio - 1).max(),
        "min_j": h["min_j"].min(),
        "mean_it": it.mean() if projection and it.size else float("nan"),
        "max_it": int(it.max()) if projection and it.size else 0,
        "converged": h["proj_converged"][1:].mean() if projection and it.size else float("nan"),
        "ended": ended,
        "ms": 1e3 * (time.perf_counter() - t0) / max(sim.num_steps, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--integrators", default="symplectic_euler,implicit_euler,projective_dynamics,xpbd")
    args = ap.parse_args()
    print(
        "| demo | integrator | FEPR | final H/H0 | max abs(H/H0-1) | min J | proj. iters mean / max | converged | end "
        "| ms/step |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, mesh, scale, dt, vz in DEMOS:
        for integ in args.integrators.split(","):
            for proj in (True, False):
                r = run(mesh, scale, dt, vz, integ, proj, args.steps)
                iters = f"{r['mean_it']:.2f} / {r['max_it']}" if proj else "-"
                conv = f"{r['converged']:.0%}" if proj else "-"
                print(
                    f"| {name}, dt = 1/{round(1 / dt)} | {integ} | {'on' if proj else 'off'} | {r['final']:.6g} | "
                    f"{r['max_dh']:.1e} | {r['min_j']:.3f} | {iters} | {conv} | {r['ended']} | {r['ms']:.1f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
