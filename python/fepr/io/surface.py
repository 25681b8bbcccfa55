"""Reading triangle surfaces (OBJ, OFF natively; STL, PLY through meshio) and checking that they are closed.

OBJ and OFF are not read by meshio (issue 36): its OBJ reader maps negative (relative) indices and index 0 to
wrong vertices without an error and fails on a ``w`` coordinate or a trailing comment; its OFF reader takes
only triangles under a bare ``OFF`` line (no polygons, COFF, colours, counts on the header line, comments in
the data). Checking its input line by line for our messages would be these readers again.

:func:`read_surface` returns ``(vertices (n, 3) float64, triangles (f, 3) int64)``. Polygons are split into
triangles as fans around their first corner; lines, points, texture coordinates, normals, groups and
materials are ignored. Vertices are kept in file order, so indices stay those of the file (0-based).

:func:`surface_problems` lists what makes a surface unusable as the boundary of a solid: degenerate or
duplicate triangles, open edges (used by one triangle) and non-manifold edges (used by more than two).
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np

from ..errors import MeshError
from ._prescan import prescan

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["SURFACE_EXTENSIONS", "read_obj", "read_off", "read_surface", "surface_problems"]

#: Surface formats :func:`read_surface` understands (lower-case extension -> description).
SURFACE_EXTENSIONS = {
    ".obj": "Wavefront OBJ",
    ".off": "OFF",
    ".stl": "STL (ASCII or binary)",
    ".ply": "PLY (ASCII or binary)",
}


def read_surface(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read a triangle surface from an OBJ, OFF, STL or PLY file.

    Parameters
    ----------
    path : str or os.PathLike
        The file; the format is chosen by the extension (``.obj``, ``.off``, ``.stl``, ``.ply``,
        case-insensitive).

    Returns
    -------
    vertices : numpy.ndarray, shape (n, 3), float64
        Vertex positions in file order (units of the file). STL stores corners per facet; equal corners are
        merged into one vertex.
    triangles : numpy.ndarray, shape (f, 3), int64
        0-based vertex indices; polygons are split into fans.

    Raises
    ------
    MeshError
        If the file is missing, malformed (for OBJ and OFF the message names the line), holds no triangles,
        has a non-finite coordinate or an index out of range.
    """
    try:
        p = Path(os.fspath(path))
    except TypeError:
        raise MeshError(f"surface path must be a string or os.PathLike, got {type(path).__name__}") from None
    suffix = p.suffix.lower()
    if suffix not in SURFACE_EXTENSIONS:
        known = ", ".join(f"{k} ({v})" for k, v in SURFACE_EXTENSIONS.items())
        raise MeshError(f"{p}: unsupported surface file (extension {p.suffix!r}); supported: {known}")
    _check_file(p)
    if suffix == ".obj":
        return read_obj(p)
    if suffix == ".off":
        return read_off(p)
    return _read_meshio_surface(p, "stl" if suffix == ".stl" else "ply", SURFACE_EXTENSIONS[suffix])


def _check_file(p: Path) -> None:
    if not p.exists():
        raise MeshError(f"{p}: file not found")
    if not p.is_file():
        raise MeshError(f"{p}: not a regular file")


def _lines(p: Path) -> List[str]:
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise MeshError(f"{p}: cannot read file: {exc.strerror or exc}") from None
    return data.decode("utf-8", errors="replace").split("\n")


def _number(p: Path, lineno: int, token: str, what: str) -> float:
    try:
        value = float(token) if "_" not in token else None
    except ValueError:
        value = None
    if value is None:
        raise MeshError(f"{p} line {lineno}: {what} must be a number, got {token!r}")
    if not math.isfinite(value):
        raise MeshError(f"{p} line {lineno}: {what} is not finite ({token})")
    return value


def _integer(p: Path, lineno: int, token: str, what: str) -> int:
    if "_" not in token:
        try:
            return int(token)
        except ValueError:
            pass
    raise MeshError(f"{p} line {lineno}: {what} must be an integer, got {token!r}")


