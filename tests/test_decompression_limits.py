"""Compressed mesh files cannot inflate beyond what they declare: ``.vtu`` data arrays (zlib or lzma; inline binary,
base64 appended or raw appended) are checked against their ``<Piece>`` counts and the cap on decompressed mesh data
(``FEPR_MAX_MESH_BYTES``, default 1 GiB) before meshio inflates anything, and ``.npz`` members against the cap and
their ``.npy`` headers before NumPy loads them. The bombs are built here, small (a few hundred kB)."""

from __future__ import annotations

import base64
import io
import lzma
import struct
import time
import tracemalloc
import zipfile
import zlib

import numpy as np
import pytest

import fepr
from fepr.cli import main
from fepr.errors import ConfigError, MeshError
from fepr.io._limits import DEFAULT_MAX_MESH_BYTES, ENV_VAR, max_mesh_bytes

V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=np.float64)
T = np.array([[0, 1, 2, 3], [1, 2, 3, 4]], dtype=np.int64)


@pytest.fixture(autouse=True)
def _default_cap(monkeypatch):
    monkeypatch.delenv(ENV_VAR, raising=False)


# ----------------------------------------------------------------------------------------------------
# Building compressed files


def zeros_stream(nbytes: int, codec: str = "zlib", chunk: int = 1 << 20) -> bytes:
    """``nbytes`` zero bytes compressed, built chunk by chunk (little memory)."""
    c = zlib.compressobj(9) if codec == "zlib" else lzma.LZMACompressor()
    out, left, z = [], nbytes, bytes(chunk)
    while left > 0:
        n = min(chunk, left)
        out.append(c.compress(z[:n]))
        left -= n
    out.append(c.flush())
    return b"".join(out)


def one_block(raw: bytes = b"", *, codec: str = "zlib", inflated: int = 0, comp: bytes = None):
    """(VTK block header, compressed data) of an array stored as one block; ``comp`` given: as is, with the header
    declaring ``inflated`` bytes (what a bomb may claim honestly or not)."""
    if comp is None:
        comp = zlib.compress(raw) if codec == "zlib" else lzma.compress(raw)
        inflated = len(raw)
    return struct.pack("<4I", 1, inflated & 0xFFFFFFFF, inflated & 0xFFFFFFFF, len(comp)), comp


def vtu(
    points=V, tets=T, *, mode="inline", codec="zlib", npoints=None, ncells=None, override=None, field=None
) -> bytes:
    """A compressed ``.vtu`` (UInt32 block headers). ``override``: {array name: (header, data)} replaces the blocks
    of ``Points``, ``connectivity``, ``offsets`` or ``types``; ``field``: (header, data) of an extra FieldData
    array (which no count bounds)."""
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    npoints = len(points) if npoints is None else npoints
    ncells = len(tets) if ncells is None else ncells
    arrays = [
        ("Points", "Points", "Float64", 3, points.tobytes()),
        ("Cells", "connectivity", "Int64", None, tets.tobytes()),
        ("Cells", "offsets", "Int64", None, (4 * np.arange(1, len(tets) + 1)).astype(np.int64).tobytes()),
        ("Cells", "types", "UInt8", None, np.full(len(tets), 10, np.uint8).tobytes()),
    ]
    if field is not None:
        arrays.append(("FieldData", "extra", "UInt8", None, None))
    override = dict(override or {})
    if field is not None:
        override["extra"] = field
    tags, appended, offset = {}, [], 0
    for section, name, typ, ncomp, raw in arrays:
        head, comp = override.get(name) or one_block(raw, codec=codec)
        nc = f' NumberOfComponents="{ncomp}"' if ncomp else ""
        if mode == "inline":
            body = base64.b64encode(head).decode() + base64.b64encode(comp).decode()
            tag = f'<DataArray type="{typ}" Name="{name}"{nc} format="binary">\n{body}\n</DataArray>'
        else:
            enc = base64.b64encode(head) + base64.b64encode(comp) if mode == "appended" else head + comp
            tag = f'<DataArray type="{typ}" Name="{name}"{nc} format="appended" offset="{offset}"/>'
            appended.append(enc)
            offset += len(enc)
        tags.setdefault(section, []).append(tag)
    compressor = {"zlib": "vtkZLibDataCompressor", "lzma": "vtkLZMADataCompressor"}[codec]
    text = (
        '<?xml version="1.0"?>\n'
        f'<VTKFile type="UnstructuredGrid" version="0.1" byte_order="LittleEndian" header_type="UInt32" '
        f'compressor="{compressor}">\n'
        "<UnstructuredGrid>\n"
        + ("<FieldData>\n" + "\n".join(tags["FieldData"]) + "\n</FieldData>\n" if "FieldData" in tags else "")
        + f'<Piece NumberOfPoints="{npoints}" NumberOfCells="{ncells}">\n'
        + "<Points>\n"
        + "\n".join(tags["Points"])
        + "\n</Points>\n<Cells>\n"
        + "\n".join(tags["Cells"])
        + "\n</Cells>\n</Piece>\n</UnstructuredGrid>\n"
    )
    data = text.encode()
    if mode != "inline":
        enc = "base64" if mode == "appended" else "raw"
        data += f'<AppendedData encoding="{enc}">\n_'.encode() + b"".join(appended) + b"\n</AppendedData>\n"
    return data + b"</VTKFile>\n"


