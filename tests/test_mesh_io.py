"""Tests of mesh file reading: fepr.io (TetGen natively, Gmsh / VTK / Medit via meshio, .npz)."""

from __future__ import annotations

import os
import re
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_meshes_dir
from fepr.errors import ConfigError, MeshError
from fepr.io import SUPPORTED_EXTENSIONS, load_mesh, read_meshio, read_npz, read_surface, read_tetgen
from fepr.mesh import TetMesh

# ----------------------------------------------------------------------------------------------------
# shared test meshes


SHARED = shared_meshes_dir()
needs_shared = pytest.mark.skipif(
    SHARED is None,
    reason="shared test meshes not found: expected ../shared/meshes next to the repository, "
    "or a directory named by FEPR_SHARED_MESHES",
)

# (relative path, vertices, tets, total volume in file units); counts and volumes from meshes/SOURCES.md and
# seed/SOURCES.md (volumes of the seed meshes computed once and fixed here).
SHARED_CASES = [
    ("bunny.msh", 4670, 19379, 6.0104),
    ("little-elephant.msh", 7008, 24953, 15.801),
    ("Armadillo_Tetra_4406.vtu", 1446, 4406, 231.21),
    ("seed/ellell.1", 20, 24, 5.0),
    ("seed/test_mesh.1", 52, 90, 16.17474),
    ("seed/monkey.1", 509, 3202, 3.532097),
    ("seed/bunny2.1", 7475, 29548, 7.497787e-4),
]


def _signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = vertices[tets]
    d = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    return np.linalg.det(d) / 6.0


@needs_shared
@pytest.mark.parametrize("rel, nv, nt, volume", SHARED_CASES, ids=[c[0] for c in SHARED_CASES])
def test_shared_mesh_loads_with_counts_and_positive_volumes(rel, nv, nt, volume):
    path = SHARED / rel
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no orientation repair needed: all files are positively oriented
        mesh = load_mesh(path)
    assert isinstance(mesh, TetMesh)
    assert (mesh.num_vertices, mesh.num_tets) == (nv, nt)
    assert mesh.vertices.dtype == np.float64 and mesh.tets.dtype == np.int64
    assert mesh.flipped_count == 0
    vols = _signed_volumes(mesh.vertices, mesh.tets)
    assert np.all(vols > 0)
    assert vols.sum() == pytest.approx(volume, rel=1e-4)
    assert mesh.source == os.fspath(path)


@needs_shared
@pytest.mark.parametrize("name", ["ellell.1", "test_mesh.1", "monkey.1", "bunny2.1"])
def test_seed_tetgen_matches_meshio_tetgen_reader(name):
    """An independent implementation (meshio's TetGen reader) gives the same arrays as ours."""
    meshio = pytest.importorskip("meshio")
    base = SHARED / "seed" / name
    v, t = read_tetgen(base)
    ref = meshio.tetgen.read(str(base) + ".node")
    np.testing.assert_array_equal(v, ref.points)
    np.testing.assert_array_equal(t, ref.cells_dict["tetra"])


# ----------------------------------------------------------------------------------------------------
# TetGen: a small two-tet mesh written by hand

V2 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float64)
T2 = np.array([[0, 1, 2, 3], [1, 2, 3, 4]], dtype=np.int64)

NODE0 = """5 3 0 0
0 0 0 0
1 1 0 0
2 0 1 0
3 0 0 1
4 1 1 1
"""
ELE0 = """2 4 0
0 0 1 2 3
1 1 2 3 4
"""
NODE1 = """5 3 0 0
1 0 0 0
2 1 0 0
3 0 1 0
4 0 0 1
5 1 1 1
"""
ELE1 = """2 4 0
1 1 2 3 4
2 2 3 4 5
"""


def _write(tmp_path: Path, node: str | None, ele: str | None, name: str = "m.1") -> Path:
    base = tmp_path / name
    if node is not None:
        Path(f"{base}.node").write_text(node)
    if ele is not None:
        Path(f"{base}.ele").write_text(ele)
    return base


@pytest.mark.parametrize("form", ["basename", ".node", ".ele", "pathlib", "str-basename"])
def test_tetgen_path_forms_read_the_same_mesh(tmp_path, form):
    base = _write(tmp_path, NODE0, ELE0)
    arg = {
        "basename": base,
        ".node": base.with_name("m.1.node"),
        ".ele": base.with_name("m.1.ele"),
        "pathlib": Path(f"{base}.node"),
        "str-basename": str(base),
    }[form]
    v, t = read_tetgen(arg)
    np.testing.assert_array_equal(v, V2)
    np.testing.assert_array_equal(t, T2)
    mesh = load_mesh(arg)
    np.testing.assert_array_equal(mesh.tets, T2)
    assert v.dtype == np.float64 and t.dtype == np.int64


