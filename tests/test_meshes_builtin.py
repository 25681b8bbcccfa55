"""Tests of the built-in procedural meshes (fepr.meshes): counts, volume, orientation, conformity, errors."""

from __future__ import annotations

import time
import warnings
from collections import Counter

import numpy as np
import pytest

from conftest import shared_meshes_dir
from fepr import meshes
from fepr.errors import ConfigError
from fepr.mesh import TetMesh

SHARED = shared_meshes_dir()


def _build(func, **kwargs) -> TetMesh:
    """Build a mesh, failing on any warning (an orientation repair would mean the generator is wrong)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = func(**kwargs)
    assert isinstance(mesh, TetMesh)
    assert mesh.flipped_count == 0
    return mesh


def _signed_volumes(mesh: TetMesh) -> np.ndarray:
    p = mesh.vertices[mesh.tets]
    d = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    return np.linalg.det(d) / 6.0


# The 4 faces of tet (a, b, c, d), each ordered so that its normal points out of the tet.
_OUTWARD_FACES = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))


def _boundary(mesh: TetMesh) -> np.ndarray:
    """Boundary triangles (faces of exactly one tet), outward oriented; asserts no face is in > 2 tets."""
    tets = mesh.tets
    faces = np.concatenate([tets[:, list(f)] for f in _OUTWARD_FACES], axis=0)
    keys = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    assert counts.max() <= 2, "a face is shared by more than two tets"
    inverse = inverse.ravel()
    boundary = faces[counts[inverse] == 1]
    # interior faces: 4k = 2 * interior + boundary
    assert 4 * len(tets) == 2 * int(np.sum(counts == 2)) + len(boundary)
    return boundary


def _check_closed_conforming_surface(mesh: TetMesh, volume: float, area: float) -> None:
    tri = _boundary(mesh)
    # each undirected edge of the boundary is used by exactly two boundary triangles, in opposite directions
    directed = Counter()
    for a, b, c in tri.tolist():
        directed[(a, b)] += 1
        directed[(b, c)] += 1
        directed[(c, a)] += 1
    assert all(n == 1 for n in directed.values()), "a directed boundary edge is used twice"
    assert all((b, a) in directed for (a, b) in directed), "boundary has an open edge"
    undirected = Counter(tuple(sorted(e)) for e in directed)
    assert set(undirected.values()) == {2}
    # genus 0: V - E + F = 2
    nverts = len(np.unique(tri))
    assert nverts - len(undirected) + len(tri) == 2
    # a non-conforming split would leave internal faces on the boundary and inflate its area
    p = mesh.vertices[tri]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert 0.5 * np.linalg.norm(cross, axis=1).sum() == pytest.approx(area, rel=1e-12)
    # outward orientation: divergence theorem gives the enclosed volume
    assert np.einsum("ij,ij->", p[:, 0], cross) / 6.0 == pytest.approx(volume, rel=1e-12)


def _check_vertices(mesh: TetMesh) -> None:
    assert mesh.vertices.dtype == np.float64 and mesh.tets.dtype == np.int64
    assert len(np.unique(mesh.vertices, axis=0)) == mesh.num_vertices, "duplicate vertices"
    assert mesh.unreferenced_count == 0
    assert np.array_equal(np.unique(mesh.tets), np.arange(mesh.num_vertices))


# ----------------------------------------------------------------------------------------------------
# box


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_box_counts(n):
    mesh = _build(meshes.box, resolution=n)
    assert mesh.num_vertices == (n + 1) ** 3
    assert mesh.num_tets == 6 * n**3
    _check_vertices(mesh)


def test_box_anisotropic_resolution_and_size():
    size, res, center = (2.0, 0.5, 3.0), (4, 1, 3), (1.0, -2.0, 0.25)
    mesh = _build(meshes.box, size=size, resolution=res, center=center)
    assert mesh.num_vertices == 5 * 2 * 4
    assert mesh.num_tets == 6 * 4 * 1 * 3
    vols = _signed_volumes(mesh)
    assert np.all(vols > 0)
    cell = (2.0 / 4) * (0.5 / 1) * (3.0 / 3)
    np.testing.assert_allclose(vols, cell / 6.0, rtol=1e-12)  # all 6 Kuhn tets of a cell have equal volume
    assert vols.sum() == pytest.approx(np.prod(size), rel=1e-12)
    lo, hi = mesh.bounding_box()
    np.testing.assert_allclose(lo, np.array(center) - np.array(size) / 2, atol=1e-15)
    np.testing.assert_allclose(hi, np.array(center) + np.array(size) / 2, atol=1e-15)
    # grid coordinates: exactly res+1 distinct values per axis
    for axis in range(3):
        assert len(np.unique(mesh.vertices[:, axis])) == res[axis] + 1
    _check_vertices(mesh)


@pytest.mark.parametrize("size, res", [(1.0, 1), ((1.0, 2.0, 0.5), 2), (0.3, (3, 2, 4))])
def test_box_is_conforming_with_closed_boundary(size, res):
    mesh = _build(meshes.box, size=size, resolution=res)
    s = np.broadcast_to(np.asarray(size, dtype=float), (3,))
    volume = float(np.prod(s))
    area = 2.0 * (s[0] * s[1] + s[1] * s[2] + s[0] * s[2])
    assert mesh.volumes().sum() == pytest.approx(volume, rel=1e-12)
    _check_closed_conforming_surface(mesh, volume, area)


def test_box_defaults():
    mesh = _build(meshes.box)
    assert (mesh.num_vertices, mesh.num_tets) == (27, 48)
    lo, hi = mesh.bounding_box()
    np.testing.assert_array_equal(lo, [-0.5, -0.5, -0.5])
    np.testing.assert_array_equal(hi, [0.5, 0.5, 0.5])


def test_box_accepts_numpy_scalars_and_is_deterministic():
    a = _build(meshes.box, size=np.float64(2.0), resolution=np.int64(2), center=np.zeros(3))
    b = _build(meshes.box, size=2.0, resolution=(2, 2, 2), center=(0, 0, 0))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.tets, b.tets)


# ----------------------------------------------------------------------------------------------------
# ell

ELL_CELLS = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 1, 1), (0, 1, 2)]  # unit cells, as in the seed's ellell.1


def _ell_vertex_count(r: int) -> int:
    footprint = (2 * r + 1) ** 2 - r**2  # lattice points of the L footprint
    return footprint * (r + 1) + 2 * r * (r + 1) ** 2


@pytest.mark.parametrize("r", [1, 2, 3])
def test_ell_counts(r):
    mesh = _build(meshes.ell, resolution=r)
    assert mesh.num_tets == 30 * r**3
    assert mesh.num_vertices == _ell_vertex_count(r)
    _check_vertices(mesh)
    assert _ell_vertex_count(1) == 24


@pytest.mark.parametrize("size, r", [(1.0, 1), (0.5, 2), (2.0, 3), (1.5, 1)])
def test_ell_volume_bbox_and_conformity(size, r):
    mesh = _build(meshes.ell, size=size, resolution=r)
    vols = _signed_volumes(mesh)
    assert np.all(vols > 0)
    np.testing.assert_allclose(vols, (size / r) ** 3 / 6.0, rtol=1e-12)
    assert vols.sum() == pytest.approx(5.0 * size**3, rel=1e-12)
    lo, hi = mesh.bounding_box()
    np.testing.assert_array_equal(lo, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(hi, [2.0 * size, 2.0 * size, 3.0 * size], rtol=1e-15)
    # surface: L prism (2*3 + 8*1 = 14) plus the column's 4 sides (8); its top replaces the covered L top
    _check_closed_conforming_surface(mesh, 5.0 * size**3, 22.0 * size**2)


def test_ell_occupies_the_seed_cells():
    mesh = _build(meshes.ell, resolution=2)
    centroids = mesh.vertices[mesh.tets].mean(axis=1)
    cell_of = np.floor(centroids).astype(int)
    per_cell = Counter(map(tuple, cell_of.tolist()))
    assert set(per_cell) == set(ELL_CELLS)
    vols = mesh.volumes()
    for cell in ELL_CELLS:
        in_cell = np.all(cell_of == np.array(cell), axis=1)
        assert vols[in_cell].sum() == pytest.approx(1.0, rel=1e-12)


@pytest.mark.skipif(SHARED is None, reason="shared seed meshes not found (../shared/meshes or FEPR_SHARED_MESHES)")
def test_ell_matches_seed_ellell_geometry():
    from fepr.io import load_mesh

    seed = load_mesh(SHARED / "seed" / "ellell.1")
    mesh = _build(meshes.ell, resolution=1)
    ours = {tuple(v) for v in mesh.vertices.tolist()}
    assert {tuple(v) for v in seed.vertices.tolist()} <= ours
    # every seed tet lies in the cells of our L (its centroid, and its corners' bounding box)
    centroids = seed.vertices[seed.tets].mean(axis=1)
    cells = {tuple(c) for c in np.floor(centroids).astype(int).tolist()}
    assert cells <= set(ELL_CELLS)
    assert seed.volumes().sum() == pytest.approx(mesh.volumes().sum(), rel=1e-12)
    np.testing.assert_array_equal(seed.bounding_box()[1], mesh.bounding_box()[1])


# ----------------------------------------------------------------------------------------------------
# argument validation and the registry


@pytest.mark.parametrize(
    "func, kwargs, param",
    [
        (meshes.box, dict(size=0.0), "size"),
        (meshes.box, dict(size=-1.0), "size"),
        (meshes.box, dict(size=float("nan")), "size"),
        (meshes.box, dict(size=float("inf")), "size"),
        (meshes.box, dict(size=(1.0, 2.0)), "size"),
        (meshes.box, dict(size=(1.0, 0.0, 1.0)), r"size\[1\]"),
        (meshes.box, dict(size="1"), "size"),
        (meshes.box, dict(size=True), "size"),
        (meshes.box, dict(resolution=0), "resolution"),
        (meshes.box, dict(resolution=-2), "resolution"),
        (meshes.box, dict(resolution=1.5), "resolution"),
        (meshes.box, dict(resolution=2.0), "resolution"),
        (meshes.box, dict(resolution=True), "resolution"),
        (meshes.box, dict(resolution=(2, 0, 2)), r"resolution\[1\]"),
        (meshes.box, dict(resolution=(2, 2)), "resolution"),
        (meshes.box, dict(center=(0.0, 0.0)), "center"),
        (meshes.box, dict(center=1.0), "center"),
        (meshes.box, dict(center=(0.0, float("nan"), 0.0)), r"center\[1\]"),
        (meshes.ell, dict(size=0), "size"),
        (meshes.ell, dict(size=-0.5), "size"),
        (meshes.ell, dict(size="big"), "size"),
        (meshes.ell, dict(size=(1.0, 1.0, 1.0)), "size"),
        (meshes.ell, dict(resolution=0), "resolution"),
        (meshes.ell, dict(resolution=1.0), "resolution"),
        (meshes.ell, dict(resolution=None), "resolution"),
    ],
)
def test_invalid_arguments_raise_config_error_naming_the_parameter(func, kwargs, param):
    with pytest.raises(ConfigError, match=param):
        func(**kwargs)


@pytest.mark.parametrize(
    "func, kwargs", [(meshes.box, dict(resolution=100_000)), (meshes.ell, dict(resolution=10_000))]
)
def test_huge_resolution_is_refused_before_allocating(func, kwargs):
    start = time.perf_counter()
    with pytest.raises(ConfigError, match="resolution too large"):
        func(**kwargs)
    assert time.perf_counter() - start < 1.0


def test_builtin_registry():
    assert set(meshes.BUILTIN) == {"box", "ell", "sphere", "cylinder"}
    assert meshes.BUILTIN["box"] is meshes.box and meshes.BUILTIN["ell"] is meshes.ell
    assert meshes.BUILTIN["sphere"] is meshes.sphere and meshes.BUILTIN["cylinder"] is meshes.cylinder
    a = meshes.builtin("box", size=(1.0, 2.0, 3.0), resolution=2)
    b = meshes.box(size=(1.0, 2.0, 3.0), resolution=2)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.tets, b.tets)
    assert meshes.builtin("ell", size=0.5).num_tets == 30


def test_builtin_unknown_name_lists_known_ones():
    with pytest.raises(ConfigError) as info:
        meshes.builtin("torus")
    msg = str(info.value)
    assert "'torus'" in msg and "box" in msg and "ell" in msg and "sphere" in msg and "cylinder" in msg


def test_builtin_unknown_parameter():
    with pytest.raises(ConfigError, match="'radius'.*size, resolution"):
        meshes.builtin("ell", radius=1.0)
    with pytest.raises(ConfigError, match="resolution"):
        meshes.builtin("box", resolution=0)


# ----------------------------------------------------------------------------------------------------
# sphere and cylinder (procedural: no mesher needed)


def _closed_manifold_boundary(mesh: TetMesh) -> np.ndarray:
    """Boundary triangles, asserting that the boundary is closed, consistently outward and genus 0."""
    tri = _boundary(mesh)
    directed = Counter()
    for a, b, c in tri.tolist():
        directed[(a, b)] += 1
        directed[(b, c)] += 1
        directed[(c, a)] += 1
    assert all(n == 1 for n in directed.values())
    assert all((b, a) in directed for (a, b) in directed)
    nverts = len(np.unique(tri))
    assert nverts - len(directed) // 2 + len(tri) == 2
    return tri


@pytest.mark.parametrize("n", [1, 2, 3, 4, 8])
def test_sphere_counts_orientation_and_surface(n):
    mesh = _build(meshes.sphere, radius=0.5, resolution=n)
    assert (mesh.num_vertices, mesh.num_tets) == ((n + 1) ** 3, 6 * n**3)
    _check_vertices(mesh)
    assert np.all(_signed_volumes(mesh) > 0)
    tri = _closed_manifold_boundary(mesh)
    on_surface = np.unique(tri)
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices[on_surface], axis=1), 0.5, rtol=1e-12)
    inside = np.setdiff1d(np.arange(mesh.num_vertices), on_surface)
    assert np.all(np.linalg.norm(mesh.vertices[inside], axis=1) < 0.5 - 1e-9)


def test_sphere_volume_quality_and_symmetry():
    mesh = _build(meshes.sphere, radius=2.0, resolution=8, center=(1.0, -1.0, 0.5))
    exact = 4.0 / 3.0 * np.pi * 2.0**3
    assert mesh.volumes().sum() == pytest.approx(exact, rel=0.02)  # inscribed polyhedron: a little smaller
    assert mesh.volumes().sum() < exact
    np.testing.assert_allclose(mesh.vertices.mean(axis=0), [1.0, -1.0, 0.5], atol=1e-12)
    from fepr.mesh_report import mesh_info

    info = mesh_info(mesh)
    assert info.quality_min > 0.15 and info.quality_median > 0.4 and info.degenerate == 0
    # the octant-mirrored split is symmetric under x -> -x
    v = mesh.vertices - [1.0, -1.0, 0.5]
    keys = {tuple(np.round(p, 12)) for p in v.tolist()}
    assert {(-x, y, z) for x, y, z in keys} == keys


@pytest.mark.parametrize("n, radius, height", [(1, 0.25, 1.0), (4, 0.25, 1.0), (8, 0.5, 0.2), (3, 1.0, 3.0)])
def test_cylinder(n, radius, height):
    mesh = _build(meshes.cylinder, radius=radius, height=height, resolution=n)
    nz = max(1, round(n * height / (2 * radius)))
    assert (mesh.num_vertices, mesh.num_tets) == ((n + 1) ** 2 * (nz + 1), 6 * n * n * nz)
    _check_vertices(mesh)
    assert np.all(_signed_volumes(mesh) > 0)
    _closed_manifold_boundary(mesh)
    lo, hi = mesh.bounding_box()
    assert lo[2] == pytest.approx(-height / 2) and hi[2] == pytest.approx(height / 2)
    assert np.linalg.norm(mesh.vertices[:, :2], axis=1).max() == pytest.approx(radius)
    exact = np.pi * radius**2 * height
    assert mesh.volumes().sum() <= exact
    if n >= 4:
        assert mesh.volumes().sum() == pytest.approx(exact, rel=0.03)


@pytest.mark.parametrize(
    "func, kwargs, param",
    [
        (meshes.sphere, dict(radius=0.0), "radius"),
        (meshes.sphere, dict(radius="1"), "radius"),
        (meshes.sphere, dict(resolution=0), "resolution"),
        (meshes.sphere, dict(resolution=2.5), "resolution"),
        (meshes.sphere, dict(center=(0, 0)), "center"),
        (meshes.sphere, dict(resolution=10_000), "resolution too large"),
        (meshes.cylinder, dict(radius=-1.0), "radius"),
        (meshes.cylinder, dict(height=float("nan")), "height"),
        (meshes.cylinder, dict(resolution=True), "resolution"),
        (meshes.cylinder, dict(height=1e12, radius=1e-12), "too large"),
    ],
)
def test_sphere_cylinder_invalid_arguments(func, kwargs, param):
    start = time.perf_counter()
    with pytest.raises(ConfigError, match=param):
        func(**kwargs)
    assert time.perf_counter() - start < 1.0


def test_sphere_and_cylinder_through_the_registry():
    a = meshes.builtin("sphere", radius=0.3, resolution=3)
    np.testing.assert_array_equal(a.vertices, meshes.sphere(radius=0.3, resolution=3).vertices)
    b = meshes.builtin("cylinder", height=2.0)
    assert b.source == "builtin:cylinder"
    with pytest.raises(ConfigError, match="'size'"):
        meshes.builtin("sphere", size=1.0)
