"""Peer comparison: the same scenes with fepr and with peer simulators, on the CPU, timed the same way in the
same run (wall time per step or per evaluation after a warm-up, best of the run's repeats).

    pip install ".[peers]"                         # newton (Warp) and pbatoolkit, from PyPI
    python benchmarks/peers/run_peers.py --json benchmarks/results/peers.json

Peers that are not installed or fail are reported with the reason (never a crash). Scenes: box_10k, the
bunny (19,379 tets; 0.5 m, E = 1e5 Pa, 1000 kg/m^3), bunny2 (29,548 tets), box_100k.

Issue 38's whole-scene runs (time per step beside min J, inverted tets and whether the body stayed upright, for
fepr's implicit integrators and each peer; see scenes38.py)::

    python benchmarks/peers/run_peers.py --scenes bunny38,armadillo_drop38 \
        --json benchmarks/results/peers-issue38.json --table /tmp/w/peers_table.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy_baseline  # noqa: E402
import scenes38  # noqa: E402

import fepr  # noqa: E402
from fepr.cli.bench import SCENES, load_scene_mesh, shared_meshes_dir, stable_dt  # noqa: E402

PEER_SCENES = ("box_10k", "bunny", "bunny2", "box_100k")


def lame(e, nu):
    return e / (2 * (1 + nu)), e * nu / ((1 + nu) * (1 - 2 * nu))


def fepr_times(scene, mesh, dt, threads, budget):
    """fepr: energy + gradient (1 and all threads), explicit step without and with FEPR."""
    out = {}
    mass = {"node_mass": scene.node_mass} if scene.node_mass is not None else {"density": scene.density}
    mat = fepr.NeoHookean(youngs_modulus=scene.youngs_modulus, poisson_ratio=scene.poisson_ratio)
    k = len(mesh.tets)
    for proj in (False, True):
        for th in (1, threads):
            sim = fepr.Simulation(mesh, material=mat, dt=dt, projection=proj, threads=th, **mass)
            x0 = sim.rest_positions
            c = x0.mean(axis=0)
            sim.positions = c + scene.stretch * (x0 - c)
            if not proj and th == 1:
                reps = max(3, int(0.3 / max(k * 50e-9, 1e-6)))
                t1 = min(sim._sim.bench_energy_gradient(reps, 1)[0] for _ in range(2))
                tn = min(sim._sim.bench_energy_gradient(reps, threads)[0] for _ in range(2))
                out["eg_ns_per_tet_1"] = 1e9 * t1 / k
                out["eg_ns_per_tet_all"] = 1e9 * tn / k
            sim.step(2)
            t0 = time.perf_counter()
            sim.step(1)
            n = int(max(3, budget / max(time.perf_counter() - t0, 1e-9)))
            t0 = time.perf_counter()
            sim.step(n)  # one call: each Python-level step() also scans the history
            per = (time.perf_counter() - t0) / n
            tag = f"{'se_fepr' if proj else 'se'}_ns_per_tet_{1 if th == 1 else 'all'}"
            out[tag] = 1e9 * per / k
            if not proj:
                # The integrator's step alone (what a peer's solver.step does), from the per-step history; the
                # Simulation step above also measures energy and momenta for the diagnostics.
                out[tag.replace("se_", "se_base_")] = 1e6 * float(np.mean(sim.history["base_ms"][-n:])) / k
    return out


def guarded(fn, *args, **kw):
    try:
        return fn(*args, **kw), None
    except ImportError as e:
        return None, f"not installed ({e})"
    except Exception as e:  # report, never crash
        return None, f"{type(e).__name__}: {e}".splitlines()[0][:300] + " | " + traceback.format_exc().splitlines()[-2]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(PEER_SCENES))
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--budget", type=float, default=1.0, help="seconds of timed steps per measurement")
    ap.add_argument(
        "--skip",
        default="",
        help="comma-separated peers to skip: newton,newton_vbd,pbat,pbat_vbd,numpy (issue-38 scenes: newton_si, "
        "newton_vbd, newton_xpbd, pbat_vbd, fepr_be, fepr_pd, fepr_xpbd)",
    )
    ap.add_argument("--table", metavar="PATH", help="issue-38 scenes: write a markdown table here")
    ap.add_argument("--table-from", metavar="JSON", help="only write --table from an earlier run's --json")
    ap.add_argument(
        "--wall-budget", type=float, default=40.0, help="issue-38 scenes: seconds of stepping at most per peer run"
    )
    args = ap.parse_args(argv)
    if args.table_from:
        Path(args.table).write_text(table38(json.loads(Path(args.table_from).read_text())))
        return 0
    skip = set(filter(None, args.skip.split(",")))
    meshes_dir = shared_meshes_dir()
    rows = []
    for name in args.scenes.split(","):
        if name in scenes38.SCENES38:
            rows.append(run_scene38(name, meshes_dir, skip, args))
            continue
        scene = SCENES[name]
        mesh, why = load_scene_mesh(scene, meshes_dir)
        if mesh is None:
            rows.append({"scene": name, "skipped": why})
            continue
        rest = np.asarray(mesh.vertices, dtype=np.float64)
        tets = np.asarray(mesh.tets, dtype=np.int64)
        k = len(tets)
        c = rest.mean(axis=0)
        x0 = c + scene.stretch * (rest - c)
        mu, lam = lame(scene.youngs_modulus, scene.poisson_ratio)
        dt = scene.integrators[0][1]
        if scene.source[0] == "file":
            dt = stable_dt(scene, mesh, "symplectic_euler", dt)
        density = scene.density if scene.density is not None else None
        # Masses as fepr lumps them (node mass or density), shared with the NumPy baseline.
        mass = {"node_mass": scene.node_mass} if scene.node_mass is not None else {"density": scene.density}
        probe = fepr.Simulation(
            mesh,
            material=fepr.NeoHookean(youngs_modulus=scene.youngs_modulus, poisson_ratio=0.3),
            dt=dt,
            projection=False,
            **mass,
        )
        masses = probe.masses
        if density is None:  # node-mass scenes: the equivalent uniform density for the peers
            density = float(masses.sum() / probe_volume(rest, tets))
        row = {"scene": name, "tets": k, "vertices": len(rest), "dt": dt}
        print(f"== {name}: {k:,} tets", flush=True)
        row["fepr"] = fepr_times(scene, mesh, dt, args.threads, args.budget)
        print("   fepr", {a: round(b, 1) for a, b in row["fepr"].items()}, flush=True)
        if "numpy" not in skip:
            r, err = guarded(numpy_baseline.time_step, rest, tets, mu, lam, masses, x0, dt, budget_s=args.budget)
            row["numpy_step_ns_per_tet"] = 1e9 * r[0] / k if r else None
            row["numpy_error"] = err
            print("   numpy", row["numpy_step_ns_per_tet"], err or "", flush=True)
        if "newton" not in skip:
            import peer_newton

            r, err = guarded(peer_newton.time_step, rest, tets, mu, lam, density, x0, dt, budget_s=args.budget)
            row["newton_step_ns_per_tet"] = 1e9 * r[0] / k if r else None
            row["newton_finite"] = r[1] if r else None
            row["newton_error"] = err
            print("   newton semi-implicit", row["newton_step_ns_per_tet"], err or "", flush=True)
        if "newton_vbd" not in skip:
            import peer_newton

            r, err = guarded(
                peer_newton.time_step, rest, tets, mu, lam, density, x0, 1 / 60, budget_s=args.budget, solver="vbd"
            )
            row["newton_vbd_ns_per_tet"] = 1e9 * r[0] / k if r else None
            row["newton_vbd_error"] = err
            print("   newton vbd", row["newton_vbd_ns_per_tet"], err or "", flush=True)
        if "pbat" not in skip:
            import peer_pbat

            r, err = guarded(peer_pbat.time_energy_gradient, rest, tets, mu, lam, x0, budget_s=args.budget)
            row["pbat_eg_ns_per_tet"] = 1e9 * r / k if r else None
            row["pbat_error"] = err
            print("   pbat energy+gradient", row["pbat_eg_ns_per_tet"], err or "", flush=True)
        if "pbat_vbd" not in skip:
            import peer_pbat

            r, err = guarded(peer_pbat.time_vbd_step, rest, tets, mu, lam, density, x0, 1 / 60, budget_s=args.budget)
            row["pbat_vbd_ns_per_tet"] = 1e9 * r / k if r else None
            row["pbat_vbd_error"] = err
            print("   pbat vbd", row["pbat_vbd_ns_per_tet"], err or "", flush=True)
        f = row["fepr"]
        ratios = {}
        if row.get("newton_step_ns_per_tet"):
            nt = row["newton_step_ns_per_tet"]
            ratios["newton_si / fepr_se_base (all threads)"] = nt / f["se_base_ns_per_tet_all"]
            ratios["newton_si / fepr_se_base (1 thread)"] = nt / f["se_base_ns_per_tet_1"]
            ratios["newton_si / fepr_se_with_diagnostics (all threads)"] = nt / f["se_ns_per_tet_all"]
        if row.get("numpy_step_ns_per_tet"):
            ratios["numpy / fepr_se_base (all threads)"] = row["numpy_step_ns_per_tet"] / f["se_base_ns_per_tet_all"]
            ratios["numpy / fepr_se_with_diagnostics (all threads)"] = (
                row["numpy_step_ns_per_tet"] / f["se_ns_per_tet_all"]
            )
        if row.get("pbat_eg_ns_per_tet"):
            ratios["pbat_eg / fepr_eg (all threads)"] = row["pbat_eg_ns_per_tet"] / f["eg_ns_per_tet_all"]
        row["ratios_peer_over_fepr"] = ratios
        print("   ratios", {a: round(b, 2) for a, b in ratios.items()}, flush=True)
        rows.append(row)
    doc = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "threads": args.threads,
        "scenes": rows,
    }
    doc["versions"] = versions()
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
    if args.table:
        Path(args.table).parent.mkdir(parents=True, exist_ok=True)
        Path(args.table).write_text(table38(doc))
    return 0


def versions():
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("fepr", "newton", "warp-lang", "pbatoolkit", "numpy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def run_scene38(name, meshes_dir, skip, args):
    """One issue-38 scene with every solver; a solver that fails is a row with the reason."""
    sc = scenes38.scene(name, meshes_dir)
    row = {"scene": name, "tets": len(sc["mesh"].tets), "vertices": len(sc["rest"]), "dt": sc["dt"],
           "duration": sc["duration"], "results": []}  # fmt: skip
    print(f"== {name}: {row['tets']:,} tets, dt = 1/{round(1 / sc['dt'])}, {sc['duration']} s", flush=True)
    runs = []
    for tag, integ in (("fepr_be", "implicit_euler"), ("fepr_pd", "projective_dynamics"), ("fepr_xpbd", "xpbd")):
        if tag not in skip:
            for proj in (False, True):
                runs.append(
                    (f"fepr {integ}" + (" + FEPR" if proj else ""), scenes38.run_fepr, (sc, integ, proj, args.threads))
                )
    for tag, solver in (("newton_vbd", "vbd"), ("newton_si", "semi_implicit"), ("newton_xpbd", "xpbd")):
        if tag not in skip:
            runs.append((f"newton {solver}", scenes38.run_newton, (sc, solver, args.wall_budget)))
    if "pbat_vbd" not in skip:
        runs.append(("pbat vbd", scenes38.run_pbat, (sc, args.wall_budget)))
    for label, fn, fargs in runs:
        t0 = time.perf_counter()
        r, err = guarded(fn, *fargs)
        if r is None:
            r = {"solver": label, "error": err}
        r["wall_s"] = time.perf_counter() - t0
        row["results"].append(r)
        brief = {k: r.get(k) for k in ("ms_per_step", "dt", "steps", "min_j_end", "min_j_worst", "inverted_end",
                                       "inverted_worst", "com_up_min", "upright", "note", "error")}  # fmt: skip
        print(f"   {r.get('solver', label)}: {brief} ({r['wall_s']:.0f} s)", flush=True)
    ref = {r["solver"]: r["ms_per_step"] for r in row["results"] if r.get("ms_per_step")}
    for r in row["results"]:
        if r.get("ms_per_step"):
            # Ratio to fepr's backward Euler without and with FEPR at the scene's dt (per step, not per second of
            # scene time: a peer at a smaller dt needs dt_scene / dt of its steps per scene step).
            for base in ("fepr implicit_euler", "fepr implicit_euler + FEPR"):
                if base in ref:
                    r[f"ratio_over_{base.replace(' ', '_')}"] = r["ms_per_step"] / ref[base]
            r["ms_per_scene_second"] = r["ms_per_step"] / r["dt"]
    return row


def _fmt(v, spec):
    if v is None:
        return "-"
    return format(v, ".2e") if spec.endswith("f") and abs(v) >= 1e3 else format(v, spec)


def table38(doc):
    """Markdown table of the issue-38 scenes in ``doc``."""
    lines = []
    v = doc.get("versions", {})
    lines.append(
        f"Peers on issue 38's scenes, one run ({doc['machine']['cpus']} CPUs, fepr threads {doc['threads']}; "
        + ", ".join(f"{k} {val}" for k, val in v.items() if val)
        + "). Times as measured on a shared machine; ratios from the same run. min J: smallest det F over the tets "
        "(NumPy, rest vs current positions); worst: over the run (fepr every step, peers every scene frame). "
        "Drop: lowest COM z of the body (fepr backward Euler at dt = 1/960: 0.103 m; start 0.724 m); upright: finite, "
        "COM never below 0.05 m, nothing through the ground. Bunny: upright = finite and the COM moved < 1 cm.\n"
    )
    for row in doc["scenes"]:
        if "results" not in row:
            continue
        lines.append(
            f"\n**{row['scene']}** ({row['tets']:,} tets, {row['vertices']:,} vertices, scene dt = "
            f"1/{round(1 / row['dt'])}, {row['duration']:g} s)\n"
        )
        lines.append(
            "| solver | dt | ms/step | steps/s | ms per scene second | / fepr BE (step) | min J end / worst "
            "| inverted end / worst | lowest COM z | upright | notes |"
        )
        lines.append("|---|---|---|---|---|---|---|---|---|---|---|")
        for r in row["results"]:
            if r.get("error"):
                lines.append(f"| {r['solver']} | | | | | | | | | no | {r['error']} |")
                continue
            dt = r["dt"]
            ratio = r.get("ratio_over_fepr_implicit_euler")
            note = r.get("note", "")
            if not r.get("finite"):
                note = (note + "; " if note else "") + "NaN / non-finite"
            elif (r.get("inverted_worst") or 0) > 0.1 * row["tets"]:
                note = (note + "; " if note else "") + "diverged (most tets inverted, the body flew apart)"
            lines.append(
                f"| {r['solver']} | 1/{round(1 / dt)} | {r['ms_per_step']:.2f} | {1e3 / r['ms_per_step']:.1f} "
                f"| {r['ms_per_scene_second']:.0f} | {_fmt(ratio, '.3f')} "
                f"| {_fmt(r.get('min_j_end'), '.3f')} / {_fmt(r.get('min_j_worst'), '.3f')} "
                f"| {_fmt(r.get('inverted_end'), 'd')} / {_fmt(r.get('inverted_worst'), 'd')} "
                f"| {_fmt(r.get('com_up_min'), '.3f')} | {'yes' if r.get('upright') else 'no'} | {note} |"
            )
    return "\n".join(lines) + "\n"


def probe_volume(rest, tets):
    d = rest[tets[:, 1:]] - rest[tets[:, [0]]]
    return float(np.abs(np.linalg.det(d)).sum() / 6.0)


if __name__ == "__main__":
    sys.exit(main())
