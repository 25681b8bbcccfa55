"""Surface to tets: :func:`tetrahedralize` fills a closed triangle surface with tetrahedra.

Meshers (optional packages, imported only when used):

``"tetgen"`` (default)
    TetGen through the ``tetgen`` package on PyPI (``pip install "fepr[mesh]"``). The wrapper is MIT
    licensed, but it contains TetGen itself, which is AGPL-3.0 (or a commercial licence from WIAS): that is
    why it is an optional extra and not a dependency of fepr. Constrained Delaunay refinement with a
    radius-edge quality bound; the surface is kept as given, so it must be closed, manifold and free of
    self-intersections.
``"ftetwild"``
    fTetWild through the ``pytetwild`` package (MPL-2.0, Python >= 3.10). Slower, tets of better shape, and it
    tolerates (repairs) open, non-manifold or self-intersecting input: the result then approximates the
    surface within a small envelope, and a warning says so.

The result is a validated :class:`~fepr.TetMesh`: every tet positively oriented (meshers that emit the other
orientation are normalised here, silently), and unreferenced vertices removed.

Both meshers write debugging files into the current directory (TetGen ``_skipped.node`` / ``.face`` when it
finds self-intersections, fTetWild ``__tracked_surface.stl``), so they run in a scratch directory that is
removed afterwards; the working directory is changed for the duration of the call.
"""

from __future__ import annotations

import contextlib
import importlib.machinery
import importlib.util
import math
import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from ._validate import real
from .errors import ConfigError, MeshError, MissingDependencyError
from .mesh import TetMesh

__all__ = ["MESHERS", "tetrahedralize"]

#: Meshers :func:`tetrahedralize` knows.
MESHERS = ("tetgen", "ftetwild")

_INSTALL = {
    "tetgen": 'the "tetgen" package is not installed: pip install "fepr[mesh]" (or pip install tetgen)',
    "ftetwild": 'the "pytetwild" package is not installed: pip install "fepr[ftetwild]" (or pip install pytetwild)',
}


