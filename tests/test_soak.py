"""Soak and fault tests (marker ``soak``, run by CI with the rest; deselect with ``-m "not soak"``): a million
steps in bounded memory, ``kill -9`` at random points of a checkpointed run followed by ``--resume`` ending
bit-identical to the uninterrupted run, and SIGINT at random points leaving only valid files."""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from fepr.cli import main
from fepr.cli.commands import EXIT_OK
from test_run_outputs import EXAMPLES, _check_valid, _fepr, _table

pytestmark = pytest.mark.soak


def test_a_million_steps_run_in_bounded_memory():
    """Memory after 1e6 steps within 2x of memory after 1e3 (the history spills to disk past its limit and
    the core keeps one row); the last row is read in O(1) (the ratio of its read times is printed)."""
    script = textwrap.dedent(
        """
        import time, numpy as np, fepr

        def rss_mb():
            with open("/proc/self/status") as fh:
                for line in fh:
                    if line.startswith("VmRSS:"):
                        return int(line.split()[1]) / 1024.0

        def last_read_s(sim):
            t0 = time.perf_counter()
            for _ in range(1000):
                sim.last
            return (time.perf_counter() - t0) / 1000

        mat = fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3)
        sim = fepr.Simulation(fepr.meshes.ell(), material=mat, node_mass=1.0, dt=0.01)
        x = sim.positions
        sim.positions = 1.2 * x  # released stretched: it vibrates (and stays near the origin, unlike a fall)
        sim.step(1000)
        a, ta = rss_mb(), last_read_s(sim)
        sim.step(10**6 - 1000)
        b, tb = rss_mb(), last_read_s(sim)
        h = sim.history
        assert len(h) == 10**6 + 1 and h["step"][-1] == 10**6 and np.all(np.diff(h["step"]) == 1)
        print(a, b, ta, tb, sim._history.spilled_rows)
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr
    a, b, ta, tb, spilled = map(float, out.stdout.split())
    print(f"RSS after 1e3 steps {a:.1f} MB, after 1e6 {b:.1f} MB ({b / a:.2f}x); last-row read {ta * 1e6:.2f} us "
          f"at 1e3 rows, {tb * 1e6:.2f} us at 1e6 ({tb / ta:.2f}x); {spilled:.0f} rows spilled")
    assert b < 2.0 * a
    assert spilled > 0


def _manifest(out: Path):
    try:
        return json.loads((out / "run.json").read_text())
    except (OSError, ValueError):
        return None


def test_kill_9_at_random_points_then_resume_ends_bit_identical(tmp_path):
    scene, steps = EXAMPLES / "hanging_bar.toml", 8000
    extra = ("--export", "vtu,obj,glb", "--export-every", "100")
    whole = tmp_path / "whole"
    assert main(["run", str(scene), "--steps", str(steps), "--out", str(whole), "-q", *extra]) == EXIT_OK
    out = tmp_path / "killed"
    rng = random.Random(35)
    kills = 0
    args = ["--checkpoint-every", "53", "-q", *extra]
    proc = _fepr("run", scene, "--steps", steps, "--out", out, *args)
    while True:
        time.sleep(rng.uniform(0.05, 0.6))
        if proc.poll() is None:
            proc.kill()
            kills += 1
        proc.communicate(timeout=60)
        m = _manifest(out)
        if m is not None and m["status"] == "complete":
            break
        if m is None or not m.get("checkpoint"):
            # killed before its first checkpoint: start again
            proc = _fepr("run", scene, "--steps", steps, "--out", out, "--overwrite", *args)
            continue
        proc = _fepr("run", "--resume", out, "-q")
    print(f"{kills} kills")
    assert kills >= 2
    _check_valid(out, status="complete")
    cols_a, a = _table(whole / "diagnostics.csv")
    cols_b, b = _table(out / "diagnostics.csv")
    assert cols_a == cols_b and np.array_equal(a, b, equal_nan=True)
    with np.load(whole / "final_state.npz") as za, np.load(out / "final_state.npz") as zb:
        assert all(np.array_equal(za[k], zb[k]) for k in za.files)
    ex_a, ex_b = whole / "export", out / "export"
    assert (ex_a / "frames.csv").read_text() == (ex_b / "frames.csv").read_text()
    for p in sorted(ex_a.rglob("*")):
        if p.is_file() and p.suffix in (".glb", ".obj"):
            assert p.read_bytes() == (ex_b / p.relative_to(ex_a)).read_bytes(), p.name


def test_sigint_at_random_points_leaves_only_valid_files(tmp_path):
    rng = random.Random(7)
    scene = EXAMPLES / "spinning_l_gravity.toml"
    for k in range(3):
        out = tmp_path / f"o{k}"
        proc = _fepr("run", scene, "--steps", 10**9, "--out", out, "--export", "vtu,ply,glb", "--export-every", 300,
                     "-q")  # fmt: skip
        time.sleep(rng.uniform(1.0, 3.0))
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 130, stderr
        _check_valid(out, status="interrupted")
