"""The history is bounded: the core keeps one row, the store keeps chunks and spills old ones to disk, reads cost
the columns read, the last row costs nothing, and a long ``step(n)`` stops at a step boundary on Ctrl-C."""

from __future__ import annotations

import gc
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import fepr
from fepr.history import CHUNK_ROWS, History, HistoryStore


def _ell(**kw):
    mat = fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3)
    return fepr.Simulation(fepr.meshes.ell(), material=mat, node_mass=1.0, dt=0.01, **kw)


def test_the_store_gives_back_every_row_whether_in_memory_or_spilled():
    cols = ["step", "a", "b"]
    store = HistoryStore(cols, memory_rows=CHUNK_ROWS)
    rng = np.random.default_rng(1)
    batches = [rng.standard_normal((k, 3)) for k in (1, 7, 4000, 3, 9000, 1, 5000)]
    for b in batches:
        store.append(b)
    full = np.concatenate(batches)
    assert len(store) == len(full)
    assert store.spilled_rows > 0, "rows beyond memory_rows go to disk"
    assert len(store) - store.spilled_rows <= CHUNK_ROWS
    assert np.array_equal(store.table(), full)
    assert np.array_equal(store.column(2), full[:, 2])
    assert np.array_equal(store.column(1, stop=5000), full[:5000, 1])
    assert np.array_equal(np.concatenate(list(store.batches(4100))), full[4100:])
    assert np.array_equal(store.last, full[-1])
    folder = store._spill
    assert folder is not None and folder.is_dir()
    del store
    gc.collect()
    assert not folder.exists(), "the spill folder goes with the store"


def test_the_store_refuses_rows_of_another_width_and_a_bad_limit():
    store = HistoryStore(["a", "b"])
    with pytest.raises(ValueError, match=r"shape \(k, 2\)"):
        store.append(np.zeros((3, 5)))
    with pytest.raises(fepr.ConfigError, match="history_memory_rows"):
        store.memory_rows = -1


def test_the_core_keeps_one_row_and_the_simulation_all_of_them():
    sim = _ell(projection=True)
    sim.step(250)
    assert sim._sim.history().shape[0] == 1, "the core hands its rows over after each batch"
    h = sim.history
    assert len(h) == 251
    assert np.array_equal(h["step"], np.arange(251))
    last = sim.last
    for c in h.columns:
        assert last[c] == h[c][-1] or (np.isnan(last[c]) and np.isnan(h[c][-1]))
    assert h.last == last


def test_a_history_taken_is_a_snapshot():
    sim = _ell()
    sim.step(10)
    h = sim.history
    sim.step(10)
    assert len(h) == 11 and h["step"][-1] == 10
    assert len(sim.history) == 21


def test_a_spilled_history_reads_and_writes_the_same_as_one_in_memory(tmp_path):
    a, b = _ell(), _ell()
    a.history_memory_rows = None
    b.history_memory_rows = CHUNK_ROWS
    for s in (a, b):
        s.step(3 * CHUNK_ROWS + 17)
    assert b._history.spilled_rows > 0 and a._history.spilled_rows == 0
    assert np.array_equal(a.history["total"], b.history["total"])
    b.save_diagnostics(tmp_path / "b.csv")
    written = np.genfromtxt(tmp_path / "b.csv", delimiter=",", names=True)
    h = b.history
    assert len(written) == len(h)
    for c in h.columns:
        assert np.array_equal(written[c], h[c], equal_nan=True), c


def test_setting_the_state_before_the_first_step_redefines_row_zero_but_not_after():
    sim = _ell()
    x = sim.positions * 1.2
    sim.positions = x
    assert np.isclose(sim.history["elastic"][0], sim.energy().elastic)
    sim.step(3)
    before = sim.history.as_dict()
    sim.positions = sim.positions * 1.01
    after = sim.history.as_dict()
    for c in before:
        assert np.array_equal(before[c], after[c], equal_nan=True), c


def test_an_array_history_behaves_as_before(tmp_path):
    h = History(np.array([[0.0, 1.5], [1.0, 2.5]]), ["step", "total"])
    assert len(h) == 2 and list(h["total"]) == [1.5, 2.5] and h.last == {"step": 1.0, "total": 2.5}
    h.to_csv(tmp_path / "h.csv")
    assert (tmp_path / "h.csv").read_text().splitlines() == ["step,total", "0,1.5", "1,2.5"]


def test_ctrl_c_stops_a_billion_step_run_at_a_step_boundary(tmp_path):
    """SIGINT during ``step(10**9)``: KeyboardInterrupt at a step boundary, the history and the state agree.
    (How fast it stops is measured by the soak benchmark; here a generous bound only catches a hang.)"""
    script = textwrap.dedent(
        """
        import os, signal, threading, time, numpy as np, fepr
        mat = fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3)
        sim = fepr.Simulation(fepr.meshes.ell(), material=mat, node_mass=1.0, dt=0.01)
        sent = []
        def interrupt():
            time.sleep(1.0)
            sent.append(time.perf_counter())
            os.kill(os.getpid(), signal.SIGINT)
        threading.Thread(target=interrupt, daemon=True).start()
        try:
            sim.step(10**9)
        except KeyboardInterrupt:
            late = time.perf_counter() - sent[0]
            h = sim.history
            assert len(h) == sim.num_steps + 1 and h["step"][-1] == sim.num_steps
            assert sim.last["time"] == sim.time
            print("stopped", sim.num_steps, late)
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    words = out.stdout.split()
    assert words[0] == "stopped" and int(words[1]) > 0
    assert float(words[2]) < 5.0
