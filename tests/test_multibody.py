"""MultiBody: several independent bodies stepped together; totals, per-body trajectories, errors, and multi-body
scenes run by ``run_scene``."""

from __future__ import annotations

import csv

import numpy as np
import pytest

import fepr
from fepr.errors import ConfigError, SimulationError
from fepr.multibody import TOTAL_COLUMNS, MultiBody
from fepr.scene import run_scene, scene_from_dict

DT = 0.01


def spinning_box(dt=DT, gravity=(0.0, 0.0, -9.81)):
    sim = fepr.Simulation(
        fepr.meshes.box(),
        material=fepr.StableNeoHookean(youngs_modulus=2e3, poisson_ratio=0.3),
        density=100.0,
        dt=dt,
        gravity=gravity,
    )
    c = sim.center_of_mass()
    x = c + 1.1 * (sim.rest_positions - c)
    sim.positions = x
    sim.velocities = np.array([0.3, 0.0, 0.5]) + np.cross([0.0, 0.5, 1.0], x - c)
    return sim


def thrown_ell(dt=DT, gravity=(0.0, 0.0, -9.81)):
    sim = fepr.Simulation(
        fepr.meshes.ell(),
        material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
        node_mass=0.5,
        dt=dt,
        gravity=gravity,
    )
    x = sim.rest_positions + np.array([3.0, -1.0, 2.0])
    c = (x * np.asarray(sim.masses)[:, None]).sum(axis=0) / sim.total_mass
    sim.positions = c + 1.2 * (x - c)
    sim.velocities = np.array([-1.0, 0.2, 0.0]) + np.cross([1.0, 0.0, 0.0], x - c)
    return sim


