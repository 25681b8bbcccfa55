"""Readers for Gmsh ``.msh``, VTK ``.vtk`` / ``.vtu`` and Medit ``.mesh`` / ``.meshb`` through meshio.

meshio is imported lazily (only when such a file is read). Only tetrahedral cells are kept: ``tetra``
blocks as they are and ``tetra10`` blocks reduced to their 4 corners; all other cells (triangles, lines,
vertices, ...) are dropped, and a :class:`UserWarning` lists the dropped cell types and their counts. All
points are kept, in file order, so indices stay those of the file.

Before meshio sees the file, the counts in its headers are checked against the file size
(:mod:`fepr.io._prescan`), so a corrupt header cannot make meshio allocate a giant array, and the compressed
arrays of a ``.vtu`` file are inflated (bounded, the output discarded) and checked against the file's counts and the
cap on decompressed mesh data, ``FEPR_MAX_MESH_BYTES`` (default 1 GiB; :mod:`fepr.io._vtu_prescan`), so a
decompression bomb cannot make meshio inflate gigabytes.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Dict, List, Tuple, Union

import numpy as np

from ..errors import MeshError
from ._checks import check_duplicate_tets
from ._prescan import prescan

PathLike = Union[str, "os.PathLike[str]"]

#: extension (lower case) -> (meshio file format, description)
MESHIO_FORMATS: Dict[str, Tuple[str, str]] = {
    ".msh": ("gmsh", "Gmsh"),
    ".vtk": ("vtk", "VTK legacy"),
    ".vtu": ("vtu", "VTK XML"),
    ".mesh": ("medit", "Medit"),
    ".meshb": ("medit", "Medit binary"),
}


def read_meshio(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read the tetrahedra of a Gmsh, VTK or Medit file with meshio.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.msh`` (Gmsh 2.2 or 4.1, ASCII or binary), ``.vtk``, ``.vtu``, ``.mesh`` or ``.meshb`` file.

    Returns
    -------
    vertices : numpy.ndarray, shape (m, 3), float64
        All points of the file, in file order (units of the file).
    tets : numpy.ndarray, shape (k, 4), int64
        0-based point indices of every ``tetra`` cell, then (in block order) the corners of ``tetra10`` cells.

    Raises
    ------
    MeshError
        If the file is missing, empty, declares counts that cannot fit in it, or cannot be parsed (the message
        names the file and meshio's error), the points do not have 3 coordinates, there are no tetrahedra (the
        message lists the cell types present), or two tets use the same four vertices; or a compressed ``.vtu``
        array inflates beyond what its ``<Piece>`` counts allow or beyond the cap on decompressed mesh data
        (environment variable ``FEPR_MAX_MESH_BYTES``, default 1 GiB; the message names the line and the array).
    ConfigError
        If ``FEPR_MAX_MESH_BYTES`` is set to something other than a number of bytes.

    Warns
    -----
    UserWarning
        When cells other than tetrahedra were dropped, e.g. ``m.msh: kept 48 tetra cells; dropped 12
        triangle, 3 line cells``.
    """
    p = Path(os.fspath(path))
    if not p.exists():
        raise MeshError(f"{p}: file not found")
    if not p.is_file():
        raise MeshError(f"{p}: not a regular file")
    file_format, description = MESHIO_FORMATS.get(p.suffix.lower(), (None, "mesh"))
    try:
        import meshio
    except ImportError:  # pragma: no cover - meshio is a dependency of fepr
        raise MeshError(f"{p}: reading {description} files needs the meshio package (pip install meshio)") from None
    prescan(p, "meshb" if p.suffix.lower() == ".meshb" else file_format or "")
    # Call the format's reader directly: meshio.read() prints and calls sys.exit(1) when a reader raises
    # meshio.ReadError, which must never end the user's program.
    reader = getattr(meshio, file_format).read if file_format else meshio.read
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # meshio's own warnings (e.g. missing Gmsh tags) are noise here
            mesh = reader(str(p))
    except (Exception, SystemExit) as exc:  # meshio raises many exception types on bad input
        detail = str(exc).strip() or f"not valid {description} data"
        raise MeshError(f"{p}: cannot read {description} file: {type(exc).__name__}: {detail}") from exc

    points = np.asarray(mesh.points)
    if points.ndim != 2 or points.shape[1] != 3:
        ncoord = points.shape[1] if points.ndim == 2 else "?"
        raise MeshError(
            f"{p}: points have {ncoord} coordinates (array shape {points.shape}); a tetrahedral mesh needs 3"
        )
    if not np.issubdtype(points.dtype, np.number):
        raise MeshError(f"{p}: point coordinates are not numeric (dtype {points.dtype})")
    vertices = np.ascontiguousarray(points, dtype=np.float64)

    blocks: List[np.ndarray] = []
    present: List[str] = []
    kept: Dict[str, int] = {}
    dropped: Dict[str, int] = {}
    for block in mesh.cells:
        if block.type not in present:
            present.append(block.type)
        data = np.asarray(block.data)
        width = {"tetra": 4, "tetra10": 10}.get(block.type)
        if width is not None and (data.ndim != 2 or data.shape[1] != width):
            raise MeshError(
                f"{p}: a {block.type} block has connectivity of shape {data.shape}, expected (k, {width}); "
                "the file is truncated or corrupt"
            )
        if block.type == "tetra":
            blocks.append(data)
        elif block.type == "tetra10":
            blocks.append(data[:, :4])
        else:
            dropped[block.type] = dropped.get(block.type, 0) + len(data)
            continue
        kept[block.type] = kept.get(block.type, 0) + len(data)
    if not blocks or sum(len(b) for b in blocks) == 0:
        kinds = ", ".join(present) if present else "none"
        raise MeshError(f"{p}: no tetrahedra found (cell types present: {kinds})")
    if not all(np.issubdtype(b.dtype, np.integer) for b in blocks):
        raise MeshError(f"{p}: tetrahedron connectivity is not integer")
    tets = np.ascontiguousarray(np.concatenate([b.astype(np.int64, copy=False) for b in blocks], axis=0))
    if dropped:
        kept_s = ", ".join(f"{n} {k}" for k, n in kept.items())
        dropped_s = ", ".join(f"{n} {k}" for k, n in dropped.items())
        warnings.warn(f"{p}: kept {kept_s} cells; dropped {dropped_s} cells", UserWarning, stacklevel=2)
    check_duplicate_tets(p, tets)
    return vertices, tets
