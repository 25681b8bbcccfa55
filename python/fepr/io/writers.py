"""Writing tetrahedral meshes: :func:`write_mesh`.

==============================  ==========================================================================
extension                       format
==============================  ==========================================================================
``.msh``                        Gmsh 4.1 ASCII (meshio)
``.vtu``                        VTK XML unstructured grid, zlib-compressed binary (meshio)
``.vtk``                        VTK legacy, binary (meshio)
``.mesh`` / ``.meshb``          Medit ASCII / binary (meshio)
``.npz``                        NumPy archive with ``vertices`` (m, 3) float64 and ``tets`` (k, 4) int64
``.node`` / ``.ele``            TetGen: both ``BASE.node`` and ``BASE.ele`` are written, 0-based, natively
==============================  ==========================================================================

Coordinates are written exactly (17 significant digits in text formats), so reading the file back with
:func:`fepr.io.read_arrays` gives the same arrays.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import List, Tuple, Union

import numpy as np

from ..errors import ConfigError, MeshError

PathLike = Union[str, "os.PathLike[str]"]

__all__ = ["WRITE_EXTENSIONS", "write_mesh"]

#: Extensions :func:`write_mesh` writes (lower case).
WRITE_EXTENSIONS: Tuple[str, ...] = (".msh", ".vtu", ".vtk", ".mesh", ".meshb", ".npz", ".node", ".ele")


def _arrays(mesh) -> Tuple[np.ndarray, np.ndarray]:
    if hasattr(mesh, "vertices") and hasattr(mesh, "tets"):
        v, t = mesh.vertices, mesh.tets
    else:
        try:
            v, t = mesh
        except (TypeError, ValueError):
            raise ConfigError("mesh must be a fepr.TetMesh or a (vertices, tets) pair") from None
    v = np.ascontiguousarray(v, dtype=np.float64)
    t = np.ascontiguousarray(t, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 4:
        raise ConfigError(f"mesh arrays must have shapes (m, 3) and (k, 4), got {v.shape} and {t.shape}")
    return v, t


def write_mesh(mesh, path: PathLike) -> List[Path]:
    """Write a tetrahedral mesh; the format is chosen by the extension (see the module docs).

    Parameters
    ----------
    mesh : TetMesh or (vertices, tets)
        The mesh; vertices (m, 3) in metres, tets (k, 4) 0-based.
    path : str or os.PathLike
        Output file. For TetGen, ``BASE.node`` or ``BASE.ele``: both files are written.

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    ConfigError
        The extension is not one of :data:`WRITE_EXTENSIONS`.
    OSError
        The file cannot be written.
    """
    v, t = _arrays(mesh)
    p = Path(os.fspath(path))
    suffix = p.suffix.lower()
    if suffix not in WRITE_EXTENSIONS:
        raise ConfigError(f"{p}: cannot write extension {p.suffix!r}; supported: {', '.join(WRITE_EXTENSIONS)}")
    if suffix == ".npz":
        with open(p, "wb") as fh:
            np.savez(fh, vertices=v, tets=t)
        return [p]
    if suffix in (".node", ".ele"):
        return _write_tetgen(v, t, p.with_suffix(""))
    import meshio

    cell_data = {}
    kwargs = {}
    if suffix == ".msh":
        ones = np.ones(len(t), dtype=np.int64)
        cell_data = {"gmsh:physical": [ones], "gmsh:geometrical": [ones]}
        kwargs = {"file_format": "gmsh", "binary": False}
    elif suffix in (".vtu", ".vtk"):
        kwargs = {"binary": True}
    m = meshio.Mesh(v, [("tetra", t)], cell_data=cell_data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            meshio.write(str(p), m, **kwargs)
    except OSError:
        raise
    except Exception as exc:  # pragma: no cover - meshio failures on valid arrays
        raise MeshError(f"{p}: cannot write: {type(exc).__name__}: {exc}") from None
    return [p]


def _write_tetgen(v: np.ndarray, t: np.ndarray, base: Path) -> List[Path]:
    node, ele = Path(f"{base}.node"), Path(f"{base}.ele")
    with open(node, "w", encoding="ascii") as fh:
        fh.write(f"{len(v)} 3 0 0\n")
        np.savetxt(fh, np.column_stack([np.arange(len(v)), v]), fmt=["%d", "%.17g", "%.17g", "%.17g"])
        fh.write("# written by fepr\n")
    with open(ele, "w", encoding="ascii") as fh:
        fh.write(f"{len(t)} 4 0\n")
        np.savetxt(fh, np.column_stack([np.arange(len(t)), t]), fmt="%d")
        fh.write("# written by fepr\n")
    return [node, ele]
