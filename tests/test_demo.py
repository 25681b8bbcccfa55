"""``fepr demo``, the showcase: the gallery's content, and a short run that writes every scene's comparison and
the index report (the full-length demo runs in CI as ``fepr demo --quiet``)."""

from __future__ import annotations

import pytest

from fepr import _core
from fepr.cli import EXIT_OK, main
from fepr.cli.demo import DEMO_SCENES, GALLERY


def test_gallery_shows_the_seed_l_three_ways_the_boxes_the_bar_and_the_dissipative_integrators():
    names = [g.name for g in GALLERY]
    assert {"seed_demo3_stretch", "seed_demo1_wobble", "spinning_l_gravity"} <= set(names)  # the seed's L
    assert all(DEMO_SCENES[n]["mesh"]["builtin"] == "ell" for n in names if n.startswith(("seed", "spinning")))
    assert "wobbly_box" in names and "implicit_cantilever" in names  # a wobbling box, a pinned bar
    compared = {i for g in GALLERY for i in (g.integrators or ())}
    assert {"implicit_euler", "projective_dynamics"} <= compared
    assert set(names) == set(DEMO_SCENES)  # every demo scene is shown


def test_short_demo_writes_every_comparison_and_the_index(tmp_path, capsys):
    pytest.importorskip("matplotlib", reason='the demo plots need matplotlib: pip install "fepr[compare]"')
    out = tmp_path / "demo"
    code = main(["demo", "--steps", "3", "--frames", "3", "--size", "160x128", "--out", str(out), "--quiet"])
    assert code == EXIT_OK
    text = capsys.readouterr().out
    assert text.lstrip().startswith("scene")
    assert f"report: {out / 'report.html'}" in text
    index = (out / "report.html").read_text()
    for item in GALLERY:
        folder = out / item.name
        for name in ("energy.png", "momentum.png", "summary.md", "summary.json", "report.html"):
            assert (folder / name).is_file(), f"{item.name}/{name}"
        assert f"{item.name}/energy.png" in index
        for integrator in item.integrators or ():
            if integrator in _core.INTEGRATORS:
                sub = "fepr" if integrator == DEMO_SCENES[item.name]["integrator"]["name"] else f"{integrator}-fepr"
                assert (folder / sub / "diagnostics.csv").is_file()
                if sub != "fepr":
                    assert f"{item.name}/{integrator}" in text  # its own rows in the table
