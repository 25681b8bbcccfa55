"""Fuzz-style tests of the mesh readers: damaged files give a MeshError naming the file, never a crash, a hang
or a MemoryError.

Two kinds: hypothesis mutates valid files (truncation, garbage tokens, NaN / inf, huge or wrong numbers,
deleted and duplicated lines, flipped bytes) and checks that reading either succeeds or raises MeshError with
the file name; and hand-made files check each damage the issue lists (truncated files, wrong counts, garbage
tokens, NaN / inf, indices out of range, duplicate tets, empty files, huge header counts) with the exact
message, including the line for the line-based formats (TetGen, OBJ, OFF).
"""

from __future__ import annotations

import contextlib
import signal
import struct
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fepr
from fepr.errors import MeshError
from fepr.io import load_mesh, read_arrays, read_surface, write_mesh

# ----------------------------------------------------------------------------------------------------
# valid seed files

BOX = fepr.meshes.box(resolution=1)  # 8 vertices, 6 tets
SURF_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
SURF_F = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def _meshio_bytes(tmp: Path, name: str, **kwargs) -> bytes:
    import meshio

    path = tmp / name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if name.endswith((".stl", ".ply", ".off")):
            meshio.write(str(path), meshio.Mesh(SURF_V, [("triangle", SURF_F)]), **kwargs)
        else:
            ones = np.ones(BOX.num_tets, dtype=np.int64)
            cell_data = {"gmsh:physical": [ones], "gmsh:geometrical": [ones]} if name.endswith(".msh") else {}
            meshio.write(str(path), meshio.Mesh(BOX.vertices, [("tetra", BOX.tets)], cell_data=cell_data), **kwargs)
    return path.read_bytes()


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seeds")
    out = {
        "g22a.msh": _meshio_bytes(tmp, "a.msh", file_format="gmsh22", binary=False),
        "g22b.msh": _meshio_bytes(tmp, "b.msh", file_format="gmsh22", binary=True),
        "g41a.msh": _meshio_bytes(tmp, "c.msh", file_format="gmsh", binary=False),
        "g41b.msh": _meshio_bytes(tmp, "d.msh", file_format="gmsh", binary=True),
        "a.vtk": _meshio_bytes(tmp, "a.vtk", binary=False),
        "b.vtk": _meshio_bytes(tmp, "b.vtk", binary=True),
        "a.vtu": _meshio_bytes(tmp, "a.vtu", binary=False),
        "b.vtu": _meshio_bytes(tmp, "b.vtu", binary=True),
        "a.mesh": _meshio_bytes(tmp, "a.mesh"),
        "a.meshb": _meshio_bytes(tmp, "a.meshb"),
        "a.stl": _meshio_bytes(tmp, "a.stl", binary=False),
        "b.stl": _meshio_bytes(tmp, "b.stl", binary=True),
        "a.ply": _meshio_bytes(tmp, "a.ply", binary=False),
        "b.ply": _meshio_bytes(tmp, "b.ply", binary=True),
    }
    write_mesh(BOX, tmp / "t.node")
    out["t.node"] = (tmp / "t.node").read_bytes()
    out["t.ele"] = (tmp / "t.ele").read_bytes()
    out["a.obj"] = b"# tet\n" + b"".join(b"v %r %r %r\n" % tuple(p) for p in SURF_V.tolist())
    out["a.obj"] += b"".join(b"f %d %d %d\n" % tuple(int(i) + 1 for i in f) for f in SURF_F)
    out["a.off"] = b"OFF\n4 4 0\n" + b"".join(b"%r %r %r\n" % tuple(p) for p in SURF_V.tolist())
    out["a.off"] += b"".join(b"3 %d %d %d\n" % tuple(int(i) for i in f) for f in SURF_F)
    return out


def _read_any(path: Path):
    """Read as the extension says: surfaces with read_surface, tet meshes with load_mesh (validation too)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if path.suffix in (".obj", ".off", ".stl", ".ply"):
            return read_surface(path)
        return load_mesh(path)


class Hang(BaseException):
    """Raised by the alarm below; a BaseException so that no reader's ``except Exception`` can swallow it."""


