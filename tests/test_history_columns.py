"""The per-step diagnostics columns: documented (docs/concepts.md, Diagnostics), and written to CSV with the
counts and flags as integers.

Guards: the diagnostics table once listed 32 of the 44 columns; ``History.to_csv`` once wrote the newer count
columns (``base_iterations``, ``contacts``, ``proj_frozen``, ...) as floats (``3.0``).
"""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np
import pytest

import fepr
from fepr import _core
from fepr.multibody import TOTAL_COLUMNS

CONCEPTS = Path(__file__).resolve().parents[1] / "docs" / "concepts.md"
INTEGER = re.compile(r"-?[0-9]+")


def documented_columns() -> list:
    """[(column, unit)] of the table in the Diagnostics section of docs/concepts.md, in table order."""
    text = CONCEPTS.read_text(encoding="utf-8")
    section = text.split("\n## Diagnostics\n", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        if not line.startswith("| `"):
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        for name in re.findall(r"`([a-z_]+)`", cells[0]):
            rows.append((name, cells[1]))
    return rows


def contact_run(integrator="implicit_euler", steps=12) -> fepr.Simulation:
    """A falling, spinning L hitting a frictional ground plane: contacts, projection, solver iterations."""
    sim = fepr.Simulation(
        fepr.meshes.ell(size=0.2),
        material=fepr.NeoHookean(youngs_modulus=2e3, poisson_ratio=0.3),
        density=100.0,
        dt=1 / 60,
        integrator=integrator,
        gravity=(0.0, 0.0, -9.81),
        obstacles=[fepr.Plane(point=(0.0, 0.0, -0.02), restitution=0.5, friction=0.3)],
        air_damping=0.1,
    )
    c = sim.center_of_mass()
    sim.velocities = np.array([0.2, 0.0, -1.0]) + np.cross([0.0, 0.0, 2.0], sim.positions - c)
    sim.step(steps)
    return sim


def test_every_history_column_is_documented_in_order():
    documented = [name for name, _ in documented_columns()]
    assert len(documented) == len(set(documented)), "a column is documented twice"
    columns = list(_core.Simulation.history_columns())
    assert len(columns) == 59
    missing = [c for c in columns if c not in documented]
    assert not missing, f"columns missing from the docs/concepts.md diagnostics table: {missing}"
    stale = [c for c in documented if c not in columns]
    assert not stale, f"documented columns that History does not produce: {stale}"
    assert documented == columns, "the table is not in the order of history_columns()"


def test_multibody_columns_are_documented():
    documented = {name for name, _ in documented_columns()}
    assert set(TOTAL_COLUMNS) <= documented
    bodies = [contact_run(steps=2), contact_run(steps=2)]
    h = fepr.MultiBody(bodies).history
    assert h.columns and set(h.columns) <= documented


def test_integer_columns_are_the_documented_counts_and_flags():
    counts = {name for name, unit in documented_columns() if unit in ("count", "0/1")}
    assert counts == set(fepr.History.INTEGER_COLUMNS)


@pytest.mark.parametrize("integrator", ["implicit_euler", "symplectic_euler", "xpbd"])
def test_integer_columns_hold_integers(integrator):
    h = contact_run(integrator, steps=6).history
    for c in fepr.History.INTEGER_COLUMNS:
        col = h[c]
        assert np.all(np.isfinite(col)) and np.all(col == np.round(col)), (c, col)


def read_back(path: Path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def check_csv(path: Path, h: fepr.History) -> None:
    header, body = read_back(path)
    assert header == h.columns and len(body) == len(h)
    for j, c in enumerate(header):
        col = h[c]
        for i, row in enumerate(body):
            cell = row[j]
            if c in fepr.History.INTEGER_COLUMNS:
                assert INTEGER.fullmatch(cell), f"{c} row {i}: {cell!r} is not written as an integer"
                assert int(cell) == col[i]
            else:
                v = float(cell)
                assert v == col[i] or (math.isnan(v) and math.isnan(col[i])), (c, i, cell, col[i])


def test_csv_writes_counts_and_flags_as_integers(tmp_path):
    sim = contact_run()
    h = sim.history
    # The run exercises the newer count columns with nonzero values.
    for c in ("base_iterations", "contacts", "proj_iterations", "proj_converged"):
        assert h[c].max() >= 1, c
    path = tmp_path / "diagnostics.csv"
    sim.save_diagnostics(path)
    check_csv(path, h)
    header, body = read_back(path)
    assert body[-1][header.index("base_iterations")] == str(int(h["base_iterations"][-1]))


def test_multibody_csv_writes_counts_and_flags_as_integers(tmp_path):
    mb = fepr.MultiBody([contact_run(steps=3), contact_run("xpbd", steps=3)])
    path = tmp_path / "totals.csv"
    mb.save_diagnostics(path)
    check_csv(path, mb.history)


def test_csv_writes_an_undefined_count_as_nan(tmp_path):
    h = fepr.History(np.array([[0.0, np.nan, 1.5], [1.0, 3.0, np.nan]]), ["step", "contacts", "total"])
    path = tmp_path / "h.csv"
    h.to_csv(path)
    header, body = read_back(path)
    assert body == [["0", "nan", "1.5"], ["1", "3", "nan"]]
