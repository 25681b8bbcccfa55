"""Checkpoints resume bit for bit: every example scene, every integrator (contact, kinematic pins, damping, bodies
touching each other), for any thread count; and a checkpoint that does not fit is a clear error."""

from __future__ import annotations

import copy
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

import fepr
from fepr.errors import CheckpointError
from fepr.multibody import MultiBody
from fepr.scene import load_scene, scene_from_dict

try:
    import tomllib as _toml
except ImportError:  # Python < 3.11
    import tomli as _toml

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

#: History columns that describe the trajectory and its books (wall times differ from run to run).
BOOK_COLUMNS = ("step", "time", "kinetic", "elastic", "gravitational", "total", "px", "py", "pz", "lx", "ly", "lz",
                "budget_total", "work_contact", "work_unresolved", "min_j", "inverted", "proj_iterations")


def _build(scene, threads=None):
    if scene.is_multibody:
        return scene.build_multibody()
    return scene.build()


def _state_bits(sim):
    return [np.asarray(a).view(np.uint64).copy() for a in (sim.positions, sim.velocities, np.float64(sim.time))]


def _assert_same(a, b, what):
    for x, y in zip(_state_bits(a), _state_bits(b)):
        assert np.array_equal(x, y), f"{what}: the resumed state differs"
    assert a.num_steps == b.num_steps
    ha, hb = a.history, b.history
    assert len(ha) == len(hb)
    for col in BOOK_COLUMNS:
        if col in ha.columns:
            assert np.array_equal(ha[col], hb[col], equal_nan=True), f"{what}: history column {col} differs"


def _resume_matches(sim, steps_before, steps_after, path, threads=None):
    """Step ``sim``, checkpoint it, resume a copy and step both on: they must agree bit for bit."""
    sim.step(steps_before)
    sim.save_checkpoint(path)
    loader = MultiBody if isinstance(sim, MultiBody) else fepr.Simulation
    resumed = loader.load_checkpoint(path, threads=threads)
    assert resumed.num_steps == sim.num_steps
    sim.step(steps_after)
    resumed.step(steps_after)
    return sim, resumed


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.toml")), ids=lambda p: p.stem)
def test_every_example_scene_resumes_bit_for_bit(path, tmp_path):
    scene = load_scene(path)
    n = min(scene.run.steps, 30)
    a, b = _resume_matches(_build(scene), n // 2, n - n // 2, tmp_path / "ck.npz")
    _assert_same(a, b, path.stem)


def _scene_with(path: Path, integrator: str, dt: float) -> fepr.scene.Scene:
    d = _toml.loads(path.read_text())
    d = copy.deepcopy(d)
    d["integrator"] = {"name": integrator, "dt": dt}
    return scene_from_dict(d, base_dir=path.parent, source=str(path))


@pytest.mark.parametrize("integrator", ["symplectic_euler", "implicit_euler", "projective_dynamics", "xpbd"])
@pytest.mark.parametrize("example", ["drop_box", "hanging_bar", "collide"])
def test_every_integrator_resumes_bit_for_bit_with_contact_pins_and_bodies(example, integrator, tmp_path):
    dt = 2e-3 if integrator == "symplectic_euler" else 1.0 / 60.0
    scene = _scene_with(EXAMPLES / f"{example}.toml", integrator, dt)
    before, after = (150, 150) if integrator == "symplectic_euler" else (20, 25)
    sim = _build(scene)
    if example == "drop_box":
        sim.step(int(0.35 / dt))  # just before the landing: the checkpoint is taken through the impact
    a, b = _resume_matches(sim, before, after, tmp_path / "ck.npz")
    _assert_same(a, b, f"{example} {integrator}")


def test_a_resumed_run_is_the_same_for_any_thread_count(tmp_path):
    scene = _scene_with(EXAMPLES / "drop_box.toml", "projective_dynamics", 1.0 / 60.0)
    sim = scene.build()
    sim.step(25)
    sim.save_checkpoint(tmp_path / "ck.npz")
    one = fepr.Simulation.load_checkpoint(tmp_path / "ck.npz", threads=1)
    two = fepr.Simulation.load_checkpoint(tmp_path / "ck.npz", threads=2)
    for s in (sim, one, two):
        s.step(20)
    _assert_same(sim, one, "1 thread")
    _assert_same(sim, two, "2 threads")


def test_a_simulation_resumes_with_forces_drag_and_damping_set_between_steps(tmp_path):
    mat = fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4)
    sim = fepr.Simulation(fepr.meshes.box(), material=mat, density=500.0, dt=0.01, integrator="implicit_euler",
                          gravity=(0, 0, -9.81), pinned=[0, 1], self_contact=(0.5, 0.2))
    sim.step(5)
    sim.set_external_forces((0.0, 2.0, 0.0))
    sim.set_drag(7, (0.3, 0.2, 0.4), 50.0)
    sim.step(5)
    a, b = _resume_matches(sim, 3, 12, tmp_path / "ck.npz")
    _assert_same(a, b, "forces and drag")


