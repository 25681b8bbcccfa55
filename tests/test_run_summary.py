"""One summary everywhere (``fepr.report.metrics``): its numbers on a hand-computed history, the same numbers through
``RunResult``, ``fepr run``, ``fepr compare`` (``summary.json``) and the demo's tables, momentum drift against the
targets with an obstacle, ``--strict`` and the end-of-run warning."""

from __future__ import annotations

import copy
import csv
import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from fepr.cli import EXIT_OK, EXIT_STRICT, main
from fepr.cli.demo import DEMO_SCENES, format_row, gallery_rows
from fepr.report.metrics import (
    FIELDS,
    RunProblemWarning,
    compute_metrics,
    energy_scale,
    length_scale,
    simulation_metrics,
    system_history,
)
from fepr.scene import load_scene, run_scene, scene_from_dict

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
DROP = EXAMPLES / "drop_box.toml"
SEED = EXAMPLES / "seed_demo3_stretch.toml"
DROP_STEPS = 300  # the box lands at about step 225 (t = 0.45 s) and is in contact after that


def read_diagnostics(path: Path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    data = np.array([[float(v) for v in r] for r in rows[1:]])
    return {c: data[:, i] for i, c in enumerate(rows[0])}


def vec(h, *names) -> np.ndarray:
    return np.stack([np.asarray(h[n]) for n in names], axis=1)


def without_timing(line: str) -> str:
    return re.sub(r", [0-9.]+ ms/step", "", line)


# ---- (a) the module on a synthetic history ----------------------------------------------------------------

M, G, R = 2.0, [0.0, 0.0, -10.0], 0.5


def synthetic(targets: bool = True) -> dict:
    h = {
        "step": [0, 1, 2],
        "time": [0.0, 0.1, 0.2],
        "kinetic": [2.0, 1.0, 1.5],
        "elastic": [1.0, 1.5, 0.5],
        "gravitational": [0.0, 0.0, 0.0],
        "total": [3.0, 2.5, 2.0],
        "budget_total": [0.0, -0.4, -1.0],
        "work_unresolved": [0.0, -0.3, -0.3],
        "px": [1.0, 1.0, 1.1],
        "py": [0.0, 0.0, 0.0],
        "pz": [0.0, -2.0, -4.0],
        "lx": [0.0, 0.0, 0.0],
        "ly": [0.0, 0.0, 0.0],
        "lz": [2.0, 2.0, 2.5],
        "min_j": [1.0, 0.5, -0.1],
        "inverted": [0, 0, 2],
        "proj_converged": [0, 1, 0],
        "proj_iterations": [0, 3, 5],
        "base_substeps": [0, 2, 3],
        "base_ms": [0.0, 1.0, 2.0],
        "proj_ms": [0.0, 0.5, 0.5],
        "base_energy_error": [0.0, 0.5, 1.5],
    }
    if targets:
        h.update(
            px_target=[1.0, 1.0, 1.0],
            py_target=[0.0, 0.0, 0.0],
            pz_target=[0.0, -2.0, -4.3],
            lx_target=[0.0, 0.0, 0.0],
            ly_target=[0.0, 0.0, 0.0],
            lz_target=[2.0, 2.1, 2.1],
        )
    return {k: np.asarray(v, dtype=float) for k, v in h.items()}


def metrics_of(h, **kw):
    args = dict(total_mass=M, gravity=G, length_scale=R, pinned=False, projection=True)
    args.update(kw)
    return compute_metrics(h, **args)


def test_module_numbers_equal_the_hand_computed_ones():
    m = metrics_of(synthetic())
    # books: H_k - (H_0 + budget_k) = [0, 2.5 - 2.6, 2.0 - 2.0], over |H0| = 3
    assert m.energy_error == pytest.approx(0.1 / 3, rel=1e-12)
    assert m.final_energy_error == pytest.approx(0.0, abs=1e-15)
    assert m.unresolved == pytest.approx(0.6 / 3, rel=1e-12)
    # p_scale = max(|P0| = 1, max |P_target| = |(1, 0, -4.3)|, sqrt(2 M (K0 + |E_el0|)) = sqrt(12))
    p_scale = math.sqrt(1.0 + 4.3**2)
    assert m.p_drift == pytest.approx(math.sqrt(0.1**2 + 0.3**2) / p_scale, rel=1e-12)
    assert m.l_drift == pytest.approx(0.4 / max(2.0, R * p_scale), rel=1e-12)
    assert m.momentum_reference == "targets"
    assert (m.min_j, m.inverted, m.final_inverted) == (-0.1, 2, 2)
    assert (m.unconverged, m.mean_iterations, m.max_iterations) == (1, 4.0, 5)
    assert (m.steps, m.substeps, m.ms_per_step, m.base_unstable_step) == (2, 5, 2.0, 2)
    assert m.final_h_ratio == pytest.approx(2.0 / 3.0) and m.max_dh == pytest.approx(1.0 / 3.0)
    unresolved = "unresolved energy 2.00e-01 (above 0.001)"
    assert m.problems() == ["2 inverted tets at the end", "1 unconverged projection", unresolved]
    assert m.notes() == ["base step unstable from step 2 (the projection kept it bounded)"]
    line = m.summary_line("toy")
    assert line.startswith("toy: 2 steps, energy error 3.33e-02 (end 0.00e+00), unresolved 2.00e-01, P drift ")
    assert "min J -0.1, inverted 2, unconverged 1, iters 4.00, substeps 5, 2.000 ms/step" in line
    assert line.endswith(f"; problems: 2 inverted tets at the end, 1 unconverged projection, {unresolved}")
    text = m.warning_text("toy")
    assert "2 inverted tets" in text and "1 of 2 projections unconverged" in text and "2.00e-01" in text
    below = synthetic()
    below["work_unresolved"] = np.array([0.0, -0.002, -0.001])  # 1e-3 of H0 = 3: at the limit, not above it
    assert metrics_of(below).unresolved == pytest.approx(1e-3) and not metrics_of(below).unresolved_problem


def test_module_fallbacks_old_csv_pins_no_projection_and_zero_energy():
    old = metrics_of(synthetic(targets=False))  # P_target = P0 + M g t, L_target = L0
    p_scale = math.sqrt(1.0 + 4.0**2)
    assert old.momentum_reference == "gravity"
    assert old.p_drift == pytest.approx(0.1 / p_scale, rel=1e-12)
    assert old.l_drift == pytest.approx(0.5 / max(2.0, R * p_scale), rel=1e-12)
    pinned = metrics_of(synthetic(), pinned=True)
    assert pinned.p_drift is None and pinned.l_drift is None and pinned.momentum_reference == "none"
    assert "P drift n/a (pinned), L drift n/a" in pinned.summary_line()
    off = synthetic()
    off["work_unresolved"] = np.zeros(3)
    off = metrics_of(off, projection=False)
    assert off.unconverged is None and off.mean_iterations is None and "projection off" in off.summary_line()
    assert off.problems() == ["2 inverted tets at the end"] and off.cell("unconverged") == "-"
    inverted_then_fine = synthetic()
    inverted_then_fine["inverted"] = np.array([0.0, 3.0, 0.0])
    inverted_then_fine["work_unresolved"] = np.zeros(3)
    m = metrics_of(inverted_then_fine)
    assert m.cell("inverted") == "0 (max 3)" and "up to 3 inverted tets during the run" in m.notes()
    assert m.problems() == ["1 unconverged projection"]
    assert metrics_of(synthetic(), runaway_step=3).problems()[0] == "runaway at step 3"
    # H0 = 0: the scale is K0 + |E_el0| + |E_grav0|, or M |g| r when that is larger
    zero = synthetic()
    zero["gravitational"] = np.array([-3.0, -3.0, -3.0])
    zero["total"] = zero["kinetic"] + zero["elastic"] + zero["gravitational"]
    assert energy_scale(zero, total_mass=M, gravity=G, length_scale=R) == pytest.approx(M * 10.0 * R)
    assert energy_scale(zero, total_mass=M, gravity=G, length_scale=0.01) == pytest.approx(6.0)


# ---- (b) the same numbers through every command -------------------------------------------------------------


SAME = ("energy_error", "final_energy_error", "unresolved", "p_drift", "l_drift", "min_j", "inverted")
SAME += ("final_inverted", "unconverged", "mean_iterations", "substeps", "base_unstable_step", "runaway_step")


@pytest.mark.parametrize("path, steps", [(DROP, DROP_STEPS), (SEED, 40)])
def test_run_result_fepr_run_and_compare_report_the_same_numbers(path, steps, tmp_path, capsys):
    scene = load_scene(path)
    result = run_scene(scene, steps=steps)
    m = result.metrics
    assert (result.max_energy_error, result.final_energy_error) == (m.energy_error, m.final_energy_error)
    assert (result.momentum_error, result.angular_momentum_error) == (m.p_drift, m.l_drift)
    assert (result.mean_iterations, result.max_iterations) == (m.mean_iterations, m.max_iterations)
    assert result.summary() == m.summary_line(f"{scene.name} (FEPR on)")

    # fepr run: the same line (up to the timing), and its diagnostics.csv gives the same numbers
    assert main(["run", str(path), "--steps", str(steps), "--out", str(tmp_path / "run"), "-q"]) == EXIT_OK
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert without_timing(printed) == without_timing(result.summary())
    diag = read_diagnostics(tmp_path / "run" / "diagnostics.csv")
    sim = result.simulation
    from_csv = compute_metrics(
        diag,
        total_mass=sim.total_mass,
        gravity=sim.gravity,
        length_scale=length_scale(sim.rest_positions),
        pinned=False,
        projection=True,
    )
    for key in SAME:
        assert getattr(from_csv, key) == getattr(m, key), key

    # fepr compare: summary.json's run with FEPR and the scene's integrator
    from fepr.cli.compare import compare

    res = compare(scene, tmp_path / "cmp", steps=steps, video=False, plots=False, html_report=True)
    info = json.loads((tmp_path / "cmp" / "summary.json").read_text())
    on = next(r for r in info["runs"] if r["projection"])
    for key in SAME:
        assert on[key] == getattr(m, key), key
    assert without_timing(on["summary"]) == without_timing(m.summary_line(res.runs[0].spec.label))
    md = (tmp_path / "cmp" / "summary.md").read_text()
    assert "| energy error | unresolved | P drift | L drift | min J | inverted | unconverged | substeps |" in md

    # fepr demo's tables: the run's row and the gallery's row have the same cells (but the timing)
    run_cells = format_row(result)[2:-1]
    gallery = [row for row in gallery_rows([res]) if row[2] == "on"][0][3:-1]
    assert run_cells == gallery == [m.cell(k) for k, _ in FIELDS][:-1]


def test_multibody_summary_uses_the_system_targets_and_its_diagnostics_file(tmp_path):
    scene = load_scene(EXAMPLES / "two_bodies.toml")
    result = run_scene(scene, steps=DROP_STEPS, out_dir=tmp_path)
    system = result.simulation
    h = system_history(system)
    # L - L_target of the system is the bodies' drifts moved to the system's centre of mass
    drift = np.zeros((len(h["step"]), 3))
    c_sys = vec(h, "cx", "cy", "cz")
    for body in system.bodies:
        b = body.history
        dp = vec(b, "px", "py", "pz") - vec(b, "px_target", "py_target", "pz_target")
        dl = vec(b, "lx", "ly", "lz") - vec(b, "lx_target", "ly_target", "lz_target")
        drift += dl + np.cross(vec(b, "cx", "cy", "cz") - c_sys, dp)
    l_sys = vec(h, "lx", "ly", "lz") - vec(h, "lx_target", "ly_target", "lz_target")
    np.testing.assert_allclose(l_sys, drift, atol=1e-12)
    m = result.metrics
    assert m.momentum_reference == "targets" and m.p_drift < 1e-10
    assert sum(b.history["contacts"].sum() for b in system.bodies) > 0
    diag = read_diagnostics(tmp_path / "diagnostics.csv")
    assert {"px_target", "lz_target", "work_unresolved"} <= set(diag)
    from_csv = simulation_metrics(system, projection=True, history=diag)
    for key in SAME:
        expected = getattr(m, key)
        assert getattr(from_csv, key) == (expected if expected is None else pytest.approx(expected, rel=1e-12)), key


# ---- (c) obstacles: momentum drift against the targets ------------------------------------------------------


def test_box_dropped_on_a_plane_reports_its_drift_against_the_targets():
    result = run_scene(load_scene(DROP), steps=DROP_STEPS)
    h = result.simulation.history
    assert h["contacts"].sum() > 0 and h["work_contact"].min() < 0.0  # it hit the ground
    m = result.metrics
    assert m.momentum_reference == "targets" and result.momentum_error is not None
    assert result.momentum_error < 1e-10
    # L about the centre of mass misses its target by a few 1e-7 (relative) in the step the contact starts
    assert result.angular_momentum_error < 1e-5
    # against P0 + M g t alone (ignoring the ground's impulses) the drift would be of order one
    naive = compute_metrics(
        {k: v for k, v in h.as_dict().items() if not k.endswith("_target")},
        total_mass=result.simulation.total_mass,
        gravity=result.simulation.gravity,
        length_scale=length_scale(result.simulation.rest_positions),
        pinned=False,
        projection=True,
    )
    assert naive.momentum_reference == "gravity" and naive.p_drift > 0.1
    assert result.max_energy_error < 1e-8  # the books: H0 plus the energy the impacts took out


# ---- (d) --strict, (e) the end-of-run warning ---------------------------------------------------------------


def unconverged_scene() -> dict:
    d = copy.deepcopy(DEMO_SCENES["spinning_l_gravity"])
    d["projection"] = {"enabled": True, "max_iterations": 1, "tolerance": 1e-12}  # too few iterations
    d["scene"]["name"] = "tight"
    return d


def write_toml(path: Path, d: dict) -> Path:
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = []
    for section, table in d.items():
        lines.append(f"[{section}]")
        lines += [f"{k} = {value(v)}" for k, v in table.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_strict_fails_on_unconverged_projections_and_inverted_tets(tmp_path, capsys):
    tight = write_toml(tmp_path / "tight.toml", unconverged_scene())
    out = str(tmp_path / "o")
    assert main(["run", str(tight), "--steps", "20", "--out", out, "-q"]) == EXIT_OK  # reported, not failed
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert re.search(r"unconverged [1-9]\d*", line) and "; problems: " in line and "unconverged projection" in line
    assert main(["run", str(tight), "--steps", "20", "--out", out, "-q", "--strict", "--overwrite"]) == EXIT_STRICT
    assert "--strict:" in capsys.readouterr().err
    # symplectic Euler alone on the stretched L: 4 tets inverted at step 13, two steps before it runs away
    code = main(["run", str(SEED), "--steps", "13", "--no-projection", "--out", out, "-q", "--strict", "--overwrite"])
    assert code == EXIT_STRICT
    captured = capsys.readouterr()
    assert "inverted tets at the end" in captured.out and "inverted tets at the end" in captured.err
    assert main(["run", str(SEED), "--steps", "13", "--no-projection", "--out", out, "-q", "--overwrite"]) == EXIT_OK
    capsys.readouterr()
    # a clean run passes --strict
    args = ["run", str(DROP), "--steps", str(DROP_STEPS), "--out", out, "-q", "--strict", "--overwrite"]
    assert main(args) == EXIT_OK
    assert "problems" not in capsys.readouterr().out


def test_compare_strict_checks_the_runs_with_fepr(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    tight = write_toml(tmp_path / "tight.toml", unconverged_scene())
    args = ["compare", str(tight), "--out", str(tmp_path / "c"), "--steps", "20", "--no-video", "-q"]
    assert main(args) == EXIT_OK
    assert main(args + ["--strict"]) == EXIT_STRICT
    err = capsys.readouterr().err
    assert "+ FEPR: " in err and "unconverged projection" in err
    # symplectic Euler alone inverts tets of the stretched L by step 13; FEPR restoring all the energy (no quality
    # guard) has no problem: --strict passes
    d = copy.deepcopy(DEMO_SCENES["seed_demo3_stretch"])
    d["projection"] = {"enabled": True, "quality_guard": False}
    seed = write_toml(tmp_path / "seed.toml", d)
    args = ["compare", str(seed), "--out", str(tmp_path / "s"), "--steps", "13", "--no-video", "-q", "--strict"]
    assert main(args) == EXIT_OK
    info = json.loads((tmp_path / "s" / "summary.json").read_text())
    assert [bool(r["problems"]) for r in info["runs"]] == [False, True]
    page = (tmp_path / "s" / "report.html").read_text()
    assert "<th>energy error</th>" in page and "problems: 4 inverted tets at the end" in page
    assert "**problems**: 4 inverted tets at the end" in (tmp_path / "s" / "summary.md").read_text()


def test_run_scene_warns_when_the_run_ends_badly():
    with pytest.warns(RuntimeWarning, match=r"tight: the run had [1-9]\d* of 20 projections unconverged"):
        result = run_scene(scene_from_dict(unconverged_scene(), "."), steps=20)
    assert any("unconverged" in w for w in result.warnings)
    assert result.problems and result.problems == result.metrics.problems()
    with pytest.warns(RunProblemWarning, match="ends with 4 inverted tets"):
        result = run_scene(load_scene(SEED), steps=13, projection=False)
    assert "ends with 4 inverted tets" in result.warnings[-1] and not result.runaway
    with warnings.catch_warnings():
        warnings.simplefilter("error", RunProblemWarning)
        result = run_scene(load_scene(DROP), steps=50)
    assert not result.problems