def _surface_arrays(surface) -> Tuple[np.ndarray, np.ndarray, str]:
    if isinstance(surface, (str, os.PathLike)):
        from .io import read_surface

        path = Path(os.fspath(surface))
        v, f = read_surface(path)
        return v, f, str(path)
    try:
        v, f = surface
    except (TypeError, ValueError):
        raise ConfigError(
            "surface must be a path to a surface file (.obj, .off, .stl, .ply) or a (vertices, triangles) pair"
        ) from None
    try:
        v = np.ascontiguousarray(v, dtype=np.float64)
        f_raw = np.asarray(f)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"surface arrays must be numeric: {exc}") from None
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"surface vertices must have shape (n, 3), got {v.shape}")
    if f_raw.ndim != 2 or f_raw.shape[1] != 3 or (f_raw.size and not np.issubdtype(f_raw.dtype, np.integer)):
        raise MeshError(f"surface triangles must be integers of shape (f, 3), got {f_raw.dtype} {f_raw.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
    if bad.size:
        raise MeshError(f"surface vertex {int(bad[0])} has a non-finite coordinate {v[bad[0]].tolist()}")
    return v, np.ascontiguousarray(f_raw, dtype=np.int64), "surface"


@contextlib.contextmanager
def _scratch_dir():
    """Run the body in a fresh temporary working directory (removed afterwards)."""
    old = os.getcwd()
    tmp = tempfile.mkdtemp(prefix="fepr-mesher-")
    try:
        os.chdir(tmp)
        yield
    finally:
        os.chdir(old)
        shutil.rmtree(tmp, ignore_errors=True)


def _run_tetgen(v: np.ndarray, f: np.ndarray, max_volume: Optional[float], quality: float, where: str):
    try:
        import tetgen
    except ImportError:
        raise MissingDependencyError(f"{where}mesher 'tetgen': {_INSTALL['tetgen']}") from None
    kwargs = {"quality": True, "minratio": quality, "quiet": True}
    if max_volume is not None:
        kwargs["maxvolume"] = max_volume
        kwargs["fixedvolume"] = True  # the -a switch: maxvolume applies to every tet
    try:
        with _scratch_dir():
            gen = tetgen.TetGen(v, f.astype(np.int32))
            out = gen.tetrahedralize(**kwargs)
    except RuntimeError as exc:
        msg = str(exc).strip()
        hint = ""
        if "intersect" in msg.lower():
            hint = " (fix the surface, or use mesher='ftetwild', which repairs it)"
        raise MeshError(f"{where}TetGen failed: {msg}{hint}") from None
    nodes, elems = out[0], out[1]
    return np.asarray(nodes, dtype=np.float64), np.asarray(elems, dtype=np.int64)


def _pytetwild_wrapper():
    """The compiled fTetWild wrapper of pytetwild, also when ``import pytetwild`` fails for want of pyvista."""
    try:
        import pytetwild

        return pytetwild, None
    except ModuleNotFoundError as exc:
        if exc.name == "pytetwild":
            raise MissingDependencyError(f"mesher 'ftetwild': {_INSTALL['ftetwild']}") from None
        cause = exc
    except ImportError as exc:
        cause = exc
    # pytetwild 0.4.2 imports pyvista in its package __init__ although tetrahedralize() does not need it:
    # load its compiled module on its own.
    spec = importlib.util.find_spec("pytetwild")
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    for folder in locations:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = Path(folder) / f"PyfTetWildWrapper{suffix}"
            if path.is_file():
                sub = importlib.util.spec_from_file_location("pytetwild.PyfTetWildWrapper", path)
                if sub is None or sub.loader is None:
                    continue
                module = importlib.util.module_from_spec(sub)
                sub.loader.exec_module(module)
                return None, module
    raise MissingDependencyError(
        f"mesher 'ftetwild': pytetwild is installed but cannot be imported ({cause}); try pip install pyvista"
    )


def _run_ftetwild(v: np.ndarray, f: np.ndarray, edge_length: Optional[float], where: str):
    package, wrapper = _pytetwild_wrapper()
    faces = np.ascontiguousarray(f, dtype=np.int32)
    try:
        with _scratch_dir():
            return _call_ftetwild(package, wrapper, v, faces, edge_length)
    except TypeError as exc:
        raise MissingDependencyError(
            f"{where}mesher 'ftetwild': this pytetwild version has an interface fepr does not know ({exc}); "
            "pip install pyvista 'pytetwild>=0.4'"
        ) from None
    except (RuntimeError, ValueError) as exc:
        raise MeshError(f"{where}fTetWild failed: {exc}") from None


def _call_ftetwild(package, wrapper, v: np.ndarray, faces: np.ndarray, edge_length: Optional[float]):
    """fTetWild through pytetwild's public function, or its compiled module directly (pytetwild 0.4 layout)."""
    if package is not None:
        kwargs = {"quiet": True}
        if edge_length is not None:
            kwargs["edge_length_abs"] = edge_length
        nodes, elems = package.tetrahedralize(v, faces, **kwargs)[:2]
    else:
        diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
        fac = 0.05 if edge_length is None or diag == 0 else min(1.0, edge_length / diag)
        empty = (np.empty((0, 3)), np.empty((0, 4), dtype=np.int32), np.empty(0))
        nodes, elems = wrapper.tetrahedralize_mesh(
            v,
            faces.view(np.uint32),
            True,  # optimize
            False,  # skip_simplify
            fac,
            0.0 if edge_length is None else float(edge_length),
            1e-3,  # envelope, relative to the bounding box
            10.0,  # stop energy
            False,  # coarsen
            0,  # threads: all
            80,  # optimisation iterations
            6,  # log level
            True,  # quiet
            False,  # vtk ordering
            False,  # disable filtering
            *empty,
        )[:2]
    return np.asarray(nodes, dtype=np.float64), np.asarray(elems, dtype=np.int64)


def _normalise(nodes: np.ndarray, elems: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Positive orientation (swap the last two vertices of negative tets) and no unreferenced vertices."""
    if elems.ndim != 2 or elems.shape[1] != 4 or len(elems) == 0:
        raise MeshError(f"the mesher returned no tetrahedra (array shape {elems.shape})")
    p = nodes[elems]
    v6 = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets = elems.copy()
    neg = v6 < 0
    tets[neg, 2], tets[neg, 3] = elems[neg, 3], elems[neg, 2]
    used = np.unique(tets)
    if len(used) < len(nodes):
        remap = np.full(len(nodes), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        nodes, tets = nodes[used], remap[tets]
    return np.ascontiguousarray(nodes), np.ascontiguousarray(tets)


def tetrahedralize(
    surface_or_path,
    *,
    max_volume: Optional[float] = None,
    edge_length: Optional[float] = None,
    quality: Optional[float] = None,
    mesher: str = "tetgen",
) -> TetMesh:
    """Fill a closed triangle surface with tetrahedra.

    Parameters
    ----------
    surface_or_path : str, os.PathLike or (vertices, triangles)
        A surface file (``.obj``, ``.off``, ``.stl``, ``.ply``; see :func:`fepr.io.read_surface`) or arrays
        ``vertices`` (n, 3) and ``triangles`` (f, 3) 0-based. Units are kept (scale afterwards with
        :func:`fepr.io.transform_mesh` if needed).
    max_volume : float, optional
        Largest tet volume (units of the surface, cubed). TetGen: the ``-a`` switch (it bounds the refinement;
        TetGen's final mesh improvement may leave a few tets up to about 15% larger); fTetWild: converted to
        the edge length of a regular tet of that volume.
    edge_length : float, optional
        Target edge length (units of the surface). fTetWild: its ideal edge length; TetGen: converted to
        ``max_volume = edge_length^3 / (6 sqrt(2))`` (the volume of a regular tet with that edge). Give at
        most one of ``max_volume`` and ``edge_length``; with neither, the surface's own edge lengths set the
        size (TetGen) or 1/20 of the bounding-box diagonal (fTetWild).
    quality : float, optional
        TetGen only: the largest radius-edge ratio of a tet (the ``-q`` switch), > 1; smaller is better
        shaped and gives more tets. Default 2.0.
    mesher : {"tetgen", "ftetwild"}
        Which mesher to use (see the module docs for their licences and behaviour).

    Returns
    -------
    TetMesh
        All tets positively oriented, no unreferenced vertices, ``source`` names the input.

    Raises
    ------
    MeshError
        The surface cannot be read, or (TetGen) is open, non-manifold, has degenerate or duplicate triangles
        or intersects itself; or the mesher failed. The message says which, with counts and an example.
    ConfigError
        An option is invalid.
    MissingDependencyError
        The mesher's package is not installed (the message says ``pip install "fepr[mesh]"``).
    """
    if mesher not in MESHERS:
        raise ConfigError(f"mesher must be one of {', '.join(map(repr, MESHERS))}, got {mesher!r}")
    if max_volume is not None and edge_length is not None:
        raise ConfigError("give at most one of max_volume and edge_length")
    vol = None if max_volume is None else real(max_volume, "max_volume", lo=0, lo_open=True)
    edge = None if edge_length is None else real(edge_length, "edge_length", lo=0, lo_open=True)
    if quality is not None and mesher != "tetgen":
        raise ConfigError(f"quality (a radius-edge ratio bound) applies to mesher='tetgen' only, not {mesher!r}")
    q = 2.0 if quality is None else real(quality, "quality", lo=1.0, lo_open=True)

    from .io.surface import compact_surface, surface_problems

    v, f, source = _surface_arrays(surface_or_path)
    where = f"{source}: "
    problems = surface_problems(v, f)
    out_of_range = problems and "out of range" in problems[0]
    if out_of_range or (problems and mesher == "tetgen"):
        raise MeshError(
            f"{where}cannot tetrahedralize: "
            + "; ".join(problems)
            + ". A solid needs a closed, manifold surface"
            + (" (mesher='ftetwild' repairs such surfaces)" if mesher == "tetgen" else "")
        )
    v, f, _ = compact_surface(v, f)
    if mesher == "tetgen":
        if edge is not None:
            vol = edge**3 / (6.0 * math.sqrt(2.0))
        nodes, elems = _run_tetgen(v, f, vol, q, where)
    else:
        if problems:
            warnings.warn(
                f"{where}the surface is not a clean closed manifold ({'; '.join(problems)}); fTetWild repairs it, "
                "so the tets fill an approximation of it",
                UserWarning,
                stacklevel=2,
            )
        if vol is not None:
            edge = (6.0 * math.sqrt(2.0) * vol) ** (1.0 / 3.0)
        nodes, elems = _run_ftetwild(v, f, edge, where)
    nodes, tets = _normalise(nodes, elems)
    return TetMesh(nodes, tets, source=f"{source} ({mesher})")