def test_totals_are_the_sums_of_the_bodies():
    a, b = spinning_box(), thrown_ell()
    system = MultiBody([a, b], names=["box", "ell"])
    system.step(40)
    h, ha, hb = system.history, a.history, b.history
    assert len(h) == 41 and system.num_steps == 40
    assert system.time == pytest.approx(40 * DT)
    for col in ("kinetic", "elastic", "gravitational", "total", "px", "py", "pz"):
        np.testing.assert_allclose(h[col], ha[col] + hb[col], rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(h["time"], ha["time"])
    e = system.energy()
    assert e.total == pytest.approx(a.energy().total + b.energy().total, rel=1e-14)
    np.testing.assert_allclose(system.linear_momentum(), a.linear_momentum() + b.linear_momentum(), rtol=1e-14)
    # Centre of mass and angular momentum of the system from the history agree with the direct measurement
    # from all vertices' positions, velocities and masses (the last row is the current state).
    np.testing.assert_allclose([h["cx"][-1], h["cy"][-1], h["cz"][-1]], system.center_of_mass(), rtol=1e-12)
    np.testing.assert_allclose(
        [h["lx"][-1], h["ly"][-1], h["lz"][-1]], system.angular_momentum(), rtol=1e-9, atol=1e-12
    )
    # ... which is not the sum of the bodies' own angular momenta about their own centres of mass.
    own = a.angular_momentum() + b.angular_momentum()
    assert np.linalg.norm(system.angular_momentum() - own) > 1e-3 * np.linalg.norm(own)
    assert [c for c in h.columns if c in TOTAL_COLUMNS] == h.columns


def test_angular_momentum_of_the_system_is_conserved_without_gravity():
    a, b = spinning_box(gravity=(0, 0, 0)), thrown_ell(gravity=(0, 0, 0))
    system = MultiBody([a, b])
    l0 = system.angular_momentum()
    system.step(60)
    h = system.history
    lsys = np.stack([h["lx"], h["ly"], h["lz"]], axis=1)
    assert np.abs(lsys - l0).max() <= 1e-9 * np.linalg.norm(l0)
    # and the energy of the system, with FEPR on both bodies
    assert np.abs(h["total"] - h["total"][0]).max() <= 1e-9 * abs(h["total"][0])


def test_a_body_moves_exactly_as_when_run_alone():
    alone = thrown_ell()
    alone.step(50)
    system = MultiBody([spinning_box(), thrown_ell()])
    system.step(20)
    system.step(30)
    ell = system["body2"]
    np.testing.assert_array_equal(ell.positions, alone.positions)
    np.testing.assert_array_equal(ell.velocities, alone.velocities)
    np.testing.assert_array_equal(ell.history["total"], alone.history["total"])


def test_dt_mismatch_is_an_error():
    with pytest.raises(ConfigError, match=r"all bodies must have the same dt: 'a' has dt = 0.01 s, 'b' has 0.02 s"):
        MultiBody([spinning_box(dt=0.01), thrown_ell(dt=0.02)], names=["a", "b"])


def test_bodies_at_different_steps_are_an_error():
    a, b = spinning_box(), thrown_ell()
    a.step(2)
    with pytest.raises(ConfigError, match=r"same step and time: 'body1' is at step 2 .* 'body2' at step 0"):
        MultiBody([a, b])


@pytest.mark.parametrize(
    "bodies,names,fragment",
    [
        ([], None, "MultiBody needs at least one body"),
        (["sim"], None, r"bodies\[0\] must be a fepr.Simulation, got str"),
        (None, ["a"], "names has 1 entries but there are 2 bodies"),
        (None, ["a", "a"], "names must be unique; 'a' is given twice"),
        (None, ["a", ""], r"names\[1\] must be a non-empty string"),
        (None, "ab", "names must be a sequence of strings"),
    ],
)
def test_bad_arguments(bodies, names, fragment):
    if bodies is None:
        bodies = [spinning_box(), thrown_ell()]
    with pytest.raises(ConfigError, match=fragment):
        MultiBody(bodies, names=names)


def test_the_same_simulation_twice_is_an_error():
    a = spinning_box()
    with pytest.raises(ConfigError, match=r"bodies\[1\] is the same Simulation as bodies\[0\]"):
        MultiBody([a, a])


def test_lookup_concatenated_arrays_and_state_file(tmp_path):
    a, b = spinning_box(), thrown_ell()
    system = MultiBody([a, b], names=["box", "ell"])
    assert system["ell"] is b and system[0] is a and len(system) == 2
    with pytest.raises(KeyError, match="no body named 'cube'"):
        system["cube"]
    na = len(a.rest_positions)
    np.testing.assert_array_equal(system.offsets, [0, na, na + len(b.rest_positions)])
    np.testing.assert_array_equal(system.positions[na:], b.positions)
    np.testing.assert_array_equal(system.tets[len(a.tets) :], np.asarray(b.tets) + na)
    assert system.total_mass == pytest.approx(a.total_mass + b.total_mass)
    system.step(3)
    system.save_state(tmp_path / "s.npz")
    with np.load(tmp_path / "s.npz") as f:
        np.testing.assert_array_equal(f["positions"][f["offsets"][1] : f["offsets"][2]], b.positions)
        assert list(f["names"]) == ["box", "ell"] and float(f["time"]) == pytest.approx(3 * DT)
    system.save_diagnostics(tmp_path / "d.csv")
    with open(tmp_path / "d.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == system.history.columns and len(rows) == 1 + 4
    assert float(rows[-1][rows[0].index("total")]) == pytest.approx(system.energy().total, rel=1e-12)


def test_a_runaway_names_the_body_and_the_history_keeps_the_common_steps():
    calm = spinning_box(dt=1 / 30, gravity=(0, 0, 0))
    wild = fepr.Simulation(  # the seed's demo 3 without projection explodes
        fepr.meshes.ell(),
        material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
        node_mass=5.0,
        dt=1 / 30,
        projection=False,
    )
    wild.positions = 1.5 * wild.rest_positions
    # They overlap in space: stepped apart (no contact between them), each body runs on its own.
    system = MultiBody([calm, wild], names=["calm", "wild"], contact=False)
    with pytest.warns(RuntimeWarning), pytest.raises(SimulationError, match=r"^body 'wild': ") as info:
        system.step(400)
    assert info.value.body == "wild" and isinstance(info.value.step, int)
    assert system.num_steps == wild.num_steps < calm.num_steps == 400
    assert len(system.history) == wild.num_steps + 1


MULTI_SCENE = {
    "scene": {"name": "pair"},
    "integrator": {"dt": DT},
    "world": {"gravity": [0.0, 0.0, -9.81]},
    "bodies": [
        {
            "name": "cube",
            "mesh": {"builtin": "box", "size": 0.5, "resolution": 2},
            "material": {"youngs_modulus": 2e3, "poisson_ratio": 0.3},
            "mass": {"density": 100.0},
            "initial": {"scale": 1.1, "scale_about": "centroid", "angular_velocity": [0, 0, 1]},
        },
        {
            "name": "ell",
            "mesh": {"builtin": "ell"},
            "material": {"model": "stable_neo_hookean", "youngs_modulus": 1e3, "poisson_ratio": 0.3},
            "mass": {"node_mass": 0.5},
            "initial": {"translate": [3.0, 0.0, 0.0], "velocity": [0.0, 1.0, 0.0]},
        },
    ],
    "run": {"steps": 30},
}


def test_run_scene_writes_totals_and_per_body_diagnostics(tmp_path):
    scene = scene_from_dict(MULTI_SCENE, ".", source="pair.toml")
    result = run_scene(scene, out_dir=tmp_path)
    assert result.steps_completed == 30 and not result.runaway
    assert result.bodies == ("cube", "ell")
    assert result.final_energy_error < 1e-9 and result.momentum_error < 1e-9
    assert result.angular_momentum_error < 1e-9
    files = {p.name for p in tmp_path.iterdir()}
    assert {"diagnostics.csv", "diagnostics_cube.csv", "diagnostics_ell.csv", "final_state.npz"} <= files
    assert result.body_diagnostics_paths["ell"] == tmp_path / "diagnostics_ell.csv"

    def column(name, col):
        with open(tmp_path / name, newline="") as fh:
            rows = list(csv.reader(fh))
        i = rows[0].index(col)
        return np.array([float(r[i]) for r in rows[1:]])

    np.testing.assert_allclose(
        column("diagnostics.csv", "total"),
        column("diagnostics_cube.csv", "total") + column("diagnostics_ell.csv", "total"),
        rtol=1e-14,
    )
    # The ell's file is exactly what running it alone gives (the same scene with one body).
    alone = dict(MULTI_SCENE, bodies=[MULTI_SCENE["bodies"][1]])
    solo = run_scene(scene_from_dict(alone, ".", source="solo.toml"), out_dir=tmp_path / "solo")
    np.testing.assert_array_equal(column("diagnostics_ell.csv", "total"), solo.simulation["ell"].history["total"])


def test_multibody_scene_exports_each_body(tmp_path):
    scene = scene_from_dict(MULTI_SCENE, ".", source="pair.toml")
    result = run_scene(scene, steps=4, out_dir=tmp_path, export="obj", export_every=2)
    assert result.export_frames == 3 and result.export_dir == tmp_path / "export"
    for body in ("cube", "ell"):
        objs = sorted((tmp_path / "export" / body / "obj").glob("*.obj"))
        assert [p.name for p in objs] == [f"pair_{body}_0000{k}.obj" for k in range(3)]
