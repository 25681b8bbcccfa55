"""Decompression checks of VTK XML (``.vtu``) files, run before meshio reads them.

A ``.vtu`` file with ``compressor="vtkZLibDataCompressor"`` (or LZMA) stores each data array as compressed blocks.
meshio inflates every block whole (``zlib.decompress``), so a 2.6 MB file whose points block inflates to 2 GB is
read into memory before anything can object. :func:`check_vtu` walks the same arrays meshio will read, in the same
way (inline ``format="binary"`` arrays, base64 ``<AppendedData>``, and raw appended data, which meshio reads when
the file is not well-formed XML), and inflates every block with a bounded decompressor (at most 1 MiB at a time,
the output discarded). It stops at the first array that would inflate to more than

- what the counts of its ``<Piece>`` allow: ``NumberOfPoints x NumberOfComponents x item size`` for ``<Points>`` and
  ``<PointData>``, ``NumberOfCells x NumberOfComponents x item size`` for ``<CellData>``, ``NumberOfCells + 1``
  items for ``offsets`` and ``types``, and at most :data:`MAX_ENTRIES_PER_CELL` items per cell for
  ``connectivity``, ``faces`` and ``faceoffsets``;
- the cap on decompressed mesh data, summed over the file's arrays (:func:`fepr.io._limits.max_mesh_bytes`:
  1 GiB unless the environment variable ``FEPR_MAX_MESH_BYTES`` says otherwise).

Counts that alone exceed the cap are rejected before anything is inflated. Files without a compressor are not
checked here: their arrays cannot be larger than the file.
"""

from __future__ import annotations

import base64
import binascii
import lzma
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple
from xml.parsers import expat

import numpy as np

from ..errors import MeshError
from ._limits import max_mesh_bytes, over_limit

__all__ = ["MAX_ENTRIES_PER_CELL", "check_vtu"]

#: Item sizes of the VTK XML data types (the names meshio accepts).
_TYPES = {
    "Int8": "i1",
    "UInt8": "u1",
    "Int16": "i2",
    "UInt16": "u2",
    "Int32": "i4",
    "UInt32": "u4",
    "Int64": "i8",
    "UInt64": "u8",
    "Float32": "f4",
    "Float64": "f8",
}

#: The most entries of ``connectivity`` (and of polyhedron ``faces``) a cell may have for the check: generous (the
#: largest fixed VTK cell, the triquadratic hexahedron, has 27 nodes; Lagrange and polyhedron cells can have more).
MAX_ENTRIES_PER_CELL = 1024

_CHUNK = 1 << 20
_SECTIONS = ("Points", "Cells", "PointData", "CellData", "FieldData")
_CODECS = {"vtkZLibDataCompressor": "zlib", "vtkLZMADataCompressor": "lzma"}


@dataclass
class _Array:
    """One ``<DataArray>``: its attributes, line, enclosing section and ``<Piece>`` (attributes and line)."""

    attrs: Dict[str, str]
    line: int
    section: Optional[str]
    piece: Optional[Dict[str, str]]
    piece_line: int = 0
    text: Tuple[int, int] = (0, 0)  # inline text: [start, end) in the file

    @property
    def name(self) -> str:
        return self.attrs.get("Name", "?")

    def where(self, p: Path) -> str:
        section = f" in <{self.section}>" if self.section else ""
        at = f"{p} line {self.line}" if self.line > 0 else f"{p}"
        return f"{at}: DataArray {self.name!r}{section}"


@dataclass
class _Budget:
    """The bytes inflated so far against the cap."""

    cap: int
    used: int = 0
    arrays: List[str] = field(default_factory=list)