def load_measured(path):
    """``load_mesh(path)``: the exception it raised (or None), seconds, peak traced memory (bytes)."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        fepr.load_mesh(path)
        exc = None
    except (MeshError, ConfigError) as e:
        exc = e
    seconds = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return exc, seconds, peak


BOMB_BYTES = 256 << 20  # inflates to 256 MiB; about 260 kB compressed


@pytest.fixture(scope="module")
def zlib_bomb():
    return zeros_stream(BOMB_BYTES)


@pytest.fixture(scope="module")
def lzma_bomb():
    return zeros_stream(BOMB_BYTES, "lzma")


# ----------------------------------------------------------------------------------------------------
# .vtu


@pytest.mark.parametrize("mode", ["inline", "appended", "raw"])
@pytest.mark.parametrize("codec", ["zlib", "lzma"])
def test_compressed_vtu_files_still_load(tmp_path, mode, codec):
    path = tmp_path / f"ok_{mode}_{codec}.vtu"
    path.write_bytes(vtu(mode=mode, codec=codec))
    mesh = fepr.load_mesh(path)
    assert mesh.num_vertices == 5 and mesh.num_tets == 2
    np.testing.assert_array_equal(np.asarray(mesh.tets), T)


def test_meshio_written_vtu_still_loads(tmp_path):
    import meshio

    for compression in ("zlib", "lzma", None):
        path = tmp_path / f"m_{compression}.vtu"
        meshio.write(str(path), meshio.Mesh(V, [("tetra", T)]), binary=True, compression=compression)
        assert fepr.load_mesh(path).num_tets == 2


@pytest.mark.parametrize("mode", ["inline", "appended", "raw"])
def test_vtu_points_bomb_is_refused_before_inflating(tmp_path, mode, zlib_bomb):
    """The points block of a 5-point file inflates to 256 MiB: refused after inflating 121 bytes, naming the
    file, the line of the array, the array and the count that bounds it."""
    path = tmp_path / f"bomb_{mode}.vtu"
    path.write_bytes(vtu(mode=mode, override={"Points": one_block(comp=zlib_bomb, inflated=BOMB_BYTES)}))
    assert path.stat().st_size < 400_000
    exc, seconds, peak = load_measured(path)
    assert isinstance(exc, MeshError), exc
    msg = str(exc)
    assert msg.startswith(f"{path} line 6: DataArray 'Points' in <Points>: its zlib-compressed data"), msg
    assert "inflates to more than 120 bytes" in msg
    assert "NumberOfPoints=5: 5 points x 3 components x 8 bytes (Float64) = 120 bytes" in msg
    assert "decompression bomb" in msg
    assert peak < 32 << 20, f"peak traced memory {peak / 1e6:.0f} MB"
    assert seconds < 5.0


def test_vtu_lzma_connectivity_bomb_is_refused(tmp_path, lzma_bomb):
    path = tmp_path / "conn.vtu"
    path.write_bytes(
        vtu(mode="appended", codec="lzma", override={"connectivity": one_block(comp=lzma_bomb, inflated=BOMB_BYTES)})
    )
    exc, _, peak = load_measured(path)
    assert isinstance(exc, MeshError), exc
    msg = str(exc)
    assert "DataArray 'connectivity' in <Cells>: its lzma-compressed data" in msg, msg
    assert "NumberOfCells=2: 2 cells x at most 1024 entries x 8 bytes (Int64) = 16384 bytes" in msg
    assert peak < 32 << 20


def test_vtu_block_header_that_lies_is_no_way_around(tmp_path, zlib_bomb):
    """The header claims 120 bytes; the data inflates to 256 MiB: what counts is what inflates."""
    path = tmp_path / "liar.vtu"
    path.write_bytes(vtu(mode="inline", override={"Points": one_block(comp=zlib_bomb, inflated=120)}))
    exc, _, peak = load_measured(path)
    assert isinstance(exc, MeshError) and "decompression bomb" in str(exc), exc
    assert peak < 32 << 20


def test_vtu_counts_beyond_the_cap_are_refused_before_inflating(tmp_path):
    """A file that declares 83 million points, consistent with its (compressed) data: refused by the cap on
    decompressed mesh data, naming the count and how to raise the cap."""
    path = tmp_path / "big.vtu"
    path.write_bytes(
        vtu(npoints=83_000_000, override={"Points": one_block(comp=zeros_stream(1 << 20), inflated=1 << 20)})
    )
    exc, seconds, _ = load_measured(path)
    assert isinstance(exc, MeshError), exc
    msg = str(exc)
    assert (
        f"{path} line 6: DataArray 'Points' in <Points>: the <Piece> on line 4 declares NumberOfPoints=83000000" in msg
    )
    assert (
        "1992000000 bytes once inflated, more than the limit on decompressed mesh data, 1073741824 bytes (1 GiB)" in msg
    )
    assert f"raise the limit with the environment variable {ENV_VAR}" in msg
    assert seconds < 2.0


def test_vtu_unbounded_array_meets_the_cap(tmp_path, monkeypatch):
    """A FieldData array has no count to bound it: the cap does (here lowered to 1 MiB)."""
    monkeypatch.setenv(ENV_VAR, "1MiB")
    path = tmp_path / "field.vtu"
    path.write_bytes(vtu(field=one_block(comp=zeros_stream(8 << 20), inflated=8 << 20)))
    exc, _, _ = load_measured(path)
    assert isinstance(exc, MeshError), exc
    msg = str(exc)
    assert "DataArray 'extra' in <FieldData>: its zlib-compressed data" in msg, msg
    assert (
        "inflates to more than 1048576 bytes: more than the limit on decompressed mesh data, 1048576 bytes (1 MiB)"
        in msg
    )


def test_the_cap_can_be_raised_and_lowered(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    pts = rng.random((100_000, 3))  # 2.4 MB of coordinates
    path = tmp_path / "medium.vtu"
    path.write_bytes(vtu(points=pts, tets=[[0, 1, 2, 3]]))
    monkeypatch.setenv(ENV_VAR, "1MiB")
    with pytest.raises(
        MeshError, match=r"NumberOfPoints=100000: .* = 2400000 bytes once inflated, more than the limit"
    ):
        fepr.io.read_arrays(path)
    monkeypatch.setenv(ENV_VAR, "3M")
    v, t = fepr.io.read_arrays(path)
    assert v.shape == (100_000, 3) and t.shape == (1, 4)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("", DEFAULT_MAX_MESH_BYTES),
        ("4096", 4096),
        ("2GiB", 2 << 30),
        ("1.5k", 1536),
        ("3 MB", 3 << 20),
        ("1e6", 10**6),
    ],
)
def test_cap_setting(monkeypatch, text, expected):
    monkeypatch.setenv(ENV_VAR, text)
    assert max_mesh_bytes() == expected


@pytest.mark.parametrize("text", ["lots", "-5", "0", "1X"])
def test_invalid_cap_setting_is_a_config_error_naming_the_variable(tmp_path, monkeypatch, text):
    path = tmp_path / "ok.vtu"
    path.write_bytes(vtu())
    monkeypatch.setenv(ENV_VAR, text)
    with pytest.raises(
        ConfigError, match=rf"^environment variable {ENV_VAR}='{text}': must be a positive number of bytes"
    ):
        fepr.load_mesh(path)


# ----------------------------------------------------------------------------------------------------
# .npz


def npz_bomb(path, nverts: int, *, tets=T, shape=None, level: int = 9):
    """An ``.npz`` whose deflated ``vertices`` member is ``nverts x 3`` float64 zeros (written in chunks);
    ``shape`` overrides the shape its ``.npy`` header declares."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=level) as zf:
        with zf.open("vertices.npy", "w", force_zip64=True) as fh:
            head = io.BytesIO()
            declared = (nverts, 3) if shape is None else shape
            np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": declared})
            fh.write(head.getvalue())
            left, z = nverts * 24, bytes(1 << 22)
            while left > 0:
                n = min(left, len(z))
                fh.write(z[:n])
                left -= n
        buf = io.BytesIO()
        np.save(buf, np.asarray(tets, dtype=np.int64))
        zf.writestr("tets.npy", buf.getvalue())


