"""Bad inputs raise the right fepr error with a message that names the problem; materials and the mesh
gradient agree with finite differences through the Python API."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

import fepr

# Two tets sharing the face (1, 2, 3), both positively oriented.
V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float64)
T = np.array([[0, 1, 2, 3], [1, 2, 3, 4]], dtype=np.int64)
SOFT = fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3)


def test_reference_mesh_is_valid():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = fepr.TetMesh(V, T)
    assert mesh.flipped_count == 0
    assert mesh.num_vertices == 5 and mesh.num_tets == 2
    np.testing.assert_allclose(mesh.volumes(), [1 / 6, 1 / 3], rtol=1e-14)


# ----------------------------------------------------------------------------------------------------
# TetMesh


@pytest.mark.parametrize("bad", [5, 7, 10**12])
def test_mesh_index_out_of_range(bad):
    tets = T.copy()
    tets[1, 3] = bad
    with pytest.raises(fepr.MeshError) as info:
        fepr.TetMesh(V, tets)
    msg = str(info.value)
    assert re.search(r"\btet 1\b", msg), msg
    assert str(bad) in msg
    assert "range" in msg


def test_mesh_negative_index():
    tets = T.copy()
    tets[1, 2] = -1
    with pytest.raises(fepr.MeshError) as info:
        fepr.TetMesh(V, tets)
    msg = str(info.value)
    assert re.search(r"\btet 1\b", msg), msg
    assert "-1" in msg


def test_mesh_repeated_vertex():
    with pytest.raises(fepr.MeshError) as info:
        fepr.TetMesh(V, [[0, 1, 2, 3], [1, 2, 2, 4]])
    msg = str(info.value)
    assert re.search(r"\btet 1\b", msg), msg
    assert "repeat" in msg


@pytest.mark.parametrize(
    "apex",
    [[0.5, 0.5, 0.0], [0.25, 0.25, 1e-14]],
    ids=["coplanar", "near-flat"],
)
def test_mesh_degenerate_tet(apex):
    v = V.copy()
    v[4] = apex
    with pytest.raises(fepr.MeshError) as info:
        fepr.TetMesh(v, [[0, 1, 2, 3], [0, 1, 2, 4]])
    msg = str(info.value)
    assert re.search(r"\btet 1\b", msg), msg
    assert "degenerate" in msg or "volume" in msg


def test_mesh_coincident_vertices():
    v = np.vstack([V, V[3]])  # vertex 5 sits on vertex 3
    with pytest.raises(fepr.MeshError, match=r"tet 2\b"):
        fepr.TetMesh(v, [[0, 1, 2, 3], [1, 2, 3, 4], [1, 2, 3, 5]])


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_mesh_non_finite_coordinates(bad):
    v = V.copy()
    v[2, 1] = bad
    with pytest.raises(fepr.MeshError) as info:
        fepr.TetMesh(v, T)
    msg = str(info.value)
    assert re.search(r"\bvertex 2\b", msg), msg
    assert "finite" in msg


@pytest.mark.parametrize(
    "vertices, tets, what",
    [
        (V[:, :2], T, "vertices"),
        (V.ravel(), T, "vertices"),
        (np.zeros((5, 3, 1)), T, "vertices"),
        (V, T[:, :3], "tets"),
        (V, T.ravel(), "tets"),
        (V, np.zeros((2, 5), dtype=np.int64), "tets"),
    ],
)
def test_mesh_wrong_shapes(vertices, tets, what):
    with pytest.raises(fepr.MeshError, match=rf"{what} must have shape"):
        fepr.TetMesh(vertices, tets)


@pytest.mark.parametrize(
    "tets",
    [T + 0.5, T.astype(bool), np.array([["a", "b", "c", "d"]] * 2), np.where(T == 4, np.nan, T)],
    ids=["fractional", "bool", "str", "nan"],
)
def test_mesh_non_integer_tets(tets):
    with pytest.raises(fepr.MeshError, match="integer"):
        fepr.TetMesh(V, tets)


def test_mesh_non_numeric_vertices():
    with pytest.raises(fepr.MeshError, match="vertices must be numeric"):
        fepr.TetMesh([["a", "b", "c"]] * 5, T)


def test_mesh_error_names_the_source():
    tets = T.copy()
    tets[0, 0] = 9
    with pytest.raises(fepr.MeshError, match=r"^my_file\.node: "):
        fepr.TetMesh(V, tets, source="my_file.node")


def test_mesh_negative_orientation_is_repaired():
    tets = np.array([[0, 1, 3, 2], [1, 2, 3, 4], [0, 2, 1, 3]], dtype=np.int64)
    with pytest.warns(UserWarning, match=r"2 of 3 tets"):
        mesh = fepr.TetMesh(V, tets)
    assert mesh.flipped_count == 2
    vol = mesh.volumes()
    assert np.all(vol > 0)
    np.testing.assert_allclose(vol, [1 / 6, 1 / 3, 1 / 6], rtol=1e-14)
    # every repaired tet still uses the same vertices
    for old, new in zip(tets, mesh.tets):
        assert sorted(old) == sorted(new)


def test_mesh_all_tets_inverted_is_repaired():
    mesh = fepr.meshes.box(resolution=2)
    flipped = mesh.tets[:, [0, 2, 1, 3]]
    with pytest.warns(UserWarning):
        repaired = fepr.TetMesh(mesh.vertices, flipped)
    assert repaired.flipped_count == mesh.num_tets
    assert np.all(repaired.volumes() > 0)
    np.testing.assert_allclose(repaired.volumes(), mesh.volumes(), rtol=1e-12)


# ----------------------------------------------------------------------------------------------------
# materials


@pytest.mark.parametrize("cls", [fepr.NeoHookean, fepr.StableNeoHookean])
@pytest.mark.parametrize("E", [0.0, -1.0, -1e3, float("nan"), float("inf")])
def test_material_bad_youngs_modulus(cls, E):
    with pytest.raises(fepr.ConfigError, match="youngs_modulus"):
        cls(youngs_modulus=E, poisson_ratio=0.3)


@pytest.mark.parametrize("cls", [fepr.NeoHookean, fepr.StableNeoHookean])
@pytest.mark.parametrize("nu", [0.5, 0.6, -1.0, -1.5, float("nan")])
def test_material_bad_poisson_ratio(cls, nu):
    with pytest.raises(fepr.ConfigError, match="poisson_ratio"):
        cls(youngs_modulus=1e3, poisson_ratio=nu)


@pytest.mark.parametrize("cls", [fepr.NeoHookean, fepr.StableNeoHookean])
@pytest.mark.parametrize(
    "E, nu, name",
    [
        ("abc", 0.3, "youngs_modulus"),
        (None, 0.3, "youngs_modulus"),
        (1e3, "x", "poisson_ratio"),
        (1e3, [], "poisson_ratio"),
    ],
)
def test_material_non_numeric(cls, E, nu, name):
    with pytest.raises(fepr.ConfigError, match=name):
        cls(youngs_modulus=E, poisson_ratio=nu)


def test_material_valid_edges_accepted():
    assert fepr.NeoHookean(youngs_modulus=1e-3, poisson_ratio=0.4999).poisson_ratio == 0.4999
    assert fepr.StableNeoHookean(youngs_modulus=1e3, poisson_ratio=-0.99).poisson_ratio == -0.99
    assert fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3, j0=1).j0 == 1.0


@pytest.mark.parametrize("j0", [0, 0.0, -0.1, 1.0001, 2, float("nan"), float("inf"), "0.5", None])
def test_neo_hookean_bad_j0(j0):
    with pytest.raises(fepr.ConfigError, match="j0"):
        fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3, j0=j0)


# ----------------------------------------------------------------------------------------------------
# Simulation parameters


def make(mesh=None, **kwargs):
    params = dict(material=SOFT, node_mass=5.0, dt=1 / 30)
    params.update(kwargs)
    params = {k: v for k, v in params.items() if v is not ...}
    return fepr.Simulation(fepr.meshes.ell() if mesh is None else mesh, **params)


M_ELL = fepr.meshes.ell().num_vertices


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(dt=0), "dt"),
        (dict(dt=-0.01), "dt"),
        (dict(dt=float("nan")), "dt"),
        (dict(dt=float("inf")), "dt"),
        (dict(dt="0.1"), "dt"),
        (dict(density=1000.0), "node_mass"),
        (dict(density=1000.0), "density"),
        (dict(node_mass=...), "node_mass"),
        (dict(node_mass=...), "density"),
        (dict(node_mass=..., density=-1.0), "density"),
        (dict(node_mass=..., density=0.0), "density"),
        (dict(node_mass=0.0), "node_mass"),
        (dict(node_mass=-2.0), "node_mass"),
        (dict(node_mass=np.ones(M_ELL - 1)), "node_mass"),
        (dict(node_mass=np.ones((M_ELL, 1))), "node_mass"),
        (dict(node_mass=np.r_[np.ones(M_ELL - 1), 0.0]), "node_mass"),
        (dict(node_mass=np.r_[np.ones(M_ELL - 1), np.nan]), "node_mass"),
        (dict(node_mass=np.r_[-1.0, np.ones(M_ELL - 1)]), "node_mass"),
        (dict(integrator="rk4"), "integrator"),
        (dict(pinned=[0, M_ELL]), "pinned"),
        (dict(pinned=[-1]), "pinned"),
        (dict(pinned=list(range(M_ELL))), "pinned"),
        (dict(pinned=np.ones(M_ELL, dtype=bool)), "pinned"),
        (dict(pinned=np.ones(5, dtype=bool)), "pinned"),
        (dict(pinned=[0.5, 1.5]), "pinned"),
        (dict(damping=1.0), "damping"),
        (dict(damping=1.5), "damping"),
        (dict(damping=-0.1), "damping"),
        (dict(damping="0.1"), "damping"),
        (dict(projection="yes"), "projection"),
        (dict(projection=1), "projection"),
        (dict(gravity=(0, -9.81)), "gravity"),
        (dict(gravity=(0, 0, -9.81, 0)), "gravity"),
        (dict(gravity=(0, 0, float("nan"))), "gravity"),
        (dict(gravity="down"), "gravity"),
        (dict(threads=0), "threads"),
        (dict(material="rubber"), "material"),
    ],
)
def test_simulation_bad_parameter(kwargs, name):
    with pytest.raises(fepr.ConfigError) as info:
        make(**kwargs)
    assert name in str(info.value)


@pytest.mark.parametrize("integrator", ["implicit_euler", "projective_dynamics", "xpbd"])
def test_step_damping_factor_is_refused_by_integrators_that_would_ignore_it(integrator):
    # The seed's per-step factor is applied by symplectic Euler only; elsewhere it used to be ignored silently.
    with pytest.raises(fepr.ConfigError, match=rf"damping.*{integrator}.*air_damping"):
        make(damping=0.01, integrator=integrator)
    make(damping=0.0, integrator=integrator)
    make(damping=0.01, integrator="symplectic_euler")


def test_simulation_bad_mesh_type():
    with pytest.raises(fepr.ConfigError, match="mesh"):
        fepr.Simulation((V, T), material=SOFT, node_mass=1.0, dt=0.01)


def test_simulation_pinned_error_names_vertex():
    with pytest.raises(fepr.ConfigError, match=rf"\b{M_ELL + 3}\b"):
        make(pinned=[1, 2, M_ELL + 3])
    with pytest.raises(fepr.ConfigError, match=r"vertex 3\b"):
        make(node_mass=np.r_[1.0, 1.0, 1.0, 0.0, np.ones(M_ELL - 4)])


@pytest.mark.parametrize("n", [-1, 1.5, "3", True])
def test_step_bad_count(n):
    sim = make()
    with pytest.raises(fepr.ConfigError, match="n must be"):
        sim.step(n)
    assert sim.num_steps == 0


# ----------------------------------------------------------------------------------------------------
# mesh files


NODE_1BASED = "5 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 1 1 1\n"


def test_tetgen_one_based_reference_to_node_zero(tmp_path):
    (tmp_path / "m.node").write_text(NODE_1BASED)
    (tmp_path / "m.ele").write_text("2 4 0\n1 1 2 3 4\n2 0 2 3 4\n")
    with pytest.raises(fepr.MeshError) as info:
        fepr.load_mesh(tmp_path / "m.node")
    msg = str(info.value)
    assert str(tmp_path / "m.ele") in msg
    assert re.search(r"\belement 2\b", msg), msg
    assert re.search(r"\bnode 0\b", msg), msg
    assert re.search(r"\bline 3\b", msg), msg


def test_tetgen_one_based_valid_file_loads(tmp_path):
    (tmp_path / "m.node").write_text(NODE_1BASED)
    (tmp_path / "m.ele").write_text("2 4 0\n1 1 2 3 4\n2 2 3 4 5\n")
    mesh = fepr.load_mesh(tmp_path / "m.node")
    np.testing.assert_array_equal(mesh.tets, T)


def test_tetgen_truncated_ele_missing_lines(tmp_path):
    (tmp_path / "t.node").write_text(NODE_1BASED)
    (tmp_path / "t.ele").write_text("3 4 0\n1 1 2 3 4\n2 2 3 4 5\n")
    with pytest.raises(fepr.MeshError) as info:
        fepr.load_mesh(tmp_path / "t.node")
    msg = str(info.value)
    assert str(tmp_path / "t.ele") in msg
    assert "truncated" in msg
    assert re.search(r"\bline \d+", msg), msg


def test_tetgen_truncated_ele_short_line(tmp_path):
    (tmp_path / "u.node").write_text(NODE_1BASED)
    (tmp_path / "u.ele").write_text("2 4 0\n1 1 2 3 4\n2 2 3")
    with pytest.raises(fepr.MeshError) as info:
        fepr.load_mesh(tmp_path / "u.ele")
    msg = str(info.value)
    assert str(tmp_path / "u.ele") in msg
    assert re.search(r"\bline 3\b", msg), msg


# ----------------------------------------------------------------------------------------------------
# materials by finite differences


def _fd_piola(mat, F, h=1e-6):
    P = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            Fp, Fm = F.copy(), F.copy()
            Fp[i, j] += h
            Fm[i, j] -= h
            P[i, j] = (mat.energy_density(Fp) - mat.energy_density(Fm)) / (2 * h)
    return P


def _fd_stress_derivative(mat, F, h=1e-6):
    D = np.zeros((9, 9))
    for i in range(3):
        for j in range(3):
            Fp, Fm = F.copy(), F.copy()
            Fp[i, j] += h
            Fm[i, j] -= h
            D[:, 3 * i + j] = ((mat.first_piola(Fp) - mat.first_piola(Fm)) / (2 * h)).ravel()
    return D


_rng = np.random.default_rng(12345)
F_GENERAL = np.eye(3) + 0.3 * _rng.normal(size=(3, 3))
F_SQUASHED = np.diag([0.4, 0.3, 0.5]) + 0.02 * _rng.normal(size=(3, 3))  # 0 < J < j0 = 0.1
F_INVERTED = np.diag([1.1, 0.9, -0.5]) + 0.05 * _rng.normal(size=(3, 3))  # J < 0
F_CASES = {"general": F_GENERAL, "J<j0": F_SQUASHED, "J<0": F_INVERTED}
MATERIALS = {
    "neo_hookean": fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
    "neo_hookean_j0_0.5": fepr.NeoHookean(youngs_modulus=2e4, poisson_ratio=0.45, j0=0.5),
    "stable_neo_hookean": fepr.StableNeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
}


def test_fd_cases_are_in_the_intended_regimes():
    assert np.linalg.det(F_GENERAL) > 0.5
    assert 0 < np.linalg.det(F_SQUASHED) < 0.1
    assert np.linalg.det(F_INVERTED) < 0


@pytest.mark.parametrize("case", list(F_CASES))
@pytest.mark.parametrize("mat_name", list(MATERIALS))
def test_first_piola_matches_finite_differences(mat_name, case):
    mat, F = MATERIALS[mat_name], F_CASES[case]
    P = mat.first_piola(F)
    assert P.shape == (3, 3)
    assert np.all(np.isfinite(P)) and np.isfinite(mat.energy_density(F))
    fd = _fd_piola(mat, F)
    assert np.abs(P - fd).max() <= 1e-5 * np.abs(P).max()


@pytest.mark.parametrize("case", list(F_CASES))
@pytest.mark.parametrize("mat_name", list(MATERIALS))
def test_stress_derivative_matches_finite_differences(mat_name, case):
    mat, F = MATERIALS[mat_name], F_CASES[case]
    D = mat.stress_derivative(F)
    assert D.shape == (9, 9)
    fd = _fd_stress_derivative(mat, F)
    assert np.abs(D - fd).max() <= 1e-5 * np.abs(D).max()
    # dP/dF of a hyperelastic energy is symmetric (a Hessian)
    np.testing.assert_allclose(D, D.T, rtol=0, atol=1e-10 * np.abs(D).max())


@pytest.mark.parametrize("mat_name", list(MATERIALS))
def test_material_batched_evaluation_matches_single(mat_name):
    mat = MATERIALS[mat_name]
    Fs = np.stack(list(F_CASES.values()))
    psi = mat.energy_density(Fs)
    P = mat.first_piola(Fs)
    D = mat.stress_derivative(Fs)
    assert psi.shape == (3,) and P.shape == (3, 3, 3) and D.shape == (3, 9, 9)
    for k, F in enumerate(Fs):
        assert psi[k] == mat.energy_density(F)
        np.testing.assert_array_equal(P[k], mat.first_piola(F))
        np.testing.assert_array_equal(D[k], mat.stress_derivative(F))
    assert mat.energy_density(np.eye(3)) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(mat.first_piola(np.eye(3)), 0.0, atol=1e-9)


@pytest.mark.parametrize("mat_name", list(MATERIALS))
def test_mesh_gradient_matches_finite_differences(mat_name):
    mat = MATERIALS[mat_name]
    mesh = fepr.meshes.box(resolution=2)
    sim = fepr.Simulation(mesh, material=mat, node_mass=1.0, dt=0.01, projection=False)
    rng = np.random.default_rng(7)
    x = 1.1 * mesh.vertices + 0.04 * rng.normal(size=mesh.vertices.shape)
    energy, grad = sim.elastic_energy_gradient(x)
    grad = np.asarray(grad)
    assert grad.shape == (mesh.num_vertices, 3)
    assert energy > 0
    sim.positions = x
    assert sim.energy().elastic == pytest.approx(energy, rel=1e-12)
    h = 1e-6
    fd = np.zeros_like(grad)
    for i in range(mesh.num_vertices):
        for a in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, a] += h
            xm[i, a] -= h
            fd[i, a] = (sim.elastic_energy_gradient(xp)[0] - sim.elastic_energy_gradient(xm)[0]) / (2 * h)
    assert np.abs(grad - fd).max() <= 1e-5 * np.abs(grad).max()
    # translation invariance: the elastic forces sum to zero
    np.testing.assert_allclose(grad.sum(axis=0), 0.0, atol=1e-10 * np.abs(grad).max())


# ----------------------------------------------------------------------------------------------------
# regression: non-numeric arrays once reached NumPy / the core and came out as a bare ValueError, not ConfigError


def test_simulation_non_numeric_node_mass_array():
    with pytest.raises(fepr.ConfigError, match="node_mass"):
        make(node_mass=["a"] * M_ELL)


@pytest.mark.parametrize("name", ["positions", "velocities"])
def test_state_assignment_non_numeric(name):
    sim = make()
    with pytest.raises(fepr.ConfigError, match=name):
        setattr(sim, name, [["a", "b", "c"]] * M_ELL)


def test_elastic_energy_gradient_bad_shape():
    sim = make()
    with pytest.raises(fepr.ConfigError, match="shape"):
        sim.elastic_energy_gradient(np.zeros((3, 3)))