def check_vtu(p: Path, mm, size: int) -> None:
    """Raise :class:`MeshError` if a compressed array of the ``.vtu`` file ``p`` (memory-mapped as ``mm``) would
    inflate beyond what its counts allow or beyond the cap on decompressed mesh data."""
    head = bytes(mm[: min(size, 1 << 16)])
    m = re.search(rb"<VTKFile\b([^>]*)>", head)
    if m is None:
        return  # not VTK XML: meshio says so
    codec = _CODECS.get(_attrs(m.group(1)).get("compressor", ""))
    if codec is None:
        return  # uncompressed (nothing inflates) or a compressor meshio rejects
    cap = max_mesh_bytes()
    parsed = _parse_xml(mm, size)
    if parsed is None:
        _check_raw(p, mm, codec, cap)
    else:
        _check_xml(p, mm, size, codec, cap, *parsed)


def _attrs(raw: bytes) -> Dict[str, str]:
    text = raw.decode("utf-8", "replace")
    return {k: v1 if v1 is not None else v2 for k, v1, v2 in _ATTR.findall(text)} if text else {}


_ATTR = re.compile(r"""([\w:.-]+)\s*=\s*(?:"([^"]*)"|'([^']*)')""")


# ----------------------------------------------------------------------------------------------------
# Well-formed XML: inline binary arrays and base64 appended data (meshio's ElementTree path)


def _parse_xml(mm, size: int):
    """``(root attributes, arrays, appended text span or None)``, or ``None`` when the file is not well-formed
    XML (meshio then reads it as raw appended data)."""
    parser = expat.ParserCreate(namespace_separator="}")  # as xml.etree.ElementTree's parser
    stack: List[str] = []
    arrays: List[_Array] = []
    root: Dict[str, str] = {}
    state: Dict[str, object] = {"piece": None, "piece_line": 0, "appended": None, "open": None}

    def start(name, attrs):
        if state["open"] is not None:  # a child inside a DataArray ends its .text
            arr, begin = state["open"]
            arr.text = (begin, parser.CurrentByteIndex)
            state["open"] = None
        if not stack and name == "VTKFile":
            root.update(attrs)
        if name == "Piece":
            state["piece"], state["piece_line"] = dict(attrs), parser.CurrentLineNumber
        if name == "DataArray":
            section = next((s for s in reversed(stack) if s in _SECTIONS), None)
            piece = state["piece"] if "Piece" in stack else None
            arr = _Array(dict(attrs), parser.CurrentLineNumber, section, piece, state["piece_line"])
            arrays.append(arr)
            state["open"] = (arr, _tag_end(mm, parser.CurrentByteIndex))
        if name == "AppendedData" and len(stack) == 1 and state["appended"] is None:
            state["appended"] = (dict(attrs), _tag_end(mm, parser.CurrentByteIndex))
        stack.append(name)

    def end(name):
        if state["open"] is not None:
            arr, begin = state["open"]
            arr.text = (begin, parser.CurrentByteIndex)
            state["open"] = None
        if name == "AppendedData" and isinstance(state["appended"], tuple) and len(state["appended"]) == 2:
            attrs, begin = state["appended"]
            state["appended"] = (attrs, begin, parser.CurrentByteIndex)
        stack.pop()

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    try:
        for pos in range(0, size, 1 << 22):
            parser.Parse(mm[pos : pos + (1 << 22)], False)
        parser.Parse(b"", True)
    except expat.ExpatError:
        return None
    return root, arrays, state["appended"]


def _tag_end(mm, pos: int) -> int:
    """The position after the ``>`` of the start tag at ``pos``."""
    end = mm.find(b">", pos)
    return len(mm) if end < 0 else end + 1


def _strip(mm, start: int, end: int) -> Tuple[int, int]:
    """``[start, end)`` without leading and trailing whitespace (as ``str.strip``)."""
    while start < end and mm[start : start + 1].isspace():
        start += 1
    while end > start and mm[end - 1 : end].isspace():
        end -= 1
    return start, end


