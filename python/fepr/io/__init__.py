"""Reading and writing meshes.

:func:`load_mesh` picks the reader from the file extension and returns a validated
:class:`~fepr.mesh.TetMesh`:

==============================  ==========================================================================
extension                       format and reader
==============================  ==========================================================================
``.node`` / ``.ele`` / basename TetGen, read natively (:func:`read_tetgen`); ``"ellell.1"`` means
                                ``ellell.1.node`` + ``ellell.1.ele`` (a ``.face`` file beside them is
                                ignored; its path may be given too)
``.msh``                        Gmsh 2.2 or 4.1, ASCII or binary (meshio, :func:`read_meshio`)
``.vtk`` / ``.vtu``             VTK legacy / VTK XML unstructured grid (ASCII, binary, appended) (meshio)
``.mesh`` / ``.meshb``          Medit (meshio)
``.npz``                        NumPy archive with ``vertices`` (or ``rest_positions`` / ``positions``) and
                                ``tets`` (:func:`read_npz`)
==============================  ==========================================================================

Surfaces (``.obj``, ``.off``, ``.stl``, ``.ply``) are read by :func:`read_surface`; turn them into tets with
:func:`fepr.tetrahedralize`. :func:`write_mesh` writes tet meshes.

Example
-------
>>> from fepr.io import load_mesh
>>> mesh = load_mesh("meshes/bunny.msh", fit=0.3, center="bbox")   # doctest: +SKIP
>>> mesh.num_vertices, mesh.num_tets                               # doctest: +SKIP
(4670, 19379)

Every failure is a :class:`~fepr.errors.MeshError` that names the file (and, for line-based formats, the
line); invalid load options are :class:`~fepr.errors.ConfigError` naming the option.

Compressed data (zlib/lzma ``.vtu`` arrays, deflated ``.npz`` members) is checked before it is inflated: against the
counts the file declares and against a cap on the decompressed bytes of one file, 1 GiB by default, set with the
environment variable ``FEPR_MAX_MESH_BYTES`` (e.g. ``FEPR_MAX_MESH_BYTES=8GiB``; see :mod:`fepr.io._limits`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import MeshError
from ..mesh import TetMesh
from .meshio_formats import MESHIO_FORMATS, read_meshio
from .npz import read_npz
from .surface import SURFACE_EXTENSIONS, read_surface
from .tetgen import read_tetgen, tetgen_paths
from .transform import LoadOptions, apply_load_options, check_load_options
from .writers import WRITE_EXTENSIONS, write_mesh

__all__ = [
    "SUPPORTED_EXTENSIONS",
    "SURFACE_EXTENSIONS",
    "WRITE_EXTENSIONS",
    "LoadOptions",
    "load_mesh",
    "read_arrays",
    "read_meshio",
    "read_npz",
    "read_surface",
    "read_tetgen",
    "transform_mesh",
    "write_mesh",
]

PathLike = Union[str, "os.PathLike[str]"]

#: Extensions :func:`load_mesh` understands (lower case); a TetGen basename without extension works too.
SUPPORTED_EXTENSIONS: Tuple[str, ...] = (".node", ".ele", ".face", *MESHIO_FORMATS, ".npz")

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
    if suffix in (".node", ".ele", ".face"):
        return read_tetgen(p)
    if suffix in MESHIO_FORMATS:
        return read_meshio(p)
    if suffix == ".npz":
        return read_npz(p)
    node_path, ele_path = tetgen_paths(p)
    if node_path.is_file() or ele_path.is_file():
        return read_tetgen(p)
    if p.exists() and suffix in SURFACE_EXTENSIONS:
        raise MeshError(
            f"{p}: {p.suffix!r} is a surface format (triangles, no tetrahedra); tetrahedralize it first with "
            f'fepr.tetrahedralize("{p.name}") or `fepr mesh {p.name} -o {p.stem}.msh`. Tet mesh formats: '
            f"{_SUPPORTED_TEXT}"
        )
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
    fit: Optional[float] = None,
    rotate=None,
    up_axis: Optional[str] = None,
    center: Union[str, bool, None] = None,
) -> TetMesh:
    """Load a tetrahedral mesh from a file, place it in fepr's frame and validate it.

    Parameters
    ----------
    path : str or os.PathLike
        The mesh file; the format is chosen by extension (see the module docs). For TetGen, the ``.node``
        file, the ``.ele`` file or their common basename.
    scale : float, optional
        Uniform scale factor (> 0) applied to the file's coordinates, e.g. 0.01 for a file in centimetres.
    translate : sequence of 3 floats, optional
        Offset in metres, added last.
    fit : float, optional
        Target size in metres: the mesh is scaled so that the largest extent of its bounding box is ``fit``
        (instead of ``scale``; at most one of the two).
    rotate : 3 floats or 3x3 array, optional
        Angles in degrees about x, then y, then z (``R = Rz @ Ry @ Rx``), or a rotation matrix.
    up_axis : {"y", "z"}, optional
        The file's up axis: ``"y"`` turns a Y-up file (OBJ, glTF, many game assets) into fepr's Z-up frame.
    center : {"bbox", "centroid"} or bool, optional
        Move the bounding-box centre (``"bbox"`` or ``True``) or the volume centroid (``"centroid"``) to the
        origin.

    The options are applied in this order: ``up_axis``, ``rotate``, ``scale`` / ``fit``, ``center``,
    ``translate`` (see :mod:`fepr.io.transform`).

    Returns
    -------
    TetMesh
        Validated mesh (negatively oriented tets repaired with a warning), ``source`` set to ``str(path)``.

    Raises
    ------
    MeshError
        The file is missing, unsupported or malformed, or the mesh is invalid (the message names the file
        and the problem); or its compressed data (``.vtu``, ``.npz``) would inflate beyond the counts it
        declares or beyond the cap on decompressed mesh data: 1 GiB per file unless the environment variable
        ``FEPR_MAX_MESH_BYTES`` sets another number of bytes (``FEPR_MAX_MESH_BYTES=8GiB`` for a trusted file).
    ConfigError
        A load option is invalid (the message names it), or ``FEPR_MAX_MESH_BYTES`` is not a number of bytes.
    """
    options = check_load_options(
        scale=scale, translate=translate, fit=fit, rotate=rotate, up_axis=up_axis, center=center
    )
    vertices, tets = read_arrays(path)
    vertices = apply_load_options(vertices, tets, options)
    return TetMesh(vertices, tets, source=os.fspath(path))


def transform_mesh(
    mesh: TetMesh,
    *,
    scale: Optional[float] = None,
    translate: Optional[Sequence[float]] = None,
    fit: Optional[float] = None,
    rotate=None,
    up_axis: Optional[str] = None,
    center: Union[str, bool, None] = None,
) -> TetMesh:
    """A copy of ``mesh`` with the load options of :func:`load_mesh` applied (same meaning and order)."""
    options = check_load_options(
        scale=scale, translate=translate, fit=fit, rotate=rotate, up_axis=up_axis, center=center
    )
    if options.is_identity():
        return mesh
    vertices = apply_load_options(np.asarray(mesh.vertices), np.asarray(mesh.tets), options)
    return TetMesh(vertices, mesh.tets, source=mesh.source)
