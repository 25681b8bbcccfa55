"""Cheap checks of the counts in a file's headers, run before meshio reads the file.

meshio allocates arrays from the counts a file declares (``$Nodes``, ``POINTS``, ``Vertices``, ...) before it
reads the data. A damaged or hostile file that declares 10^12 nodes would make it try to allocate terabytes.
:func:`prescan` reads only the headers (the file is memory-mapped, not loaded) and rejects every count that
cannot fit in the file: each item needs at least a known number of bytes. Compressed ``.vtu`` arrays, which can
inflate far beyond the file, are checked against the file's counts and a cap (:mod:`fepr.io._vtu_prescan`). What it
cannot check it leaves to meshio, whose errors are turned into :class:`~fepr.errors.MeshError` by the caller.
"""

from __future__ import annotations

import mmap
import re
import struct
from pathlib import Path
from typing import List, Tuple

from ..errors import ConfigError, MeshError

__all__ = ["prescan"]


def prescan(p: Path, fmt: str) -> None:
    """Raise :class:`MeshError` naming the file (and the line) if a header count cannot fit in the file.

    ``fmt`` is ``"gmsh"``, ``"vtk"``, ``"vtu"``, ``"medit"`` (ASCII ``.mesh``), ``"meshb"``, ``"stl"`` or ``"ply"``;
    other formats are not checked. For ``"vtu"``, compressed data arrays are inflated (bounded, the output discarded)
    and checked against the counts the file declares and the cap on decompressed mesh data
    (:mod:`fepr.io._vtu_prescan`, :mod:`fepr.io._limits`).
    """
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise MeshError(f"{p}: cannot read file: {exc.strerror or exc}") from None
    if size == 0:
        raise MeshError(f"{p}: cannot read: the file is empty (0 bytes)")
    check = _CHECKS.get(fmt)
    if check is None:
        return
    try:
        with open(p, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            check(p, mm, size)
    except ConfigError:  # FEPR_MAX_MESH_BYTES is invalid: the message names it
        raise
    except MeshError as exc:
        if fmt == "vtu":  # names the file, line and array already
            raise
        raise MeshError(f"{p}: cannot read file: {exc}") from None
    except (OSError, ValueError) as exc:
        raise MeshError(f"{p}: cannot read file: {exc}") from None


def _lineno(mm, pos: int) -> int:
    return mm[:pos].count(b"\n") + 1 if pos < 50_000_000 else -1


def _where(p: Path, mm, pos: int) -> str:
    n = _lineno(mm, pos)
    return f"{p} line {n}" if n > 0 else f"{p}"


def _too_many(p: Path, mm, pos: int, count: int, what: str, need: int, size: int) -> MeshError:
    return MeshError(
        f"{_where(p, mm, pos)}: the header declares {count} {what}, but the file has only {size} bytes "
        f"(at least {need} bytes would be needed); the file is truncated or corrupt"
    )


def _check_count(p: Path, mm, pos: int, count: int, what: str, min_bytes: int, size: int) -> None:
    if count < 0:
        raise MeshError(f"{_where(p, mm, pos)}: the header declares a negative number of {what} ({count})")
    need = count * min_bytes
    if need > size:
        raise _too_many(p, mm, pos, count, what, need, size)


def _line_at(mm, pos: int) -> Tuple[bytes, int]:
    """The line starting at ``pos`` (without its newline) and the position after it."""
    end = mm.find(b"\n", pos)
    if end < 0:
        end = len(mm)
    return bytes(mm[pos:end]).strip(), end + 1


def _ints(p: Path, mm, pos: int, line: bytes, n: int, what: str) -> List[int]:
    tokens = line.split()
    try:
        values = [int(t) for t in tokens[:n]]
    except ValueError:
        values = []
    if len(values) != n:
        raise MeshError(f"{_where(p, mm, pos)}: expected {n} integer(s) ({what}), got {line[:80]!r}")
    return values


# ----------------------------------------------------------------------------------------------------
# Gmsh


def _gmsh(p: Path, mm, size: int) -> None:
    start = mm.find(b"$MeshFormat")
    if start < 0:
        return  # not a Gmsh file; meshio says so
    line, pos = _line_at(mm, mm.find(b"\n", start) + 1)
    tokens = line.split()
    if len(tokens) < 3:
        return
    try:
        version, binary, dsize = float(tokens[0]), int(tokens[1]) == 1, int(tokens[2])
    except ValueError:
        return
    if dsize not in (4, 8):
        return
    st = "<Q" if dsize == 8 else "<I"
    for section in (b"$Nodes", b"$Elements"):
        at = mm.find(section + b"\n", pos)
        if at < 0:
            at = mm.find(section + b"\r\n", pos)
        if at < 0:
            continue
        body = mm.find(b"\n", at) + 1
        nodes = section == b"$Nodes"
        what = "nodes" if nodes else "elements"
        if version < 3:
            line, _ = _line_at(mm, body)
            (count,) = _ints(p, mm, body, line, 1, f"number of {what}")
            _check_count(p, mm, body, count, what, (28 if nodes else 12) if binary else 8, size)
        elif not binary:
            _gmsh4_ascii(p, mm, body, nodes, size)
        else:
            _gmsh4_binary(p, mm, body, nodes, size, st, dsize)


def _gmsh4_ascii(p: Path, mm, body: int, nodes: bool, size: int) -> None:
    what = "nodes" if nodes else "elements"
    line, pos = _line_at(mm, body)
    nblocks, total, _, _ = _ints(p, mm, body, line, 4, f"numEntityBlocks num{what.title()} minTag maxTag")
    _check_count(p, mm, body, nblocks, "entity blocks", 8, size)
    _check_count(p, mm, body, total, what, 8 if nodes else 4, size)
    seen = 0
    for _ in range(nblocks):
        if pos >= size:
            raise MeshError(f"{p}: file is truncated inside the ${what.title()} section")
        line, nxt = _line_at(mm, pos)
        _, _, parametric, count = _ints(p, mm, pos, line, 4, "entityDim entityTag parametric/type count")
        seen += count
        if count < 0 or seen > total:
            raise MeshError(
                f"{_where(p, mm, pos)}: an entity block declares {count} {what}, more than the {total} the "
                f"${what.title()} header declares in all"
            )
        # skip the block's lines without parsing them: nodes have a tag line and a coordinate line each
        skip = 2 * count if nodes else count
        for _ in range(skip):
            nl = mm.find(b"\n", nxt)
            if nl < 0:
                raise MeshError(
                    f"{p}: file is truncated: the entity block on line {_lineno(mm, pos)} declares {count} {what}"
                )
            nxt = nl + 1
        pos = nxt


def _gmsh4_binary(p: Path, mm, body: int, nodes: bool, size: int, st: str, dsize: int) -> None:
    what = "nodes" if nodes else "elements"
    head = mm[body : body + 4 * dsize]
    if len(head) < 4 * dsize:
        raise MeshError(f"{p}: file is truncated in the ${what.title()} header")
    nblocks, total, _, _ = (struct.unpack_from(st, head, i * dsize)[0] for i in range(4))
    _check_count(p, mm, body, nblocks, "entity blocks", 12 + dsize, size)
    _check_count(p, mm, body, total, what, dsize + 24 if nodes else 2 * dsize, size)
    pos = body + 4 * dsize
    seen = 0
    for _ in range(nblocks):
        rec = mm[pos : pos + 12 + dsize]
        if len(rec) < 12 + dsize:
            raise MeshError(f"{p}: file is truncated inside the ${what.title()} section (byte {pos})")
        _, _, kind = struct.unpack_from("<iii", rec, 0)
        count = struct.unpack_from(st, rec, 12)[0]
        seen += count
        if seen > total:
            raise MeshError(
                f"{p}: an entity block (byte {pos}) declares {count} {what}, more than the {total} the "
                f"${what.title()} header declares in all"
            )
        if nodes:
            if kind != 0:
                return  # parametric nodes: meshio refuses them
            nbytes = count * (dsize + 24)
        else:
            per = GMSH_NODES_PER_ELEMENT.get(kind)
            if per is None:
                return  # unknown element type: meshio reports it
            nbytes = count * (1 + per) * dsize
        pos += 12 + dsize + nbytes
        if pos > size:
            raise _too_many(p, mm, 0, count, f"{what} in one entity block", nbytes, size)


# ----------------------------------------------------------------------------------------------------
# VTK legacy

_VTK_SIZES = {"bit": 1, "char": 1, "unsigned_char": 1, "short": 2, "unsigned_short": 2, "int": 4}


def _vtk(p: Path, mm, size: int) -> None:
    head = bytes(mm[:4096]).split(b"\n")
    binary = len(head) > 2 and head[2].strip().upper() == b"BINARY"
    patterns = [
        (rb"(?m)^POINTS[ \t]+(\d+)[ \t]+(\w+)", "points", 3),
        (rb"(?m)^CELLS[ \t]+(\d+)[ \t]+(\d+)", "cells", 1),
        (rb"(?m)^CELL_TYPES[ \t]+(\d+)", "cell types", 1),
        (rb"(?m)^POINT_DATA[ \t]+(\d+)", "point data values", 1),
        (rb"(?m)^CELL_DATA[ \t]+(\d+)", "cell data values", 1),
    ]
    for pattern, what, width in patterns:
        for m in re.finditer(pattern, mm):
            counts = [int(g) for g in m.groups() if g.isdigit()]
            per = 1 if binary else 2
            if what == "points" and binary:
                per = 8 if m.group(2).lower() == b"double" else 4
            for count in counts:
                _check_count(p, mm, m.start(), count * width, what, per, size + 1)


# ----------------------------------------------------------------------------------------------------
# Medit

_MEDIT_WIDTH = {
    b"Vertices": 4,
    b"Edges": 3,
    b"Triangles": 4,
    b"Quadrilaterals": 5,
    b"Tetrahedra": 5,
    b"Prisms": 7,
    b"Pyramids": 6,
    b"Hexahedra": 9,
    b"Hexaedra": 9,
    b"Corners": 1,
    b"Normals": 3,
    b"NormalAtVertices": 2,
    b"SubDomainFromMesh": 4,
    b"VertexOnGeometricVertex": 2,
    b"VertexOnGeometricEdge": 3,
    b"EdgeOnGeometricEdge": 2,
    b"Identifier": 1,
    b"Geometry": 1,
}


def _medit(p: Path, mm, size: int) -> None:
    for m in re.finditer(rb"(?m)^[ \t]*([A-Za-z]+)[ \t]*\r?\n[ \t]*(-?\d+)", mm):
        width = _MEDIT_WIDTH.get(m.group(1))
        if width is not None:
            _check_count(p, mm, m.start(2), int(m.group(2)), m.group(1).decode().lower(), 2 * width - 1, size + 1)


#: Nodes per element of the Gmsh element types (the ``elm-type`` codes of the Gmsh file format, section "MSH file
#: format" of the Gmsh reference manual). The scan's own table: meshio keeps its copy private, and a scan that
#: imported it would break on a meshio upgrade. A type not listed stops the scan (meshio reads or reports it).
GMSH_NODES_PER_ELEMENT = {
    1: 2, 2: 3, 3: 4, 4: 4, 5: 8, 6: 6, 7: 5, 8: 3, 9: 6, 10: 9, 11: 10, 12: 27, 13: 18, 14: 14, 15: 1, 16: 8,
    17: 20, 18: 15, 19: 13, 20: 9, 21: 10, 22: 12, 23: 15, 24: 15, 25: 21, 26: 4, 27: 5, 28: 6, 29: 20, 30: 35,
    31: 56, 92: 64, 93: 125,
}  # fmt: skip

#: The binary Medit (``.meshb``) keywords the scan walks, by code (libMeshb's ``GmfKwdCod``): name, whether a count
#: follows, and the item layout (``i`` an integer, ``r`` a real, ``d`` the next letter repeated once per space
#: dimension). The common element and vertex keywords; at any other the scan stops and leaves the file to meshio.
MESHB_KEYWORDS = {
    1: ("GmfMeshVersionFormatted", "", "i"),
    2: ("GmfReserved", "", ""),
    3: ("GmfDimension", "", "i"),
    4: ("GmfVertices", "i", "dri"),
    5: ("GmfEdges", "i", "iii"),
    6: ("GmfTriangles", "i", "iiii"),
    7: ("GmfQuadrilaterals", "i", "iiiii"),
    8: ("GmfTetrahedra", "i", "iiiii"),
    9: ("GmfPrisms", "i", "iiiiiii"),
    10: ("GmfHexahedra", "i", "iiiiiiiii"),
    12: ("GmfReserved", "", ""),
    13: ("GmfCorners", "i", "i"),
    14: ("GmfRidges", "i", "i"),
    15: ("GmfRequiredVertices", "i", "i"),
    54: ("GmfEnd", "", ""),
}


def _meshb_item_bytes(layout: str, dim: int, int_bytes: int, real_bytes: int) -> int:
    """Bytes of one item of a ``.meshb`` keyword with ``layout`` (see :data:`MESHB_KEYWORDS`)."""
    total, repeat = 0, 1
    for c in layout:
        if c == "d":
            repeat = dim
            continue
        total += repeat * (int_bytes if c == "i" else real_bytes)
        repeat = 1
    return total


def _meshb(p: Path, mm, size: int) -> None:
    import numpy as np

    if size < 8:
        raise MeshError(f"{p}: file is truncated ({size} bytes; a .meshb file starts with 8 header bytes)")
    code, version = struct.unpack_from("<ii", mm, 0)
    if code != 1 or not 1 <= version <= 4:
        return  # byte-swapped or not a meshb file: meshio decides
    itype, ftype, pbytes = {1: ("i4", "f4", 4), 2: ("i4", "f8", 4), 3: ("i4", "f8", 8), 4: ("i8", "f8", 8)}[version]
    pos = 8
    dim = 3
    while pos + 4 <= size:
        (field,) = struct.unpack_from("<i", mm, pos)
        info = MESHB_KEYWORDS.get(field)
        if info is None or info[0] == "GmfEnd":
            return  # a keyword this scan does not know: meshio reads (or reports) the rest
        pos += 4
        if info[0] == "GmfReserved":
            continue
        pos += pbytes
        nitems = 1
        if info[1] == "i":
            isize = np.dtype(itype).itemsize
            if pos + isize > size:
                raise MeshError(f"{p}: file is truncated at byte {pos} (keyword {info[0]})")
            nitems = int(np.frombuffer(mm, dtype=itype, count=1, offset=pos)[0])
            pos += isize
        if info[0] == "GmfDimension":  # its value is an int32 whatever the version (as meshio reads it)
            if pos + 4 > size:
                raise MeshError(f"{p}: file is truncated at byte {pos} (keyword Dimension)")
            (dim,) = struct.unpack_from("<i", mm, pos)
            if dim not in (2, 3):
                return
            pos += 4
            continue
        item = _meshb_item_bytes(info[2], dim, np.dtype(itype).itemsize, np.dtype(ftype).itemsize)
        if nitems < 0 or pos + nitems * item > size:
            raise MeshError(
                f"{p}: keyword {info[0][3:]} at byte {pos} declares {nitems} items of {item} bytes, but the file "
                f"has only {size} bytes; the file is truncated or corrupt"
            )
        pos += nitems * item


# ----------------------------------------------------------------------------------------------------
# STL, PLY


def _stl(p: Path, mm, size: int) -> None:
    if size < 84 or bytes(mm[:5]).lower() == b"solid" and b"facet" in bytes(mm[: min(size, 1024)]):
        return  # ASCII (meshio reads it line by line)
    (count,) = struct.unpack_from("<I", mm, 80)
    if 84 + 50 * count > size:
        raise MeshError(
            f"{p}: the binary STL header declares {count} triangles ({84 + 50 * count} bytes), but the file has "
            f"only {size} bytes; the file is truncated or corrupt"
        )


_PLY_SIZES = {
    "char": 1,
    "uchar": 1,
    "int8": 1,
    "uint8": 1,
    "short": 2,
    "ushort": 2,
    "int16": 2,
    "uint16": 2,
    "int": 4,
    "uint": 4,
    "int32": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}


def _ply(p: Path, mm, size: int) -> None:
    end = mm.find(b"end_header")
    if end < 0:  # meshio would wait for it forever
        raise MeshError(f"{p}: the PLY header is not terminated by an 'end_header' line (truncated or not PLY)")
    lines = bytes(mm[:end]).decode("latin-1").split("\n")
    binary = any(line.startswith("format binary") for line in lines)
    elements: List[Tuple[int, int, List[int]]] = []  # (line, count, property sizes)
    for i, line in enumerate(lines, start=1):
        tokens = line.split()
        if len(tokens) >= 3 and tokens[0] == "element":
            try:
                count = int(tokens[2])
            except ValueError:
                raise MeshError(f"{p} line {i}: element count must be an integer, got {tokens[2]!r}") from None
            elements.append((i, count, []))
        elif len(tokens) >= 3 and tokens[0] == "property" and elements:
            key = tokens[2] if tokens[1] == "list" else tokens[1]
            elements[-1][2].append(_PLY_SIZES.get(key, 1))
    for lineno, count, sizes in elements:
        per = max(1, sum(sizes)) if binary else max(1, 2 * len(sizes) - 1)
        if count < 0 or count * per > size:
            raise MeshError(
                f"{p} line {lineno}: the header declares {count} elements, but the file has only {size} bytes; "
                "the file is truncated or corrupt"
            )


def _vtu(p: Path, mm, size: int) -> None:
    from ._vtu_prescan import check_vtu

    check_vtu(p, mm, size)


_CHECKS = {"gmsh": _gmsh, "vtk": _vtk, "vtu": _vtu, "medit": _medit, "meshb": _meshb, "stl": _stl, "ply": _ply}
