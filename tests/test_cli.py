"""The ``fepr`` command: run, demo, --version, exit codes (in-process via ``fepr.cli.main``, once as a
subprocess)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import fepr
from fepr.cli import EXIT_INVALID, EXIT_OK, EXIT_RUNAWAY, main
from fepr.cli.demo import DEMO_SCENES

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
REQUIRED_COLUMNS = (
    "step,time,kinetic,elastic,gravitational,total,px,py,pz,lx,ly,lz,"
    "proj_iterations,proj_converged,proj_residual,base_ms,proj_ms"
).split(",")


def _cell(text: str) -> float:
    t = text.strip().lower()
    if t in ("true", "false"):
        return float(t == "true")
    try:
        return float(t)
    except ValueError:
        return np.nan


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    header = [h.strip() for h in rows[0]]
    data = np.array([[_cell(x) for x in r] for r in rows[1:]], dtype=np.float64).reshape(-1, len(header))
    return header, data


def col(header: list[str], data: np.ndarray, name: str) -> np.ndarray:
    return data[:, header.index(name)]


def write_scene(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


RUNAWAY_SCENE = """
[mesh]
builtin = "ell"
[material]
youngs_modulus = 1e7
poisson_ratio = 0.3
[mass]
node_mass = 1.0
[initial]
scale = 1.5
[integrator]
dt = 0.1
[projection]
enabled = false
[run]
steps = 2000
"""


# ---- run -----------------------------------------------------------------------------------------------


def test_run_writes_diagnostics_and_state(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["run", str(EXAMPLES / "seed_demo3_stretch.toml"), "--steps", "12", "--out", str(out)])
    assert code == EXIT_OK
    captured = capsys.readouterr()
    line = captured.out.splitlines()[-2]  # the summary, then the "wrote ..." line
    assert line.startswith("seed_demo3_stretch (FEPR on): 12 steps, energy error ") and " ms/step" in line
    for word in ("unresolved", "P drift", "L drift", "min J", "inverted", "unconverged", "substeps"):
        assert word in line, word
    header, data = read_csv(out / "diagnostics.csv")
    for c in REQUIRED_COLUMNS:
        assert c in header, c
    assert data.shape[0] == 12 + 1  # the initial state plus one row per step
    np.testing.assert_array_equal(col(header, data, "step"), np.arange(13))
    np.testing.assert_allclose(col(header, data, "time"), np.arange(13) / 30.0, rtol=1e-9, atol=1e-12)
    total = col(header, data, "total")
    books = total - total[0] - col(header, data, "budget_total")
    assert np.all(np.abs(books / total[0]) < 1e-9)  # FEPR on: energy kept to its books
    # the budget is the unresolved energy the quality guard booked (symplectic Euler is unstable at this dt)
    np.testing.assert_allclose(
        col(header, data, "budget_total"), np.cumsum(col(header, data, "work_unresolved")), rtol=1e-12, atol=1e-12
    )
    assert np.all(col(header, data, "proj_converged")[1:] == 1)
    state = np.load(out / "final_state.npz")
    assert len(state.files) > 0
    arrays = {k: state[k] for k in state.files}
    assert any(a.ndim == 2 and a.shape[1] == 3 for a in arrays.values())


def test_run_default_output_folder_and_scene_steps(tmp_path, monkeypatch):
    scene = write_scene(
        tmp_path / "tiny.toml",
        '[mesh]\nbuiltin = "box"\nresolution = 1\n[material]\nyoungs_modulus = 1e4\npoisson_ratio = 0.3\n'
        "[mass]\ndensity = 100.0\n[initial]\nscale = 1.1\n[integrator]\ndt = 0.01\n[run]\nsteps = 7\n",
    )
    monkeypatch.chdir(tmp_path)
    assert main(["run", "tiny.toml", "--quiet"]) == EXIT_OK
    out = tmp_path / "fepr-out" / "tiny"
    assert (out / "final_state.npz").is_file()
    _, data = read_csv(out / "diagnostics.csv")
    assert data.shape[0] == 7 + 1
    assert scene.is_file()


def test_run_no_projection(tmp_path, capsys):
    out = tmp_path / "plain"
    code = main(
        [
            "run",
            str(EXAMPLES / "spinning_l_gravity.toml"),
            "--steps",
            "5",
            "--out",
            str(out),
            "--no-projection",
        ]
    )
    assert code == EXIT_OK
    assert "FEPR off" in capsys.readouterr().out
    header, data = read_csv(out / "diagnostics.csv")
    assert data.shape[0] == 6
    iters = col(header, data, "proj_iterations")[1:]
    assert np.all((iters == 0) | np.isnan(iters))


def test_run_with_and_without_projection_differ(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    scene = str(EXAMPLES / "seed_demo3_stretch.toml")
    assert main(["run", scene, "--steps", "20", "--out", str(a), "--quiet"]) == EXIT_OK
    code = main(["run", scene, "--steps", "20", "--out", str(b), "--quiet", "--no-projection"])
    assert code in (EXIT_OK, EXIT_RUNAWAY)
    ha, da = read_csv(a / "diagnostics.csv")
    hb, db = read_csv(b / "diagnostics.csv")
    # the books: H against H0 + budget_total (with FEPR the budget is the energy booked as unresolved)
    ea = np.abs((col(ha, da, "total") - col(ha, da, "budget_total")) / col(ha, da, "total")[0] - 1).max()
    eb = np.abs((col(hb, db, "total") - col(hb, db, "budget_total")) / col(hb, db, "total")[0] - 1).max()
    assert ea < 1e-6 < eb


def test_runaway_writes_diagnostics_and_exits_3(tmp_path, capsys):
    scene = write_scene(tmp_path / "boom.toml", RUNAWAY_SCENE)
    out = tmp_path / "boom"
    code = main(["run", str(scene), "--out", str(out)])
    assert code == EXIT_RUNAWAY
    captured = capsys.readouterr()
    assert "runaway at step" in captured.err
    header, data = read_csv(out / "diagnostics.csv")
    assert 1 <= data.shape[0] < 2000 + 1
    finite_cols = ["step", "time", "px", "py", "pz"]  # energies of the last kept state may overflow
    assert np.all(np.isfinite(data[:, [header.index(c) for c in finite_cols]]))
    assert (out / "final_state.npz").is_file()
    # the step it reports is the first one that did not complete
    k = int(captured.err.split("runaway at step", 1)[1].split(":")[0])
    assert k == data.shape[0]  # rows 0..k-1 are the finite states


def test_invalid_scene_exits_2_naming_the_key(tmp_path, capsys):
    scene = write_scene(
        tmp_path / "bad.toml",
        '[mesh]\nbuiltin = "ell"\n[material]\nyoungs_modulu = 1e3\npoisson_ratio = 0.3\n[mass]\nnode_mass = 5.0\n',
    )
    assert main(["run", str(scene), "--out", str(tmp_path / "o")]) == EXIT_INVALID
    err = capsys.readouterr().err
    assert "bad.toml: [material] unknown key 'youngs_modulu'" in err
    assert not (tmp_path / "o").exists()


def test_missing_scene_exits_2(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.toml")]) == EXIT_INVALID
    assert "scene file not found" in capsys.readouterr().err


def test_bad_steps_argument_exits_2(capsys):
    assert main(["run", str(EXAMPLES / "wobbly_box.toml"), "--steps", "-3"]) == EXIT_INVALID
    assert main(["run", str(EXAMPLES / "wobbly_box.toml"), "--steps", "many"]) == EXIT_INVALID
    capsys.readouterr()


def test_zero_steps_writes_the_initial_row(tmp_path):
    out = tmp_path / "zero"
    assert main(["run", str(EXAMPLES / "wobbly_box.toml"), "--steps", "0", "--out", str(out), "-q"]) == 0
    header, data = read_csv(out / "diagnostics.csv")
    assert data.shape[0] == 1


# ---- demo ----------------------------------------------------------------------------------------------


def test_demo_prints_the_table(tmp_path, capsys):
    code = main(["demo", "--steps", "4", "--out", str(tmp_path / "demo")])
    assert code == EXIT_OK
    out = capsys.readouterr().out
    header = out.splitlines()[[ln.startswith("scene ") for ln in out.splitlines()].index(True)]
    for word in ("scene", "FEPR", "energy error", "unresolved", "P drift", "L drift", "min J", "inverted"):
        assert word in header
    for word in ("unconverged", "substeps", "iters", "ms/step"):
        assert word in header
    lines = out.splitlines()
    for name in DEMO_SCENES:
        rows = [ln for ln in lines if ln.startswith(name + " ")]
        assert len(rows) == 2, name  # on and off
        assert any(" on " in r for r in rows) and any(" off " in r for r in rows)
        assert (tmp_path / "demo" / name / "fepr" / "diagnostics.csv").is_file()
        assert (tmp_path / "demo" / name / "plain" / "final_state.npz").is_file()


def test_demo_quiet_prints_only_the_table(capsys):
    assert main(["demo", "--steps", "2", "--quiet"]) == EXIT_OK
    out = capsys.readouterr().out
    assert out.lstrip().startswith("scene")


def test_demo_reference_numbers_with_projection():
    """The full demo's projected runs conserve what they should (spec section 7, loosely)."""
    from fepr.cli.demo import run_demos

    results = {(r.scene, r.projection): r for r in run_demos()}
    seed = results[("seed_demo3_stretch", True)]
    assert not seed.runaway and seed.steps_completed == 300
    assert seed.max_energy_error < 1e-8
    assert seed.momentum_error < 1e-8 and seed.angular_momentum_error < 1e-8
    spin = results[("spinning_l_gravity", True)]
    assert not spin.runaway and spin.max_energy_error < 1e-8
    assert spin.momentum_error < 1e-8 and spin.angular_momentum_error < 1e-8
    drop = results[("dropped_box", True)]
    assert drop.max_energy_error < 1e-10 and drop.momentum_error < 1e-10
    assert results[("dropped_box", False)].max_energy_error > drop.max_energy_error
    wobble = results[("wobbly_box", True)]
    assert not wobble.runaway and wobble.max_energy_error < 1e-6
    assert wobble.momentum_error is None  # pinned: momenta are not conserved