def test_tetgen_one_based_numbering(tmp_path):
    v, t = read_tetgen(_write(tmp_path, NODE1, ELE1))
    np.testing.assert_array_equal(v, V2)
    np.testing.assert_array_equal(t, T2)


def test_tetgen_one_based_node_file_with_zero_reference_names_element_and_line(tmp_path):
    ele = """# element file with a 0-based reference
2 4 0

1 1 2 3 4
2 0 3 4 5
"""
    base = _write(tmp_path, NODE1, ele)
    with pytest.raises(MeshError) as info:
        read_tetgen(base)
    msg = str(info.value)
    assert "m.1.ele line 5" in msg
    assert "element 2 refers to node 0" in msg
    assert "1..5" in msg


def test_tetgen_non_contiguous_node_numbers_are_mapped(tmp_path):
    node = "5 3 0 0\n10 0 0 0\n20 1 0 0\n30 0 1 0\n40 0 0 1\n50 1 1 1\n"
    ele = "2 4 0\n0 10 20 30 40\n1 20 30 40 50\n"
    v, t = read_tetgen(_write(tmp_path, node, ele))
    np.testing.assert_array_equal(v, V2)
    np.testing.assert_array_equal(t, T2)
    bad = "2 4 0\n0 10 20 30 40\n1 20 30 40 45\n"
    with pytest.raises(MeshError, match=r"m\.2\.ele line 3: element 1 refers to node 45.*gaps"):
        read_tetgen(_write(tmp_path, node, bad, name="m.2"))


def test_tetgen_comments_attributes_markers_and_region_attributes(tmp_path):
    node = """# TetGen node file, 2 attributes and boundary markers

5  3  2  1   # header with a trailing comment
   0    0  0  0   0.5 -1   1
   1    1  0  0   0.5 -1   1  # trailing comment

# a full-line comment between data lines
   2    0  1  0   0.5 -1   0
   3    0  0  1   1e3 2.5  1
   4    1  1  1   0   0    0
# Generated by hand
"""
    ele = """2  4  1
    0     0  1  2  3    -7   # region attribute
    1     1  2  3  4    2.5
# trailer
"""
    v, t = read_tetgen(_write(tmp_path, node, ele))
    np.testing.assert_array_equal(v, V2)
    np.testing.assert_array_equal(t, T2)


def test_tetgen_ten_node_tets_keep_the_corners(tmp_path):
    # nodes 5..10: arbitrary extra (mid-edge) nodes, referenced only as the last 6 nodes of each tet
    extra = "".join(f"{i} {0.1 * i} 0.2 0.3\n" for i in range(5, 11))
    node = "11 3 0 0\n" + NODE0.split("\n", 1)[1] + extra
    ele = "2 10 0\n0 0 1 2 3 5 6 7 8 9 10\n1 1 2 3 4 10 9 8 7 6 5\n"
    v, t = read_tetgen(_write(tmp_path, node, ele))
    assert v.shape == (11, 3)
    np.testing.assert_array_equal(t, T2)
    mesh = load_mesh(tmp_path / "m.1")
    assert mesh.unreferenced_count == 6


def _replace_line(text: str, lineno: int, new: str) -> str:
    lines = text.split("\n")
    lines[lineno - 1] = new
    return "\n".join(lines)


