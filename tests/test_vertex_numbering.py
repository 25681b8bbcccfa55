"""The core runs on the mesh renumbered in a locality order; Python sees the user's numbering everywhere.

Guards: a simulation's results do not depend on how the user numbers the vertices (bit for bit: both numberings
reach the same internal order), and every per-vertex array in and out is in the user's numbering.
"""

import numpy as np
import pytest

import fepr
from fepr.errors import ConfigError


def _shuffled(mesh: fepr.TetMesh, seed: int):
    """The same mesh with its vertices numbered by a random permutation: returns (mesh, new index of vertex v)."""
    rng = np.random.default_rng(seed)
    new_of = rng.permutation(mesh.num_vertices)
    vertices = np.empty_like(mesh.vertices)
    vertices[new_of] = mesh.vertices
    return fepr.TetMesh(vertices, new_of[mesh.tets]), new_of


def _world(mesh: fepr.TetMesh, pinned, forces, integrator="symplectic_euler", dt=2e-4):
    sim = fepr.Simulation(
        mesh,
        material=fepr.NeoHookean(youngs_modulus=2e4, poisson_ratio=0.3),
        density=1000.0,
        integrator=integrator,
        dt=dt,
        gravity=(0.0, 0.0, -9.81),
        pinned=pinned,
        external_forces=forces,
    )
    x0 = sim.rest_positions
    c = x0.mean(axis=0)
    sim.positions = c + 1.05 * (x0 - c)
    sim.velocities = np.cross([0.0, 0.0, 2.0], x0 - c)
    return sim


@pytest.mark.parametrize("integrator,dt", [("symplectic_euler", 2e-4), ("implicit_euler", 1.0 / 60.0)])
def test_results_do_not_depend_on_the_users_vertex_numbering(integrator, dt):
    mesh = fepr.meshes.box(size=(0.2, 0.1, 0.1), resolution=(5, 3, 3))
    other, new_of = _shuffled(mesh, seed=1)
    m = mesh.num_vertices
    pinned = np.flatnonzero(mesh.vertices[:, 0] <= mesh.vertices[:, 0].min() + 1e-12)
    forces = np.zeros((m, 3))
    forces[np.argmax(mesh.vertices[:, 0])] = [0.0, 0.5, 0.0]
    a = _world(mesh, pinned, forces, integrator, dt)
    moved_forces = np.empty_like(forces)
    moved_forces[new_of] = forces
    b = _world(other, new_of[pinned], moved_forces, integrator, dt)
    steps = 40 if integrator == "symplectic_euler" else 4
    start = a.positions
    a.step(steps)
    b.step(steps)
    # Row v of `a` is row new_of[v] of `b`, bit for bit.
    assert np.array_equal(b.positions[new_of], a.positions)
    assert np.array_equal(b.velocities[new_of], a.velocities)
    assert np.array_equal(b.masses[new_of], a.masses)
    assert np.array_equal(b.pinned[new_of], a.pinned)
    assert a.history["total"][-1] == b.history["total"][-1]
    _, ga = a.elastic_energy_gradient()
    _, gb = b.elastic_energy_gradient()
    assert np.array_equal(gb[new_of], ga)
    # The vertices the user pinned stayed put; the others moved.
    free = np.setdiff1d(np.arange(m), pinned)
    assert np.array_equal(a.positions[pinned], start[pinned])
    assert np.all(a.velocities[pinned] == 0.0)
    assert np.all(np.linalg.norm(a.positions[free] - start[free], axis=1) > 0.0)


def test_per_vertex_arrays_are_in_the_users_numbering():
    mesh, _ = _shuffled(fepr.meshes.box(size=1.0, resolution=4), seed=2)
    m = mesh.num_vertices
    pinned = [0, 5, m - 1]
    sim = fepr.Simulation(
        mesh,
        material=fepr.NeoHookean(youngs_modulus=1e4, poisson_ratio=0.3),
        density=500.0,
        dt=1e-3,
        pinned=pinned,
    )
    assert np.array_equal(sim.rest_positions, mesh.vertices)
    assert np.array_equal(np.flatnonzero(sim.pinned), pinned)
    # Lumped masses: a quarter of each tet's mass to each of its corners, in the user's numbering.
    want = np.zeros(m)
    np.add.at(want, mesh.tets, 0.25 * 500.0 * mesh.volumes()[:, None])
    assert np.allclose(sim.masses, want, rtol=1e-12, atol=0.0)
    rng = np.random.default_rng(3)
    x = mesh.vertices + 0.01 * rng.standard_normal((m, 3))
    v = rng.standard_normal((m, 3))
    sim.positions = x
    sim.velocities = v
    assert np.array_equal(sim.positions, x)
    v[pinned] = 0.0
    assert np.array_equal(sim.velocities, v)
    # The gradient matches a central difference on a vertex the user names.
    e0, g = sim.elastic_energy_gradient(x)
    k, h = 7, 1e-7
    xp, xm = x.copy(), x.copy()
    xp[k, 1] += h
    xm[k, 1] -= h
    fd = (sim.elastic_energy_gradient(xp)[0] - sim.elastic_energy_gradient(xm)[0]) / (2 * h)
    assert abs(fd - g[k, 1]) <= 1e-5 * max(1.0, np.abs(g).max())
    # The drag spring pulls the vertex the user names (from rest, without gravity: nothing else moves it).
    rest = sim.rest_positions
    sim.positions = rest
    sim.velocities = np.zeros((m, 3))
    sim.set_drag(3, rest[3] + [0.0, 0.0, 0.1], 50.0)
    sim.step(1)
    moved = np.linalg.norm(sim.positions - rest, axis=1)
    assert np.argmax(moved) == 3 and moved[3] > 10 * np.partition(moved, -2)[-2]


def test_errors_name_the_users_rows_and_vertices():
    mesh, _ = _shuffled(fepr.meshes.box(size=1.0, resolution=3), seed=4)
    sim = fepr.Simulation(mesh, material=fepr.NeoHookean(youngs_modulus=1e4, poisson_ratio=0.3), node_mass=0.1, dt=1e-3)
    x = sim.positions.copy()
    x[11, 2] = np.nan
    with pytest.raises(ValueError, match="row 11"):
        sim._sim.positions = x  # the core's own check (the Python layer checks first)
    # A vertex no tet references gets no mass from a density: the error names it in the user's numbering. It
    # comes first in the user's numbering and last in the internal one (it lies beyond the box's far corner).
    vertices = np.vstack([[[5.0, 5.0, 5.0]], mesh.vertices])
    lonely = fepr.TetMesh(vertices, mesh.tets + 1)
    with pytest.raises(ConfigError, match="vertex 0:"):
        fepr.Simulation(
            lonely, material=fepr.NeoHookean(youngs_modulus=1e4, poisson_ratio=0.3), density=1000.0, dt=1e-3
        )