def test_npz_bomb_is_refused_from_the_zip_directory(tmp_path, monkeypatch):
    """4 million vertices (96 MB) in a ~100 kB archive, cap lowered to 16 MiB: refused before anything is
    inflated, naming the file and the array."""
    path = tmp_path / "bomb.npz"
    npz_bomb(path, 4_000_000)
    assert path.stat().st_size < 400_000
    monkeypatch.setenv(ENV_VAR, "16MiB")
    exc, seconds, peak = load_measured(path)
    assert isinstance(exc, MeshError), exc
    msg = str(exc)
    assert msg.startswith(f"{path}: array 'vertices' declares 96000128 bytes uncompressed ("), msg
    assert "more than the limit on decompressed mesh data, 16777216 bytes (16 MiB)" in msg
    assert seconds < 1.0 and peak < 8 << 20


def test_npz_with_a_larger_cap_loads_on(tmp_path, monkeypatch):
    path = tmp_path / "zeros.npz"
    npz_bomb(path, 1000)
    monkeypatch.setenv(ENV_VAR, "1KiB")
    with pytest.raises(MeshError, match="array 'vertices' declares 24128 bytes"):
        fepr.io.read_arrays(path)
    monkeypatch.setenv(ENV_VAR, "1MiB")
    v, t = fepr.io.read_arrays(path)
    assert v.shape == (1000, 3) and t.shape == (2, 4)


