"""A report on a mesh: :func:`mesh_info` returns a :class:`MeshInfo` (what ``fepr mesh INPUT --info`` prints).

For a file, the counts of inverted and degenerate tets are taken from the arrays as stored, before the
orientation repair that loading does; for a :class:`~fepr.TetMesh` (already repaired) ``inverted`` is the
number of tets its construction repaired (``flipped_count``). Surfaces (``.obj``, ``.off``, ``.stl``,
``.ply``) are reported too: triangles, enclosed volume and closedness.

Definitions
-----------
quality
    ``q = 6 sqrt(2) |V| / l_max^3`` with ``V`` the tet's volume and ``l_max`` its longest edge: 1 for a
    regular tet, 0 for a flat one.
inverted
    Tets with negative orientation, ``det[b - a, c - a, d - a] < 0`` (and not degenerate).
degenerate
    Tets with a repeated vertex, or that :class:`~fepr.TetMesh` would reject as (near-)flat or tiny:
    ``|6 V| <= 1e-10 l_max^3`` or ``l_max <= 1e-9`` times the bounding-box diagonal.
boundary faces
    Triangles used by exactly one tet. The boundary is *closed* when every edge of a boundary face is shared
    by exactly two boundary faces.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from .errors import MeshError

__all__ = ["MeshInfo", "boundary_faces", "mesh_info", "tet_quality"]

#: Thresholds of :class:`fepr.TetMesh`'s degenerate-tet test (``DEGENERATE_RELATIVE_*`` in the Rust core).
DEGENERATE_RELATIVE_VOLUME = 1e-10
DEGENERATE_RELATIVE_SIZE = 1e-9


@dataclass
class MeshInfo:
    """Counts and measures of a mesh (lengths and volumes in the units of the mesh: metres for a TetMesh).

    ``kind`` is ``"tets"`` or ``"surface"``; for a surface the tet fields are 0 or ``None``,
    ``boundary_faces`` is the number of triangles and ``volume`` the enclosed (signed) volume.
    """

    source: Optional[str]
    kind: str
    num_vertices: int
    num_tets: int
    bbox_min: Tuple[float, float, float]
    bbox_max: Tuple[float, float, float]
    volume: float
    quality_min: Optional[float]
    quality_median: Optional[float]
    inverted: int
    degenerate: int
    boundary_faces: int
    closed: bool
    open_edges: int
    nonmanifold_edges: int
    nonmanifold_faces: int
    unreferenced_vertices: int
    notes: list = field(default_factory=list)

    @property
    def size(self) -> Tuple[float, float, float]:
        """Extent of the bounding box along x, y, z."""
        return tuple(float(b - a) for a, b in zip(self.bbox_min, self.bbox_max))  # type: ignore[return-value]

    def __str__(self) -> str:
        def vec(x) -> str:
            return "(" + ", ".join(f"{c:.6g}" for c in x) + ")"

        lines = [f"mesh: {self.source or '(in memory)'}"]
        lines.append(f"  vertices          {self.num_vertices:,} ({self.unreferenced_vertices:,} unreferenced)")
        if self.kind == "surface":
            lines.append(f"  triangles         {self.boundary_faces:,} (a surface: tetrahedralize it to simulate)")
        else:
            lines.append(f"  tets              {self.num_tets:,}")
        lines.append(f"  bounding box      min {vec(self.bbox_min)}  max {vec(self.bbox_max)}")
        lines.append(f"  size              {' x '.join(f'{s:.6g}' for s in self.size)}")
        lines.append(f"  volume            {self.volume:.6g}" + (" (enclosed)" if self.kind == "surface" else ""))
        if self.kind == "tets":
            if self.quality_min is not None:
                lines.append(
                    f"  quality           min {self.quality_min:.3g}  median {self.quality_median:.3g}  "
                    "(6 sqrt(2) |V| / l_max^3; 1 = regular tet)"
                )
            lines.append(f"  inverted tets     {self.inverted:,}")
            lines.append(f"  degenerate tets   {self.degenerate:,}")
        state = "closed" if self.closed else "OPEN"
        details = []
        if self.open_edges:
            details.append(f"{self.open_edges:,} open edges")
        if self.nonmanifold_edges:
            details.append(f"{self.nonmanifold_edges:,} non-manifold edges")
        if self.nonmanifold_faces:
            details.append(f"{self.nonmanifold_faces:,} faces shared by 3 or more tets")
        extra = f" ({', '.join(details)})" if details else ""
        what = "triangles" if self.kind == "surface" else "boundary faces"
        lines.append(f"  boundary          {self.boundary_faces:,} {what}, {state}{extra}")
        lines.extend(f"  note: {n}" for n in self.notes)
        return "\n".join(lines)


def _signed_v6(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = vertices[tets]
    a = p[:, 1] - p[:, 0]
    b = p[:, 2] - p[:, 0]
    c = p[:, 3] - p[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c))


def _longest_edge(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = vertices[tets]
    lmax = np.zeros(len(tets))
    for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        lmax = np.maximum(lmax, np.linalg.norm(p[:, i] - p[:, j], axis=1))
    return lmax


def tet_quality(vertices, tets) -> np.ndarray:
    """``q = 6 sqrt(2) |V| / l_max^3`` for every tet, shape (k,) (1 for a regular tet, 0 when flat)."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64)
    lmax = _longest_edge(v, t)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = math.sqrt(2.0) * np.abs(_signed_v6(v, t)) / lmax**3
    return np.where(lmax > 0, q, 0.0)


def boundary_faces(tets, num_vertices: Optional[int] = None) -> Tuple[np.ndarray, int]:
    """Faces used by exactly one tet (outward oriented for positive tets, in tet order), shape (b, 3), and the
    number of faces shared by three or more tets (:func:`fepr.export.surface.face_use`; ``num_vertices`` is not
    needed and ignored)."""
    from .export.surface import face_use

    faces, use, nonmanifold = face_use(tets)
    return faces[use == 1], nonmanifold