def read_obj(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read the ``v`` and ``f`` statements of a Wavefront OBJ file (see :func:`read_surface`).

    Face corners may be ``i``, ``i/t``, ``i//n`` or ``i/t/n``; indices are 1-based, negative ones count back
    from the last vertex defined so far. Only the first three numbers of a ``v`` line are used (extra ones,
    such as a weight or a colour, are ignored). Every error names the file and the line.
    """
    p = Path(os.fspath(path))
    coords: List[float] = []
    tris: List[int] = []
    nverts = 0
    for lineno, raw in enumerate(_lines(p), start=1):
        line = raw.split("#", 1)[0]
        tokens = line.split()
        if not tokens:
            continue
        key = tokens[0]
        if key == "v":
            if len(tokens) < 4:
                raise MeshError(f"{p} line {lineno}: a vertex needs 3 coordinates, got {len(tokens) - 1}")
            for axis, token in zip("xyz", tokens[1:4]):
                coords.append(_number(p, lineno, token, f"coordinate {axis} of vertex {nverts + 1}"))
            nverts += 1
        elif key == "f":
            corners = tokens[1:]
            if len(corners) < 3:
                raise MeshError(f"{p} line {lineno}: a face needs at least 3 corners, got {len(corners)}")
            idx = []
            for corner in corners:
                ref = _integer(p, lineno, corner.split("/", 1)[0], "face vertex index")
                if ref > 0:
                    row = ref - 1
                elif ref < 0:
                    row = nverts + ref
                else:
                    raise MeshError(f"{p} line {lineno}: face vertex index 0 is invalid (OBJ indices start at 1)")
                if not 0 <= row < nverts:
                    raise MeshError(
                        f"{p} line {lineno}: face refers to vertex {ref}, but only {nverts} vertices are defined "
                        "before this line"
                    )
                idx.append(row)
            for k in range(1, len(idx) - 1):
                tris.extend((idx[0], idx[k], idx[k + 1]))
    if not tris:
        raise MeshError(f"{p}: no faces found (an OBJ surface needs 'f' lines; it has {nverts} vertices)")
    return np.array(coords, dtype=np.float64).reshape(-1, 3), np.array(tris, dtype=np.int64).reshape(-1, 3)


def read_off(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read an OFF file (``OFF`` header, counts, vertices, faces ``n i1 ... in``), see :func:`read_surface`.

    ``#`` starts a comment. Extra values on vertex or face lines (colours) are ignored. Every error names the
    file and the line; header counts are checked against the data before anything is allocated.
    """
    p = Path(os.fspath(path))
    records = []
    for lineno, raw in enumerate(_lines(p), start=1):
        tokens = raw.split("#", 1)[0].split()
        if tokens:
            records.append((lineno, tokens))
    if not records:
        raise MeshError(f"{p}: the file is empty")
    lineno, tokens = records[0]
    if not tokens[0].upper().endswith("OFF"):
        raise MeshError(f"{p} line {lineno}: expected the header 'OFF', got {tokens[0]!r}")
    rest = records[1:]
    if len(tokens) > 1:  # counts on the header line
        rest = [(lineno, tokens[1:])] + rest
    if not rest:
        raise MeshError(f"{p}: file is truncated: no line with the vertex and face counts")
    lineno, counts = rest[0]
    if len(counts) < 2:
        raise MeshError(f"{p} line {lineno}: expected the counts '<vertices> <faces> [<edges>]'")
    nv = _integer(p, lineno, counts[0], "number of vertices")
    nf = _integer(p, lineno, counts[1], "number of faces")
    if nv < 0 or nf < 0:
        raise MeshError(f"{p} line {lineno}: counts must not be negative, got {nv} vertices and {nf} faces")
    data = rest[1:]
    if len(data) < nv + nf:
        raise MeshError(
            f"{p}: file is truncated: line {lineno} declares {nv} vertices and {nf} faces, "
            f"but only {len(data)} data lines follow"
        )
    coords: List[float] = []
    for i, (ln, toks) in enumerate(data[:nv]):
        if len(toks) < 3:
            raise MeshError(f"{p} line {ln}: vertex {i} needs 3 coordinates, got {len(toks)}")
        for axis, token in zip("xyz", toks[:3]):
            coords.append(_number(p, ln, token, f"coordinate {axis} of vertex {i}"))
    tris: List[int] = []
    for j, (ln, toks) in enumerate(data[nv : nv + nf]):
        n = _integer(p, ln, toks[0], f"corner count of face {j}")
        if n < 3 or len(toks) < 1 + n:
            raise MeshError(f"{p} line {ln}: face {j} must list n >= 3 vertex indices after n, got {toks!r}")
        idx = [_integer(p, ln, t, f"vertex index of face {j}") for t in toks[1 : 1 + n]]
        for ref in idx:
            if not 0 <= ref < nv:
                raise MeshError(f"{p} line {ln}: face {j} refers to vertex {ref}, out of range 0..{nv - 1}")
        for k in range(1, n - 1):
            tris.extend((idx[0], idx[k], idx[k + 1]))
    if len(data) > nv + nf:
        raise MeshError(
            f"{p} line {data[nv + nf][0]}: unexpected data after the {nv} vertices and {nf} faces declared on "
            f"line {lineno}"
        )
    if not tris:
        raise MeshError(f"{p}: no faces found")
    return np.array(coords, dtype=np.float64).reshape(-1, 3), np.array(tris, dtype=np.int64).reshape(-1, 3)


def _read_meshio_surface(p: Path, fmt: str, description: str) -> Tuple[np.ndarray, np.ndarray]:
    prescan(p, fmt)
    import meshio

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = getattr(meshio, fmt).read(str(p))
    except (Exception, SystemExit) as exc:
        detail = str(exc).strip() or f"not valid {description} data"
        raise MeshError(f"{p}: cannot read {description} file: {type(exc).__name__}: {detail}") from None
    points = np.asarray(mesh.points)
    if points.ndim != 2 or points.shape[1] != 3 or not np.issubdtype(points.dtype, np.number):
        raise MeshError(f"{p}: points must have 3 numeric coordinates, got shape {points.shape}")
    vertices = np.ascontiguousarray(points, dtype=np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))
    if bad.size:
        raise MeshError(f"{p}: vertex {int(bad[0])} has a non-finite coordinate {vertices[bad[0]].tolist()}")
    tris: List[np.ndarray] = []
    for block in mesh.cells:
        if block.type in ("triangle", "quad") or block.type.startswith("polygon"):
            data = np.asarray(block.data, dtype=np.int64)
            if data.ndim != 2 or data.shape[1] < 3:
                continue
            for k in range(1, data.shape[1] - 1):
                tris.append(data[:, [0, k, k + 1]])
    if not tris:
        kinds = ", ".join(b.type for b in mesh.cells) or "none"
        raise MeshError(f"{p}: no triangles found (cell types present: {kinds})")
    triangles = np.ascontiguousarray(np.concatenate(tris, axis=0))
    out = np.flatnonzero((triangles < 0).any(axis=1) | (triangles >= len(vertices)).any(axis=1))
    if out.size:
        raise MeshError(
            f"{p}: triangle {int(out[0])} refers to a vertex out of range {triangles[out[0]].tolist()} "
            f"(the file has {len(vertices)} vertices)"
        )
    return vertices, triangles