# ---- version, help, python -m --------------------------------------------------------------------------


def test_version_and_help(capsys):
    assert main(["--version"]) == EXIT_OK
    out = capsys.readouterr().out
    assert out.startswith("fepr ")
    assert main(["--help"]) == EXIT_OK
    out = capsys.readouterr().out
    assert "run" in out and "demo" in out
    assert main(["run", "--help"]) == EXIT_OK
    assert "--no-projection" in capsys.readouterr().out


def test_no_command_prints_help_and_exits_2(capsys):
    assert main([]) == EXIT_INVALID
    assert "usage: fepr" in capsys.readouterr().err


def _env() -> dict:
    env = dict(os.environ)
    pkg_root = str(Path(fepr.__file__).resolve().parent.parent)
    env["PYTHONPATH"] = pkg_root + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_python_m_fepr_version():
    proc = subprocess.run(
        [sys.executable, "-m", "fepr", "--version"], capture_output=True, text=True, env=_env(), timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("fepr ")


def test_python_m_fepr_run_and_runaway_exit_code(tmp_path):
    scene = write_scene(tmp_path / "boom.toml", RUNAWAY_SCENE)
    proc = subprocess.run(
        [sys.executable, "-m", "fepr", "run", str(scene), "--out", str(tmp_path / "o"), "--quiet"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=60,
    )
    assert proc.returncode == 3, proc.stderr
    assert "runaway at step" in proc.stderr
    assert (tmp_path / "o" / "diagnostics.csv").is_file()


@pytest.mark.parametrize("example", sorted(p.name for p in EXAMPLES.glob("*.toml")))
def test_every_example_runs_from_the_command_line(example, tmp_path):
    assert main(["run", str(EXAMPLES / example), "--steps", "3", "--out", str(tmp_path), "-q"]) == EXIT_OK
    assert (tmp_path / "diagnostics.csv").is_file()
