"""Tests of fepr.mesh_info / MeshInfo and `fepr mesh INPUT --info`."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import fepr
from conftest import shared_meshes_dir
from fepr import MeshInfo, mesh_info, meshes
from fepr.cli import main
from fepr.errors import MeshError
from fepr.mesh_report import tet_quality

SHARED = shared_meshes_dir()
needs_shared = pytest.mark.skipif(SHARED is None, reason="shared test meshes (../shared/meshes) not found")

REGULAR = np.array([[1, 1, 1], [1, -1, -1], [-1, -1, 1], [-1, 1, -1]], dtype=float)  # [0, 1, 2, 3] positive


def write_tetgen(base: Path, v, t) -> Path:
    Path(f"{base}.node").write_text(
        f"{len(v)} 3 0 0\n" + "".join(f"{i} {x!r} {y!r} {z!r}\n" for i, (x, y, z) in enumerate(np.asarray(v).tolist()))
    )
    Path(f"{base}.ele").write_text(
        f"{len(t)} 4 0\n" + "".join(f"{i} {a} {b} {c} {d}\n" for i, (a, b, c, d) in enumerate(np.asarray(t).tolist()))
    )
    return base


def test_regular_tet_has_quality_one():
    q = tet_quality(REGULAR, np.array([[0, 1, 2, 3], [0, 1, 3, 2]]))
    np.testing.assert_allclose(q, [1.0, 1.0], rtol=1e-12)
    info = mesh_info((REGULAR, np.array([[0, 1, 2, 3]])))
    assert info.quality_min == pytest.approx(1.0) and info.quality_median == pytest.approx(1.0)
    assert info.volume == pytest.approx(8.0 / 3.0)
    assert info.boundary_faces == 4 and info.closed


@pytest.mark.parametrize("n", [1, 2, 3])
def test_box_report(n):
    info = mesh_info(meshes.box(size=(2.0, 1.0, 1.0), resolution=n))
    assert isinstance(info, MeshInfo) and info.kind == "tets"
    assert (info.num_vertices, info.num_tets) == ((n + 1) ** 3, 6 * n**3)
    assert info.bbox_min == (-1.0, -0.5, -0.5) and info.bbox_max == (1.0, 0.5, 0.5)
    assert info.size == (2.0, 1.0, 1.0)
    assert info.volume == pytest.approx(2.0, rel=1e-12)
    assert info.boundary_faces == 12 * n * n  # 6 sides, n^2 squares each, 2 triangles per square
    assert info.closed and info.open_edges == info.nonmanifold_edges == info.nonmanifold_faces == 0
    assert info.inverted == info.degenerate == info.unreferenced_vertices == 0
    # Kuhn tets of a 2:1:1 cell all have the same shape
    assert info.quality_min == pytest.approx(info.quality_median, rel=1e-12)
    assert info.source == "builtin:box"


def test_file_counts_inverted_and_degenerate_tets_before_repair(tmp_path):
    # tet 0 positive; tet 1 inverted (vertex 4 mirrors vertex 3 through the face 0 1 2); tet 2 flat: vertices
    # 0, 5, 6 are collinear; vertex 7 is unreferenced
    v = np.vstack([REGULAR, [[-1 / 3, 1 / 3, -1 / 3]], 2 * REGULAR[:1], 3 * REGULAR[:1], [[9.0, 9.0, 9.0]]])
    v[4] = v[:3].mean(axis=0) - (v[3] - v[:3].mean(axis=0))
    t = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 5, 6, 1]])
    base = write_tetgen(tmp_path / "bad.1", v, t)
    info = mesh_info(base)
    assert info.inverted == 1 and info.degenerate == 1
    assert info.unreferenced_vertices == 1  # vertex 6
    assert info.source == str(base)
    assert "inverted tets     1" in str(info) and "degenerate tets   1" in str(info)
    with pytest.raises(MeshError, match="degenerate"):
        fepr.load_mesh(base)  # loading rejects it; the report does not


def test_tetmesh_report_uses_its_repair_count():
    t = np.array([[0, 2, 1, 3]])  # negatively oriented
    with pytest.warns(UserWarning):
        mesh = fepr.TetMesh(REGULAR, t)
    info = mesh_info(mesh)
    assert info.inverted == 1 and info.degenerate == 0
    assert "repaired" in str(info)


def test_tets_sharing_only_an_edge_have_an_unclosed_boundary():
    # two tets that share the edge (0, 1) and nothing else: the edge is on 4 boundary faces
    v = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [1, 1, 0], [-1, 0, 0], [-1, -1, 0]], dtype=float)
    t = np.array([[0, 2, 3, 1], [0, 4, 5, 1]])
    negative = np.linalg.det(np.stack([v[t[:, i]] - v[t[:, 0]] for i in (1, 2, 3)], axis=2)) < 0
    t = np.where(negative[:, None], t[:, [0, 1, 3, 2]], t)
    info = mesh_info((v, t))
    assert info.boundary_faces == 8
    assert not info.closed and info.nonmanifold_edges == 1
    assert "OPEN" in str(info) and "1 non-manifold edges" in str(info)


def test_face_shared_by_three_tets_is_reported():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1], [0.3, 0.1, -1], [0.1, 0.3, 2]], dtype=float)
    t = np.array([[0, 1, 2, 3], [0, 2, 1, 4], [0, 1, 2, 5]])
    info = mesh_info((v, t))
    assert info.nonmanifold_faces == 1


def test_str_is_readable():
    text = str(mesh_info(meshes.ell()))
    keys = ("mesh: builtin:ell", "vertices          24", "tets              30", "bounding box", "volume            5")
    for key in keys:
        assert key in text, text
    assert "quality           min" in text and "boundary          " in text and "closed" in text


def test_surface_report(tmp_path):
    path = tmp_path / "tri.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 5 5 5\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n")
    info = mesh_info(path)
    assert info.kind == "surface" and info.boundary_faces == 4 and info.num_tets == 0
    assert info.closed and info.unreferenced_vertices == 1
    assert info.volume == pytest.approx(1.0 / 6.0)
    assert "triangles         4" in str(info)
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\n")
    info = mesh_info(path)
    assert not info.closed and info.open_edges == 3


@pytest.mark.parametrize(
    "arg, pattern",
    [
        ((np.zeros((4, 3)), np.array([[0, 1, 2, 4]])), "out of range"),
        ((np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([[0, 1, 2, 3]])), "non-finite"),
        ((np.zeros((4, 2)), np.array([[0, 1, 2, 3]])), "shape"),
        (42, "needs a TetMesh"),
    ],
)
def test_bad_input(arg, pattern):
    with pytest.raises(MeshError, match=pattern):
        mesh_info(arg)


def test_missing_file():
    with pytest.raises(MeshError, match="not found"):
        mesh_info("no/such/file.msh")


@needs_shared
@pytest.mark.parametrize(
    "rel, nv, nt, volume, qmin, qmed, bfaces",
    [
        ("bunny.msh", 4670, 19379, 6.0104, 0.0019, 0.289, 6266),
        ("little-elephant.msh", 7008, 24953, 15.801, 0.011, 0.287, 10466),
        ("Armadillo_Tetra_4406.vtu", 1446, 4406, 231.21, 0.0035, 0.314, 2532),
    ],
)
def test_shared_meshes_match_their_documented_numbers(rel, nv, nt, volume, qmin, qmed, bfaces):
    info = mesh_info(SHARED / rel)
    assert (info.num_vertices, info.num_tets, info.boundary_faces) == (nv, nt, bfaces)
    assert info.volume == pytest.approx(volume, rel=1e-4)
    # SOURCES.md rounds to 2 or 3 significant digits
    assert info.quality_min == pytest.approx(qmin, rel=0.03) and info.quality_median == pytest.approx(qmed, abs=6e-4)
    assert info.closed and info.inverted == 0 and info.degenerate == 0


@needs_shared
def test_shared_surface_reports_closed():
    info = mesh_info(SHARED / "elephant.obj")
    assert (info.num_vertices, info.boundary_faces) == (6034, 12064)
    assert info.closed and info.volume == pytest.approx(1.939e5, rel=1e-3)


def test_cli_info(tmp_path, capsys):
    base = write_tetgen(tmp_path / "two.1", np.vstack([REGULAR, [[2.0, 2.0, 2.0]]]), [[0, 1, 2, 3], [1, 2, 4, 3]])
    assert main(["mesh", str(base) + ".node", "--info"]) == 0
    out = capsys.readouterr().out
    assert "vertices          5" in out and "tets              2" in out
    assert main(["mesh", str(tmp_path / "nope.msh"), "--info"]) == 2
    assert "nope.msh: file not found" in capsys.readouterr().err


def test_quality_formula_on_a_random_tet():
    rng = np.random.default_rng(3)
    p = rng.normal(size=(4, 3))
    vol = abs(np.linalg.det(np.stack([p[1] - p[0], p[2] - p[0], p[3] - p[0]]))) / 6
    lmax = max(np.linalg.norm(p[i] - p[j]) for i in range(4) for j in range(i + 1, 4))
    assert tet_quality(p, np.array([[0, 1, 2, 3]]))[0] == pytest.approx(6 * math.sqrt(2) * vol / lmax**3)