def _check_xml(p: Path, mm, size: int, codec: str, cap: int, root, arrays: List[_Array], appended) -> None:
    header = _header_dtype(root.get("header_type", "UInt32"), root.get("byte_order"))
    if header is None:
        return  # meshio rejects the header type
    app: Optional[Tuple[int, int]] = None
    if appended is not None and len(appended) == 3 and appended[0].get("encoding") == "base64":
        start, end = _strip(mm, appended[1], appended[2])
        if start < end and mm[start : start + 1] == b"_":
            app = (start + 1, end)
    budget = _Budget(cap)
    for arr in arrays:
        fmt = arr.attrs.get("format", "ascii")
        if fmt not in ("binary", "appended") or arr.attrs.get("type") not in _TYPES:
            continue  # ascii (not compressed) or an unknown type (meshio rejects it before inflating)
        bound = _bound(p, arr, cap)
        if fmt == "binary":
            span = _strip(mm, *arr.text)
        else:
            # (meshio reads the arrays of <FieldData> before those of the pieces, whatever their order in the file:
            # an array it cannot read is skipped here, not the end of the check)
            if app is None:
                continue  # no base64 appended data: meshio fails on this array
            try:
                offset = int(arr.attrs.get("offset", ""))
            except ValueError:
                continue  # meshio's int() fails on this array before inflating it
            n = app[1] - app[0]
            offset = max(0, offset + n) if offset < 0 else min(offset, n)
            span = (app[0] + offset, app[1])
        _check_b64_array(p, mm, span, header, codec, arr, bound, budget)


def _check_b64_array(p: Path, mm, span, header: np.dtype, codec: str, arr: _Array, bound, budget: _Budget) -> None:
    """The base64 blocks of one array, as meshio's ``read_compressed_binary`` reads them."""
    start, end = span
    isz = header.itemsize
    first = _b64(mm[start : min(end, start + _b64_chars(isz))])
    if first is None or len(first) < isz:
        return  # meshio fails on the header
    nblocks = int(np.frombuffer(first[:isz], header)[0])
    nhead_chars = _b64_chars(isz * (3 + max(nblocks, 0)))
    head = _b64(mm[start : min(end, start + nhead_chars)])
    if head is None or len(head) % isz:
        return
    items = np.frombuffer(head, header)
    sizes = [int(s) for s in items[3:]][: max(nblocks, 0)]
    # meshio decodes the rest of the text and cuts it at the cumulative block sizes (in the header's integer type)
    wrap = 1 << (8 * isz)
    offsets = [0]
    for s in sizes:
        offsets.append((offsets[-1] + s) % wrap)
    data_start = start + nhead_chars
    need = max(offsets)
    data = _b64(mm[data_start : min(end, data_start + _b64_chars(need))])
    if data is None or (len(data) < need and data_start + _b64_chars(need) < end):
        data = _b64(mm[data_start:end])  # whitespace inside the text: decode all of it, as meshio does
        if data is None:
            return
    blocks = (data[offsets[k] : offsets[k + 1]] for k in range(len(sizes)))
    _inflate_array(p, codec, blocks, arr, bound, budget)


def _b64(raw) -> Optional[bytes]:
    try:
        return base64.b64decode(bytes(raw))
    except (binascii.Error, ValueError):
        return None


