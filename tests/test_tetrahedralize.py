"""Tests of fepr.tetrahedralize and `fepr mesh`: surfaces to tets with TetGen (and fTetWild when installed)."""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import fepr
from conftest import shared_meshes_dir
from fepr import tetrahedralize
from fepr.cli import main
from fepr.errors import ConfigError, MeshError, MissingDependencyError
from fepr.io import read_arrays, read_surface
from fepr.io.surface import surface_volume

HAS_TETGEN = importlib.util.find_spec("tetgen") is not None
HAS_PYTETWILD = importlib.util.find_spec("pytetwild") is not None
needs_tetgen = pytest.mark.skipif(
    not HAS_TETGEN, reason='the optional mesher package "tetgen" is not installed (pip install "fepr[mesh]")'
)
needs_pytetwild = pytest.mark.skipif(
    not HAS_PYTETWILD, reason='the optional mesher package "pytetwild" is not installed (pip install "fepr[ftetwild]")'
)
SHARED = shared_meshes_dir()
needs_shared = pytest.mark.skipif(SHARED is None, reason="shared test meshes (../shared/meshes) not found")


def cube_surface(size: float = 1.0):
    """The surface of a cube [0, size]^3: 8 vertices, 12 outward triangles."""
    v = size * np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    f = []
    for a, b, c, d in quads:
        f += [(a, b, c), (a, c, d)]
    return v, np.array(f, dtype=np.int64)


