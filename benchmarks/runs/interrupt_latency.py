"""How long ``fepr run`` takes to stop after SIGINT or SIGTERM, keeping its work (issue target: 0.2 s).

Runs ``examples/spinning_l_gravity.toml`` (a small body, about 4 us per step) with 10^9 steps and exports
(vtu + glb every 200 steps), sends the signal after a few seconds, and measures the wall time from the signal to
the process's exit: the stop at the next step boundary, the diagnostics' last rows, the final state, the
checkpoint, the closed exports, the manifest with every file's hash, the summary, and the interpreter's exit.
Each run's folder is checked to hold valid files (``tests/test_run_outputs.py::_check_valid``).

    python benchmarks/runs/interrupt_latency.py [--repeats 5] [--after 3]
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "examples" / "spinning_l_gravity.toml"


def one(out: Path, after: float, sig: int) -> dict:
    cmd = [sys.executable, "-m", "fepr", "run", str(SCENE), "--steps", str(10**9), "--out", str(out), "-q",
           "--export", "vtu,glb", "--export-every", "200"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(after)
    t0 = time.perf_counter()
    proc.send_signal(sig)
    proc.communicate(timeout=120)
    latency = time.perf_counter() - t0
    manifest = json.loads((out / "run.json").read_text())
    return {"latency_s": latency, "code": proc.returncode, "steps": manifest["steps_completed"],
            "status": manifest["status"], "files": len(manifest["files"])}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--after", type=float, default=3.0, help="seconds of running before the signal")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT / "tests"))
    from test_run_outputs import _check_valid

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            for sig in (signal.SIGINT, signal.SIGTERM):
                out = Path(tmp) / f"run{k}_{sig.name}"
                r = one(out, args.after, sig)
                _check_valid(out, status="interrupted")
                rows.append(r)
                print(f"{sig.name}: exit {r['code']} {r['latency_s'] * 1e3:.0f} ms after the signal, "
                      f"{r['steps']} steps, {r['files']} files, valid", flush=True)  # fmt: skip
    lat = [r["latency_s"] for r in rows]
    print(f"signal to exit: median {statistics.median(lat) * 1e3:.0f} ms, max {max(lat) * 1e3:.0f} ms "
          f"over {len(lat)} runs")  # fmt: skip


if __name__ == "__main__":
    main()
