"""The boundary surface of a tetrahedral mesh: the triangles used by exactly one tet, oriented outward.

For a positively oriented tet ``(a, b, c, d)`` (``det[b - a, c - a, d - a] > 0``, as every
:class:`fepr.TetMesh` is) the vertex ``d`` lies on the side of the triangle ``(a, b, c)`` that its normal
``(b - a) x (c - a)`` points to, so ``(a, b, c)`` faces inward and ``(a, c, b)`` outward. The four outward
faces, each listed opposite the vertex it leaves out, are::

    opposite a: (b, c, d)    opposite b: (a, d, c)    opposite c: (a, b, d)    opposite d: (a, c, b)

A face shared by two tets is interior; a face used once is on the boundary and keeps the orientation it has in
its tet, so every boundary triangle's normal (counter-clockwise winding, right-hand rule) points out of the
body. The signed volume enclosed by the boundary, ``sum (p0 . (p1 x p2)) / 6`` over its triangles, then equals
the mesh volume (:func:`enclosed_volume`).
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import numpy as np

from ..errors import MeshError

__all__ = ["BoundarySurface", "boundary_surface", "enclosed_volume", "vertex_normals"]

#: Outward faces of a positively oriented tet, as local vertex indices, one row per left-out vertex 0..3.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)


class BoundarySurface(NamedTuple):
    """The boundary of a tet mesh (from :func:`boundary_surface`).

    Attributes
    ----------
    faces : (f, 3) int64
        Boundary triangles as indices into the mesh's vertices, outward normals (counter-clockwise).
    vertices : (n,) int64
        The mesh vertices that lie on the boundary, sorted ascending.
    local_faces : (f, 3) int64
        ``faces`` re-indexed into ``vertices``: the triangles of the compact surface mesh whose points are
        ``positions[vertices]``.
    """

    faces: np.ndarray
    vertices: np.ndarray
    local_faces: np.ndarray

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])


def boundary_surface(tets) -> BoundarySurface:
    """Boundary triangles of a tetrahedral mesh with outward normals, and a compact re-indexing.

    Parameters
    ----------
    tets : array_like, shape (k, 4), integer
        Positively oriented tets (as :attr:`fepr.TetMesh.tets` and :attr:`fepr.Simulation.tets` are).

    Returns
    -------
    BoundarySurface
        ``faces`` (f, 3) int64 into the mesh vertices, ``vertices`` (n,) int64 the boundary vertices (sorted)
        and ``local_faces`` (f, 3) int64 into ``vertices``. ``faces, vertices, local = boundary_surface(t)``
        unpacks it. Faces come in the order of their tets (tet 0's boundary faces first).

    Raises
    ------
    MeshError
        If ``tets`` is not an integer array of shape (k, 4) with non-negative indices.

    Notes
    -----
    A face used by three or more tets (a non-manifold mesh) is treated as interior. Faces are matched by their
    vertex sets, so the result depends only on the connectivity, not on the positions.
    """
    t = np.asarray(tets)
    if t.ndim != 2 or t.shape[1] != 4:
        raise MeshError(f"tets must have shape (k, 4), got {t.shape}")
    if t.size and not np.issubdtype(t.dtype, np.integer):
        raise MeshError(f"tets must hold integer vertex indices, got dtype {t.dtype}")
    t = t.astype(np.int64, copy=False)
    if t.size and t.min() < 0:
        raise MeshError("tets hold a negative vertex index")
    if t.shape[0] == 0:
        empty = np.zeros((0, 3), dtype=np.int64)
        return BoundarySurface(empty, np.zeros(0, dtype=np.int64), empty.copy())
    faces, use, _ = face_use(t)
    boundary = faces[use == 1]
    verts, local = np.unique(boundary, return_inverse=True)
    local = np.asarray(local, dtype=np.int64).reshape(-1, 3)
    return BoundarySurface(np.ascontiguousarray(boundary), verts.astype(np.int64), local)


def face_use(tets) -> Tuple[np.ndarray, np.ndarray, int]:
    """The four outward faces of every tet and how many tets use each (faces matched by their vertex sets).

    The one face matching of fepr: the boundary surface, the viewer's coloured boundary and ``fepr mesh --info``
    all use it.

    Parameters
    ----------
    tets : array_like, shape (k, 4), non-negative integers

    Returns
    -------
    faces : (4k, 3) int64
        Face ``j`` of tet ``e`` (outward, :data:`TET_FACES`) at row ``4 e + j``.
    use : (4k,) int64
        The number of tets that use the face of each row: 1 on the boundary, 2 inside, 3 or more non-manifold.
    nonmanifold : int
        The number of distinct faces used by three or more tets.
    """
    faces = np.asarray(tets, dtype=np.int64)[:, TET_FACES].reshape(-1, 3)
    if len(faces) == 0:
        return faces, np.zeros(0, dtype=np.int64), 0
    s = np.sort(faces, axis=1)
    n = int(s[:, 2].max()) + 1
    if n <= 2_000_000:  # one int64 key per face, (a n + b) n + c < n^3 < 2^63: far faster than np.unique(axis=0)
        keys = (s[:, 0] * n + s[:, 1]) * n + s[:, 2]
    else:
        keys = s.view([("a", np.int64), ("b", np.int64), ("c", np.int64)]).ravel()
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    return faces, counts[np.asarray(inverse).reshape(-1)], int(np.sum(counts > 2))


def enclosed_volume(points, faces) -> float:
    """Signed volume enclosed by a triangle surface, m^3: ``sum p0 . (p1 x p2) / 6`` over the triangles.

    Positive when the surface is closed and its triangles face outward (counter-clockwise seen from outside).

    Parameters
    ----------
    points : (n, 3) float
        Vertex positions, m.
    faces : (f, 3) int
        Triangles as indices into ``points``.
    """
    p = np.asarray(points, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def vertex_normals(points, faces) -> np.ndarray:
    """Area-weighted unit vertex normals of a triangle surface, (n, 3) float64 (zero for unused points).

    Parameters
    ----------
    points : (n, 3) float
        Vertex positions, m.
    faces : (f, 3) int
        Triangles as indices into ``points``, counter-clockwise seen from the side the normals point to.
    """
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = p[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    n = np.zeros_like(p)
    for j in range(3):
        np.add.at(n, f[:, j], fn)
    length = np.linalg.norm(n, axis=1)
    ok = length > 0
    n[ok] /= length[ok, None]
    return n
