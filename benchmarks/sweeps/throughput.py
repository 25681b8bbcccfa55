"""Throughput of a sweep: 16 runs of a 1-2 s scene, as serial `fepr run` processes, on the local pool and on Ray.

    python benchmarks/sweeps/throughput.py [--runs 16] [--steps 400] [--json out.json] [--keep DIR]

The scene is a 343-vertex box (backward Euler with FEPR, 400 steps at dt = 1/240 s: about 1.3 s of stepping on one
thread of this machine); the 16 runs differ in Young's modulus and initial stretch (a 4 x 4 grid). Measured:

- serial: each run's ``scene.toml`` (as the sweep writes it) run by ``fepr run`` in a subprocess, one after the
  other, as a shell loop would, with the scene's default threads (all cores) and again with ``[run] threads = 1``;
- pool: ``fepr.sweep.run_sweep(..., backend="pool")`` into a fresh folder (processes = cores);
- ray: ``fepr.sweep.run_sweep(..., backend="ray")`` into a fresh folder, starting and stopping a local Ray
  instance with the machine's cores (the time includes both).

Speedups are serial (default threads) time over each. Ray's overhead per task is reported two ways: from the sweep
itself, ``(makespan x slots - sum of the tasks' busy time) / runs`` (busy: from entering the run to returning, as
``status.json`` records it; makespan: first start to last finish), next to the same figure for the pool; and from
1000 empty Ray tasks (submitted at once; wall x CPUs / tasks) and 200 sequential round trips.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import fepr.sweep
from fepr.sweep.backends import available_cores


def sweep_spec(runs: int, steps: int) -> dict:
    side = int(round(runs**0.5))
    if side * side != runs:
        raise SystemExit(f"--runs must be a square (a side x side grid), got {runs}")
    return {
        "sweep": {"name": "throughput", "steps": steps, "frames_every": 20, "checkpoint_every": 100},
        "base": {
            "mesh": {"builtin": "box", "size": [1.0, 1.0, 1.0], "resolution": 6},
            "material": {"model": "stable_neo_hookean", "youngs_modulus": 1e4, "poisson_ratio": 0.3},
            "mass": {"density": 100.0},
            "integrator": {"name": "implicit_euler", "dt": 1 / 240},
        },
        "grid": {
            "material.youngs_modulus": [1e4 * (1.25**k) for k in range(side)],
            "initial.scale": [1.05 + 0.05 * k for k in range(side)],
        },
    }


def serial_fepr_run(spec: dict, work: Path, threads: int | None) -> float:
    """Every run's scene file through `fepr run`, one subprocess after another; returns the wall time, s."""
    plans = fepr.sweep.plan_runs(fepr.sweep.sweep_from_dict(spec))
    scenes = []
    for p in plans:
        text = p.scene_text("throughput")
        if threads is not None:
            text = text.replace("[run]\n", f"[run]\nthreads = {threads}\n")
        path = work / f"scene_{p.run_id}.toml"
        path.write_text(text)
        scenes.append(path)
    t0 = time.perf_counter()
    for path in scenes:
        subprocess.run(
            [sys.executable, "-m", "fepr", "run", str(path), "--out", str(work / f"out_{path.stem}"), "-q"],
            check=True,
            stdout=subprocess.DEVNULL,
        )
    return time.perf_counter() - t0


def sweep_timing(spec: dict, out: Path, backend: str) -> dict:
    t0 = time.perf_counter()
    df = fepr.sweep.run_sweep(spec, out, backend=backend, progress=False)
    wall = time.perf_counter() - t0
    assert (df["status"] == "complete").all(), df[["status", "error"]]
    info = df.attrs["sweep"]
    starts, ends, busy = [], [], []
    for run in df["path"]:
        log = json.loads((out / run / "status.json").read_text())["attempt_log"][-1]
        starts.append(log["started"])
        ends.append(log["finished"])
        busy.append(log["finished"] - log["started"])
    makespan = max(ends) - min(starts)
    slots = info["slots"]
    return {
        "wall_s": wall,
        "startup_s": info["startup_s"],
        "slots": slots,
        "makespan_s": makespan,
        "busy_s": sum(busy),
        "stepping_s": float(df["wall_s"].sum()),
        "overhead_per_task_s": (makespan * slots - sum(busy)) / len(df),
        "fixed_s": wall - makespan,
        "hashes": df["result_sha256"].tolist(),
    }