# (case id, node text, ele text, file in message, expected regex)
TETGEN_ERRORS = [
    (
        "node-truncated",
        "\n".join(NODE0.split("\n")[:5]) + "\n",
        ELE0,
        "m.1.node",
        r"truncated.*declares 5 nodes.*only 4",
    ),
    ("ele-truncated", NODE0, "2 4 0\n0 0 1 2 3\n", "m.1.ele", r"truncated.*declares 2 tetrahedra.*only 1"),
    (
        "node-garbage",
        _replace_line(NODE0, 4, "2 0 abc 0"),
        ELE0,
        "m.1.node",
        r"line 4: coordinate y of node 2.*'abc'",
    ),
    ("node-underscore", _replace_line(NODE0, 4, "2 0 1_0 0"), ELE0, "m.1.node", r"line 4: .*'1_0'"),
    (
        "node-nan",
        _replace_line(NODE0, 3, "1 nan 0 0"),
        ELE0,
        "m.1.node",
        r"line 3: coordinate x of node 1 is not finite",
    ),
    (
        "node-inf",
        _replace_line(NODE0, 6, "4 1 1 -inf"),
        ELE0,
        "m.1.node",
        r"line 6: coordinate z of node 4 is not finite",
    ),
    (
        "node-index-float",
        _replace_line(NODE0, 3, "1.0 1 0 0"),
        ELE0,
        "m.1.node",
        r"line 3: node number must be an integer",
    ),
    (
        "node-duplicate",
        _replace_line(NODE0, 5, "2 0 0 1"),
        ELE0,
        "m.1.node",
        r"line 5: node 2 is listed twice \(first on line 4\)",
    ),
    (
        "node-token-count",
        _replace_line(NODE0, 3, "1 1 0"),
        ELE0,
        "m.1.node",
        r"line 3: expected 4 values.*got 3",
    ),
    (
        "node-token-count-marker",
        NODE0.replace("5 3 0 0", "5 3 0 1"),
        ELE0,
        "m.1.node",
        r"line 2: expected 5 values.*boundary marker.*got 4",
    ),
    ("node-dim-2", NODE0.replace("5 3 0 0", "5 2 0 0"), ELE0, "m.1.node", r"line 1: dimension must be 3"),
    (
        "node-marker-flag",
        NODE0.replace("5 3 0 0", "5 3 0 2"),
        ELE0,
        "m.1.node",
        r"line 1: boundary marker flag must be 0 or 1",
    ),
    (
        "node-header-garbage",
        NODE0.replace("5 3 0 0", "five 3 0 0"),
        ELE0,
        "m.1.node",
        r"line 1: header value 'number of nodes'.*'five'",
    ),
    (
        "node-header-negative",
        NODE0.replace("5 3 0 0", "-5 3 0 0"),
        ELE0,
        "m.1.node",
        r"line 1: .*must not be negative",
    ),
    (
        "node-header-too-long",
        NODE0.replace("5 3 0 0", "5 3 0 0 7"),
        ELE0,
        "m.1.node",
        r"line 1: header has 5 values",
    ),
    ("node-extra-data", NODE0 + "5 2 2 2\n", ELE0, "m.1.node", r"line 7: unexpected data after the 5 nodes"),
    ("node-empty", "", ELE0, "m.1.node", r"empty"),
    ("node-only-comments", "# nothing\n\n   # here\n", ELE0, "m.1.node", r"empty"),
    ("node-zero-count", "0 3 0 0\n", ELE0, "m.1.node", r"declares 0 nodes"),
    ("ele-empty", NODE0, "", "m.1.ele", r"empty"),
    ("ele-zero-count", NODE0, "0 4 0\n", "m.1.ele", r"declares 0 tetrahedra"),
    (
        "ele-out-of-range",
        NODE0,
        _replace_line(ELE0, 3, "1 1 2 3 5"),
        "m.1.ele",
        r"line 3: element 1 refers to node 5, but the \.node file numbers nodes 0\.\.4",
    ),
    (
        "ele-negative-ref",
        NODE0,
        _replace_line(ELE0, 2, "0 0 1 -2 3"),
        "m.1.ele",
        r"line 2: element 0 refers to node -2",
    ),
    (
        "ele-garbage",
        NODE0,
        _replace_line(ELE0, 3, "1 1 2 x 4"),
        "m.1.ele",
        r"line 3: node number of element 1 must be an integer, got 'x'",
    ),
    (
        "ele-token-count",
        NODE0,
        _replace_line(ELE0, 2, "0 0 1 2"),
        "m.1.ele",
        r"line 2: expected 5 values.*got 4",
    ),
    (
        "ele-nodes-per-tet",
        NODE0,
        ELE0.replace("2 4 0", "2 6 0"),
        "m.1.ele",
        r"line 1: nodes per tetrahedron must be 4 or 10, got 6",
    ),
    (
        "ele-extra-data",
        NODE0,
        ELE0 + "2 0 1 2 4\n",
        "m.1.ele",
        r"line 4: unexpected data after the 2 tetrahedra",
    ),
    (
        "ele-bad-attribute",
        NODE0,
        "2 4 1\n0 0 1 2 3 1\n1 1 2 3 4 region\n",
        "m.1.ele",
        r"line 3: attribute of element 1 must be a number",
    ),
    ("binary-garbage", NODE0, "\x00\x01\x02 \xff\xfe\n", "m.1.ele", r"line 1: header value"),
]


@pytest.mark.parametrize("case, node, ele, where, pattern", TETGEN_ERRORS, ids=[c[0] for c in TETGEN_ERRORS])
def test_tetgen_malformed_files_raise_mesh_error_naming_file_and_line(tmp_path, case, node, ele, where, pattern):
    base = _write(tmp_path, node, ele)
    with pytest.raises(MeshError) as info:
        read_tetgen(base)
    msg = str(info.value)
    assert where in msg, msg
    assert f"{base}.{where.rsplit('.', 1)[1]}" in msg, msg  # the full path of the offending file
    assert re.search(pattern, msg), msg
    # load_mesh reports the same error
    with pytest.raises(MeshError):
        load_mesh(base)