def icosphere(subdivisions: int = 1, radius: float = 1.0):
    t = (1.0 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t)]
    v += [(t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2)]
    faces += [(10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5)]
    faces += [(2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(subdivisions):
        cache: dict = {}

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    return radius * np.array(verts), np.array(faces, dtype=np.int64)


def write_obj(path: Path, v, f) -> Path:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(v).tolist()]
    lines += ["f " + " ".join(str(i + 1) for i in tri) for tri in np.asarray(f).tolist()]
    path.write_text("# test surface\n" + "\n".join(lines) + "\n")
    return path


def signed_volumes(mesh) -> np.ndarray:
    p = mesh.vertices[mesh.tets]
    return np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6.0


def mesh_quietly(*args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # mesher output must need no repair warning
        return tetrahedralize(*args, **kwargs)


# ----------------------------------------------------------------------------------------------------
# TetGen


@needs_tetgen
@pytest.mark.parametrize("shape", ["cube", "icosphere"])
def test_tetgen_fills_the_surface_exactly(shape):
    v, f = cube_surface(2.0) if shape == "cube" else icosphere(2, 0.5)
    mesh = mesh_quietly((v, f))
    assert isinstance(mesh, fepr.TetMesh)
    vols = signed_volumes(mesh)
    assert np.all(vols > 0)
    # TetGen keeps the surface: the tets fill exactly the enclosed volume
    assert vols.sum() == pytest.approx(surface_volume(v, f), rel=1e-10)
    info = fepr.mesh_info(mesh)
    assert info.closed and info.inverted == 0 and info.degenerate == 0 and info.unreferenced_vertices == 0
    assert mesh.source == "surface (tetgen)"


@needs_tetgen
def test_tetgen_max_volume_and_edge_length_bound_the_tets():
    v, f = cube_surface(1.0)
    coarse = mesh_quietly((v, f))
    fine = mesh_quietly((v, f), max_volume=1e-3)
    assert fine.num_tets > coarse.num_tets
    # TetGen's -a bound holds during refinement; its final mesh improvement may exceed it a little
    assert fine.volumes().mean() < 1e-3 and fine.volumes().max() < 1.5e-3
    by_edge = mesh_quietly((v, f), edge_length=0.1)
    bound = 0.1**3 / (6 * 2**0.5)
    assert by_edge.volumes().mean() < bound and by_edge.volumes().max() < 1.5 * bound


@needs_tetgen
def test_tetgen_quality_bound_changes_the_mesh():
    v, f = icosphere(2)
    loose = fepr.mesh_info(mesh_quietly((v, f), quality=3.0))
    tight = fepr.mesh_info(mesh_quietly((v, f), quality=1.2))
    assert tight.num_tets > loose.num_tets  # a tighter radius-edge bound inserts more points
    assert tight.degenerate == loose.degenerate == 0


@needs_tetgen
@pytest.mark.parametrize("ext", [".obj", ".off", ".stl", ".ply"])
def test_tetrahedralize_reads_surface_files(tmp_path, ext):
    v, f = icosphere(1)
    path = tmp_path / f"ball{ext}"
    if ext == ".obj":
        write_obj(path, v, f)
    else:
        import meshio

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            meshio.write(str(path), meshio.Mesh(v, [("triangle", f)]))
    rv, rf = read_surface(path)
    assert rf.shape == (80, 3)
    mesh = mesh_quietly(path)
    assert mesh.source == f"{path} (tetgen)"
    assert mesh.volumes().sum() == pytest.approx(surface_volume(v, f), rel=1e-6)


@needs_tetgen
@needs_shared
def test_bunny_obj_tetrahedralizes():
    mesh = mesh_quietly(SHARED / "bunny.obj")
    info = fepr.mesh_info(mesh)
    assert info.closed and info.inverted == 0 and info.degenerate == 0
    assert 10_000 < mesh.num_tets < 100_000
    assert info.volume == pytest.approx(7.447e-4, rel=1e-3)  # SOURCES.md: the surface encloses 7.447e-4
    assert info.quality_min > 1e-3


# ----------------------------------------------------------------------------------------------------
# bad surfaces: a clear error before the mesher runs


def _open_cube():
    v, f = cube_surface()
    return v, f[:-1]


def _nonmanifold():
    v, f = cube_surface()
    # a fin: one more triangle on the edge (0, 1), making it shared by three triangles
    v = np.vstack([v, [[0.5, -1.0, -1.0]]])
    return v, np.vstack([f, [[0, 1, 8]]])


def _degenerate():
    v, f = cube_surface()
    return v, np.vstack([f, [[0, 0, 1]]])


def _duplicate():
    v, f = cube_surface()
    return v, np.vstack([f, f[:1]])


@pytest.mark.parametrize(
    "make, pattern",
    [
        (_open_cube, r"open: 3 edge\(s\) belong to only one triangle"),
        (_nonmanifold, r"non-manifold: 1 edge\(s\) are shared by three or more triangles \(first: vertices \[0, 1\]"),
        (_degenerate, r"1 triangle\(s\) repeat a vertex"),
        (_duplicate, r"1 duplicate triangle"),
    ],
    ids=["open", "non-manifold", "degenerate", "duplicate"],
)
def test_bad_surface_is_a_clear_mesh_error(make, pattern):
    with pytest.raises(MeshError, match=r"surface: cannot tetrahedralize: .*" + pattern):
        tetrahedralize(make())


def test_bad_surface_file_names_the_file(tmp_path):
    v, f = _open_cube()
    path = write_obj(tmp_path / "open.obj", v, f)
    with pytest.raises(MeshError, match=r"open\.obj: cannot tetrahedralize: the surface is open"):
        tetrahedralize(path)


@needs_tetgen
def test_self_intersecting_surface_is_a_mesh_error():
    a_v, a_f = cube_surface(1.0)
    b_v, b_f = cube_surface(1.0)
    v = np.vstack([a_v, b_v + 0.5])  # two overlapping closed cubes in one surface
    f = np.vstack([a_f, b_f + 8])
    with pytest.raises(MeshError, match=r"surface: TetGen failed: .*self-intersect.*ftetwild"):
        tetrahedralize((v, f))


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(max_volume=1.0, edge_length=1.0), "at most one of max_volume and edge_length"),
        (dict(max_volume=0.0), "max_volume"),
        (dict(max_volume=-1.0), "max_volume"),
        (dict(edge_length=float("nan")), "edge_length"),
        (dict(edge_length="1"), "edge_length"),
        (dict(quality=1.0), "quality"),
        (dict(quality=True), "quality"),
        (dict(mesher="gmsh"), "mesher must be one of 'tetgen', 'ftetwild'"),
        (dict(mesher="ftetwild", quality=1.5), "quality .* applies to mesher='tetgen' only"),
    ],
)
def test_invalid_options_are_config_errors(kwargs, pattern):
    with pytest.raises(ConfigError, match=pattern):
        tetrahedralize(cube_surface(), **kwargs)


@pytest.mark.parametrize(
    "surface, pattern",
    [
        (42, "surface must be a path"),
        ((np.zeros((4, 2)), np.zeros((1, 3), int)), r"vertices must have shape \(n, 3\)"),
        ((np.zeros((4, 3)), np.zeros((1, 3))), "triangles must be integers"),
        ((np.array([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]])), "non-finite"),
        ((np.zeros((3, 3)), np.array([[0, 1, 3]])), "out of range"),
    ],
)
def test_invalid_surface_arrays(surface, pattern):
    with pytest.raises((MeshError, ConfigError), match=pattern):
        tetrahedralize(surface)


