"""Native reader for TetGen ``.node`` / ``.ele`` files (no third-party dependency).

File format (https://wias-berlin.de/software/tetgen/fformats.html), as read here:

``.node``
    header ``<#points> <dimension (3)> <#attributes> <boundary marker flag (0 or 1)>``, then one line per
    point:
    ``<point #> <x> <y> <z> [attributes] [boundary marker]``.
``.ele``
    header ``<#tetrahedra> <nodes per tet (4 or 10)> <#region attributes>``, then one line per tet:
    ``<tet #> <node> <node> <node> <node> [6 more nodes for 10-node tets] [attributes]``.

``#`` starts a comment (whole line or trailing); blank lines are ignored. Points are numbered from 0 or from 1
as the first point line says; the ``.ele`` node references are mapped through the point numbers actually
listed in the ``.node`` file, so a reference to a point that is not listed is an error naming the ``.ele``
line.

Every problem is reported as a :class:`~fepr.errors.MeshError` naming the file, the line and the problem.
Header counts are never trusted for allocation: the data lines are collected first and compared with the
header.

Not meshio's reader (issue 36): ``meshio.tetgen.read`` (5.3) reads only a plain subset. It fails on comments
after the header, node numbers with gaps, 10-node tets, a short or tab-separated header and ``.NODE``; it
does not check the values per line (one missing value silently shifts every later number), data beyond the
counts, finiteness or node references. A pre-scan making it safe would be this reader again.
``test_native_readers_read_what_meshio_cannot`` (tests/test_mesh_io.py) tells when that changes.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Dict, List, Tuple, Union

import numpy as np

from ..errors import MeshError
from ._checks import check_duplicate_tets

PathLike = Union[str, "os.PathLike[str]"]

_Record = Tuple[int, List[str]]  # (1-based line number, tokens)


def tetgen_paths(path: PathLike) -> Tuple[Path, Path]:
    """The ``(.node, .ele)`` pair for ``path`` (a ``.node`` file, an ``.ele`` file or their common basename).

    Nothing is checked on disk here; see :func:`read_tetgen`.
    """
    p = Path(os.fspath(path))
    suffix = p.suffix
    if suffix.lower() == ".face":  # the boundary file written beside them: read and ignored
        return p.with_suffix(".node" if suffix.islower() else ".NODE"), p.with_suffix(
            ".ele" if suffix.islower() else ".ELE"
        )
    if suffix.lower() == ".node":
        return p, p.with_suffix(".ele" if suffix.islower() else ".ELE")
    if suffix.lower() == ".ele":
        return p.with_suffix(".node" if suffix.islower() else ".NODE"), p
    return Path(f"{p}.node"), Path(f"{p}.ele")


def read_tetgen(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read a TetGen mesh.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.node`` file, the ``.ele`` file, the ``.face`` file, or the common basename without extension
        (e.g. ``"ellell.1"``); the ``.node`` and ``.ele`` files must exist. A ``.face`` file (the boundary
        triangles TetGen writes) is allowed beside them and ignored: the boundary follows from the tets.

    Returns
    -------
    vertices : numpy.ndarray, shape (m, 3), float64
        Point coordinates in file order (units of the file).
    tets : numpy.ndarray, shape (k, 4), int64
        0-based row indices into ``vertices``; for 10-node tets only the 4 corners are kept.

    Raises
    ------
    MeshError
        If a file is missing, empty, truncated or malformed, or two tets use the same four nodes; the message
        names the file and line.
    """
    given = Path(os.fspath(path))
    node_path, ele_path = tetgen_paths(given)
    suffix = given.suffix.lower()
    if suffix == ".face":
        suffix = ""
        given = given.with_suffix("")
    node_exists, ele_exists = node_path.is_file(), ele_path.is_file()
    if suffix == ".node":
        if not node_exists:
            raise MeshError(f"{node_path}: file not found")
        if not ele_exists:
            raise MeshError(
                f"{node_path}: the matching element file {ele_path.name} was not found next to it "
                "(a TetGen mesh needs both the .node and the .ele file)"
            )
    elif suffix == ".ele":
        if not ele_exists:
            raise MeshError(f"{ele_path}: file not found")
        if not node_exists:
            raise MeshError(
                f"{ele_path}: the matching node file {node_path.name} was not found next to it "
                "(a TetGen mesh needs both the .node and the .ele file)"
            )
    else:
        if not node_exists and not ele_exists:
            raise MeshError(f"{given}: file not found (no TetGen files {node_path.name} / {ele_path.name} either)")
        if not node_exists:
            raise MeshError(
                f"{given}: TetGen node file {node_path} not found (found {ele_path.name}; a TetGen mesh needs both)"
            )
        if not ele_exists:
            raise MeshError(
                f"{given}: TetGen element file {ele_path} not found (found {node_path.name}; a TetGen mesh needs both)"
            )
    vertices, numbers = _read_node(node_path)
    tets = _read_ele(ele_path, numbers)
    return vertices, tets


