"""Sweeps on a real local Ray instance (the sweep extra; CI installs it): `fepr sweep` starting and stopping its own
Ray, a 12-run sweep completing, a second invocation skipping all 12, Ray and the local pool bit-identical, and a
worker process killed with SIGKILL mid-sweep (Ray retries its run, which continues from its checkpoint, with results
identical to the undisturbed sweep); the same kill on the local pool.

The module's Ray instance has 2 CPUs, as CI's machines; the whole file takes about half a minute there."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ray = pytest.importorskip("ray", reason="Ray is not installed (pip install '.[sweep]' brings it; CI installs it)")
pytest.importorskip("pandas", reason="fepr sweep writes its index with pandas (the sweep extra)")
pytest.importorskip("pyarrow", reason="fepr sweep writes its index as Parquet with pyarrow (the sweep extra)")

import fepr.sweep  # noqa: E402

PY = sys.executable


def twelve_runs() -> dict:
    """12 runs of about 0.3 s each (a 216-vertex box, backward Euler): 3 moduli x FEPR on/off x 2 random stretches,
    with a checkpoint every 25 steps, so that a run killed in the middle continues from one."""
    return {
        "sweep": {
            "name": "ray12",
            "steps": 150,
            "frames_every": 15,
            "seed": 11,
            "samples": 2,
            "checkpoint_every": 25,
            "retries": 2,
        },
        "base": {
            "mesh": {"builtin": "box", "size": [1.0, 1.0, 1.0], "resolution": 5},
            "material": {"model": "stable_neo_hookean", "youngs_modulus": 1e4, "poisson_ratio": 0.3},
            "mass": {"density": 100.0},
            "integrator": {"name": "implicit_euler", "dt": 1 / 240},
        },
        "grid": {"material.youngs_modulus": [5e3, 1e4, 2e4], "projection.enabled": [True, False]},
        "random": {"initial.scale": {"uniform": [1.05, 1.2]}},
    }


def test_fepr_sweep_starts_and_stops_its_own_ray(tmp_path):
    # Before the module's Ray instance exists: the command starts a local one with the machine's cores and stops it.
    spec = tmp_path / "s.toml"
    spec.write_text(
        '[sweep]\nsteps = 20\n[base.mesh]\nbuiltin = "ell"\n[base.material]\nyoungs_modulus = 1e3\n'
        "poisson_ratio = 0.3\n[base.mass]\nnode_mass = 5.0\n[grid]\nmaterial.youngs_modulus = [1e3, 2e3]\n"
    )
    proc = subprocess.run(
        [PY, "-m", "fepr", "sweep", str(spec), "--out", str(tmp_path / "o"), "-q"], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    assert "2 runs: 2 complete" in proc.stdout and "on ray" in proc.stdout
    manifest = json.loads((tmp_path / "o" / "sweep.json").read_text())
    assert manifest["backend"] == "ray" and manifest["slots"] >= 1
    # stopped after: no Ray instance is left for this machine to join
    code = "import ray, sys\ntry:\n    ray.init(address='auto')\nexcept ConnectionError:\n    sys.exit(7)\nsys.exit(0)"
    assert subprocess.run([PY, "-c", code], capture_output=True, text=True).returncode == 7


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def reference(local_ray, tmp_path_factory):
    """The undisturbed 12-run sweep on Ray."""
    out = tmp_path_factory.mktemp("ray") / "reference"
    df = fepr.sweep.run_sweep(twelve_runs(), out, progress=False)
    return out, df


def test_a_12_run_sweep_completes_on_ray(reference):
    out, df = reference
    assert df.attrs["sweep"]["backend"] == "ray" and df.attrs["sweep"]["slots"] == 2
    assert len(df) == 12 and (df["status"] == "complete").all() and (df["attempts"] == 1).all()
    assert len(set(df["result_sha256"])) == 12 and (df["frames"] == 11).all()
    on = df[df["projection.enabled"]]
    assert (on["energy_error"] < 1e-8).all() and (on["unconverged"] == 0).all()
    for run in df["path"]:
        status = json.loads((out / run / "status.json").read_text())
        assert status["status"] == "complete" and status["threads"] == 1  # the one CPU Ray gave the task
    # Ray's worker processes ran the runs, not this one
    assert os.getpid() not in {json.loads((out / r / "status.json").read_text())["pid"] for r in df["path"]}


def test_a_second_invocation_skips_all_12(reference):
    out, df = reference
    t0 = time.perf_counter()
    again = fepr.sweep.run_sweep(twelve_runs(), out, progress=False)
    assert again["skipped"].all() and (again["status"] == "complete").all()
    assert again["result_sha256"].tolist() == df["result_sha256"].tolist()
    assert again.attrs["sweep"]["counts"] == {"runs": 12, "skipped": 12, "complete": 12}
    assert time.perf_counter() - t0 < 5.0


def test_ray_and_local_pool_are_bit_identical(reference, tmp_path):
    _, df = reference
    pool = fepr.sweep.run_sweep(twelve_runs(), tmp_path / "pool", backend="pool", workers=2, progress=False)
    assert pool.attrs["sweep"]["backend"] == "pool"
    assert pool["run_id"].tolist() == df["run_id"].tolist()
    assert pool["result_sha256"].tolist() == df["result_sha256"].tolist()


def _kill_a_running_run(out: Path, done: threading.Event, killed: list) -> None:
    """SIGKILL the process of the first run seen running past its second checkpoint, with steps left to go."""
    me = os.getpid()
    while not done.is_set():
        for path in out.glob("runs/*/status.json"):
            try:
                st = json.loads(path.read_text())
            except (OSError, ValueError):
                continue  # being replaced
            step = (st.get("checkpoint") or {}).get("step", 0)
            if st.get("status") == "running" and 50 <= step <= 100 and st.get("pid") not in (None, me):
                os.kill(st["pid"], signal.SIGKILL)
                killed.append((st["run_id"], st["pid"], step))
                return
        time.sleep(0.002)


def _sweep_with_a_kill(out: Path, **kw):
    done, killed = threading.Event(), []
    killer = threading.Thread(target=_kill_a_running_run, args=(out, done, killed), daemon=True)
    killer.start()
    try:
        df = fepr.sweep.run_sweep(twelve_runs(), out, progress=False, **kw)
    finally:
        done.set()
        killer.join()
    return df, killed


def test_killing_a_ray_worker_mid_sweep_still_completes_it_identically(reference, tmp_path):
    _, ref = reference
    df, killed = _sweep_with_a_kill(tmp_path / "killed")
    assert killed, "no run was seen running to kill"
    assert (df["status"] == "complete").all()
    assert df["result_sha256"].tolist() == ref["result_sha256"].tolist()
    retried = df[df["attempts"] > 1]
    assert len(retried) >= 1 and retried["resumed"].all()  # Ray ran it again; it went on from its checkpoint


def test_killing_a_pool_worker_mid_sweep_still_completes_it_identically(reference, tmp_path):
    _, ref = reference
    df, killed = _sweep_with_a_kill(tmp_path / "killed", backend="pool", workers=2)
    assert killed, "no run was seen running to kill"
    assert (df["status"] == "complete").all()
    assert df["result_sha256"].tolist() == ref["result_sha256"].tolist()
    run_id = killed[0][0]
    row = df[df["run_id"] == run_id].iloc[0]
    assert row["attempts"] >= 2 and row["resumed"]


def test_an_address_where_nothing_answers_is_an_error_at_once(tmp_path):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # free once closed
    t0 = time.perf_counter()
    proc = subprocess.run(
        [
            PY,
            "-m",
            "fepr",
            "sweep",
            "-q",
            "--out",
            str(tmp_path / "o"),
            "--address",
            f"127.0.0.1:{port}",
            str(Path(__file__).resolve().parent.parent / "examples" / "sweeps" / "material_study.toml"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and f"--address 127.0.0.1:{port}: nothing answers" in proc.stderr
    assert time.perf_counter() - t0 < 20