@pytest.mark.parametrize("which", ["node", "ele"])
def test_tetgen_huge_header_count_fails_fast_without_allocating(tmp_path, which):
    huge = 10**15
    node = NODE0.replace("5 3 0 0", f"{huge} 3 0 0") if which == "node" else NODE0
    ele = ELE0.replace("2 4 0", f"{huge} 4 0") if which == "ele" else ELE0
    base = _write(tmp_path, node, ele)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(MeshError, match=rf"m\.1\.{which}: file is truncated.*declares {huge}"):
            read_tetgen(base)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - start < 1.0
    assert peak < 1_000_000, f"peak traced allocation {peak} bytes"


def test_tetgen_missing_partner_files(tmp_path):
    base = _write(tmp_path, NODE0, None)
    with pytest.raises(MeshError, match=r"m\.1\.node: the matching element file m\.1\.ele was not found"):
        read_tetgen(f"{base}.node")
    with pytest.raises(MeshError, match=r"element file .*m\.1\.ele not found"):
        load_mesh(base)

    base2 = _write(tmp_path, None, ELE0, name="e.1")
    with pytest.raises(MeshError, match=r"e\.1\.ele: the matching node file e\.1\.node was not found"):
        load_mesh(f"{base2}.ele")
    with pytest.raises(MeshError, match=r"node file .*e\.1\.node not found"):
        read_tetgen(base2)

    with pytest.raises(MeshError, match=r"nothere\.1\.node: file not found"):
        read_tetgen(tmp_path / "nothere.1.node")
    with pytest.raises(MeshError, match=r"nothere\.1: file not found"):
        read_tetgen(tmp_path / "nothere.1")


def test_tetgen_negative_tet_is_repaired_with_warning(tmp_path):
    ele = "2 4 0\n0 0 1 3 2\n1 1 2 3 4\n"  # first tet negatively oriented
    base = _write(tmp_path, NODE0, ele)
    with pytest.warns(UserWarning, match="1 of 2 tets"):
        mesh = load_mesh(base)
    assert mesh.flipped_count == 1
    assert np.all(_signed_volumes(mesh.vertices, mesh.tets) > 0)


def test_tetgen_degenerate_tet_is_rejected_by_validation_naming_the_source(tmp_path):
    node = NODE0 + "5 2 2 0\n"  # node 5 = (2, 2, 0) is coplanar with nodes 0, 1, 2
    node = node.replace("5 3 0 0", "6 3 0 0")
    ele = "3 4 0\n0 0 1 2 3\n1 1 2 3 4\n2 0 1 2 5\n"
    base = _write(tmp_path, node, ele)
    v, t = read_tetgen(base)  # the reader itself only checks the file format
    assert t.shape == (3, 4)
    with pytest.raises(MeshError, match=str(base).replace(".", r"\.")):
        load_mesh(base)


# Files our hand-written readers read that meshio's readers (meshio 5.3) reject or misread: why TetGen, OBJ and
# OFF are not read through meshio (issue 36). (name, {file: text}, expected vertices, expected cells)
_QUAD = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
_COMMENTED = NODE0.replace("2 0 1 0\n", "# a comment\n2 0 1 0  # and another\n")
_GAPS = "5 3 0 0\n" + "".join(f"{10 * i} {x:g} {y:g} {z:g}\n" for i, (x, y, z) in enumerate(V2))
_COFF = "COFF\n3 1 0\n0 0 0 1 1 1 1\n1 0 0 1 1 1 1\n0 1 0 1 1 1 1\n3 0 1 2 9 9 9\n"
BEYOND_MESHIO = [
    ("tetgen-comments", {"m.node": _COMMENTED, "m.ele": ELE0}, V2, T2),
    ("tetgen-gaps", {"m.node": _GAPS, "m.ele": "2 4 0\n0 0 10 20 30\n1 10 20 30 40\n"}, V2, T2),
    ("tetgen-10-node", {"m.node": NODE0, "m.ele": "1 10 0\n0 0 1 2 3 4 4 4 4 4 4\n"}, V2, T2[:1]),
    ("obj-negative-indices", {"m.obj": _QUAD + "f -4 -3 -2\nf -4 -2 -1\n"}, None, [[0, 1, 2], [0, 2, 3]]),
    ("obj-w-coordinate", {"m.obj": _QUAD.replace("v 0 0 0", "v 0 0 0 1.0") + "f 1 2 3\n"}, None, [[0, 1, 2]]),
    ("off-quad", {"m.off": "OFF\n4 1 0\n" + _QUAD.replace("v ", "") + "4 0 1 2 3\n"}, None, [[0, 1, 2], [0, 2, 3]]),
    ("off-colours", {"m.off": _COFF}, None, [[0, 1, 2]]),
]