def ray_empty_tasks(cpus: int) -> dict:
    import ray

    ray.init(num_cpus=cpus, include_dashboard=False, log_to_driver=False)
    try:

        @ray.remote(num_cpus=1)
        def nothing():
            return None

        ray.get([nothing.remote() for _ in range(2 * cpus)])  # the workers started
        t0 = time.perf_counter()
        ray.get([nothing.remote() for _ in range(1000)])
        batch = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(200):
            ray.get(nothing.remote())
        roundtrip = (time.perf_counter() - t0) / 200
    finally:
        ray.shutdown()
    return {"per_task_cpu_s": batch * cpus / 1000, "roundtrip_s": roundtrip}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=16)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="keep the outputs in this folder")
    args = ap.parse_args()
    spec = sweep_spec(args.runs, args.steps)
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="fepr-throughput-"))
    work.mkdir(parents=True, exist_ok=True)
    cores = available_cores()
    print(f"{args.runs} runs of a 343-vertex box, backward Euler + FEPR, {args.steps} steps; {cores} cores", flush=True)
    res: dict = {"runs": args.runs, "steps": args.steps, "cores": cores}
    try:
        (work / "serial").mkdir(exist_ok=True)
        res["serial_s"] = serial_fepr_run(spec, work / "serial", None)
        print(f"serial fepr run (default threads): {res['serial_s']:.2f} s", flush=True)
        (work / "serial1").mkdir(exist_ok=True)
        res["serial_1thread_s"] = serial_fepr_run(spec, work / "serial1", 1)
        print(f"serial fepr run (threads = 1):     {res['serial_1thread_s']:.2f} s", flush=True)
        res["pool"] = sweep_timing(spec, work / "pool", "pool")
        print(f"local pool:                        {res['pool']['wall_s']:.2f} s", flush=True)
        try:
            import ray  # noqa: F401
        except ImportError:
            print("ray: not installed (pip install '.[sweep]'); skipped", flush=True)
        else:
            res["ray"] = sweep_timing(spec, work / "ray", "ray")
            print(f"ray (with start and stop):         {res['ray']['wall_s']:.2f} s", flush=True)
            assert res["ray"]["hashes"] == res["pool"]["hashes"], "Ray and the pool disagree"
            res["ray_empty"] = ray_empty_tasks(cores)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print()
    base = res["serial_s"]
    print(f"{'':34s} {'wall s':>8s} {'speedup':>8s} {'vs 1-thread serial':>19s}")
    print(f"{'serial fepr run (default threads)':34s} {base:8.2f} {1.0:8.2f} {res['serial_1thread_s'] / base:19.2f}")
    print(
        f"{'serial fepr run (threads = 1)':34s} {res['serial_1thread_s']:8.2f} {base / res['serial_1thread_s']:8.2f} "
        f"{1.0:19.2f}"
    )
    for name in ("pool", "ray"):
        if name in res:
            r = res[name]
            print(
                f"{name:34s} {r['wall_s']:8.2f} {base / r['wall_s']:8.2f} {res['serial_1thread_s'] / r['wall_s']:19.2f}"
            )
    print()
    for name in ("pool", "ray"):
        if name in res:
            r = res[name]
            print(
                f"{name}: {r['slots']} at a time; runs' stepping {r['stepping_s']:.2f} s, busy {r['busy_s']:.2f} s, "
                f"makespan {r['makespan_s']:.2f} s; overhead per task {1e3 * r['overhead_per_task_s']:.0f} ms; "
                f"fixed {r['fixed_s']:.2f} s (of which starting Ray {r['startup_s']:.2f} s)"
            )
    if "ray_empty" in res:
        e = res["ray_empty"]
        print(
            f"ray empty tasks: {1e3 * e['per_task_cpu_s']:.2f} ms of a CPU per task (1000 at once), "
            f"{1e3 * e['roundtrip_s']:.2f} ms per sequential round trip"
        )
    if args.json:
        for name in ("pool", "ray"):
            res.get(name, {}).pop("hashes", None)
        args.json.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
