"""The quick-start notebook (examples/quickstart.ipynb) runs from top to bottom, as a reader would run it: its
code cells in order in one namespace, in a fresh folder, with matplotlib off-screen. (Jupyter itself is not needed
to check that; the notebook is kept without outputs.)"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parent.parent / "examples" / "quickstart.ipynb"


def test_the_quickstart_notebook_runs_and_shows_fepr_keeping_the_energy(tmp_path, monkeypatch):
    mpl = pytest.importorskip("matplotlib", reason="the notebook plots with matplotlib")
    mpl.use("Agg")
    nb = json.loads(NOTEBOOK.read_text(encoding="utf-8"))
    cells = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert cells and all(not c.get("outputs") for c in cells), "the notebook is committed without outputs"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__main__"}
    for k, cell in enumerate(cells):
        exec(compile("".join(cell["source"]), f"{NOTEBOOK.name} cell {k}", "exec"), namespace)
    runs = namespace["runs"]
    fepr_run, plain = runs["FEPR"], runs["no projection"]
    h = fepr_run.history
    books = abs(h["total"][-1] - (h["total"][0] + h["budget_total"][-1])) / abs(h["total"][0])
    assert fepr_run.num_steps == 150 and books < 1e-8 and h["inverted"].max() == 0
    assert plain.num_steps < 150 or plain.last["inverted"] > 0, "without projection the step is unstable"
    assert (tmp_path / "ell_final.vtu").is_file() and (tmp_path / "diagnostics.csv").is_file()
    assert os.path.getsize(tmp_path / "ell.vtu") > 0