def test_npz_header_declaring_more_than_the_member_holds(tmp_path):
    """The .npy header claims 83 million vertices, the member holds 10: refused before NumPy allocates."""
    path = tmp_path / "liar.npz"
    npz_bomb(path, 10, shape=(83_000_000, 3))
    exc, _, peak = load_measured(path)
    assert isinstance(exc, MeshError), exc
    assert str(exc) == (
        f"{path}: array 'vertices' declares shape (83000000, 3) of float64 (1992000000 bytes), but its member of "
        "the archive holds only 240 bytes of data; the file is truncated or corrupt"
    )
    assert peak < 8 << 20


def test_npz_total_of_arrays_to_load_meets_the_cap(tmp_path, monkeypatch):
    path = tmp_path / "two.npz"
    rng = np.random.default_rng(1)
    np.savez(path, vertices=rng.random((4000, 3)), tets=np.zeros((4000, 4), dtype=np.int64), unused=np.zeros(10**6))
    monkeypatch.setenv(ENV_VAR, "150KiB")  # each array to load fits (96 kB, 128 kB), both together do not
    with pytest.raises(
        MeshError, match=r"the arrays to load declare 224256 bytes uncompressed in all \(the largest, 'tets'"
    ):
        fepr.io.read_arrays(path)


def test_cli_mesh_info_on_npz_bomb_fails_with_the_message(tmp_path, monkeypatch, capsys):
    path = tmp_path / "bomb.npz"
    npz_bomb(path, 2_000_000)
    monkeypatch.setenv(ENV_VAR, "8MiB")
    code = main(["mesh", str(path), "--info"])
    err = capsys.readouterr().err
    assert code != 0
    assert "array 'vertices' declares 48000128 bytes uncompressed" in err, err
    assert "Traceback" not in err


def test_scene_velocities_npy_declaring_a_huge_shape(tmp_path):
    """``[initial] velocities``: a .npy header declaring 1e10 rows is an error naming the file (was a MemoryError
    traceback: numpy allocated by the header's shape)."""
    from fepr.scene import scene_from_dict

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (10**10, 3)})
    (tmp_path / "v.npy").write_bytes(head.getvalue() + bytes(240))
    d = {
        "mesh": {"builtin": "box", "size": 0.1, "resolution": 1},
        "material": {"youngs_modulus": 1e5, "poisson_ratio": 0.3},
        "mass": {"density": 1000.0},
        "initial": {"velocity": [0.0, 0.0, 1.0], "velocities": "v.npy"},
    }
    scene = scene_from_dict(d, tmp_path, source="s.toml")
    with pytest.raises(ConfigError, match=r"^s\.toml: \[initial\] velocities: cannot read .*v\.npy"):
        scene.build()
