"""Issue 38's scenes for ``run_peers.py --scenes bunny38,armadillo_drop38``: each solver (fepr's three implicit
integrators with and without FEPR, Newton's VBD, semi-implicit and XPBD, PBAT's VBD) runs the whole scene from
the same mesh (fepr's loader), and reports its time per step beside the quality of what it computed.

- **bunny38**: /work/shared/meshes/bunny.msh fit to 0.5 m, Neo-Hookean E = 1e5 Pa, Poisson 0.3, 1000 kg/m^3,
  stretched 10% about the centroid, released at rest, no gravity, dt = 1/30, 1 s (30 steps).
- **armadillo_drop38**: Armadillo_Tetra_4406.vtu fit to 1 m (as loaded, the frame of fepr's tests of this drop),
  Stable Neo-Hookean E = 1e5 Pa, Poisson 0.4, 1000 kg/m^3, its lowest point 0.3 m above the ground z = 0,
  gravity -9.81 m/s^2 along z, dt = 1/60, 3 s (180 steps). fepr's ground: ``fepr.Plane`` restitution 0,
  friction 0.5 (as tests/test_contact_in_solve.py); Newton's: its ground plane, friction 0.5, penalty 1e5 N/m.

Solvers that blow up at the scene's dt (Newton's semi-implicit and, on these meshes, its XPBD) run at their
largest stable dt (``peer_newton.largest_stable_dt``: halvings of the scene's dt until 300 steps from the
10%-stretched start stay bounded) and for at most ``wall_budget_s`` of stepping; the row says how much of the
scene's time that covered.

Quality (``quality.Quality``, NumPy, the same for every solver): J = det F per tet from the rest and current
positions; min J and inverted tets (J <= 0) at the end and the worst over the run (fepr: every step from its
history; peers: sampled every frame of the scene's dt). "upright": finite, and for the drop the centre of mass
never below ``COLLAPSED`` and no vertex more than 1 cm below the ground at the end (a body that lands on its
side squashes its limbs: fepr's backward Euler at dt = 1/960 has its lowest centre of mass at 0.103 m from 0.72
m, a rest height of 0.42 m above its lowest point, docs/world.md; half that is "flattened"); for the bunny (no
gravity) the centre of mass moved less than 1 cm.
"""

from __future__ import annotations

import time
import warnings

import numpy as np
from quality import Quality

import fepr

SHARED = "/work/shared/meshes"
SCENES38 = ("bunny38", "armadillo_drop38")
COLLAPSED = 0.05  # m, half the fine-step reference's lowest centre of mass (0.103 m) in the drop


def lame(e, nu):
    return e / (2 * (1 + nu)), e * nu / ((1 + nu) * (1 - 2 * nu))


def scene(name, meshes_dir):
    """Mesh (fepr's loader), material, start positions and run settings of an issue-38 scene."""
    if name == "bunny38":
        mesh = fepr.load_mesh(f"{meshes_dir}/bunny.msh", fit=0.5)
        rest = np.asarray(mesh.vertices, dtype=np.float64)
        c = rest.mean(axis=0)
        return dict(
            name=name, mesh=mesh, rest=rest, x0=c + 1.10 * (rest - c), material="neo_hookean",
            E=1e5, nu=0.3, density=1000.0, dt=1 / 30, duration=1.0, gravity=(0.0, 0.0, 0.0), ground=None,
        )  # fmt: skip
    if name == "armadillo_drop38":
        mesh = fepr.load_mesh(f"{meshes_dir}/Armadillo_Tetra_4406.vtu", fit=1.0)
        rest = np.asarray(mesh.vertices, dtype=np.float64)
        x0 = rest + np.array([0.0, 0.0, 0.3 - rest[:, 2].min()])
        return dict(
            name=name, mesh=mesh, rest=rest, x0=x0, material="stable_neo_hookean",
            E=1e5, nu=0.4, density=1000.0, dt=1 / 60, duration=3.0, gravity=(0.0, 0.0, -9.81), ground=0.5,
        )  # fmt: skip
    raise KeyError(name)


def lumped_masses(rest, tets, density):
    """rho V / 4 of each tet to each of its vertices (fepr's, Newton's and PBAT's lumping)."""
    d = rest[tets[:, 1:]] - rest[tets[:, [0]]]
    vol = np.abs(np.linalg.det(d)) / 6.0
    m = np.zeros(len(rest))
    np.add.at(m, np.asarray(tets).ravel(), np.repeat(density * vol / 4.0, 4))
    return m


def _finish(sc, q):
    """Start centre of mass (lumped masses) and the upright test (see the module docstring)."""
    tets = np.asarray(sc["mesh"].tets, dtype=np.int64)
    m = lumped_masses(sc["rest"], tets, sc["density"])
    c0 = (m[:, None] * sc["x0"]).sum(axis=0) / m.sum()
    q["com_start"] = c0.tolist()
    if not q.get("finite") or q.get("com_end") is None:
        q["upright"] = False
    elif sc["ground"] is None:  # no gravity: the centre of mass should stay where it was
        q["upright"] = bool(np.linalg.norm(np.asarray(q["com_end"]) - c0) < 0.01)
    else:  # the drop: not flattened (see COLLAPSED), nothing through the ground
        q["com_rest_height"] = float(c0[2] - sc["x0"][:, 2].min())
        low = min(q["com_up_min"] if q.get("com_up_min") is not None else np.inf, q["com_end"][2])
        q["upright"] = bool(low >= COLLAPSED and q["lowest_end"] > -0.01)
    return q


