"""fepr bench: the command runs, writes JSON with every field, and reports (never asserts on) timings."""

from __future__ import annotations

import json
import math
import os

import pytest

from fepr.cli import bench, main


def test_run_scene_reports_every_field_and_bit_identical_energy_gradient():
    r = bench.run_scene("box_1k", quick=True, budget_s=0.01)
    assert r["tets"] == 1296 and r["vertices"] == 343
    eg = r["energy_gradient"]
    for key in ("ns_per_tet_1_thread", "ns_per_tet_all_threads", "speedup", "ceiling", "speedup_of_ceiling"):
        assert 0 < eg[key] < math.inf
    assert eg["bit_identical"] is True
    names = [s["integrator"] for s in r["integrators"]]
    assert names == ["symplectic_euler", "projective_dynamics", "implicit_euler"]
    for s in r["integrators"]:
        assert s["steps"] >= 2 and s["ms_per_step"] > 0
        assert 0 <= s["proj_share"] <= 1
        assert s["proj_converged"] == 1.0
    assert r["memory"]["peak_rss_mb"] > 0


def test_one_thread_has_a_ceiling_of_one_without_measuring_it():
    r = bench.run_scene("box_1k", quick=True, budget_s=0.01, threads=1)
    eg = r["energy_gradient"]
    assert eg["ceiling"] == 1.0 and eg["speedup_of_ceiling"] == eg["speedup"]
    assert math.isnan(eg["ms_per_copy_apart"])


def test_energy_gradient_apart_times_every_copy_and_rejects_nonsense():
    import fepr

    material = fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3)
    sim = fepr.Simulation(fepr.meshes.box(resolution=(3, 3, 3)), material=material, node_mass=0.05, dt=1e-3)
    # Three copies on however many CPUs there are: each copy runs on its own thread and is timed.
    assert 0 < sim._sim.bench_energy_gradient_apart(4, 3) < math.inf
    for repeats, copies in ((0, 2), (4, 0)):
        with pytest.raises(ValueError, match="at least 1"):
            sim._sim.bench_energy_gradient_apart(repeats, copies)


def test_missing_mesh_is_skipped_with_a_reason(tmp_path):
    r = bench.run_scene("bunny2", quick=True, meshes_dir=tmp_path)
    assert "skipped" in r and "not present" in r["skipped"]


def test_cli_bench_writes_json(tmp_path, capsys):
    out = tmp_path / "b.json"
    code = main(["bench", "--quick", "--quiet", "--scenes", "box_1k", "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["quick"] is True and doc["scenes"][0]["scene"] == "box_1k"
    machine = doc["machine"]
    assert machine["sync_threads"] >= 1 and machine["parallel_region_us"] > 0
    printed = capsys.readouterr().out
    assert "symplectic_euler+fepr" in printed and "a parallel region that" in printed


def test_sync_floor_measures_a_joined_region_and_a_round_trip():
    m = bench.sync_floor(2)
    # Measured, not asserted on (0.8 us and 0.25 us here on a quiet machine): finite positive times.
    assert m["sync_threads"] == 2 and 0 < m["parallel_region_us"] < math.inf
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if usable >= 2:
        assert 0 < m["core_round_trip_ns"] < math.inf
    else:
        assert m["core_round_trip_ns"] is None
    assert "2 threads join" in bench.format_sync_floor(m)


def test_cli_bench_rejects_unknown_scene(capsys):
    assert main(["bench", "--scenes", "nope"]) == 2
    assert "unknown scene" in capsys.readouterr().err


@pytest.mark.parametrize("name", list(bench.SCENES))
def test_scene_table_is_consistent(name):
    s = bench.SCENES[name]
    assert (s.node_mass is None) != (s.density is None)
    assert s.integrators and all(dt > 0 for _, dt in s.integrators)