@contextlib.contextmanager
def time_limit(seconds: float):
    """Fail (instead of hanging the test run) when the body takes longer than ``seconds`` (POSIX only)."""
    if not hasattr(signal, "setitimer"):  # pragma: no cover - Windows
        yield
        return

    def on_alarm(signum, frame):
        raise Hang(f"reading took longer than {seconds} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _expect_mesh_error_or_success(path: Path, names=None) -> None:
    try:
        with time_limit(5.0):
            _read_any(path)
    except MeshError as exc:
        msg = str(exc)
        assert any(n in msg for n in (names or [path.name])), msg
    except Hang:
        pytest.fail(f"reading {path.name} hangs on: {path.read_bytes()[:400]!r}")
    # anything else (MemoryError, IndexError, SystemExit, ...) fails the test


TOKENS = ["nan", "inf", "-inf", "-1", "0", "7", "99999999999999999999", "1e400", "x", "#", "$Nodes", "", "3.5", "-0"]
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@st.composite
def text_mutation(draw, text: bytes):
    lines = text.split(b"\n")
    op = draw(st.sampled_from(["truncate", "token", "delete", "duplicate", "swap"]))
    if op == "truncate":
        return text[: draw(st.integers(0, max(0, len(text) - 1)))]
    i = draw(st.integers(0, len(lines) - 1))
    if op == "token":
        tokens = lines[i].split(b" ")
        j = draw(st.integers(0, len(tokens) - 1))
        tokens[j] = draw(st.sampled_from(TOKENS)).encode()
        lines[i] = b" ".join(tokens)
    elif op == "delete":
        del lines[i]
    elif op == "duplicate":
        lines.insert(i, lines[i])
    else:
        j = draw(st.integers(0, len(lines) - 1))
        lines[i], lines[j] = lines[j], lines[i]
    return b"\n".join(lines)


@st.composite
def byte_mutation(draw, data: bytes):
    op = draw(st.sampled_from(["truncate", "flip", "zero", "ones"]))
    if op == "truncate":
        return data[: draw(st.integers(0, len(data) - 1))]
    out = bytearray(data)
    i = draw(st.integers(0, len(out) - 1))
    n = draw(st.integers(1, 8))
    for k in range(i, min(len(out), i + n)):
        out[k] = {"flip": out[k] ^ 0xFF, "zero": 0, "ones": 0xFF}[op]
    return bytes(out)


TEXT_FORMATS = ["g22a.msh", "g41a.msh", "a.vtk", "a.vtu", "a.mesh", "a.obj", "a.off", "a.stl", "a.ply"]
BINARY_FORMATS = ["g22b.msh", "g41b.msh", "b.vtk", "b.vtu", "a.meshb", "b.stl", "b.ply"]


@pytest.mark.parametrize("name", TEXT_FORMATS)
def test_fuzz_text_formats(tmp_path, seeds, name):
    @FUZZ
    @given(data=st.data())
    def run(data):
        path = tmp_path / name
        path.write_bytes(data.draw(text_mutation(seeds[name])))
        _expect_mesh_error_or_success(path)

    run()


@pytest.mark.parametrize("name", BINARY_FORMATS)
def test_fuzz_binary_formats(tmp_path, seeds, name):
    @FUZZ
    @given(data=st.data())
    def run(data):
        path = tmp_path / name
        path.write_bytes(data.draw(byte_mutation(seeds[name])))
        _expect_mesh_error_or_success(path)

    run()


@pytest.mark.parametrize("which", ["node", "ele"])
def test_fuzz_tetgen(tmp_path, seeds, which):
    @FUZZ
    @given(data=st.data())
    def run(data):
        (tmp_path / "t.node").write_bytes(seeds["t.node"])
        (tmp_path / "t.ele").write_bytes(seeds["t.ele"])
        (tmp_path / f"t.{which}").write_bytes(data.draw(text_mutation(seeds[f"t.{which}"])))
        _expect_mesh_error_or_success(tmp_path / "t.node", names=["t.node", "t.ele"])

    run()


@FUZZ
@given(values=st.lists(st.one_of(st.floats(), st.integers(-(2**40), 2**40)), min_size=0, max_size=40))
def test_fuzz_npz_arrays(tmp_path_factory, values):
    path = tmp_path_factory.mktemp("npz") / "m.npz"
    arr = np.array(values, dtype=np.float64)
    n = len(arr) // 3
    tets = np.array(values[: 4 * (len(values) // 4)], dtype=np.float64).reshape(-1, 4)
    tets = np.clip(np.nan_to_num(tets, nan=0, posinf=0, neginf=0), -(2**40), 2**40).astype(np.int64)
    np.savez(path, vertices=arr[: 3 * n].reshape(n, 3), tets=tets)
    _expect_mesh_error_or_success(path)


# ----------------------------------------------------------------------------------------------------
# the damages the issue lists, one by one, with the exact message


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


NODE = "4 3 0 0\n0 0 0 0\n1 1 0 0\n2 0 1 0\n3 0 0 1\n"
ELE = "1 4 0\n0 0 1 2 3\n"


@pytest.mark.parametrize(
    "name, text, pattern",
    [
        ("t.obj", "v 0 0 0\nv 1 0\n", r"t\.obj line 2: a vertex needs 3 coordinates, got 2"),
        ("t.obj", "v 0 0 0\nv 1 0 nan\n", r"t\.obj line 2: coordinate z of vertex 2 is not finite"),
        ("t.obj", "v 0 0 0\nv 1 0 inf\n", r"t\.obj line 2: coordinate z of vertex 2 is not finite"),
        ("t.obj", "v 0 0 0\nv 1 0 zz\n", r"t\.obj line 2: coordinate z of vertex 2 must be a number, got 'zz'"),
        ("t.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", r"t\.obj line 4: face refers to vertex 4, but only 3"),
        ("t.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", r"t\.obj line 4: face vertex index 0 is invalid"),
        ("t.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", r"t\.obj line 4: face refers to vertex -4"),
        ("t.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"t\.obj line 4: a face needs at least 3 corners"),
        ("t.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 b 3\n", r"t\.obj line 4: face vertex index must be an integer"),
        ("t.obj", "", r"t\.obj: no faces found"),
        ("t.obj", "v 0 0 0\n# nothing else\n", r"t\.obj: no faces found"),
        ("t.off", "", r"t\.off: the file is empty"),
        ("t.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n", r"t\.off: file is truncated: line 2 declares 4 vertices and 1 faces"),
        ("t.off", "OFF\n3 1 0\n0 0 0\n1 0 nan\n0 1 0\n3 0 1 2\n", r"t\.off line 4: coordinate z of vertex 1 is not"),
        ("t.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n", r"t\.off line 6: face 0 refers to vertex 3, out of"),
        ("t.off", "OFF\n99999999999 1 0\n0 0 0\n", r"t\.off: file is truncated: line 2 declares 99999999999"),
        ("t.off", "OFX\n", r"t\.off line 1: expected the header 'OFF'"),
        ("t.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n9 9 9\n", r"t\.off line 7: unexpected data"),
    ],
)
def test_surface_damage_names_file_and_line(tmp_path, name, text, pattern):
    path = _write(tmp_path, name, text)
    with pytest.raises(MeshError, match=pattern):
        read_surface(path)


def test_obj_accepts_its_usual_statements(tmp_path):
    text = (
        "mtllib x.mtl\no thing\ng part\nv 0 0 0 1.0\nv 1 0 0\nv 0 1 0\nv 0 0 1 0.5 0.5 0.5\nvt 0 0\nvn 0 0 1\n"
        "usemtl red\ns off\nf 1/1/1 3/1/1 2/1/1\nf -4//1 -3//1 -1//1\nf 2 3 4\nf 1 4 3\nl 1 2\n"
    )
    v, f = read_surface(_write(tmp_path, "ok.obj", text))
    np.testing.assert_array_equal(v, SURF_V)
    np.testing.assert_array_equal(f, SURF_F[[0, 1, 2, 3]])
    quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n"
    np.testing.assert_array_equal(read_surface(_write(tmp_path, "q.obj", quad))[1], [[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("ext", [".msh", ".vtk", ".vtu", ".mesh", ".meshb", ".npz", ".node", ".ele", ".stl", ".ply"])
def test_empty_files(tmp_path, ext):
    path = tmp_path / f"empty{ext}"
    path.write_bytes(b"")
    if ext in (".node", ".ele"):
        (tmp_path / "empty.node").write_bytes(b"")
        (tmp_path / "empty.ele").write_bytes(b"")
    with pytest.raises(MeshError, match=r"empty\.\w+: .*(empty|cannot read)"):
        _read_any(path)


def _huge_cases(seeds):
    """(file name, bytes) with a header count of about 10^12 that the data does not hold."""
    big = 10**12
    g41b = bytearray(seeds["g41b.msh"])
    at = g41b.index(b"$Nodes\n") + len(b"$Nodes\n")
    struct.pack_into("<Q", g41b, at + 8, big)  # numNodes
    g41b_block = bytearray(seeds["g41b.msh"])
    struct.pack_into("<Q", g41b_block, at + 32 + 12, big)  # numNodesInBlock of the first entity block
    el = bytearray(seeds["g41b.msh"])
    at_el = el.index(b"$Elements\n") + len(b"$Elements\n")
    struct.pack_into("<Q", el, at_el + 32 + 12, big)  # numElementsInBlock
    meshb = bytearray(seeds["a.meshb"])
    # meshio writes version 4: int32 keyword codes, int64 positions and counts. Dimension (code 3) comes first
    # (code, position, value), then Vertices (code 4): code, position of the next keyword, count.
    assert struct.unpack_from("<ii", meshb, 0) == (1, 4) and struct.unpack_from("<i", meshb, 8)[0] == 3
    assert struct.unpack_from("<i", meshb, 24)[0] == 4
    struct.pack_into("<q", meshb, 24 + 4 + 8, big)
    stl = bytearray(seeds["b.stl"])
    struct.pack_into("<I", stl, 80, 2**32 - 1)
    g41a = seeds["g41a.msh"].decode()
    nodes_hdr = g41a.split("$Nodes\n", 1)[1].split("\n", 1)[0]
    block_hdr = g41a.split("$Nodes\n", 1)[1].split("\n", 2)[1]
    return {
        "g22a.msh": seeds["g22a.msh"].replace(b"$Nodes\n8\n", b"$Nodes\n%d\n" % big),
        "g22a-elements.msh": seeds["g22a.msh"].replace(b"$Elements\n6\n", b"$Elements\n%d\n" % big),
        "g22b.msh": seeds["g22b.msh"].replace(b"$Nodes\n8\n", b"$Nodes\n%d\n" % big),
        "g41a.msh": g41a.replace(nodes_hdr, f"1 {big} 1 {big}", 1).encode(),
        "g41a-block.msh": g41a.replace(block_hdr, " ".join(block_hdr.split()[:3] + [str(big)]), 1).encode(),
        "g41b.msh": bytes(g41b),
        "g41b-block.msh": bytes(g41b_block),
        "g41b-elements.msh": bytes(el),
        "a.vtk": seeds["a.vtk"].replace(b"POINTS 8", b"POINTS %d" % big),
        "b.vtk": seeds["b.vtk"].replace(b"POINTS 8", b"POINTS %d" % big),
        "a-cells.vtk": seeds["a.vtk"].replace(b"CELL_TYPES 6", b"CELL_TYPES %d" % big),
        "a.mesh": seeds["a.mesh"].replace(b"Vertices\n8\n", b"Vertices\n%d\n" % big),
        "a-tets.mesh": seeds["a.mesh"].replace(b"Tetrahedra\n6\n", b"Tetrahedra\n%d\n" % big),
        "a.meshb": bytes(meshb),
        "b.stl": bytes(stl),
        "a.ply": seeds["a.ply"].replace(b"element vertex 4", b"element vertex %d" % big),
        "b.ply": seeds["b.ply"].replace(b"element face 4", b"element face %d" % big),
        "a.off": b"OFF\n%d 4 0\n0 0 0\n" % big,
    }


HUGE = [
    "g22a.msh",
    "g22a-elements.msh",
    "g22b.msh",
    "g41a.msh",
    "g41a-block.msh",
    "g41b.msh",
    "g41b-block.msh",
    "g41b-elements.msh",
    "a.vtk",
    "b.vtk",
    "a-cells.vtk",
    "a.mesh",
    "a-tets.mesh",
    "a.meshb",
    "b.stl",
    "a.ply",
    "b.ply",
    "a.off",
]


def test_truncated_ply_header_does_not_hang(tmp_path, seeds):
    path = tmp_path / "cut.ply"
    path.write_bytes(seeds["a.ply"][: seeds["a.ply"].index(b"end_header")])
    with time_limit(5.0), pytest.raises(MeshError, match=r"cut\.ply: the PLY header is not terminated"):
        read_surface(path)


@pytest.mark.parametrize("case", HUGE)
def test_huge_header_counts_fail_fast_without_allocating(tmp_path, seeds, case):
    data = _huge_cases(seeds)[case]
    stem, ext = case.rsplit(".", 1)
    path = tmp_path / f"{stem}.{ext}"
    path.write_bytes(data)
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(MeshError) as info:
            _read_any(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    msg = str(info.value)
    assert str(path) in msg, msg
    assert "MemoryError" not in msg and "allocate" not in msg, msg
    assert time.perf_counter() - start < 2.0
    assert peak < 50_000_000, f"peak traced allocation {peak} bytes"


def test_huge_count_message_names_the_line(tmp_path, seeds):
    path = tmp_path / "h.msh"
    path.write_bytes(_huge_cases(seeds)["g22a.msh"])
    with pytest.raises(MeshError, match=r"h\.msh line 5: the header declares 1000000000000 nodes, but the file has"):
        load_mesh(path)


# duplicate tets: an error naming both tets (and, for TetGen, both lines)


def test_tetgen_duplicate_tet_names_both_tets_and_lines(tmp_path):
    node = NODE + "4 1 1 1\n"
    node = node.replace("4 3 0 0", "5 3 0 0")
    ele = "3 4 0\n0 0 1 2 3\n1 1 2 3 4\n2 3 2 1 0\n"
    _write(tmp_path, "d.node", node)
    _write(tmp_path, "d.ele", ele)
    with pytest.raises(
        MeshError, match=r"d\.ele line 4: tet 2 \[3, 2, 1, 0\] duplicates tet 0 \(line 2\) \[0, 1, 2, 3\]"
    ):
        load_mesh(tmp_path / "d.node")


@pytest.mark.parametrize("ext", [".npz", ".vtu", ".msh", ".mesh"])
def test_duplicate_tets_in_other_formats(tmp_path, ext):
    tets = np.vstack([BOX.tets, BOX.tets[[4]][:, ::-1]])
    path = tmp_path / f"dup{ext}"
    write_mesh((BOX.vertices, tets), path)
    with pytest.raises(MeshError, match=rf"dup\{ext}: tet 6 .* duplicates tet 4 .*"):
        read_arrays(path)


# NaN / inf and indices out of range in the meshio formats end in validation naming the file


@pytest.mark.parametrize("ext", [".msh", ".vtu", ".vtk", ".mesh", ".npz", ".node"])
@pytest.mark.parametrize("damage", ["nan", "inf", "index"])
def test_nan_inf_and_index_out_of_range(tmp_path, ext, damage):
    v, t = BOX.vertices.copy(), BOX.tets.copy()
    if damage == "nan":
        v[3, 1] = np.nan
    elif damage == "inf":
        v[3, 1] = -np.inf
    else:
        t[2, 1] = 8
    path = tmp_path / f"bad{ext}"
    write_mesh((v, t), path)
    expected = {"nan": r"(not finite|non-finite)", "inf": r"(not finite|non-finite)", "index": r"(8|out of range)"}
    with pytest.raises(MeshError, match=expected[damage]) as info:
        load_mesh(path)
    assert "bad." in str(info.value)
    if ext == ".node":  # line-based: the line is named
        assert " line " in str(info.value)
