"""Reader for NumPy ``.npz`` archives holding a tetrahedral mesh.

The archive holds ``tets`` (k, 4) integer and the vertex positions (m, 3) under the first of these names
that is present: ``vertices``, ``rest_positions``, ``positions``. Nothing is unpickled
(``allow_pickle=False``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Tuple, Union

import numpy as np

from ..errors import MeshError
from ._checks import check_duplicate_tets

PathLike = Union[str, "os.PathLike[str]"]

VERTEX_KEYS = ("vertices", "rest_positions", "positions")


def read_npz(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read a mesh from an ``.npz`` archive.

    Returns
    -------
    vertices : numpy.ndarray, shape (m, 3), float64
    tets : numpy.ndarray, shape (k, 4), int64

    Raises
    ------
    MeshError
        If the file is missing or not an ``.npz`` archive, an array is missing (the message lists the arrays
        present), or an array has the wrong shape or type.
    """
    p = Path(os.fspath(path))
    if not p.exists():
        raise MeshError(f"{p}: file not found")
    if not p.is_file():
        raise MeshError(f"{p}: not a regular file")
    try:
        archive = np.load(p, allow_pickle=False)
    except Exception as exc:
        raise MeshError(f"{p}: cannot read as an .npz archive: {type(exc).__name__}: {exc}") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise MeshError(f"{p}: not an .npz archive (it holds a single array; save with numpy.savez)")
    with archive:
        names = list(archive.files)
        key = next((k for k in VERTEX_KEYS if k in names), None)
        if key is None or "tets" not in names:
            missing = [] if key else ["vertices (or rest_positions / positions)"]
            missing += [] if "tets" in names else ["tets"]
            raise MeshError(
                f"{p}: missing array(s) {', '.join(missing)}; the archive holds: {', '.join(names) or 'nothing'}"
            )
        try:
            vertices = archive[key]
            tets = archive["tets"]
        except Exception as exc:
            raise MeshError(f"{p}: cannot read arrays: {type(exc).__name__}: {exc}") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{p}: array '{key}' must have shape (m, 3), got {vertices.shape}")
    if not (np.issubdtype(vertices.dtype, np.floating) or np.issubdtype(vertices.dtype, np.integer)):
        raise MeshError(f"{p}: array '{key}' must be numeric, got dtype {vertices.dtype}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"{p}: array 'tets' must have shape (k, 4), got {tets.shape}")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(f"{p}: array 'tets' must hold integer vertex indices, got dtype {tets.dtype}")
    tets = np.ascontiguousarray(tets, dtype=np.int64)
    check_duplicate_tets(p, tets)
    return np.ascontiguousarray(vertices, dtype=np.float64), tets