def test_a_checkpoint_without_history_resumes_the_state_and_starts_its_history_there(tmp_path):
    scene = load_scene(EXAMPLES / "spinning_l_gravity.toml")
    sim = scene.build()
    sim.step(40)
    sim.save_checkpoint(tmp_path / "ck.npz", history=False)
    resumed = fepr.Simulation.load_checkpoint(tmp_path / "ck.npz")
    assert len(resumed.history) == 1 and resumed.history["step"][0] == 40
    sim.step(10)
    resumed.step(10)
    assert np.array_equal(sim.positions, resumed.positions)
    assert np.array_equal(sim.history["total"][-11:], resumed.history["total"])


def _checkpoint(tmp_path) -> Path:
    sim = load_scene(EXAMPLES / "hanging_bar.toml").build()
    sim.step(3)
    path = tmp_path / "ck.npz"
    sim.save_checkpoint(path)
    return path


def _rewrite(path: Path, out: Path, edit) -> Path:
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    edit(meta, arrays)
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(out, **arrays)
    return out


def test_a_checkpoint_that_does_not_fit_is_a_clear_error(tmp_path):
    path = _checkpoint(tmp_path)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        fepr.Simulation.load_checkpoint(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        fepr.Simulation.load_checkpoint(tmp_path / "junk.npz")
    np.savez(tmp_path / "state.npz", positions=np.zeros((3, 3)))
    with pytest.raises(CheckpointError, match="not a fepr checkpoint"):
        fepr.Simulation.load_checkpoint(tmp_path / "state.npz")

    def newer(meta, arrays):
        meta["version"] = 99

    with pytest.raises(CheckpointError, match="checkpoint version 99"):
        fepr.Simulation.load_checkpoint(_rewrite(path, tmp_path / "v99.npz", newer))

    def other_mesh(meta, arrays):
        name = meta["body"]["recipe"]["mesh"]["vertices"]["array"]
        arrays[name] = arrays[name] * 1.01

    with pytest.raises(CheckpointError, match="does not match its recorded hash"):
        fepr.Simulation.load_checkpoint(_rewrite(path, tmp_path / "mesh.npz", other_mesh))

    def other_material(meta, arrays):
        meta["body"]["recipe"]["material"]["fields"]["youngs_modulus"] = 2e5

    with pytest.raises(CheckpointError, match="another model"):
        fepr.Simulation.load_checkpoint(_rewrite(path, tmp_path / "material.npz", other_material))

    def lost_entry(meta, arrays):
        del arrays["carry/x"]

    with pytest.raises(CheckpointError, match="lacks 'carry/x'"):
        fepr.Simulation.load_checkpoint(_rewrite(path, tmp_path / "lost.npz", lost_entry))

    def code(meta, arrays):
        meta["body"]["recipe"]["material"]["type"] = "os.system"

    with pytest.raises(CheckpointError, match="unknown type 'os.system'"):
        fepr.Simulation.load_checkpoint(_rewrite(path, tmp_path / "code.npz", code))

    # A truncated file (a copy cut short, as a crash during a plain write would leave it).
    data = path.read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        fepr.Simulation.load_checkpoint(tmp_path / "cut.npz")
    with pytest.raises(CheckpointError, match="MultiBody.load_checkpoint"):
        scene = load_scene(EXAMPLES / "collide.toml")
        system = scene.build_multibody()
        system.save_checkpoint(tmp_path / "multi.npz")
        fepr.Simulation.load_checkpoint(tmp_path / "multi.npz")


def test_a_checkpoint_is_written_atomically(tmp_path, monkeypatch):
    """A failure while writing leaves the earlier checkpoint as it was and no temporary file behind."""
    path = _checkpoint(tmp_path)
    before = path.read_bytes()
    sim = fepr.Simulation.load_checkpoint(path)
    sim.step(2)

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken)
    with pytest.raises(OSError, match="disk full"):
        sim.save_checkpoint(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ck.npz"]
    assert zipfile.is_zipfile(path)


@pytest.mark.parametrize(
    "integrator, fps",
    [("implicit_euler", 60), ("projective_dynamics", 60), ("xpbd", 60), ("projective_dynamics", 30), ("xpbd", 30)],
)
def test_a_scanned_mesh_landing_at_a_game_step_resumes_bit_for_bit(shared_meshes, tmp_path, integrator, fps):
    """The 4,406-tet armadillo (1 m, Stable Neo-Hookean 1e5 / 0.4) dropped 0.3 m onto a plane at dt = 1/60 and
    1/30 with FEPR: the checkpoint is taken in the air, the resumed run lands (contact inside the solve, the quality
    guard's search) and its books, min J and inverted tets are the original's, bit for bit."""
    mesh = fepr.io.load_mesh(shared_meshes / "Armadillo_Tetra_4406.vtu", fit=1.0)
    lowest = float(mesh.vertices[:, 2].min())

    def make():
        sim = fepr.Simulation(
            mesh, material=fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4), density=1000.0,
            dt=1.0 / fps, integrator=integrator, gravity=(0, 0, -9.81),
            obstacles=[fepr.Plane(point=(0, 0, lowest - 0.3), restitution=0.0, friction=0.5)],
        )  # fmt: skip
        return sim

    before = 10 if fps == 60 else 4  # in the air: the 0.3 m fall takes about 0.25 s
    a, b = _resume_matches(make(), before, 30 if fps == 60 else 15, tmp_path / "ck.npz")
    _assert_same(a, b, f"armadillo {integrator}")
    h = a.history
    assert h["contacts"].max() > 0, "the resumed steps include the landing"


def test_backward_euler_standing_on_the_ground_resumes_bit_for_bit(shared_meshes, tmp_path):
    """The armadillo dropped 0.3 m, landed and standing: the vertices the impact stiffened keep their contact
    penalty from step to step while they touch the ground (at the plain one they would sink deeper than 1% of an
    edge again, and every step would solve twice); the checkpoint carries it, else the resumed run would solve its
    next steps with the plain penalty."""
    mesh = fepr.io.load_mesh(shared_meshes / "Armadillo_Tetra_4406.vtu", fit=1.0)
    sim = fepr.Simulation(
        mesh, material=fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4), density=1000.0,
        dt=1.0 / 60.0, integrator="implicit_euler", gravity=(0, 0, -9.81), projection=False,
        obstacles=[fepr.Plane(point=(0, 0, float(mesh.vertices[:, 2].min()) - 0.3), restitution=0.0, friction=0.5)],
    )  # fmt: skip
    sim.step(40)  # landed at step 15
    a, b = _resume_matches(sim, 2, 8, tmp_path / "ck.npz")
    _assert_same(a, b, "armadillo standing, backward Euler")
    assert a.history["contacts"][-1] > 0
