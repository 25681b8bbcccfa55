"""``save_state(path)`` writes exactly ``path`` (numpy.savez appended ``.npz``: ``x.npy`` became ``x.npy.npz``),
atomically (no temporary file left behind, a failed write leaves the previous file); ``fepr.io.npz.save_npz`` is the
helper behind it."""

from __future__ import annotations

import os

import numpy as np
import pytest

import fepr
from fepr.io.npz import save_npz
from fepr.multibody import MultiBody

MESH = fepr.meshes.builtin("box", size=0.1, resolution=1)


def make_sim(offset=(0.0, 0.0, 0.0)):
    mesh = fepr.TetMesh(np.asarray(MESH.vertices) + np.asarray(offset), MESH.tets)
    return fepr.Simulation(
        mesh, material=fepr.NeoHookean(youngs_modulus=1e5, poisson_ratio=0.3), density=1000.0, dt=1e-3
    )


@pytest.mark.parametrize("name", ["x.npy", "state", "final_state.npz", "s.data"])
def test_simulation_save_state_writes_exactly_the_path(tmp_path, name):
    sim = make_sim()
    sim.step(2)
    path = tmp_path / name
    sim.save_state(path)
    assert sorted(os.listdir(tmp_path)) == [name]
    with np.load(path, allow_pickle=False) as z:
        assert set(z.files) == {"positions", "velocities", "rest_positions", "tets", "masses", "time"}
        np.testing.assert_array_equal(z["positions"], sim.positions)
        assert float(z["time"]) == pytest.approx(sim.time)


def test_multibody_save_state_writes_exactly_the_path(tmp_path):
    system = MultiBody([make_sim(), make_sim((1.0, 0.0, 0.0))], names=["a", "b"])
    path = tmp_path / "bodies.npy"
    system.save_state(str(path))
    assert sorted(os.listdir(tmp_path)) == ["bodies.npy"]
    with np.load(path, allow_pickle=False) as z:
        assert list(z["names"]) == ["a", "b"]
        assert z["offsets"].tolist() == [0, 8, 16]


def test_save_state_result_loads_as_a_mesh(tmp_path):
    path = tmp_path / "state.npz"
    make_sim().save_state(path)
    mesh = fepr.load_mesh(path)
    assert mesh.num_vertices == MESH.num_vertices


def test_save_npz_replaces_atomically_and_cleans_up(tmp_path, monkeypatch):
    path = tmp_path / "a.npy"
    assert save_npz(path, {"x": np.arange(3)}) == path

    def fails_halfway(fh, **arrays):
        fh.write(b"PK half an archive")
        raise OSError("disk full")

    with monkeypatch.context() as m:
        m.setattr(np, "savez", fails_halfway)
        with pytest.raises(OSError, match="disk full"):
            save_npz(path, {"y": np.ones(2)})
    assert sorted(os.listdir(tmp_path)) == ["a.npy"]  # the previous file is intact, no temporary left
    with np.load(path) as z:
        assert z["x"].tolist() == [0, 1, 2]
    save_npz(path, {"y": np.ones(2)}, compressed=True)
    with np.load(path) as z:
        assert z.files == ["y"]