def _read(path: Path):
    from .io import SURFACE_EXTENSIONS, read_arrays, read_surface

    if path.suffix.lower() in SURFACE_EXTENSIONS:
        v, f = read_surface(path)
        return "surface", v, f
    v, t = read_arrays(path)
    return "tets", v, t


def mesh_info(mesh_or_path) -> MeshInfo:
    """Report on a mesh: counts, bounding box, volume, tet quality, inverted and degenerate tets, boundary.

    Parameters
    ----------
    mesh_or_path : TetMesh, (vertices, tets) pair, or path
        A mesh, raw arrays, or any file :func:`fepr.load_mesh` or :func:`fepr.io.read_surface` reads. A file
        is read as stored (no orientation repair, no validation), so its inverted and degenerate tets are
        counted, not rejected.

    Returns
    -------
    MeshInfo
        ``str(info)`` is a readable multi-line report.

    Raises
    ------
    MeshError
        The file cannot be read, or an index is out of range or a coordinate is not finite (nothing sensible
        can be measured then).
    """
    flipped = None
    if isinstance(mesh_or_path, (str, os.PathLike)):
        path = Path(os.fspath(mesh_or_path))
        kind, v, t = _read(path)
        source: Optional[str] = str(path)
    elif hasattr(mesh_or_path, "vertices") and hasattr(mesh_or_path, "tets"):
        kind, v, t = "tets", mesh_or_path.vertices, mesh_or_path.tets
        source = getattr(mesh_or_path, "source", None)
        flipped = getattr(mesh_or_path, "flipped_count", None)
    else:
        try:
            v, t = mesh_or_path
        except (TypeError, ValueError):
            raise MeshError("mesh_info needs a TetMesh, a (vertices, tets) pair or a path") from None
        kind, source = "tets", None
    v = np.asarray(v, dtype=np.float64)
    t = np.asarray(t, dtype=np.int64)
    where = f"{source}: " if source else ""
    width = 3 if kind == "surface" else 4
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError(f"{where}vertices must have shape (m, 3) with m >= 1, got {v.shape}")
    if t.ndim != 2 or t.shape[1] != width:
        raise MeshError(f"{where}cells must have shape (k, {width}), got {t.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
    if bad.size:
        raise MeshError(f"{where}vertex {int(bad[0])} has a non-finite coordinate {v[bad[0]].tolist()}")
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        row = int(np.flatnonzero((t < 0).any(axis=1) | (t >= len(v)).any(axis=1))[0])
        raise MeshError(f"{where}cell {row} {t[row].tolist()} refers to a vertex out of range 0..{len(v) - 1}")
    n = len(v)
    lo, hi = v.min(axis=0), v.max(axis=0)
    unreferenced = n - len(np.unique(t)) if t.size else n
    notes = []
    from .io.surface import edge_use, surface_volume

    if kind == "surface":
        counts = edge_use(t)[1]
        open_e, nonman_e = int(np.sum(counts == 1)), int(np.sum(counts > 2))
        return MeshInfo(
            source=source,
            kind="surface",
            num_vertices=n,
            num_tets=0,
            bbox_min=tuple(map(float, lo)),  # type: ignore[arg-type]
            bbox_max=tuple(map(float, hi)),  # type: ignore[arg-type]
            volume=float(surface_volume(v, t) or 0.0),
            quality_min=None,
            quality_median=None,
            inverted=0,
            degenerate=0,
            boundary_faces=len(t),
            closed=len(t) > 0 and open_e == 0 and nonman_e == 0,
            open_edges=open_e,
            nonmanifold_edges=nonman_e,
            nonmanifold_faces=0,
            unreferenced_vertices=unreferenced,
            notes=notes,
        )
    v6 = _signed_v6(v, t)
    lmax = _longest_edge(v, t)
    diag = float(np.linalg.norm(hi - lo))
    s = np.sort(t, axis=1)
    repeated = np.any(s[:, 1:] == s[:, :-1], axis=1)
    flat = np.abs(v6) <= DEGENERATE_RELATIVE_VOLUME * lmax**3
    degenerate = repeated | flat | (lmax <= DEGENERATE_RELATIVE_SIZE * diag)
    inverted = int(np.sum((v6 < 0) & ~degenerate))
    if flipped is not None:
        inverted = int(flipped)
        if flipped:
            notes.append("inverted tets were repaired (two vertices swapped) when this TetMesh was built")
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.where(lmax > 0, math.sqrt(2.0) * np.abs(v6) / lmax**3, 0.0)
    faces, nonman_faces = boundary_faces(t, n)
    counts = edge_use(faces)[1]
    open_e, nonman_e = int(np.sum(counts == 1)), int(np.sum(counts > 2))
    return MeshInfo(
        source=source,
        kind="tets",
        num_vertices=n,
        num_tets=len(t),
        bbox_min=tuple(map(float, lo)),  # type: ignore[arg-type]
        bbox_max=tuple(map(float, hi)),  # type: ignore[arg-type]
        volume=float(np.abs(v6).sum() / 6.0),
        quality_min=float(q.min()) if len(q) else None,
        quality_median=float(np.median(q)) if len(q) else None,
        inverted=inverted,
        degenerate=int(np.sum(degenerate)),
        boundary_faces=len(faces),
        closed=len(faces) > 0 and open_e == 0 and nonman_e == 0,
        open_edges=open_e,
        nonmanifold_edges=nonman_e,
        nonmanifold_faces=nonman_faces,
        unreferenced_vertices=unreferenced,
        notes=notes,
    )
