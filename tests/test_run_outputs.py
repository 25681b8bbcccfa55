"""``fepr run`` keeps its work and never leaves half-written files: the output folder is checked before the first
step, an earlier run is not overwritten by accident, SIGINT and SIGTERM stop at a step boundary and keep valid
diagnostics, state, exports and a checkpoint, a killed run resumes bit for bit, and run.json lists every file."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fepr.cli import main
from fepr.cli.commands import EXIT_INVALID, EXIT_OK

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
HANGING = EXAMPLES / "hanging_bar.toml"
SPINNING = EXAMPLES / "spinning_l_gravity.toml"
#: History columns that are wall times (they differ from run to run).
TIMING = {"base_ms", "proj_ms"}


def _table(path: Path):
    """A diagnostics CSV as (columns, rows) with the timing columns dropped."""
    data = np.genfromtxt(path, delimiter=",", names=True)
    cols = [c for c in data.dtype.names if c not in TIMING]
    return cols, np.stack([data[c] for c in cols], axis=1)


def _fepr(*args, **kw) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "fepr", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def _wait_for(path: Path, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while not path.exists():
        if time.monotonic() - t0 > timeout:
            raise TimeoutError(path)
        time.sleep(0.05)


def _check_valid(out: Path, *, status: str) -> dict:
    """Every file of a run folder is complete: the manifest's hashes match, the diagnostics parse with one row
    per step, the state loads, every exported frame reads back and the collection lists existing files."""
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["status"] == status
    listed = {f["path"]: f for f in manifest["files"]}
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.name != "run.json"}
    assert set(listed) == on_disk, "run.json lists exactly the files in the folder (no temporary files left)"
    for rel, f in listed.items():
        data = (out / rel).read_bytes()
        assert len(data) == f["size"] and hashlib.sha256(data).hexdigest() == f["sha256"], rel
    steps = manifest["steps_completed"] + manifest["start_step"]
    cols, rows = _table(out / "diagnostics.csv")
    assert rows.shape[0] == steps + 1 and np.array_equal(rows[:, cols.index("step")], np.arange(steps + 1))
    with np.load(out / "final_state.npz") as z:
        assert np.all(np.isfinite(z["positions"]))
    export = out / "export"
    if export.is_dir():
        import fepr
        from fepr.export import read_pvd

        for _t, vtu in read_pvd(next(export.glob("*.pvd"))):
            assert vtu.is_file()
            fepr.load_mesh(vtu)
        for glb in export.glob("*.glb"):
            pygltflib = pytest.importorskip("pygltflib")
            assert pygltflib.GLTF2().load_binary(str(glb)).meshes
    return manifest


def test_an_output_folder_that_cannot_be_written_fails_before_the_first_step(tmp_path, capsys):
    if os.geteuid() == 0:
        # root writes anywhere: a file where the folder should be stands in for a read-only folder
        out = tmp_path / "file"
        out.write_text("not a folder")
    else:
        out = tmp_path / "ro"
        out.mkdir()
        out.chmod(0o500)
    t0 = time.perf_counter()
    code = main(["run", str(SPINNING), "--steps", "20000000", "--out", str(out / "run"), "-q"])
    assert code != EXIT_OK and time.perf_counter() - t0 < 30
    assert "cannot" in capsys.readouterr().err


def test_an_earlier_run_is_refused_and_overwrite_removes_only_its_files(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["run", str(HANGING), "--steps", "20", "--out", str(out), "--export", "vtu", "-q"]) == EXIT_OK
    mine = out / "notes.txt"
    mine.write_text("the user's own file")
    assert main(["run", str(HANGING), "--steps", "5", "--out", str(out), "-q"]) == EXIT_INVALID
    err = capsys.readouterr().err
    assert "earlier run" in err and "--overwrite" in err and "diagnostics.csv" in err
    args = ["run", str(HANGING), "--steps", "5", "--out", str(out), "--export", "vtu", "-q", "--overwrite"]
    assert main(args) == EXIT_OK
    assert len(list((out / "export" / "vtu").glob("*.vtu"))) == 6, "no stale frames of the earlier run"
    assert mine.read_text() == "the user's own file", "files the earlier run did not write stay"
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["status"] == "complete" and manifest["settings"]["steps"] == 5
    assert manifest["scene"]["name"] == "hanging_bar" and manifest["fepr"]


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_stops_a_long_run_and_keeps_valid_files(tmp_path, sig, code):
    out = tmp_path / "o"
    proc = _fepr("run", SPINNING, "--steps", 10**9, "--out", out, "--export", "vtu,glb", "--export-every", 200, "-q")
    _wait_for(out / "export" / "vtu" / "spinning_l_gravity_00002.vtu")
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == code, stderr
    assert f"{signal.Signals(sig).name}: stopped at step" in stderr and "--resume" in stderr
    manifest = _check_valid(out, status="interrupted")
    assert manifest["interrupted_by"] == signal.Signals(sig).name
    assert manifest["checkpoint"]["step"] == manifest["steps_completed"]


def _run_to_end(tmp_path, scene, steps, extra=()) -> Path:
    out = tmp_path / "whole"
    assert main(["run", str(scene), "--steps", str(steps), "--out", str(out), "-q", *extra]) == EXIT_OK
    return out


@pytest.mark.parametrize(
    "scene, steps, extra",
    [
        (HANGING, 3000, ("--export", "vtu,glb", "--export-every", "50")),
        (EXAMPLES / "collide.toml", 150, ()),
    ],
    ids=["hanging_bar", "collide"],
)
def test_a_killed_run_resumes_bit_for_bit(tmp_path, scene, steps, extra):
    whole = _run_to_end(tmp_path, scene, steps, extra)
    out = tmp_path / "killed"
    proc = _fepr("run", scene, "--steps", steps, "--out", out, "--checkpoint-every", 7, "-q", *extra)
    # kill -9 once a few checkpoints are in (but before the end)
    t0 = time.monotonic()
    while True:
        try:
            ck = json.loads((out / "run.json").read_text()).get("checkpoint")
        except (OSError, ValueError):
            ck = None
        if ck and ck["step"] >= 3 * 7 or proc.poll() is not None or time.monotonic() - t0 > 60:
            break
        time.sleep(0.01)
    proc.kill()
    proc.communicate(timeout=60)
    manifest = json.loads((out / "run.json").read_text())
    if manifest["status"] == "complete":
        pytest.skip("the run finished before it could be killed")
    assert manifest["status"] == "running"
    assert main(["run", "--resume", str(out), "-q"]) == EXIT_OK
    _check_valid(out, status="complete")
    for name in [p.name for p in whole.glob("diagnostics*.csv")]:
        cols_a, a = _table(whole / name)
        cols_b, b = _table(out / name)
        assert cols_a == cols_b and np.array_equal(a, b, equal_nan=True), name
    with np.load(whole / "final_state.npz") as za, np.load(out / "final_state.npz") as zb:
        for k in za.files:
            assert np.array_equal(za[k], zb[k]), k
    if (whole / "export").is_dir():
        a = (whole / "export" / "frames.csv").read_text()
        assert a == (out / "export" / "frames.csv").read_text()
        glb_a = next((whole / "export").glob("*.glb")).read_bytes()
        assert glb_a == next((out / "export").glob("*.glb")).read_bytes(), "the animation holds the whole run"


def test_resume_needs_a_resumable_run(tmp_path, capsys):
    out = _run_to_end(tmp_path, HANGING, 10)
    assert main(["run", "--resume", str(out), "-q"]) == EXIT_INVALID
    assert "complete; nothing to resume" in capsys.readouterr().err
    assert main(["run", "--resume", str(tmp_path / "nothing"), "-q"]) == EXIT_INVALID
    assert "run.json" in capsys.readouterr().err
    assert main(["run", str(HANGING), "--resume", str(out), "--overwrite", "-q"]) == EXIT_INVALID