def _b64_chars(nbytes: int) -> int:
    return -(-nbytes // 3) * 4


def _header_dtype(name: str, byte_order: Optional[str]) -> Optional[np.dtype]:
    code = _TYPES.get(name)
    if code is None:
        return None
    dt = np.dtype(code)
    if byte_order is not None:
        dt = dt.newbyteorder("<" if byte_order == "LittleEndian" else ">")
    return dt


# ----------------------------------------------------------------------------------------------------
# Raw appended data (meshio's _parse_raw_binary path)


def _check_raw(p: Path, mm, codec: str, cap: int) -> None:
    import xml.etree.ElementTree as ET

    m = re.search(rb'<AppendedData[^>]+(?:">)', mm)
    if m is None:
        return  # meshio raises ReadError
    i_start, i_stop = m.end(), mm.find(b"</AppendedData>")
    try:
        root = ET.fromstring(bytes(mm[:i_start]).decode() + bytes(mm[i_stop:]).decode())
    except (ET.ParseError, UnicodeDecodeError, ValueError):
        return  # meshio fails the same way, before inflating
    header = _header_dtype(root.get("header_type", "UInt32"), None)
    if header is None:
        return
    if "byte_order" in root.attrib:
        header = header.newbyteorder("<" if root.get("byte_order") == "LittleEndian" else ">")
    under = mm.find(b"_", i_start, i_stop) if i_stop >= i_start else -1
    if under < 0:
        return  # meshio's split fails
    base = under + 1
    nl = mm.rfind(b"\n", base, i_stop)
    stop = nl if nl >= 0 else i_stop
    arrays = _raw_arrays(root, mm[:i_start])
    budget = _Budget(cap)
    isz = header.itemsize
    i = 0
    n = stop - base
    while i < n:
        arr = arrays.get(str(i))
        if arr is None:
            return  # meshio: no DataArray at this offset
        first = mm[base + i : min(base + i + isz, stop)]
        if len(first) < isz:
            return
        nblocks = int(np.frombuffer(first, header)[0])
        if nblocks < 0:
            return  # meshio reads no block and then fails on the offsets
        nhead = (3 + nblocks) * isz
        raw_head = mm[base + i : min(base + i + nhead, stop)]
        if len(raw_head) % isz:
            return
        items = np.frombuffer(raw_head, header)
        sizes = [int(s) for s in items[3 : 3 + max(nblocks, 0)]]

        def blocks(i=i, nhead=nhead, sizes=sizes):
            j = 0
            for s in sizes:
                lo, hi = base + i + j + nhead, min(base + i + j + s + nhead, stop)
                yield mm[lo:hi] if hi > lo else b""
                j += s

        _inflate_array(p, codec, blocks(), arr, _bound(p, arr, cap), budget)
        if len(sizes) < nblocks:
            return  # meshio fails on the missing block size
        i += sum(sizes) + nhead


def _raw_arrays(root, header_bytes) -> Dict[str, _Array]:
    """The DataArrays of the raw path by their ``offset`` attribute (the first one for each), with section and
    piece, and the lines of their tags and pieces found in the header text."""
    text = bytes(header_bytes)
    lines = {}
    for m in re.finditer(rb"""<DataArray\b[^>]*\boffset\s*=\s*["']([^"']*)["']""", text):
        lines.setdefault(m.group(1).decode("utf-8", "replace"), text.count(b"\n", 0, m.start()) + 1)
    piece_lines = [text.count(b"\n", 0, m.start()) + 1 for m in re.finditer(rb"<Piece\b", text)]
    out: Dict[str, _Array] = {}
    pieces = iter(piece_lines)

    def visit(elem, section, piece, piece_line):
        for child in elem:
            sec = child.tag if child.tag in _SECTIONS else section
            pc, pl = piece, piece_line
            if child.tag == "Piece":
                pc, pl = dict(child.attrib), next(pieces, 0)
            if child.tag == "DataArray":
                off = child.get("offset")
                if off is not None and off not in out:
                    out[off] = _Array(dict(child.attrib), lines.get(off, 0), sec, pc, pl)
            visit(child, sec, pc, pl)

    visit(root, None, None, 0)
    return out


# ----------------------------------------------------------------------------------------------------
# Bounds and bounded inflation


def _bound(p: Path, arr: _Array, cap: int) -> Optional[Tuple[int, str]]:
    """``(bytes, reason)``: the most the array may inflate to by the counts of its Piece, or ``None`` when nothing
    bounds it but the cap. Raises when the size the counts give (points, point and cell data, offsets, types: not
    the loose bound of connectivity) alone exceeds the cap."""
    if arr.piece is None or arr.section not in ("Points", "Cells", "PointData", "CellData"):
        return None
    if arr.attrs.get("type") not in _TYPES:
        return None
    isz = np.dtype(_TYPES[arr.attrs["type"]]).itemsize
    kind = arr.attrs["type"]
    ncomp = _int(arr.attrs.get("NumberOfComponents", "")) or (3 if arr.section == "Points" else 1)
    if ncomp < 1:
        ncomp = 1
    if arr.section in ("Points", "PointData"):
        key, what = "NumberOfPoints", "points"
    else:
        key, what = "NumberOfCells", "cells"
    count = _int(arr.piece.get(key, ""))
    if count is None or count < 0:
        return None  # meshio's int() fails, or there is nothing to read
    piece = f"the <Piece> on line {arr.piece_line}" if arr.piece_line > 0 else "its <Piece>"
    exact = True  # the bound is the array's size in a valid file (not only an upper bound)
    if arr.section == "Cells":
        if arr.name in ("offsets", "types"):
            items, how = count + 1, f"{count} cells (+ 1)"
        else:
            items, how = count * MAX_ENTRIES_PER_CELL, f"{count} cells x at most {MAX_ENTRIES_PER_CELL} entries"
            exact = False
        nbytes = items * isz
        reason = f"{piece} declares {key}={count}: {how} x {isz} bytes ({kind}) = {nbytes} bytes"
    else:
        nbytes = count * ncomp * isz
        per = f"{ncomp} components x {isz} bytes ({kind})"
        reason = f"{piece} declares {key}={count}: {count} {what} x {per} = {nbytes} bytes"
    if exact and nbytes > cap:  # a valid file of these counts exceeds the cap: refuse before inflating
        raise MeshError(f"{arr.where(p)}: {reason} once inflated, {over_limit(cap)}")
    return nbytes, reason


def _int(text: str) -> Optional[int]:
    try:
        return int(text)
    except (TypeError, ValueError):
        return None


def _inflate_array(p: Path, codec: str, blocks: Iterable, arr: _Array, bound, budget: _Budget) -> None:
    """Inflate ``blocks`` (discarding the output) and raise as soon as the total exceeds the array's bound or the
    cap left over from the arrays before it."""
    limit_bound = bound[0] if bound is not None else None
    room = budget.cap - budget.used
    limit = room if limit_bound is None else min(limit_bound, room)
    total = 0
    compressed = 0
    for block in blocks:
        compressed += len(block)
        total += _inflated_size(codec, block, limit - total)
        if total > limit:
            what = f"its {codec}-compressed data ({compressed} bytes) inflates to more than {limit} bytes"
            if limit_bound is not None and limit == limit_bound:
                raise MeshError(f"{arr.where(p)}: {what}, but {bound[1]}; the file is corrupt or a decompression bomb")
            before = f", after {budget.used} bytes in the arrays before it" if budget.used else ""
            raise MeshError(f"{arr.where(p)}: {what}{before}: {over_limit(budget.cap)}")
    budget.used += total


def _inflated_size(codec: str, block, limit: int) -> int:
    """The bytes ``block`` inflates to as meshio inflates it (``zlib.decompress`` / ``lzma.decompress``), counted
    in chunks of 1 MiB and only up to ``limit + 1``. Corrupt data counts what inflated before the error (meshio
    stops there too)."""
    data = bytes(block)
    total = 0
    if codec == "zlib":
        d = zlib.decompressobj()
        try:
            while True:
                out = d.decompress(data, _CHUNK)
                total += len(out)
                if total > limit or d.eof:
                    return total
                data = d.unconsumed_tail
                if not data and len(out) < _CHUNK:
                    return total + len(d.flush())
        except zlib.error:
            return total
    while data:  # lzma.decompress reads concatenated streams
        d2 = lzma.LZMADecompressor()
        try:
            out = d2.decompress(data, _CHUNK)
            while True:
                total += len(out)
                if total > limit or d2.eof or d2.needs_input:
                    break
                out = d2.decompress(b"", _CHUNK)
        except lzma.LZMAError:
            return total
        if total > limit or not d2.eof:
            return total
        data = d2.unused_data
    return total
