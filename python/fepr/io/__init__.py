"""Reading tetrahedral meshes from files.

:func:`load_mesh` picks the reader from the file extension and returns a validated
:class:`~fepr.mesh.TetMesh`:

==============================  ==========================================================================
extension                       format and reader
==============================  ==========================================================================
``.node`` / ``.ele`` / basename TetGen, read natively (:func:`read_tetgen`); ``"ellell.1"`` means
                                ``ellell.1.node`` + ``ellell.1.ele``
``.msh``                        Gmsh 2.2 or 4.1, ASCII or binary (meshio, :func:`read_meshio`)
``.vtk`` / ``.vtu``             VTK legacy / VTK XML unstructured grid (meshio)
``.mesh`` / ``.meshb``          Medit (meshio)
``.npz``                        NumPy archive with ``vertices`` (or ``rest_positions`` / ``positions``) and
                                ``tets`` (:func:`read_npz`)
==============================  ==========================================================================

Example
-------
>>> from fepr.io import load_mesh
>>> mesh = load_mesh("meshes/bunny.msh", scale=0.1)        # doctest: +SKIP
>>> mesh.num_vertices, mesh.num_tets                       # doctest: +SKIP
(4670, 19379)

Every failure is a :class:`~fepr.errors.MeshError` that names the file (and, for TetGen files, the line).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from .._validate import real
from ..errors import ConfigError, MeshError
from ..mesh import TetMesh
from .meshio_formats import MESHIO_FORMATS, read_meshio
from .npz import read_npz
from .tetgen import read_tetgen, tetgen_paths

__all__ = ["SUPPORTED_EXTENSIONS", "load_mesh", "read_meshio", "read_npz", "read_tetgen", "read_arrays"]

PathLike = Union[str, "os.PathLike[str]"]

#: Extensions :func:`load_mesh` understands (lower case); a TetGen basename without extension works too.
SUPPORTED_EXTENSIONS: Tuple[str, ...] = (".node", ".ele", *MESHIO_FORMATS, ".npz")

_SUPPORTED_TEXT = (
    ".node/.ele (TetGen; or their basename without extension), .msh (Gmsh 2.2/4.1), .vtk, .vtu (VTK), "
    ".mesh/.meshb (Medit), .npz (NumPy: vertices + tets)"
)


def read_arrays(path: PathLike) -> Tuple[np.ndarray, np.ndarray]:
    """Read ``(vertices (m,3) float64, tets (k,4) int64)`` from any supported file, without validation.

    The reader is chosen as in :func:`load_mesh`. Raises :class:`~fepr.errors.MeshError`.
    """
    try:
        p = Path(os.fspath(path))
    except TypeError:
        raise MeshError(f"mesh path must be a string or os.PathLike, got {type(path).__name__}") from None
    suffix = p.suffix.lower()
    if suffix in (".node", ".ele"):
        return read_tetgen(p)
    if suffix in MESHIO_FORMATS:
        return read_meshio(p)
    if suffix == ".npz":
        return read_npz(p)
    node_path, ele_path = tetgen_paths(p)
    if node_path.is_file() or ele_path.is_file():
        return read_tetgen(p)
    if p.exists():
        kind = "directory" if p.is_dir() else f"extension {p.suffix!r}" if p.suffix else "no extension"
        raise MeshError(f"{p}: unsupported mesh file ({kind}); supported: {_SUPPORTED_TEXT}")
    raise MeshError(
        f"{p}: file not found (nor TetGen files {node_path.name} / {ele_path.name}); supported: {_SUPPORTED_TEXT}"
    )


def load_mesh(
    path: PathLike,
    *,
    scale: Optional[float] = None,
    translate: Optional[Sequence[float]] = None,
) -> TetMesh:
    """Load a tetrahedral mesh from a file and validate it.

    Parameters
    ----------
    path : str or os.PathLike
        The mesh file; the format is chosen by extension (see the module docs). For TetGen, the ``.node``
        file, the ``.ele`` file or their common basename.
    scale : float, optional
        Uniform scale factor (> 0) applied to the file's coordinates, e.g. to convert to metres.
    translate : sequence of 3 floats, optional
        Offset in metres added after scaling: the vertices are ``scale * x + translate``.

    Returns
    -------
    TetMesh
        Validated mesh (negatively oriented tets repaired with a warning), ``source`` set to ``str(path)``.

    Raises
    ------
    MeshError
        The file is missing, unsupported or malformed, or the mesh is invalid (the message names the file
        and the problem).
    ConfigError
        ``scale`` or ``translate`` is invalid.
    """
    factor = _check_scale(scale)
    offset = _check_translate(translate)
    vertices, tets = read_arrays(path)
    if factor is not None:
        vertices = vertices * factor
    if offset is not None:
        vertices = vertices + offset
    return TetMesh(vertices, tets, source=os.fspath(path))


def _check_scale(scale) -> Optional[float]:
    return None if scale is None else real(scale, "scale", lo=0, lo_open=True)


def _check_translate(translate) -> Optional[np.ndarray]:
    if translate is None:
        return None
    try:
        offset = np.asarray(translate, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"translate must be 3 numbers (metres), got {translate!r}") from None
    if offset.shape != (3,):
        raise ConfigError(f"translate must be 3 numbers (metres), got shape {offset.shape}")
    if not np.all(np.isfinite(offset)):
        raise ConfigError(f"translate must be finite, got {translate!r}")
    return offset