# ----------------------------------------------------------------------------------------------------
# helpers


def _records(path: Path) -> List[_Record]:
    """Non-empty, comment-stripped lines of ``path`` as (line number, tokens)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MeshError(f"{path}: cannot read file: {exc.strerror or exc}") from None
    text = data.decode("utf-8", errors="replace")
    out: List[_Record] = []
    for lineno, line in enumerate(text.split("\n"), start=1):
        cut = line.find("#")
        if cut >= 0:
            line = line[:cut]
        tokens = line.split()
        if tokens:
            out.append((lineno, tokens))
    return out


def _int(path: Path, lineno: int, token: str, what: str) -> int:
    if "_" not in token:
        try:
            return int(token)
        except ValueError:
            pass
    raise MeshError(f"{path} line {lineno}: {what} must be an integer, got {token!r}")


def _float(path: Path, lineno: int, token: str, what: str) -> float:
    value = None
    if "_" not in token:
        try:
            value = float(token)
        except ValueError:
            value = None
    if value is None:
        raise MeshError(f"{path} line {lineno}: {what} must be a number, got {token!r}")
    return value


def _header(path: Path, records: List[_Record], defaults: Tuple[int, ...], names: Tuple[str, ...]) -> Tuple[int, ...]:
    if not records:
        raise MeshError(f"{path}: the file is empty (no header line; it holds only blank lines or comments)")
    lineno, tokens = records[0]
    if len(tokens) > len(names):
        raise MeshError(
            f"{path} line {lineno}: header has {len(tokens)} values, expected at most {len(names)} ({', '.join(names)})"
        )
    values = list(defaults)
    for i, token in enumerate(tokens):
        values[i] = _int(path, lineno, token, f"header value '{names[i]}'")
        if values[i] < 0:
            raise MeshError(f"{path} line {lineno}: header value '{names[i]}' must not be negative, got {values[i]}")
    return tuple(values)


def _data_records(path: Path, records: List[_Record], count: int, what: str) -> List[_Record]:
    """The ``count`` data records after the header; checks the file holds exactly that many."""
    data = records[1:]
    header_line = records[0][0]
    if len(data) < count:
        last = f" (last data on line {data[-1][0]})" if data else ""
        raise MeshError(
            f"{path}: file is truncated: the header on line {header_line} declares {count} {what}, "
            f"but only {len(data)} {what} lines follow{last}"
        )
    if len(data) > count:
        lineno = data[count][0]
        raise MeshError(
            f"{path} line {lineno}: unexpected data after the {count} {what} declared in the header on line "
            f"{header_line} (the file holds {len(data)} {what} lines)"
        )
    return data


def _read_node(path: Path) -> Tuple[np.ndarray, List[int]]:
    records = _records(path)
    n, dim, nattr, nmarker = _header(
        path,
        records,
        (0, 3, 0, 0),
        ("number of nodes", "dimension", "number of attributes", "boundary markers"),
    )
    header_line = records[0][0]
    if n == 0:
        raise MeshError(f"{path} line {header_line}: the header declares 0 nodes")
    if dim != 3:
        raise MeshError(f"{path} line {header_line}: dimension must be 3 for a tetrahedral mesh, got {dim}")
    if nmarker not in (0, 1):
        raise MeshError(f"{path} line {header_line}: boundary marker flag must be 0 or 1, got {nmarker}")
    data = _data_records(path, records, n, "nodes")
    ntok = 1 + 3 + nattr + nmarker
    coords: List[float] = []
    numbers: List[int] = []
    first_line: Dict[int, int] = {}
    for lineno, tokens in data:
        if len(tokens) != ntok:
            raise MeshError(
                f"{path} line {lineno}: expected {ntok} values (node number, x, y, z"
                f"{', ' + str(nattr) + ' attribute(s)' if nattr else ''}"
                f"{', boundary marker' if nmarker else ''}), "
                f"got {len(tokens)}"
            )
        number = _int(path, lineno, tokens[0], "node number")
        if number in first_line:
            raise MeshError(f"{path} line {lineno}: node {number} is listed twice (first on line {first_line[number]})")
        first_line[number] = lineno
        for axis, token in zip("xyz", tokens[1:4]):
            value = _float(path, lineno, token, f"coordinate {axis} of node {number}")
            if not math.isfinite(value):
                raise MeshError(f"{path} line {lineno}: coordinate {axis} of node {number} is not finite ({token})")
            coords.append(value)
        for token in tokens[4 : 4 + nattr]:
            _float(path, lineno, token, f"attribute of node {number}")
        if nmarker:
            _int(path, lineno, tokens[-1], f"boundary marker of node {number}")
        numbers.append(number)
    vertices = np.array(coords, dtype=np.float64).reshape(n, 3)
    return vertices, numbers


def _read_ele(path: Path, numbers: List[int]) -> np.ndarray:
    records = _records(path)
    k, npt, nattr = _header(
        path, records, (0, 4, 0), ("number of tetrahedra", "nodes per tetrahedron", "number of attributes")
    )
    header_line = records[0][0]
    if k == 0:
        raise MeshError(f"{path} line {header_line}: the header declares 0 tetrahedra")
    if npt not in (4, 10):
        raise MeshError(f"{path} line {header_line}: nodes per tetrahedron must be 4 or 10, got {npt}")
    data = _data_records(path, records, k, "tetrahedra")

    n = len(numbers)
    first = numbers[0]
    contiguous = numbers == list(range(first, first + n))
    lookup: Dict[int, int] = {} if contiguous else {num: row for row, num in enumerate(numbers)}
    if contiguous:
        numbering = f"numbers nodes {first}..{first + n - 1}"
    else:
        numbering = f"has no such node (its node numbers run from {min(numbers)} to {max(numbers)} with gaps)"

    ntok = 1 + npt + nattr
    rows: List[int] = []
    lines: List[int] = []
    for lineno, tokens in data:
        lines.append(lineno)
        if len(tokens) != ntok:
            raise MeshError(
                f"{path} line {lineno}: expected {ntok} values (element number, {npt} node numbers"
                f"{', ' + str(nattr) + ' attribute(s)' if nattr else ''}), got {len(tokens)}"
            )
        number = _int(path, lineno, tokens[0], "element number")
        for i, token in enumerate(tokens[1 : 1 + npt]):
            ref = _int(path, lineno, token, f"node number of element {number}")
            if contiguous:
                row = ref - first
                ok = 0 <= row < n
            else:
                row = lookup.get(ref, -1)
                ok = row >= 0
            if not ok:
                raise MeshError(
                    f"{path} line {lineno}: element {number} refers to node {ref}, but the .node file {numbering}"
                )
            if i < 4:
                rows.append(row)
        for token in tokens[1 + npt :]:
            _float(path, lineno, token, f"attribute of element {number}")
    tets = np.array(rows, dtype=np.int64).reshape(k, 4)
    check_duplicate_tets(path, tets, lines)
    return tets