def run_fepr(sc, integrator, projection, threads=None):
    """fepr on the scene: wall time of ``sim.step(n)`` per step (its diagnostics included), quality from its
    history (every step) and the end state (NumPy)."""
    mat = (fepr.NeoHookean if sc["material"] == "neo_hookean" else fepr.StableNeoHookean)(
        youngs_modulus=sc["E"], poisson_ratio=sc["nu"]
    )
    obstacles = [fepr.Plane((0, 0, 0), (0, 0, 1), restitution=0.0, friction=sc["ground"])] if sc["ground"] else []
    sim = fepr.Simulation(
        sc["mesh"], material=mat, density=sc["density"], integrator=integrator, dt=sc["dt"],
        projection=projection, gravity=sc["gravity"], obstacles=obstacles, threads=threads,
    )  # fmt: skip
    sim.positions = sc["x0"]
    q = Quality(sc["rest"], sc["mesh"].tets, sim.masses, ref=sc["x0"])
    steps = int(round(sc["duration"] / sc["dt"]))
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim.step(steps)
    wall = time.perf_counter() - t0
    h = sim.history
    out = q.summary(sim.positions)
    mj, inv = np.asarray(h["min_j"], float), np.asarray(h["inverted"])
    out["min_j_worst"] = float(min(np.nanmin(mj), out["min_j_end"] if out["min_j_end"] is not None else np.inf))
    out["inverted_worst"] = int(max(inv.max(), out["inverted_end"] or 0))
    out["com_up_min"] = float(np.min(h["cz"]))
    out.update(
        solver=f"fepr {integrator}" + (" + FEPR" if projection else ""), steps=steps, steps_planned=steps,
        dt=sc["dt"], ms_per_step=1e3 * wall / steps, base_ms_mean=float(np.mean(h["base_ms"])),
        proj_ms_mean=float(np.mean(h["proj_ms"])) if projection else 0.0,
        mass=float(sim.masses.sum()),
    )  # fmt: skip
    return _finish(sc, out)


def run_newton(sc, solver, wall_budget_s):
    import peer_newton

    mu, lam = lame(sc["E"], sc["nu"])
    tets = np.asarray(sc["mesh"].tets, dtype=np.int64)
    dt, note, tried = sc["dt"], "", None
    if solver in ("semi_implicit", "xpbd"):
        c = sc["rest"].mean(axis=0)
        probe = c + 1.10 * (sc["rest"] - c)  # the stability probe: the 10%-stretched body, no gravity
        dt, tried = peer_newton.largest_stable_dt(
            sc["rest"], tets, mu, lam, sc["density"], probe, sc["dt"], solver=solver
        )
        if dt is None:
            why = "no stable dt down to the scene's dt / 2^13"
            return {"solver": f"newton {solver}", "error": why, "dt_tried": tried}
        if dt < sc["dt"]:
            note = f"unstable at dt = 1/{round(1 / sc['dt'])}; largest stable dt 1/{round(1 / dt)} ({dt:.3g} s)"
    r = peer_newton.simulate(
        sc["rest"], tets, mu, lam, sc["density"], sc["x0"], dt, sc["duration"], solver=solver,
        gravity=sc["gravity"], ground=sc["ground"], frame=sc["dt"], wall_budget_s=wall_budget_s,
    )  # fmt: skip
    if r["steps"] < r["steps_planned"]:
        note += ("; " if note else "") + (
            f"ran {r['steps'] * dt:.3g} s of {sc['duration']:.3g} s (wall budget {wall_budget_s:.0f} s)"
        )
    r.update(solver=f"newton {solver}" + (" (10 it)" if solver in ("vbd", "xpbd") else ""), note=note)
    if tried:
        r["dt_tried"] = tried
    return _finish(sc, r)


def run_pbat(sc, wall_budget_s):
    import peer_pbat

    if sc["ground"] is not None:
        return {
            "solver": "pbat vbd (10 it)",
            "error": "not run: PBAT's VBD (Python API, 0.0.11) has no ground plane or other static obstacle; its "
            "contact is between simulated meshes' surfaces (with_bodies)",
        }
    mu, lam = lame(sc["E"], sc["nu"])
    tets = np.asarray(sc["mesh"].tets, dtype=np.int64)
    r = peer_pbat.simulate(
        sc["rest"], tets, mu, lam, sc["density"], sc["x0"], sc["dt"], sc["duration"], frame=sc["dt"],
        wall_budget_s=wall_budget_s, masses=lumped_masses(sc["rest"], tets, sc["density"]),
    )  # fmt: skip
    r.update(solver="pbat vbd (10 it)", note="")
    return _finish(sc, r)