def test_missing_mesher_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "tetgen", None)  # makes `import tetgen` raise ImportError
    with pytest.raises(MissingDependencyError, match=r'pip install "fepr\[mesh\]"') as info:
        tetrahedralize(cube_surface())
    assert isinstance(info.value, ImportError) and isinstance(info.value, fepr.FeprError)


def test_mesher_output_orientation_is_normalised_without_warning(monkeypatch):
    """A mesher that emits negatively oriented tets (as fTetWild does) gives a positive mesh, silently."""
    box = fepr.meshes.box(resolution=2)
    flipped = box.tets[:, [0, 1, 3, 2]]
    extra = np.vstack([box.vertices, [[9.0, 9.0, 9.0]]])  # plus an unreferenced vertex

    def fake(v, f, max_volume, quality, where):
        return extra, flipped

    monkeypatch.setattr(sys.modules["fepr.mesher"], "_run_tetgen", fake)
    mesh = mesh_quietly(cube_surface())
    assert mesh.flipped_count == 0
    assert np.all(signed_volumes(mesh) > 0)
    assert mesh.num_vertices == box.num_vertices and mesh.unreferenced_count == 0
    np.testing.assert_array_equal(np.sort(mesh.tets, axis=1), np.sort(box.tets, axis=1))


# ----------------------------------------------------------------------------------------------------
# fTetWild (optional)


@needs_pytetwild
def test_ftetwild_gives_positive_tets_and_repairs_open_surfaces():
    v, f = cube_surface(1.0)
    mesh = mesh_quietly((v, f), mesher="ftetwild", edge_length=0.5)
    assert np.all(signed_volumes(mesh) > 0)
    assert mesh.volumes().sum() == pytest.approx(1.0, rel=0.05)
    with pytest.warns(UserWarning, match="the surface is open.*fTetWild repairs it"):
        repaired = tetrahedralize(_open_cube(), mesher="ftetwild", edge_length=0.5)
    assert np.all(signed_volumes(repaired) > 0)


# ----------------------------------------------------------------------------------------------------
# fepr mesh


@needs_tetgen
@pytest.mark.parametrize("out", ["ball.msh", "ball.vtu", "ball.vtk", "ball.mesh", "ball.npz", "ball.1.node"])
def test_cli_mesh_writes_every_format(tmp_path, capsys, out):
    src = write_obj(tmp_path / "ball.obj", *icosphere(1))
    dest = tmp_path / out
    assert main(["mesh", str(src), "-o", str(dest), "--max-volume", "0.05"]) == 0
    text = capsys.readouterr().out
    assert "tets (tetgen" in text and f"wrote {dest}" in text
    v, t = read_arrays(dest)
    mesh = fepr.load_mesh(dest)
    assert mesh.volumes().mean() < 0.05 and mesh.volumes().max() < 1.5 * 0.05
    assert mesh.num_tets == len(t)


@needs_tetgen
def test_cli_mesh_info_and_edge_length(tmp_path, capsys):
    src = write_obj(tmp_path / "cube.obj", *cube_surface())
    assert main(["mesh", str(src), "--info"]) == 0
    text = capsys.readouterr().out
    assert "triangles         12" in text and "closed" in text
    dest = tmp_path / "cube.vtu"
    assert main(["mesh", str(src), "-o", str(dest), "--edge-length", "0.25", "--quality", "1.5", "--info"]) == 0
    text = capsys.readouterr().out
    assert "volume            1" in text and "inverted tets     0" in text and "boundary" in text


def test_cli_mesh_errors(tmp_path, capsys):
    src = write_obj(tmp_path / "open.obj", *_open_cube())
    assert main(["mesh", str(src)]) == 2
    assert "give -o OUTPUT" in capsys.readouterr().err
    assert main(["mesh", str(src), "-o", str(tmp_path / "x.msh")]) == 2
    assert "the surface is open" in capsys.readouterr().err
    assert main(["mesh", str(src), "-o", str(tmp_path / "x.xyz")]) == 2
    assert main(["mesh", str(src), "--max-volume", "1", "--edge-length", "1", "-o", "x.msh"]) == 2
    assert main(["mesh", str(src), "--max-volume", "-1", "-o", "x.msh"]) == 2
    tet = tmp_path / "box.npz"
    fepr.io.write_mesh(fepr.meshes.box(), tet)
    assert main(["mesh", str(tet), "-o", str(tmp_path / "box.vtu"), "--max-volume", "1"]) == 2
    assert "apply to surfaces" in capsys.readouterr().err
    assert main(["mesh", str(tet), "-o", str(tmp_path / "box.vtu")]) == 0  # conversion
    np.testing.assert_array_equal(read_arrays(tmp_path / "box.vtu")[1], fepr.meshes.box().tets)