def edge_use(triangles: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Undirected edges of ``triangles`` (e, 2) (sorted pairs, ascending) and how many triangles use each, (e,).

    Indices must be non-negative (callers check the range first).
    """
    t = np.asarray(triangles, dtype=np.int64)
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], axis=0)
    edges.sort(axis=1)
    if len(edges) == 0:
        return edges.reshape(0, 2), np.zeros(0, dtype=np.int64)
    n = int(edges[:, 1].max()) + 1  # one int64 key per edge, a n + b < n^2: far faster than np.unique(axis=0)
    keys, counts = np.unique(edges[:, 0] * n + edges[:, 1], return_counts=True)
    return np.stack([keys // n, keys % n], axis=1), counts


def surface_problems(vertices: np.ndarray, triangles: np.ndarray) -> List[str]:
    """What keeps a triangle surface from bounding a solid (an empty list when it is closed and manifold).

    Checked: indices in range, triangles with a repeated vertex, zero-area triangles, duplicate triangles,
    open edges (used by one triangle) and non-manifold edges (used by three or more). Each problem is one
    sentence naming counts and a first example. Self-intersections are not looked for here (the mesher
    reports them).
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    out: List[str] = []
    if len(t) == 0:
        return ["the surface has no triangles"]
    bad = np.flatnonzero((t < 0).any(axis=1) | (t >= len(v)).any(axis=1))
    if bad.size:
        return [f"triangle {int(bad[0])} {t[bad[0]].tolist()} refers to a vertex out of range 0..{len(v) - 1}"]
    repeated = np.flatnonzero((t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2]))
    if repeated.size:
        out.append(
            f"{repeated.size} triangle(s) repeat a vertex (first: triangle {int(repeated[0])} "
            f"{t[repeated[0]].tolist()})"
        )
    p = v[t]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    lmax = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
    flat = np.flatnonzero((area2 <= 1e-12 * lmax**2) & ~np.isin(np.arange(len(t)), repeated))
    if flat.size:
        out.append(f"{flat.size} triangle(s) have zero area (first: triangle {int(flat[0])} {t[flat[0]].tolist()})")
    keys = np.sort(t, axis=1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup = keys[first[counts > 1][0]]
        out.append(f"{int(np.sum(counts - 1))} duplicate triangle(s) (first: vertices {dup.tolist()})")
    edges, use = edge_use(t)
    open_edges = edges[use == 1]
    if len(open_edges):
        out.append(
            f"the surface is open: {len(open_edges)} edge(s) belong to only one triangle "
            f"(first: vertices {open_edges[0].tolist()})"
        )
    nonmanifold = edges[use > 2]
    if len(nonmanifold):
        out.append(
            f"the surface is non-manifold: {len(nonmanifold)} edge(s) are shared by three or more triangles "
            f"(first: vertices {nonmanifold[0].tolist()}, {int(use[use > 2][0])} triangles)"
        )
    return out


def compact_surface(vertices: np.ndarray, triangles: np.ndarray) -> Tuple[np.ndarray, np.ndarray, int]:
    """Drop vertices no triangle uses; returns ``(vertices, triangles, number dropped)``."""
    used = np.unique(triangles)
    if len(used) == len(vertices):
        return vertices, triangles, 0
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[triangles], len(vertices) - len(used)


def surface_volume(vertices: np.ndarray, triangles: np.ndarray) -> Optional[float]:
    """Signed enclosed volume (divergence theorem; positive for outward-facing triangles)."""
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles, dtype=np.int64)]
    if len(p) == 0:
        return None
    return float(np.einsum("ij,ij->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0)
