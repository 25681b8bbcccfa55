"""``fepr compare``: every listed file is written, the video has the expected frames and size, the plots are
real images, and the numbers in ``summary.md`` are those of the diagnostics.

The video needs polyscope with an EGL driver (Debian: libegl1 libegl-mesa0 libgl1-mesa-dri; ``.ci/run`` installs
them) and imageio-ffmpeg; without them that part is skipped with the reason.
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest

from fepr.cli import EXIT_INVALID, EXIT_OK, main
from fepr.report.metrics import compute_metrics
from fepr.report.runs import frame_steps
from fepr.report.summary import COLUMNS

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "seed_demo3_stretch.toml"
STEPS, FRAMES = 40, 12


def read_diagnostics(path: Path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    header, data = rows[0], np.array([[float(v) for v in r] for r in rows[1:]])
    return {c: data[:, i] for i, c in enumerate(header)}


def md_rows(text: str):
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    split = [[c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", ln)[1:-1]] for ln in lines]
    header = split[0]
    return [dict(zip(header, r)) for r in split[1:]]


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    pytest.importorskip("matplotlib", reason='plots need matplotlib: pip install "fepr[compare]"')
    out = tmp_path_factory.mktemp("cmp")
    args = ["compare", str(SCENE), "--out", str(out), "--steps", str(STEPS), "--frames", str(FRAMES)]
    code = main(args + ["--size", "320x240", "--integrators", "symplectic_euler", "--quiet"])
    assert code == EXIT_OK
    return out


def test_compare_writes_every_file(compared):
    for name in ("energy.png", "momentum.png", "summary.md", "summary.json", "report.html"):
        assert (compared / name).is_file() and (compared / name).stat().st_size > 0, name
    for run in ("fepr", "plain"):
        assert (compared / run / "diagnostics.csv").is_file()
        assert (compared / run / "final_state.npz").is_file()
    html = (compared / "report.html").read_text()
    for ref in ("energy.png", "momentum.png", "fepr/diagnostics.csv"):
        assert ref in html


def test_plots_are_non_empty_images(compared):
    from PIL import Image

    for name in ("energy.png", "momentum.png"):
        img = np.asarray(Image.open(compared / name).convert("RGB")).astype(float)
        assert img.shape[0] > 300 and img.shape[1] > 600
        assert img.std() > 10  # not a blank canvas
        # both run colours appear: warm (FEPR) and cool (no projection)
        r, g, b = img[..., 0], img[..., 1], img[..., 2]
        assert np.sum((r > 200) & (g < 130) & (b < 80)) > 50, name
        assert np.sum((b > 180) & (r < 80)) > 50, name


def test_video_has_the_expected_frames_and_size(compared):
    info = json.loads((compared / "summary.json").read_text())
    if info["video"] is None:
        pytest.skip("no video was rendered here (polyscope/EGL or imageio-ffmpeg missing)")
    import imageio.v2 as iio
    from PIL import Image

    reader = iio.get_reader(str(compared / "side_by_side.mp4"))
    n = reader.count_frames()
    w, h = reader.get_meta_data()["size"]
    frame = reader.get_data(n // 2)
    reader.close()
    assert n == FRAMES == len(frame_steps(STEPS, FRAMES))
    assert (w, h) == (2 * 320, 240) == (info["video"]["width"], info["video"]["height"])
    assert frame.std() > 10
    gif = Image.open(compared / "side_by_side.gif")
    assert gif.n_frames == FRAMES


def test_summary_numbers_equal_the_diagnostics(compared):
    info = json.loads((compared / "summary.json").read_text())
    setup = info["setup"]
    rows = md_rows((compared / "summary.md").read_text())
    assert [r["FEPR"] for r in rows] == ["on", "off"]
    for run, row in zip(info["runs"], rows):
        diag = read_diagnostics(compared / run["folder"] / "diagnostics.csv")
        state = np.load(compared / run["folder"] / "final_state.npz")
        m = compute_metrics(
            diag,
            total_mass=float(state["masses"].sum()),
            gravity=setup["gravity"],
            length_scale=setup["length_scale"],
            pinned=setup["pinned"],
            projection=run["projection"],
            runaway_step=run["runaway_step"],
        )
        assert m.energy_error == pytest.approx(run["energy_error"], rel=1e-12)
        assert m.unresolved == pytest.approx(run["unresolved"], rel=1e-12, abs=1e-300)
        assert (m.inverted, m.final_inverted, m.unconverged) == (
            run["inverted"],
            run["final_inverted"],
            run["unconverged"],
        )
        assert run["summary"] == m.summary_line(row["run"])
        for key, header in COLUMNS[3:]:
            assert row[header] == m.cell(key), header
        # and against the raw columns directly: the energy against the books, the momentum against its targets
        h = diag["total"]
        books = np.abs(h - h[0] - diag["budget_total"]) / abs(h[0])
        books = np.where(np.isfinite(books), books, np.inf)
        assert run["energy_error"] == pytest.approx(books.max(), rel=1e-12)
        assert float(row["energy error"]) == pytest.approx(books.max(), rel=1e-2)
        assert run["unresolved"] == pytest.approx(-diag["work_unresolved"][1:].sum() / abs(h[0]), rel=1e-12, abs=1e-300)
        P = np.stack([diag["px"], diag["py"], diag["pz"]], axis=1)
        target = np.stack([diag["px_target"], diag["py_target"], diag["pz_target"]], axis=1)
        mass = float(state["masses"].sum())
        p_scale = max(
            np.linalg.norm(P[0]),
            np.linalg.norm(target, axis=1).max(),
            np.sqrt(2 * mass * (diag["kinetic"][0] + abs(diag["elastic"][0]))),
        )
        assert run["p_drift"] == pytest.approx(np.linalg.norm(P - target, axis=1).max() / p_scale, rel=1e-12)
        assert float(row["min J"]) == pytest.approx(diag["min_j"].min(), rel=1e-3)
        assert run["final_inverted"] == int(diag["inverted"][-1])
        if run["projection"]:
            assert float(row["iters"]) == pytest.approx(diag["proj_iterations"][1:].mean(), abs=5e-3)
            assert run["unconverged"] == int(np.sum(diag["proj_converged"][1:] == 0))
        else:
            assert run["unconverged"] is None and row["unconverged"] == "-"
    fepr_on, plain = info["runs"]
    assert fepr_on["energy_error"] < 1e-8 and plain["runaway_step"] is not None  # the seed scene runs away without FEPR
    assert "runaway at step" in plain["summary"] and plain["problems"]
    # Without gravity, contact or damping the only budget is the unresolved energy (what the projection's quality
    # guard could not restore): H falls by exactly that share.
    assert fepr_on["final_h_ratio"] - 1.0 == pytest.approx(-fepr_on["unresolved"], abs=1e-8)


def test_bad_input_is_a_clear_error_with_exit_2(tmp_path, capsys):
    assert main(["compare", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")]) == EXIT_INVALID
    assert "scene file not found" in capsys.readouterr().err
    code = main(["compare", str(SCENE), "--out", str(tmp_path / "o"), "--integrators", "symplectic_euler,rk4"])
    assert code == EXIT_INVALID
    err = capsys.readouterr().err
    assert "unknown integrator 'rk4'" in err and "symplectic_euler" in err
    assert main(["compare", str(SCENE), "--out", str(tmp_path / "o"), "--size", "big"]) == EXIT_INVALID


def test_several_integrators_get_their_own_runs(tmp_path):
    from fepr import _core
    from fepr.cli.compare import compare

    names = [n for n in ("symplectic_euler", "implicit_euler") if n in _core.INTEGRATORS]
    res = compare(SCENE, tmp_path, integrators=names, steps=6, video=False, plots=False)
    assert [(r.spec.integrator, r.spec.projection) for r in res.runs] == [(n, p) for n in names for p in (True, False)]
    assert (tmp_path / "implicit_euler-fepr" / "diagnostics.csv").is_file()
    assert len(md_rows((tmp_path / "summary.md").read_text())) == 2 * len(names)


def test_a_scene_of_several_bodies_is_compared_as_one(tmp_path):
    # Two bodies colliding in space: both runs hold the scene's totals, and the frames hold every body's vertices.
    from fepr.cli.compare import compare

    scene = Path(__file__).resolve().parents[1] / "examples" / "collide.toml"
    res = compare(scene, tmp_path, steps=20, video=False, plots=False)
    assert [r.spec.projection for r in res.runs] == [True, False]
    for r in res.runs:
        assert r.frames.shape[1] == len(r.rest_positions) and len(r.tets) > 0
    assert (tmp_path / "fepr" / "diagnostics.csv").is_file()