@pytest.mark.parametrize("case, files, vertices, cells", BEYOND_MESHIO, ids=[c[0] for c in BEYOND_MESHIO])
def test_native_readers_read_what_meshio_cannot(tmp_path, case, files, vertices, cells):
    import meshio

    for name, text in files.items():
        (tmp_path / name).write_text(text)
    first = tmp_path / next(iter(files))
    v, c = read_tetgen(first) if case.startswith("tetgen") else read_surface(first)
    np.testing.assert_array_equal(c, cells)
    if vertices is not None:
        np.testing.assert_array_equal(v, vertices)
    fmt = case.split("-", 1)[0]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = getattr(meshio, fmt).read(str(first))  # meshio.read() would print and sys.exit(1) on failure
        theirs = np.concatenate([b.data[:, :3] if fmt != "tetgen" else b.data for b in mesh.cells])
    except (Exception, SystemExit):
        return
    assert not np.array_equal(theirs, c), f"meshio now reads {case}: route {fmt} through meshio (issue 36)"


# ----------------------------------------------------------------------------------------------------
# meshio formats


def _box_arrays(jitter: bool = True):
    """A 2x2x2-cell box (27 vertices, 48 positive tets) with non-representable coordinates."""
    rng = np.random.default_rng(1234)
    g = np.linspace(-0.5, 0.5, 3)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    idx = np.arange(27).reshape(3, 3, 3)
    tets = []
    for i in range(2):
        for j in range(2):
            for k in range(2):
                c = [idx[i + a, j + b, k + d] for d in (0, 1) for b in (0, 1) for a in (0, 1)]
                # 6 Kuhn tets along the main diagonal c[0] - c[7]
                for p in ([0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]):
                    tets.append([c[q] for q in p])
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    if jitter:
        v = v + rng.uniform(-0.03, 0.03, v.shape)
    t = np.array(tets, dtype=np.int64)
    assert np.all(_signed_volumes(v, t) > 0)
    return v, t


MESHIO_CASES = [
    ("gmsh22-ascii", "m.msh", dict(file_format="gmsh22", binary=False), True),
    ("gmsh22-binary", "m.msh", dict(file_format="gmsh22", binary=True), True),
    ("gmsh41-ascii", "m.msh", dict(file_format="gmsh", binary=False), True),
    ("gmsh41-binary", "m.msh", dict(file_format="gmsh", binary=True), True),
    ("vtu-ascii", "m.vtu", dict(binary=False), False),
    ("vtu-binary", "m.vtu", dict(binary=True), True),
    ("vtk-ascii", "m.vtk", dict(binary=False), True),
    ("vtk-binary", "m.vtk", dict(binary=True), True),
    ("medit", "m.mesh", {}, True),
    ("medit-binary", "m.meshb", {}, True),
]


def _meshio_write(path: Path, points, cells, **kwargs):
    meshio = pytest.importorskip("meshio")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # meshio warns about missing gmsh tags
        meshio.write(str(path), meshio.Mesh(points, cells), **kwargs)


