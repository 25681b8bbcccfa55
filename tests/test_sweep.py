"""Sweeps without Ray (fepr.sweep): the sweep file's validation (errors naming the key), the plan (grid x samples,
stable ids, seeded draws), the runs on the serial executor and the local process pool (bit-identical to each other
and to `fepr run` on a run's scene.toml), resuming a killed run from its checkpoint, retries and failures recorded
in the index, runaways as results, a second invocation skipping finished runs, and the dataset export read with
NumPy alone. The Ray executor has its own file (tests/test_sweep_ray.py)."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pandas", reason="fepr sweep writes its index with pandas (the sweep extra)")
pytest.importorskip("pyarrow", reason="fepr sweep writes its index as Parquet with pyarrow (the sweep extra)")

import fepr  # noqa: E402
import fepr.sweep  # noqa: E402
from fepr.errors import ConfigError  # noqa: E402
from fepr.sweep import load_sweep, plan_runs, sweep_from_dict  # noqa: E402
from fepr.sweep.runner import RunTask, read_status, run_one  # noqa: E402
from fepr.sweep.sampling import parse_distribution, sample_value  # noqa: E402
from fepr.sweep.toml_text import scene_toml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
PY = sys.executable


def _base(resolution: int = 2, integrator: str = "symplectic_euler") -> dict:
    return {
        "mesh": {"builtin": "box", "size": [1.0, 1.0, 1.0], "resolution": resolution},
        "material": {"youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"density": 100.0},
        "initial": {"scale": 1.2},
        "integrator": {"name": integrator, "dt": 1 / 120},
    }


def small_sweep(**sweep) -> dict:
    """8 runs of a 27-vertex box, a few milliseconds each: 2 moduli x FEPR on/off x 2 random draws."""
    return {
        "sweep": {"name": "small", "steps": 60, "frames_every": 10, "seed": 5, "samples": 2, **sweep},
        "base": _base(),
        "grid": {"material": {"youngs_modulus": [1e3, 2e3]}, "projection.enabled": [True, False]},
        "random": {"initial": {"scale": {"uniform": [1.1, 1.3]}, "angular_velocity": {"uniform": [[-1] * 3, [1] * 3]}}},
    }


def _error(d: dict, match: str, base_dir=".", source="sweep.toml"):
    with pytest.raises(ConfigError, match=match) as info:
        plan_runs(sweep_from_dict(d, base_dir, source=source))
    return str(info.value)


# --- the sweep file ---------------------------------------------------------------------------------------------


def test_bad_sweep_files_name_the_key():
    ok = small_sweep()
    msg = _error({**ok, "grdi": {}}, r"unknown section \[grdi\]")
    assert msg.startswith("sweep.toml: ")
    _error({**ok, "sweep": {**ok["sweep"], "stpes": 3}}, r"\[sweep\] unknown key 'stpes' \(known: name, scene")
    _error({**ok, "sweep": {**ok["sweep"], "steps": "10"}}, r"\[sweep\] steps must be an integer, got '10'")
    _error({**ok, "sweep": {**ok["sweep"], "retries": -1}}, r"\[sweep\] retries must be >= 0")
    msg = _error({**ok, "grid": {"material": {"youngs_modulu": [1.0]}}}, r"\[grid\] parameter 'material.youngs_modulu'")
    assert "unknown key 'youngs_modulu' in material (known: model, youngs_modulus, poisson_ratio, j0)" in msg
    _error({**ok, "grid": {"materials.youngs_modulus": [1.0]}}, r"unknown section 'materials'")
    _error({**ok, "grid": {"run.threads": [1, 2]}}, r"threads are set by the sweep")
    _error({**ok, "grid": {"export.formats": [["vtu"]]}}, r"\[export\] cannot be varied")
    _error(
        {**ok, "grid": {"material.youngs_modulus": 1e3}}, r"\[grid\] material.youngs_modulus must be a non-empty list"
    )
    _error({**ok, "grid": {"material.youngs_modulus": []}}, r"must be a non-empty list")
    _error({**ok, "grid": {"world.obstacles.0.friction": [0.1]}}, r"world.obstacles is not a list in the base scene")
    _error(
        {**ok, "random": {"initial.scale": {"unifrom": [1, 2]}}},
        r"\[random\] initial.scale: unknown distribution 'unifrom' \(known: uniform, loguniform",
    )
    _error({**ok, "random": {"initial.scale": {"uniform": [2, 1]}}}, r"uniform must be \[lo, hi\] with lo < hi")
    _error({**ok, "random": {"initial.scale": {"loguniform": [0, 1]}}}, r"loguniform needs 0 < lo")
    _error({**ok, "random": {"initial.velocity": {"uniform": [[0, 0], [1, 1, 1]]}}}, r"lists of the same length")
    no_samples = {**ok, "sweep": {k: v for k, v in ok["sweep"].items() if k != "samples"}}
    _error(no_samples, r"\[sweep\] samples is required with \[random\]")
    _error({**ok, "grid": {"initial.scale": [1.1]}}, r"\[random\] parameter 'initial.scale' is varied in \[grid\] too")
    both = {**ok, "sweep": {**ok["sweep"], "scene": "x.toml"}}
    _error(both, r"give exactly one base scene")
    _error({"sweep": {"scene": "missing.toml"}}, r"\[sweep\] scene: file not found: .*missing.toml")
    _error({**ok, "dataset": {"split": [0.5, 0.5, 0.5]}}, r"\[dataset\] split must be \[train, validation, test\]")
    _error({**ok, "cases": [{"integrator": {"dtt": 0.1}}]}, r"\[\[cases\]\] #1 parameter 'integrator.dtt'")


def test_bad_values_name_the_run_and_the_scene_key():
    d = small_sweep()
    d["grid"]["material"]["poisson_ratio"] = [0.3, 0.6]
    msg = _error(d, r"the run with .*\"material.poisson_ratio\":0.6")
    assert "[material] poisson_ratio must be in (-1.0, 0.5), got 0.6" in msg
    d = small_sweep()
    d["grid"]["material"]["youngs_modulus"] = [1e3, 1e3]
    _error(d, r"two runs are the same simulation .* is a value listed twice")


def test_an_invalid_base_scene_is_an_error_naming_its_key(tmp_path):
    (tmp_path / "base.toml").write_text(
        '[mesh]\nbuiltin = "box"\n[material]\nyoungs_modulus = -1.0\npoisson_ratio = 0.3\n[mass]\ndensity = 100.0\n'
    )
    (tmp_path / "s.toml").write_text('[sweep]\nscene = "base.toml"\n[grid]\nintegrator.dt = [0.01, 0.02]\n')
    with pytest.raises(ConfigError, match=r"base.toml: \[material\] youngs_modulus must be > 0"):
        load_sweep(tmp_path / "s.toml")


def test_sweep_file_with_dotted_and_quoted_paths(tmp_path):
    (tmp_path / "s.toml").write_text(
        textwrap.dedent(
            """
            [sweep]
            scene = "../{}"
            steps = 20

            [grid]
            material.youngs_modulus = [1e3, 2e3]
            "projection.enabled" = [true, false]
            """.format(os.path.relpath(EXAMPLES / "seed_demo3_stretch.toml", tmp_path.parent))
        )
    )
    spec = load_sweep(tmp_path / "s.toml")
    assert spec.name == "s" and spec.base_source.endswith("seed_demo3_stretch.toml")
    runs = plan_runs(spec)
    assert [r.params for r in runs] == [
        {"material.youngs_modulus": a, "projection.enabled": b} for a in (1e3, 2e3) for b in (True, False)
    ]
    assert all(r.steps == 20 and r.scene["run"]["steps"] == 20 for r in runs)


# --- the plan ---------------------------------------------------------------------------------------------------


def test_plan_is_cases_by_grid_by_samples_with_stable_ids():
    d = small_sweep()
    d["cases"] = [
        {"integrator": {"dt": 1 / 120}, "run": {"steps": 60}},
        {"integrator": {"dt": 1 / 60}, "run": {"steps": 30}},
    ]
    runs = plan_runs(sweep_from_dict(d))
    assert len(runs) == 2 * 4 * 2
    assert [r.number for r in runs] == list(range(16))
    assert [r.sample for r in runs[:4]] == [0, 1, 0, 1]
    assert runs[8].params["integrator.dt"] == 1 / 60 and runs[8].steps == 30
    assert len({r.run_id for r in runs}) == 16 and all(len(r.run_id) == 16 for r in runs)
    # the same sweep planned again, in another process, gives the same ids
    again = plan_runs(sweep_from_dict(d))
    assert [r.run_id for r in again] == [r.run_id for r in runs]
    code = (
        "import json,sys; from fepr.sweep import plan_runs, sweep_from_dict;"
        "print(json.dumps([r.run_id for r in plan_runs(sweep_from_dict(json.loads(sys.argv[1])))]))"
    )
    other = subprocess.run([PY, "-c", code, json.dumps(d)], capture_output=True, text=True, check=True)
    assert json.loads(other.stdout) == [r.run_id for r in runs]


def test_run_id_follows_what_is_simulated_not_how():
    runs = plan_runs(sweep_from_dict(small_sweep()))
    # the sweep's name and threads do not change ids; a frame stride or one more step does
    assert [r.run_id for r in plan_runs(sweep_from_dict(small_sweep(name="other", cpus_per_run=2)))] == [
        r.run_id for r in runs
    ]
    assert plan_runs(sweep_from_dict(small_sweep(frames_every=5)))[0].run_id != runs[0].run_id
    assert plan_runs(sweep_from_dict(small_sweep(steps=61)))[0].run_id != runs[0].run_id


def test_random_draws_are_seeded_per_sample_and_parameter():
    dist = parse_distribution({"uniform": [1.0, 2.0]}, ConfigError)
    a = [sample_value(dist, 7, k, "initial.scale") for k in range(5)]
    assert a == [sample_value(dist, 7, k, "initial.scale") for k in range(5)]
    assert all(1.0 <= x < 2.0 for x in a) and len(set(a)) == 5
    assert a != [sample_value(dist, 8, k, "initial.scale") for k in range(5)]
    assert a[0] != sample_value(dist, 7, 0, "material.youngs_modulus")
    # a sample is the same draw at every grid point, and adding a random parameter leaves the others' draws
    runs = plan_runs(sweep_from_dict(small_sweep()))
    assert runs[0].params["initial.scale"] == runs[2].params["initial.scale"] != runs[1].params["initial.scale"]
    d = small_sweep()
    d["random"]["material"] = {"poisson_ratio": {"uniform": [0.2, 0.4]}}
    more = plan_runs(sweep_from_dict(d))
    assert [r.params["initial.scale"] for r in more] == [r.params["initial.scale"] for r in runs]
    lo = parse_distribution({"loguniform": [1e3, 1e5]}, ConfigError)
    assert all(1e3 <= sample_value(lo, 0, k, "x") < 1e5 for k in range(50))
    ints = parse_distribution({"integers": [2, 3]}, ConfigError)
    assert {sample_value(ints, 0, k, "x") for k in range(50)} == {2, 3}
    choice = parse_distribution({"choice": ["box", "ell"]}, ConfigError)
    assert {sample_value(choice, 0, k, "x") for k in range(50)} == {"box", "ell"}
    vec = parse_distribution({"uniform": [[0, -1, 5], [1, 0, 6]]}, ConfigError)
    v = sample_value(vec, 0, 0, "x")
    assert len(v) == 3 and 0 <= v[0] < 1 and -1 <= v[1] < 0 and 5 <= v[2] < 6


def test_whole_section_from_a_list_picks_the_mesh():
    d = small_sweep()
    d["grid"] = {"mesh": [{"builtin": "box", "resolution": 2}, {"builtin": "ell"}]}
    runs = plan_runs(sweep_from_dict(d))
    assert [r.scene["mesh"] for r in runs[::2]] == [{"builtin": "box", "resolution": 2}, {"builtin": "ell"}]


def test_scene_toml_round_trips():
    import tomllib

    scene = {
        "scene": {"name": 'a b "quoted"'},
        "mesh": {"builtin": "box", "size": [1.0, 2.0, 0.1], "resolution": 3},
        "material": {"youngs_modulus": 1e-5, "poisson_ratio": 0.1 + 0.2},
        "world": {
            "gravity": [0.0, 0.0, -9.81],
            "pin_below": {"axis": "z", "value": 1e-06},
            "obstacles": [{"type": "plane", "restitution": 0.5, "motion": {"translation": "sinusoidal"}}],
        },
        "projection": {"enabled": False, "tolerance": float("inf")},
        "bodies": [{"name": "x", "mesh": {"builtin": "ell"}}, {"name": "y", "initial": {"scale": 1.5}}],
    }
    assert tomllib.loads(scene_toml(scene, "a header\nover two lines")) == scene


# --- running ----------------------------------------------------------------------------------------------------


def test_serial_sweep_writes_runs_index_and_manifest(tmp_path):
    out = tmp_path / "s"
    df = fepr.sweep(small_sweep(), out, backend="serial", progress=False)  # the package is callable
    assert len(df) == 8 and (df["status"] == "complete").all() and (df["attempts"] == 1).all()
    assert list(df.columns[:7]) == [
        "run_id",
        "number",
        "sample",
        "material.youngs_modulus",
        "projection.enabled",
        "initial.scale",
        "initial.angular_velocity",
    ]
    for c in ("energy_error", "p_drift", "l_drift", "min_j", "inverted", "unconverged", "unresolved", "wall_s"):
        assert c in df.columns
    on = df[df["projection.enabled"]]
    assert (on["energy_error"] < 1e-8).all() and (on["unconverged"] == 0).all()
    assert (df["min_j"] > 0).all() and (df["frames"] == 7).all()
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["status"] == "complete" and [r["run_id"] for r in manifest["runs"]] == list(df["run_id"])
    assert manifest["counts"] == {"runs": 8, "skipped": 0, "complete": 8}
    import pandas as pd

    assert pd.read_parquet(out / "index.parquet")["result_sha256"].tolist() == df["result_sha256"].tolist()
    run = out / "runs" / df["run_id"][0]
    x = np.load(run / "positions.npy")
    assert x.shape == (7, 27, 3) and np.load(run / "velocities.npy").shape == (7, 27, 3)
    np.testing.assert_allclose(np.load(run / "frame_times.npy"), np.arange(7) * 10 / 120, rtol=1e-12, atol=1e-15)
    with np.load(run / "final_state.npz") as z:
        np.testing.assert_array_equal(z["positions"], x[-1])
    assert not (run / "checkpoint").exists()
    from fepr.scene import load_scene

    assert load_scene(run / "scene.toml").name == f"small-{df['run_id'][0]}"
    mesh = np.load(out / "meshes" / f"{df['mesh_id'][0]}.npz")
    assert mesh["rest_positions"].shape == (27, 3) and mesh["tets"].shape == (48, 4)
    # the second invocation skips every run (status and file hashes), and changes nothing
    again = fepr.sweep.run_sweep(small_sweep(), out, backend="serial", progress=False)
    assert again["skipped"].all() and again["result_sha256"].tolist() == df["result_sha256"].tolist()
    assert again.attrs["sweep"]["backend"].startswith("none")


def test_a_run_alone_with_fepr_run_gives_the_same_results(tmp_path):
    df = fepr.sweep.run_sweep(small_sweep(), tmp_path / "s", backend="serial", progress=False)
    run = tmp_path / "s" / df["path"][3]
    alone = tmp_path / "alone"
    subprocess.run([PY, "-m", "fepr", "run", str(run / "scene.toml"), "--out", str(alone), "-q"], check=True)
    with np.load(run / "final_state.npz") as a, np.load(alone / "final_state.npz") as b:
        for k in ("positions", "velocities", "time"):
            np.testing.assert_array_equal(a[k], b[k])
    ours = np.genfromtxt(run / "diagnostics.csv", delimiter=",", names=True)
    theirs = np.genfromtxt(alone / "diagnostics.csv", delimiter=",", names=True)
    assert ours.dtype.names == theirs.dtype.names and len(ours) == 61
    for c in ours.dtype.names:
        if not c.endswith("_ms"):  # wall times differ; everything else is bit-identical
            np.testing.assert_array_equal(ours[c], theirs[c], err_msg=c)


def test_pool_and_serial_results_are_bit_identical(tmp_path):
    serial = fepr.sweep.run_sweep(small_sweep(), tmp_path / "a", backend="serial", progress=False)
    pool = fepr.sweep.run_sweep(small_sweep(), tmp_path / "b", backend="pool", workers=2, progress=False)
    assert pool.attrs["sweep"]["backend"] == "pool" and (pool["status"] == "complete").all()
    assert pool["result_sha256"].tolist() == serial["result_sha256"].tolist()
    assert len(set(pool["result_sha256"])) == 8


def test_a_runaway_is_a_result_not_a_failure(tmp_path):
    d = {
        "sweep": {"scene": str(EXAMPLES / "seed_demo3_stretch.toml"), "steps": 100, "frames_every": 10},
        "grid": {"projection.enabled": [True, False]},
    }
    df = fepr.sweep.run_sweep(d, tmp_path / "r", backend="serial", progress=False)
    assert df["status"].tolist() == ["complete", "runaway"]
    bad = df.iloc[1]
    assert bad["attempts"] == 1 and bad["runaway_step"] == 15 and bad["frames"] == 2
    assert "runaway at step 15" in bad["problems"]
    assert np.load(tmp_path / "r" / bad["path"] / "positions.npy").shape == (2, 24, 3)


def test_cli_exit_status_for_runaways_and_strict(tmp_path):
    (tmp_path / "s.toml").write_text(
        f'[sweep]\nscene = "{EXAMPLES / "seed_demo3_stretch.toml"}"\nsteps = 30\n'
        "[grid]\nprojection.enabled = [true, false]\n"
    )
    cmd = [PY, "-m", "fepr", "sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o"), "--backend", "serial"]
    proc = subprocess.run(cmd + ["-q"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr  # a runaway is a result of its parameters
    assert "2 runs: 1 complete, 1 runaway" in proc.stdout
    proc = subprocess.run(cmd + ["-q", "--strict"], capture_output=True, text=True)
    assert proc.returncode == 3 and "--strict: 2 runs ran away or have problems" in proc.stderr
    assert "(2 already finished, skipped)" in proc.stdout


def test_failures_are_retried_then_recorded_without_stopping_the_sweep(tmp_path, monkeypatch):
    from fepr.sweep import runner

    real = runner._Run.go
    calls = {}

    def flaky(self):
        n = calls[self.task.run_id] = calls.get(self.task.run_id, 0) + 1
        if self.task.params["material.youngs_modulus"] == 2e3 and self.task.params["projection.enabled"]:
            raise OSError("disk on fire")  # fails every attempt
        if n == 1 and self.task.params["projection.enabled"]:
            raise OSError("a passing hiccup")  # fails once, then works
        return real(self)

    monkeypatch.setattr(runner._Run, "go", flaky)
    df = fepr.sweep.run_sweep(small_sweep(retries=2), tmp_path / "f", backend="serial", progress=False)
    failed = df[df["status"] == "failed"]
    assert len(failed) == 2 and (failed["attempts"] == 3).all()
    assert failed["error"].str.contains("OSError: disk on fire").all()
    assert failed["error"].str.contains("after 3 attempts").all()
    hiccup = df[(df["material.youngs_modulus"] == 1e3) & df["projection.enabled"]]
    assert (hiccup["status"] == "complete").all() and (hiccup["attempts"] == 2).all()
    assert (df[~df["projection.enabled"]]["attempts"] == 1).all()
    # the failed runs run again on the next invocation, the others are skipped
    monkeypatch.setattr(runner._Run, "go", real)
    again = fepr.sweep.run_sweep(small_sweep(retries=2), tmp_path / "f", backend="serial", progress=False)
    assert (again["status"] == "complete").all() and again["skipped"].sum() == 6


def test_an_invalid_mesh_fails_its_run_at_once(tmp_path):
    (tmp_path / "bad.node").write_text("garbage\n")
    (tmp_path / "bad.ele").write_text("garbage\n")
    d = small_sweep()
    d["grid"] = {"mesh": [{"builtin": "box", "resolution": 2}, {"path": "bad"}]}
    df = fepr.sweep.run_sweep(d, tmp_path / "m", backend="serial", progress=False, base_dir=tmp_path)
    bad = df[df["status"] == "failed"]
    assert len(bad) == 2 and (bad["attempts"] == 1).all()  # not retried: it would fail again
    assert bad["error"].str.contains("MeshError").all() and bad["error"].str.contains("bad.node").all()
    assert (df[df["status"] != "failed"]["status"] == "complete").all()


def _task(tmp_path: Path, steps: int = 400) -> RunTask:
    d = {
        "sweep": {"steps": steps, "frames_every": 20, "checkpoint_every": 25},
        "base": _base(resolution=5, integrator="implicit_euler"),
    }
    spec = sweep_from_dict(d)
    plan = plan_runs(spec)[0]
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "sweep.json").write_text("{}")
    return RunTask(
        run_id=plan.run_id,
        run_dir=str(tmp_path / "runs" / plan.run_id),
        sweep_dir=str(tmp_path),
        scene_text=plan.scene_text("k"),
        params=plan.params,
        steps=plan.steps,
        frames_every=20,
        frame_velocities=True,
        checkpoint_every=25,
        checkpoint_seconds=30.0,
        threads=1,
        fepr_version=fepr.__version__,
    )


def test_a_killed_run_resumes_from_its_checkpoint_bit_identically(tmp_path):
    ref = run_one(_task(tmp_path / "ref"))
    assert ref["status"] == "complete" and ref["attempt_log"][0]["resumed_from"] is None
    task = _task(tmp_path / "kill")
    code = "import pickle,sys; from fepr.sweep.runner import run_one; run_one(pickle.loads(bytes.fromhex(sys.argv[1])))"
    import pickle

    proc = subprocess.Popen([PY, "-c", code, pickle.dumps(task).hex()])
    folder = Path(task.run_dir)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        st = read_status(folder) or {}
        if (st.get("checkpoint") or {}).get("step", 0) >= 100:
            break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = read_status(folder)
    assert killed_at["status"] == "running" and 100 <= killed_at["checkpoint"]["step"] < 400
    resumed = run_one(task)
    assert resumed["status"] == "complete" and resumed["attempts"] == 2
    assert resumed["attempt_log"][-1]["resumed_from"] >= killed_at["checkpoint"]["step"]
    assert resumed["result_sha256"] == ref["result_sha256"]
    for name in ("positions.npy", "velocities.npy", "frame_times.npy"):
        np.testing.assert_array_equal(np.load(folder / name), np.load(Path(_task(tmp_path / "ref").run_dir) / name))


def test_a_worker_that_cannot_see_the_sweep_folder_says_so(tmp_path):
    task = _task(tmp_path)
    (tmp_path / "sweep.json").unlink()
    record = run_one(task)
    assert record["status"] == "failed" and "is not visible on" in record["error"]
    assert "shared" in record["error"] or "NFS" in record["error"]


# --- the dataset ------------------------------------------------------------------------------------------------


def test_dataset_layout_and_split(tmp_path):
    d = small_sweep(samples=5)
    d["dataset"] = {"split": [0.6, 0.2, 0.2], "seed": 3}
    df = fepr.sweep.run_sweep(d, tmp_path / "d", backend="serial", progress=False, dataset=True)
    ds = Path(df.attrs["sweep"]["dataset"])
    info = json.loads((ds / "dataset.json").read_text())
    assert info["trajectories"] == 20 and info["split"]["counts"] == {"train": 12, "validation": 4, "test": 4}
    rows = list(csv.DictReader(open(ds / "metadata.csv", encoding="utf-8")))
    assert [r["run_id"] for r in rows] == df["run_id"].tolist()
    for r in rows:
        x = np.load(ds / "positions" / f"{r['run_id']}.npy")
        assert x.shape == (int(r["frames"]), int(r["vertices"]), 3) == (7, 27, 3)
        assert np.load(ds / "velocities" / f"{r['run_id']}.npy").shape == x.shape
        assert np.load(ds / "masses" / f"{r['run_id']}.npy").shape == (27,)
        assert float(r["frame_dt_s"]) == pytest.approx(10 / 120)
        assert len(json.loads(r["initial.angular_velocity"])) == 3
    mesh = np.load(ds / "meshes" / f"{rows[0]['mesh_id']}.npz")
    assert mesh["tets"].max() == 26
    split = [r["split"] for r in rows]
    # the same seed gives the same split; another seed another one
    fepr.sweep.write_dataset(tmp_path / "d", split=(0.6, 0.2, 0.2), seed=3)
    assert [r["split"] for r in csv.DictReader(open(ds / "metadata.csv", encoding="utf-8"))] == split
    fepr.sweep.write_dataset(tmp_path / "d", split=(0.6, 0.2, 0.2), seed=4)
    assert [r["split"] for r in csv.DictReader(open(ds / "metadata.csv", encoding="utf-8"))] != split


def test_dataset_needs_frames(tmp_path):
    with pytest.raises(ConfigError, match="--dataset needs frames: set \\[sweep\\] frames_every"):
        fepr.sweep.run_sweep(small_sweep(frames_every=0), tmp_path / "x", backend="serial", dataset=True)


# --- the command and the examples -------------------------------------------------------------------------------


def test_cli_errors_name_the_file_and_key(tmp_path):
    (tmp_path / "s.toml").write_text('[sweep]\nscene = "nope.toml"\n')
    proc = subprocess.run(
        [PY, "-m", "fepr", "sweep", str(tmp_path / "s.toml"), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2 and "s.toml: [sweep] scene: file not found" in proc.stderr
    (tmp_path / "s.toml").write_text(
        f'[sweep]\nscene = "{EXAMPLES / "seed_demo3_stretch.toml"}"\n[grid]\nmaterial.youngs_modulus = 3\n'
    )
    proc = subprocess.run([PY, "-m", "fepr", "sweep", str(tmp_path / "s.toml")], capture_output=True, text=True)
    assert proc.returncode == 2 and "[grid] material.youngs_modulus must be a non-empty list" in proc.stderr


def test_cli_runs_a_sweep_on_the_pool(tmp_path):
    proc = subprocess.run(
        [
            PY,
            "-m",
            "fepr",
            "sweep",
            str(EXAMPLES / "sweeps" / "material_study.toml"),
            "--out",
            str(tmp_path / "o"),
            "--backend",
            "pool",
            "-q",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    assert "fepr sweep material_study: 12 runs:" in proc.stdout
    import pandas as pd

    df = pd.read_parquet(tmp_path / "o" / "index.parquet")
    assert len(df) == 12 and set(df["status"]) <= {"complete", "runaway"}
    assert (df[df["status"] == "complete"]["min_j"] > 0).all()
    off = df[~df["projection.enabled"] & (df["integrator.name"] == "symplectic_euler")]
    assert (off["status"] == "runaway").all()  # the seed demo's point: without FEPR this step runs away
    done = df[df["projection.enabled"] & (df["status"] == "complete")]
    assert len(done) >= 4 and (done["energy_error"] < 1e-8).all()  # FEPR keeps the energy books closed


def test_the_dataset_example_builds_and_loads_a_dataset(tmp_path):
    proc = subprocess.run(
        [PY, str(EXAMPLES / "sweeps" / "load_dataset.py"), "--build", str(tmp_path / "ds")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "train" in proc.stdout and "(frames, m, 3) = (41, 64, 3)" in proc.stdout
    # the loader itself needs NumPy only: it runs with fepr hidden
    code = (
        "import runpy, sys; sys.modules['fepr'] = None; script = sys.argv[1]; sys.argv = sys.argv[1:];"
        "runpy.run_path(script, run_name='__main__')"
    )
    script = str(EXAMPLES / "sweeps" / "load_dataset.py")
    proc = subprocess.run([PY, "-c", code, script, str(tmp_path / "ds" / "dataset")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "one-step pairs of" in proc.stdout and "inputs (40, 64, 3)" in proc.stdout


def test_a_list_in_random_says_where_lists_go():
    d = small_sweep()
    d["random"] = {"material": {"youngs_modulus": [1e3, 2e3]}}
    _error(d, r"\[random\] material.youngs_modulus must be a distribution such as \{ uniform = \[lo, hi\] \}")


def test_a_stopped_sweep_keeps_what_finished_and_continues(tmp_path, monkeypatch):
    from fepr.sweep import backends

    real, calls = backends.run_one, []

    def stop_at_the_third(task):
        calls.append(task.run_id)
        if len(calls) == 3:
            raise KeyboardInterrupt  # Ctrl-C
        return real(task)

    monkeypatch.setattr(backends, "run_one", stop_at_the_third)
    out = tmp_path / "s"
    with pytest.raises(KeyboardInterrupt):
        fepr.sweep.run_sweep(small_sweep(), out, backend="serial", progress=False)
    import pandas as pd

    df = pd.read_parquet(out / "index.parquet")
    assert df["status"].tolist() == ["complete"] * 2 + ["pending"] * 6
    assert json.loads((out / "sweep.json").read_text())["status"] == "interrupted"
    monkeypatch.setattr(backends, "run_one", real)
    again = fepr.sweep.run_sweep(small_sweep(), out, backend="serial", progress=False)
    assert (again["status"] == "complete").all() and again["skipped"].tolist() == [True] * 2 + [False] * 6


def test_options_that_do_not_go_together(tmp_path):
    with pytest.raises(ConfigError, match="--address joins a Ray cluster"):
        fepr.sweep.run_sweep(small_sweep(), tmp_path / "a", backend="pool", address="auto")
    with pytest.raises(ConfigError, match="backend must be one of auto, ray, pool, serial"):
        fepr.sweep.run_sweep(small_sweep(), tmp_path / "b", backend="dask")
