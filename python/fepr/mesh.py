"""Tetrahedral meshes: :class:`TetMesh`, validated on construction.

Validation runs in the Rust core (``fepr._core.validate_mesh``): index range, repeated vertices in a tet,
non-finite coordinates, zero or near-zero volume (relative to the tet's own size), a tet tiny compared with the
mesh, and orientation. Negatively oriented tets are repaired by swapping their last two vertices; the count is
reported in a warning.
"""

from __future__ import annotations

import warnings
from typing import Optional

import numpy as np

from . import _core
from .errors import MeshError


class TetMesh:
    """A tetrahedral mesh in metres.

    Parameters
    ----------
    vertices : array_like, shape (m, 3), float64
        Vertex positions in metres.
    tets : array_like, shape (k, 4), integer
        Vertex indices of each tetrahedron, 0-based.
    source : str, optional
        Where the mesh came from (a file path); used in error messages.

    Raises
    ------
    MeshError
        If the arrays have the wrong shape or type, an index is out of range, a tet repeats a vertex, a
        coordinate is NaN or infinite, or a tet has zero or near-zero volume. The message names the tet.

    Notes
    -----
    Tets with negative orientation (``det[b-a, c-a, d-a] < 0``) are repaired by swapping their last two
    vertices; :attr:`flipped_count` says how many, and a :class:`UserWarning` is issued.
    """

    def __init__(self, vertices, tets, *, source: Optional[str] = None):
        where = f"{source}: " if source else ""
        try:
            v = np.asarray(vertices, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise MeshError(f"{where}vertices must be numeric, shape (m, 3): {exc}") from None
        t_raw = np.asarray(tets)
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f"{where}vertices must have shape (m, 3), got {v.shape}")
        if t_raw.ndim != 2 or t_raw.shape[1] != 4:
            raise MeshError(f"{where}tets must have shape (k, 4), got {t_raw.shape}")
        if t_raw.size and not np.issubdtype(t_raw.dtype, np.integer):
            if (
                np.issubdtype(t_raw.dtype, np.floating)
                and np.all(np.isfinite(t_raw))
                and np.all(t_raw == np.round(t_raw))
            ):
                t_raw = t_raw.astype(np.int64)
            else:
                raise MeshError(f"{where}tets must hold integer vertex indices, got dtype {t_raw.dtype}")
        t = np.ascontiguousarray(t_raw, dtype=np.int64)
        v = np.ascontiguousarray(v)
        try:
            fixed, flipped, unreferenced = _core.validate_mesh(v, t)
        except ValueError as exc:
            raise MeshError(f"{where}{exc}") from None
        self._vertices = v.copy()
        self._vertices.setflags(write=False)
        self._tets = np.asarray(fixed, dtype=np.int64)
        self._tets.setflags(write=False)
        self.flipped_count: int = int(flipped)
        self.unreferenced_count: int = int(unreferenced)
        self.source = source
        if flipped:
            warnings.warn(
                f"{where}{flipped} of {len(self._tets)} tets were negatively oriented and have been repaired "
                "(two vertices swapped)",
                UserWarning,
                stacklevel=2,
            )

    @property
    def vertices(self) -> np.ndarray:
        """Vertex positions, shape (m, 3) float64, metres (read-only)."""
        return self._vertices

    @property
    def tets(self) -> np.ndarray:
        """Tetrahedra as vertex indices, shape (k, 4) int64, positively oriented (read-only)."""
        return self._tets

    @property
    def num_vertices(self) -> int:
        return int(self._vertices.shape[0])

    @property
    def num_tets(self) -> int:
        return int(self._tets.shape[0])

    def volumes(self) -> np.ndarray:
        """Rest volume of every tet, shape (k,) float64, m^3 (all positive)."""
        p = self._vertices[self._tets]
        d = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
        return np.linalg.det(d) / 6.0

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the axis-aligned bounding box, each shape (3,) float64, metres."""
        return self._vertices.min(axis=0), self._vertices.max(axis=0)

    def transformed(self, *, scale: float = 1.0, translate=(0.0, 0.0, 0.0)) -> TetMesh:
        """A copy with vertices ``scale * x + translate`` (scale > 0 keeps the orientation)."""
        if not (np.isfinite(scale) and scale > 0):
            raise MeshError(f"scale must be a positive finite number, got {scale}")
        return TetMesh(self._vertices * scale + np.asarray(translate, dtype=np.float64), self._tets, source=self.source)

    def __repr__(self) -> str:
        src = f", source={self.source!r}" if self.source else ""
        return f"TetMesh({self.num_vertices} vertices, {self.num_tets} tets{src})"