@pytest.mark.parametrize("case, name, kwargs, exact", MESHIO_CASES, ids=[c[0] for c in MESHIO_CASES])
def test_meshio_round_trip(tmp_path, case, name, kwargs, exact):
    v, t = _box_arrays()
    path = tmp_path / name
    _meshio_write(path, v, [("tetra", t)], **kwargs)
    rv, rt = read_meshio(path)
    assert rv.dtype == np.float64 and rt.dtype == np.int64
    if exact:
        np.testing.assert_array_equal(rv, v)
    else:  # meshio's ASCII VTU writer rounds to about 12 significant digits
        np.testing.assert_allclose(rv, v, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(rt, t)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = load_mesh(path)
    assert mesh.flipped_count == 0
    np.testing.assert_array_equal(mesh.tets, t)


@pytest.mark.parametrize(
    "name, kwargs",
    [
        ("mixed.msh", dict(file_format="gmsh22", binary=False)),
        ("mixed.vtu", {}),
        ("mixed.vtk", {}),
        ("mixed.mesh", {}),
    ],
)
def test_meshio_mixed_cells_keep_only_tets(tmp_path, name, kwargs):
    v, t = _box_arrays()
    cells = [("triangle", t[:7, :3]), ("tetra", t[:20]), ("line", t[:3, :2]), ("tetra", t[20:])]
    if not name.endswith(".mesh"):
        cells.append(("vertex", np.array([[0], [5]])))
    path = tmp_path / name
    _meshio_write(path, v, cells, **kwargs)
    with pytest.warns(UserWarning, match=r"kept 48 tetra cells; dropped 7 triangle, 3 line"):
        rv, rt = read_meshio(path)
    np.testing.assert_array_equal(rv, v)
    np.testing.assert_array_equal(rt, t)  # both tet blocks, in order
    with pytest.warns(UserWarning, match="dropped"):
        assert load_mesh(path).num_tets == len(t)


def test_meshio_tetra10_keeps_corners(tmp_path):
    v, t = _box_arrays()
    mids = [(v[a] + v[b]) / 2 for a, b in ((0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))]
    v10 = np.vstack([v, mids])
    t10 = np.hstack([t[:3], np.tile(np.arange(27, 33), (3, 1))])
    path = tmp_path / "quadratic.vtu"
    _meshio_write(path, v10, [("tetra10", t10)])
    rv, rt = read_meshio(path)
    assert rv.shape == (33, 3)
    np.testing.assert_array_equal(rt, t[:3])


def test_meshio_without_tets_lists_cell_types(tmp_path):
    v, t = _box_arrays()
    path = tmp_path / "surface.vtu"
    _meshio_write(path, v, [("triangle", t[:, :3]), ("line", t[:, :2])])
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    msg = str(info.value)
    assert "surface.vtu" in msg
    assert "no tetrahedra found (cell types present: triangle, line)" in msg


def test_meshio_two_coordinate_points_rejected(tmp_path):
    v, t = _box_arrays()
    path = tmp_path / "flat.mesh"
    _meshio_write(path, v[:, :2], [("tetra", t)])
    with pytest.raises(MeshError, match=r"flat\.mesh: points have 2 coordinates"):
        read_meshio(path)


def _corrupt_cases(tmp_path: Path):
    v, t = _box_arrays()
    good = tmp_path / "good.msh"
    _meshio_write(good, v, [("tetra", t)], file_format="gmsh22", binary=True)
    data = good.read_bytes()
    return {
        "truncated.msh": data[: len(data) // 2],
        "garbage.msh": b"this is not a mesh\n",
        "empty.msh": b"",
        "bad-nodes.msh": b"$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 2 x\n",
        "binary-noise.msh": bytes(range(256)) * 8,
        "garbage.vtu": b"<VTKFile",
        "garbage.vtk": b"# vtk DataFile Version 4.2\nx\nASCII\nDATASET UNSTRUCTURED_GRID\nPOINTS 3 float\n1 2\n",
        "garbage.mesh": b"MeshVersionFormatted 1\nDimension 3\nVertices\n5\n1 2 3\n",
    }


@pytest.mark.parametrize(
    "name",
    [
        "truncated.msh",
        "garbage.msh",
        "empty.msh",
        "bad-nodes.msh",
        "binary-noise.msh",
        "garbage.vtu",
        "garbage.vtk",
        "garbage.mesh",
    ],
)
def test_meshio_corrupt_file_raises_mesh_error_with_file_name(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(_corrupt_cases(tmp_path)[name])
    # meshio.read() itself calls sys.exit(1) on some errors; ours must raise MeshError instead
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    msg = str(info.value)
    assert str(path) in msg
    assert "cannot read" in msg


def test_meshio_uppercase_extension(tmp_path):
    v, t = _box_arrays()
    path = tmp_path / "UPPER.MSH"
    _meshio_write(path, v, [("tetra", t)], file_format="gmsh22", binary=False)
    np.testing.assert_array_equal(load_mesh(path).tets, t)


# ----------------------------------------------------------------------------------------------------
# .npz


@pytest.mark.parametrize("key", ["vertices", "rest_positions", "positions"])
def test_npz_round_trip(tmp_path, key):
    v, t = _box_arrays()
    path = tmp_path / "m.npz"
    np.savez(path, **{key: v, "tets": t.astype(np.int32)})
    rv, rt = read_npz(path)
    np.testing.assert_array_equal(rv, v)
    np.testing.assert_array_equal(rt, t)
    assert rt.dtype == np.int64
    np.testing.assert_array_equal(load_mesh(path).vertices, v)


def test_npz_prefers_vertices_over_positions(tmp_path):
    v, t = _box_arrays()
    path = tmp_path / "m.npz"
    np.savez(path, positions=v * 2.0, rest_positions=v * 3.0, vertices=v, tets=t)
    np.testing.assert_array_equal(read_npz(path)[0], v)
    np.savez(path, positions=v * 2.0, rest_positions=v * 3.0, tets=t)
    np.testing.assert_array_equal(read_npz(path)[0], v * 3.0)


@pytest.mark.parametrize(
    "arrays, pattern",
    [
        (dict(vertices=np.zeros((4, 3))), r"missing array\(s\) tets; the archive holds: vertices"),
        (
            dict(points=np.zeros((4, 3)), tets=np.zeros((1, 4), int)),
            r"missing array\(s\) vertices .*holds: points, tets",
        ),
        (dict(vertices=np.zeros((4, 2)), tets=np.zeros((1, 4), int)), r"'vertices' must have shape \(m, 3\)"),
        (dict(vertices=np.zeros((4, 3)), tets=np.zeros((1, 3), int)), r"'tets' must have shape \(k, 4\)"),
        (dict(vertices=np.zeros((4, 3)), tets=np.zeros((1, 4))), r"'tets' must hold integer"),
        (dict(vertices=np.array([["a", "b", "c"]]), tets=np.zeros((1, 4), int)), r"must be numeric"),
    ],
)
def test_npz_errors(tmp_path, arrays, pattern):
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(MeshError, match=r"bad\.npz: .*" + pattern):
        load_mesh(path)


def test_npz_not_an_archive(tmp_path):
    path = tmp_path / "noise.npz"
    path.write_bytes(b"definitely not a zip file")
    with pytest.raises(MeshError, match=r"noise\.npz: cannot read as an \.npz archive"):
        load_mesh(path)
    single = tmp_path / "single.npz"
    with open(single, "wb") as fh:
        np.save(fh, np.zeros((4, 3)))
    with pytest.raises(MeshError, match=r"single\.npz: not an \.npz archive"):
        load_mesh(single)


# ----------------------------------------------------------------------------------------------------
# load_mesh: dispatch, missing files, scale / translate


def test_unknown_extension_lists_supported(tmp_path):
    path = tmp_path / "model.stl"
    path.write_text("solid x\nendsolid x\n")
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    msg = str(info.value)
    assert "model.stl" in msg and "'.stl'" in msg
    for ext in (".node", ".ele", ".msh", ".vtk", ".vtu", ".mesh", ".npz"):
        assert ext in msg
        assert ext in SUPPORTED_EXTENSIONS


@pytest.mark.parametrize(
    "name",
    [
        "missing.msh",
        "missing.vtu",
        "missing.vtk",
        "missing.mesh",
        "missing.npz",
        "missing.node",
        "missing.ele",
        "missing.1",
        "missing",
    ],
)
def test_missing_file_is_a_mesh_error_naming_the_path(tmp_path, name):
    path = tmp_path / name
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    assert not isinstance(info.value, FileNotFoundError)
    assert str(path) in str(info.value)
    assert "not found" in str(info.value)


def test_directory_is_rejected(tmp_path):
    d = tmp_path / "dir.msh"
    d.mkdir()
    with pytest.raises(MeshError, match="not a regular file"):
        load_mesh(d)
    with pytest.raises(MeshError, match="directory"):
        load_mesh(tmp_path)


def test_non_path_argument():
    with pytest.raises(MeshError, match="must be a string or os.PathLike"):
        load_mesh(42)


def test_scale_and_translate(tmp_path):
    base = _write(tmp_path, NODE0, ELE0)
    mesh = load_mesh(base, scale=2.5, translate=(1.0, -2.0, 0.5))
    np.testing.assert_allclose(mesh.vertices, 2.5 * V2 + np.array([1.0, -2.0, 0.5]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(mesh.volumes(), _signed_volumes(V2, T2) * 2.5**3, rtol=1e-12)
    only_scale = load_mesh(base, scale=3)
    np.testing.assert_array_equal(only_scale.vertices, 3.0 * V2)
    only_translate = load_mesh(base, translate=np.array([0, 0, 7]))
    np.testing.assert_array_equal(only_translate.vertices, V2 + [0, 0, 7])


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(scale=0), "scale"),
        (dict(scale=-1.0), "scale"),
        (dict(scale=float("nan")), "scale"),
        (dict(scale=float("inf")), "scale"),
        (dict(scale=True), "scale"),
        (dict(scale="2"), "scale"),
        (dict(translate=(1, 2)), "translate"),
        (dict(translate=(0, 0, float("nan"))), "translate"),
        (dict(translate="abc"), "translate"),
    ],
)
def test_invalid_scale_or_translate_is_config_error(tmp_path, kwargs, pattern):
    base = _write(tmp_path, NODE0, ELE0)
    with pytest.raises(ConfigError, match=pattern):
        load_mesh(base, **kwargs)


# ----------------------------------------------------------------------------------------------------
# TetGen .face files, appended VTU, mixed cells, writers


@needs_shared
def test_tetgen_face_file_is_allowed_and_ignored():
    base = SHARED / "seed" / "bunny2.1"
    via_face = load_mesh(f"{base}.face")
    np.testing.assert_array_equal(via_face.tets, load_mesh(base).tets)
    assert f"{base}.face" == via_face.source


def test_tetgen_face_path_without_node_file(tmp_path):
    (tmp_path / "x.1.face").write_text("0 0\n")
    with pytest.raises(MeshError, match=r"x\.1: file not found"):
        load_mesh(tmp_path / "x.1.face")


def _appended_vtu(points: np.ndarray, tets: np.ndarray, encoding: str, header: str) -> bytes:
    """A VTU file with all arrays in one <AppendedData> block (what ParaView writes), made by hand."""
    import base64

    htype = {"UInt32": "<u4", "UInt64": "<u8"}[header]
    arrays = [
        ("Float64", "Points", 3, points.astype("<f8")),
        ("Int64", "connectivity", 1, tets.astype("<i8").ravel()),
        ("Int64", "offsets", 1, (4 * np.arange(1, len(tets) + 1)).astype("<i8")),
        ("UInt8", "types", 1, np.full(len(tets), 10, dtype="u1")),
    ]
    blob, xml, offset = b"", [], 0
    for dtype, name, ncomp, data in arrays:
        raw = data.tobytes()
        chunk = np.array([len(raw)], dtype=htype).tobytes() + raw
        if encoding == "base64":
            chunk = base64.b64encode(np.array([len(raw)], dtype=htype).tobytes()) + base64.b64encode(raw)
        comps = f' NumberOfComponents="{ncomp}"' if ncomp > 1 else ""
        xml.append(f'<DataArray type="{dtype}" Name="{name}"{comps} format="appended" offset="{offset}"/>')
        blob += chunk
        offset += len(chunk)
    head = (
        f'<?xml version="1.0"?>\n<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" '
        f'header_type="{header}">\n<UnstructuredGrid>\n'
        f'<Piece NumberOfPoints="{len(points)}" NumberOfCells="{len(tets)}">\n'
        f"<Points>\n{xml[0]}\n</Points>\n<Cells>\n" + "\n".join(xml[1:]) + "\n</Cells>\n</Piece>\n"
        f'</UnstructuredGrid>\n<AppendedData encoding="{encoding}">\n_'
    )
    return head.encode() + blob + b"\n</AppendedData>\n</VTKFile>\n"


@pytest.mark.parametrize("encoding", ["raw", "base64"])
@pytest.mark.parametrize("header", ["UInt32", "UInt64"])
def test_vtu_appended_data_round_trip(tmp_path, encoding, header):
    v, t = _box_arrays()
    path = tmp_path / "appended.vtu"
    path.write_bytes(_appended_vtu(v, t, encoding, header))
    rv, rt = read_meshio(path)
    np.testing.assert_array_equal(rv, v)
    np.testing.assert_array_equal(rt, t)


@pytest.mark.parametrize("compression", [None, "zlib", "lzma"])
def test_vtu_binary_compressions_round_trip(tmp_path, compression):
    v, t = _box_arrays()
    path = tmp_path / "c.vtu"
    _meshio_write(path, v, [("tetra", t)], binary=True, compression=compression)
    rv, rt = read_meshio(path)
    np.testing.assert_array_equal(rv, v)
    np.testing.assert_array_equal(rt, t)


def test_mixed_cells_warning_lists_dropped_types_and_counts(tmp_path):
    v, t = _box_arrays()
    cells = [("triangle", t[:7, :3]), ("tetra", t[:20]), ("line", t[:3, :2]), ("tetra", t[20:])]
    cells.append(("triangle", t[:2, :3]))
    path = tmp_path / "mixed.msh"
    _meshio_write(path, v, cells, file_format="gmsh22", binary=False)
    with pytest.warns(UserWarning, match=r"mixed\.msh: kept 48 tetra cells; dropped 9 triangle, 3 line cells"):
        load_mesh(path)


def test_only_tets_no_warning(tmp_path):
    v, t = _box_arrays()
    path = tmp_path / "pure.vtu"
    _meshio_write(path, v, [("tetra", t)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_mesh(path)


@pytest.mark.parametrize("name", ["w.msh", "w.vtu", "w.vtk", "w.mesh", "w.meshb", "w.npz", "w.1.node", "w.1.ele"])
def test_write_mesh_round_trip_is_exact(tmp_path, name):
    from fepr.io import read_arrays, write_mesh

    v, t = _box_arrays()
    written = write_mesh((v, t), tmp_path / name)
    assert all(p.is_file() for p in written)
    rv, rt = read_arrays(tmp_path / name)
    np.testing.assert_array_equal(rv, v)
    np.testing.assert_array_equal(rt, t)
    mesh = load_mesh(tmp_path / name)
    np.testing.assert_array_equal(mesh.vertices, v)


def test_write_mesh_errors(tmp_path):
    from fepr.io import write_mesh

    with pytest.raises(ConfigError, match=r"cannot write extension '\.obj'"):
        write_mesh(load_mesh_box(), tmp_path / "x.obj")
    with pytest.raises(ConfigError, match="TetMesh or a"):
        write_mesh(42, tmp_path / "x.msh")


def load_mesh_box():
    from fepr import meshes

    return meshes.box()


def test_surface_file_given_to_load_mesh_says_tetrahedralize(tmp_path):
    path = tmp_path / "ball.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"ball\.obj: '\.obj' is a surface format .*fepr\.tetrahedralize"):
        load_mesh(path)
