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

Meshing to a size (``target_tets``, :func:`tetrahedralize_to_size`, ``fepr mesh --target-tets N``): a dense
scan (tens of thousands of triangles) fills with far more tets than a real-time simulation can step, whatever
the volume bound, because TetGen keeps every surface triangle. So the surface is first decimated with
quadric error metrics (``fast-simplification``), then filled by TetGen with a volume bound, and the size is
corrected by measuring the tet count (a few passes, deterministic). See :func:`tetrahedralize_to_size`.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from ._validate import real
from .errors import ConfigError, MeshError, MissingDependencyError
from .mesh import TetMesh

__all__ = ["MESHERS", "SizedMesh", "SizingPass", "tetrahedralize", "tetrahedralize_to_size"]

#: Meshers :func:`tetrahedralize` knows.
MESHERS = ("tetgen", "ftetwild")

_INSTALL = {
    "tetgen": 'the "tetgen" package is not installed: pip install "fepr[mesh]" (or pip install tetgen)',
    "ftetwild": 'the "pytetwild" package is not installed: pip install "fepr[ftetwild]" (or pip install pytetwild)',
    "decimate": 'the "fast-simplification" package is not installed: pip install "fepr[mesh]" '
    "(or pip install fast-simplification)",
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


def _checked_surface(
    surface_or_path, mesher: str, *, repair_hint: bool = True
) -> Tuple[np.ndarray, np.ndarray, str, List[str]]:
    """The surface's arrays without unreferenced vertices, its source and its problems (a ``MeshError`` when
    the mesher cannot use it: TetGen needs a closed manifold; indices out of range stop every mesher).
    ``repair_hint``: say that mesher='ftetwild' repairs such surfaces (not where it cannot be chosen)."""
    from .io.surface import compact_surface, surface_problems

    v, f, source = _surface_arrays(surface_or_path)
    problems = surface_problems(v, f)
    out_of_range = problems and "out of range" in problems[0]
    if out_of_range or (problems and mesher == "tetgen"):
        raise MeshError(
            f"{source}: cannot tetrahedralize: "
            + "; ".join(problems)
            + ". A solid needs a closed, manifold surface"
            + (" (mesher='ftetwild' repairs such surfaces)" if mesher == "tetgen" and repair_hint else "")
        )
    v, f, _ = compact_surface(v, f)
    return v, f, source, problems


def tetrahedralize(
    surface_or_path,
    *,
    max_volume: Optional[float] = None,
    edge_length: Optional[float] = None,
    quality: Optional[float] = None,
    mesher: str = "tetgen",
    target_tets: Optional[int] = None,
    max_tets: Optional[int] = None,
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
    target_tets : int, optional
        Aim at about this many tets (within :data:`SIZE_TOLERANCE`, 10%): the surface is decimated first and
        the volume bound chosen by measuring (see :func:`tetrahedralize_to_size`, which also reports the
        decimation). TetGen only; not with ``max_volume`` or ``edge_length``.
    max_tets : int, optional
        A hard upper bound on the number of tets: never exceeded. With ``target_tets`` the sizing passes
        retry below it; without, a mesh with more tets is refused (``MeshError``) rather than returned.

    Returns
    -------
    TetMesh
        All tets positively oriented, no unreferenced vertices, ``source`` names the input.

    Raises
    ------
    MeshError
        The surface cannot be read, or (TetGen) is open, non-manifold, has degenerate or duplicate triangles
        or intersects itself; or the mesher failed. The message says which, with counts and an example.
        Also when the mesh would have more than ``max_tets`` tets.
    ConfigError
        An option is invalid.
    MissingDependencyError
        The mesher's package is not installed (the message says ``pip install "fepr[mesh]"``).
    """
    if target_tets is not None:
        if max_volume is not None or edge_length is not None:
            raise ConfigError(
                "give target_tets or one of max_volume and edge_length, not both: target_tets chooses the volume "
                "bound itself"
            )
        if mesher != "tetgen":
            raise ConfigError(f"target_tets works with mesher='tetgen' only, not {mesher!r}")
        return tetrahedralize_to_size(surface_or_path, target_tets=target_tets, max_tets=max_tets, quality=quality).mesh
    limit = None if max_tets is None else _tet_count(max_tets, "max_tets")
    if mesher not in MESHERS:
        raise ConfigError(f"mesher must be one of {', '.join(map(repr, MESHERS))}, got {mesher!r}")
    if max_volume is not None and edge_length is not None:
        raise ConfigError("give at most one of max_volume and edge_length")
    vol = None if max_volume is None else real(max_volume, "max_volume", lo=0, lo_open=True)
    edge = None if edge_length is None else real(edge_length, "edge_length", lo=0, lo_open=True)
    if quality is not None and mesher != "tetgen":
        raise ConfigError(f"quality (a radius-edge ratio bound) applies to mesher='tetgen' only, not {mesher!r}")
    q = 2.0 if quality is None else real(quality, "quality", lo=1.0, lo_open=True)

    v, f, source, problems = _checked_surface(surface_or_path, mesher)
    where = f"{source}: "
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
    if limit is not None and len(tets) > limit:
        raise MeshError(
            f"{where}the mesh would have {len(tets):,} tets, more than max_tets={limit:,}; give target_tets "
            "(--target-tets: it decimates the surface first) or a larger max_volume or edge_length"
        )
    return TetMesh(nodes, tets, source=f"{source} ({mesher})")


# --- Meshing to a size ---------------------------------------------------------------------------------------

#: How close (relative) the tet count must come to ``target_tets`` before the sizing passes stop.
SIZE_TOLERANCE = 0.1
#: Most decimate-and-fill passes of :func:`tetrahedralize_to_size`; after them the closest result is taken.
MAX_SIZING_PASSES = 6
#: Relative change of the enclosed volume by decimation above which :func:`tetrahedralize_to_size` warns.
VOLUME_CHANGE_WARNING = 0.05

# First guess of the size, calibrated by measuring (subdivided bunny and elephant scans with and without noise,
# and a bumpy sphere, 80k-190k triangles, 5k-20k tets, radius-edge bound 2.0): the first pass then lands within
# 0.8-1.3 times the target, and one or two corrections bring it within SIZE_TOLERANCE.
# TetGen's tets under a fixed volume bound (-a) average about a third of the bound ...
_BOUND_PER_TET = 3.0
# ... and quadric decimation puts its triangles where the surface bends, so half the triangle count of a uniform
# triangulation with the tets' edge length resolves the shape (a uniform count gives 1.4-2.5x the tets).
_SURFACE_SHARE = 0.5
# fast-simplification's aggressiveness (`agg`, 0 careful .. 10 fast; its default is 7). Lower values keep the
# volume and the shape better (a subdivided Armadillo at 1,300 triangles: -1.2% with 4, -2.4% with 5, -4.7%
# with 7; they also gave better-shaped triangles and fewer tets) but stop short of small counts (4 stops near
# 500 triangles on the scans, 3 near 2,000), and all of them sometimes pinch a thin part into a non-manifold
# edge. So candidate surfaces (factor on the triangle count asked, agg) are tried in this order, each rejected
# if unusable: the careful settings at up to 25% more triangles first (the volume matters more than a few
# more tets, which the next pass corrects), then agg 7, then up to twice the triangles (less decimation), as a
# very coarse surface can pinch or fold where a finer one does not.
_CANDIDATES = (
    (1.0, 4.0),
    (1.0, 5.0),
    (1.1, 4.0),
    (1.1, 5.0),
    (1.25, 4.0),
    (1.25, 5.0),
    (1.0, 7.0),
    (1.1, 7.0),
    (1.25, 7.0),
    (1.6, 4.0),
    (1.6, 5.0),
    (1.6, 7.0),
    (2.0, 4.0),
    (2.0, 5.0),
    (2.0, 7.0),
)
# Decimation that stops short of the count asked by more than this factor is treated as failed (next candidate).
_SHORT_STOP = 1.2
# Quadric decimation can leave two vertices 1e-13 apart (the optimal positions of neighbouring collapses
# coincide; measured on a subdivided bunny). TetGen then fails ("split_segment") or refines around the needle
# triangles to 10x the tets. Edges shorter than this fraction of the median edge are collapsed: it moves the
# surface by at most 1% of an edge.
_WELD_FRACTION = 1e-2
# Fewer triangles than this cannot describe a solid usefully (an icosahedron has 20).
_MIN_TRIANGLES = 20
_REGULAR_TET = 6.0 * math.sqrt(2.0)  # V = l^3 / (6 sqrt 2) for a regular tet with edge l
_EQUILATERAL = math.sqrt(3.0) / 4.0  # A = sqrt(3)/4 l^2 for an equilateral triangle with edge l


@dataclass(frozen=True)
class SizingPass:
    """One decimate-and-fill pass of :func:`tetrahedralize_to_size`.

    ``surface_triangles``: triangles of the surface TetGen filled; ``max_volume``: TetGen's volume bound
    (surface units cubed); ``tets``: the tets it gave; ``rejected``: surfaces of this pass that could not be
    used, and why (e.g. ``"agg 5: TetGen failed: ... self-intersections"``), tried before the one that was.
    """

    surface_triangles: int
    max_volume: float
    tets: int
    rejected: Tuple[str, ...] = ()


@dataclass
class SizedMesh:
    """The result of :func:`tetrahedralize_to_size`: the mesh and what was done to reach its size.

    Volumes are enclosed volumes in surface units cubed; ``decimated`` is False when the input surface was
    already coarse enough and was filled as given.
    """

    mesh: TetMesh
    target_tets: int
    max_tets: Optional[int]
    input_triangles: int
    surface_triangles: int
    input_volume: float
    surface_volume: float
    decimated: bool
    passes: List[SizingPass] = field(default_factory=list)

    @property
    def volume_change(self) -> float:
        """Relative change of the enclosed volume by decimation: ``surface_volume / input_volume - 1``."""
        return self.surface_volume / self.input_volume - 1.0

    def __str__(self) -> str:
        surface = (
            f"surface decimated {self.input_triangles:,} -> {self.surface_triangles:,} triangles "
            f"(volume change {100.0 * self.volume_change:+.2f}%)"
            if self.decimated
            else f"surface kept as given ({self.input_triangles:,} triangles)"
        )
        bound = "" if self.max_tets is None else f", at most {self.max_tets:,}"
        tries = "; ".join(f"{p.surface_triangles:,} triangles -> {p.tets:,} tets" for p in self.passes)
        return (
            f"{surface}; {self.mesh.num_tets:,} tets for a target of {self.target_tets:,}{bound} "
            f"({len(self.passes)} pass{'es' if len(self.passes) != 1 else ''}: {tries})"
        )


def _tet_count(value, name: str) -> int:
    """A positive whole number of tets (Python or NumPy integer; not bool, not a float)."""
    import numbers

    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral) or int(value) < 1:
        raise ConfigError(f"{name} must be a positive whole number of tets, got {value!r}")
    return int(value)


def _surface_area(v: np.ndarray, f: np.ndarray) -> float:
    p = v[f]
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


def _weld_short_edges(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Collapse edges shorter than ``_WELD_FRACTION`` of the median edge; returns the new triangles.

    Triangles left with a repeated vertex are dropped, and so are both triangles of a pair that the collapse
    made identical (a fin of zero volume). Done here with NumPy because no small maintained package does this
    one step (trimesh and PyVista merge by coordinates, not along edges, and are much larger dependencies).
    """
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=0)
    length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    short = edges[length < _WELD_FRACTION * float(np.median(length))]
    if len(short) == 0:
        return f
    # Each vertex takes the smallest index of its cluster of short edges (clusters are a few vertices, so
    # this propagation ends after a few rounds).
    label = np.arange(len(v))
    while True:
        low = np.minimum(label[short[:, 0]], label[short[:, 1]])
        new = label.copy()
        np.minimum.at(new, short[:, 0], low)
        np.minimum.at(new, short[:, 1], low)
        new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    f = label[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    _, inverse, counts = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True, return_counts=True)
    return f[counts[inverse.ravel()] == 1]


def _decimator(where: str):
    # fast-simplification (MIT, by the PyVista developers, a wheel of well under 1 MB with only NumPy as a
    # dependency) wraps Sven Forstmann's Fast-Quadric-Mesh-Simplification: quadric error metrics (Garland &
    # Heckbert), which keep the shape and the volume of a scan well at a 100x reduction, in a fraction of a
    # second for 100k triangles. PyVista's decimate (VTK) does the same but brings VTK (hundreds of MB).
    try:
        import fast_simplification
    except ImportError:
        raise MissingDependencyError(f"{where}decimation: {_INSTALL['decimate']}") from None
    return fast_simplification.simplify


def _decimate(simplify, v: np.ndarray, f: np.ndarray, triangles: int, agg: float):
    """Decimated surface ``(vertices, triangles)`` and what makes it unusable (empty when closed, manifold)."""
    from .io.surface import compact_surface, surface_problems

    # Fast-Quadric-Mesh-Simplification stops collapsing at an absolute quadric error (1e-9 (k + 3)^agg in
    # iteration k), so it works in the units of the input: an elephant 100 units long stopped at 3,240 of
    # 193k triangles. Decimating a copy scaled to a unit bounding-box diagonal makes it independent of units.
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    scale = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    dv, df = simplify((v - centre) / scale, f, target_count=triangles, agg=agg)
    dv = np.ascontiguousarray(dv, dtype=np.float64) * scale + centre
    df = _weld_short_edges(dv, np.asarray(df, dtype=np.int64))
    if len(df) == 0:
        return dv, df, ["nothing left"]
    dv, df, _ = compact_surface(dv, df)
    problems = surface_problems(dv, df)
    if len(df) > _SHORT_STOP * triangles:
        problems.append(f"decimation stopped at {len(df):,} triangles")
    return dv, np.ascontiguousarray(df), problems


def _fill(simplify, v, f, triangles: int, bound: float, quality: float, where: str, cache: Dict):
    """One sizing pass: a usable decimated surface with about ``triangles`` triangles, filled by TetGen.

    Returns ``(surface vertices, surface triangles, nodes, elems, rejected)``. Candidates are tried in a fixed
    order (so the result is deterministic), those of ``_CANDIDATES``. A surface is rejected when decimation
    left it open or non-manifold or stopped short, or TetGen cannot fill it (self-intersections).
    """
    if triangles >= len(f):  # coarse enough already: keep the surface exactly as given
        nodes, elems = _run_tetgen(v, f, bound, quality, where)
        return v, f, nodes, elems, ()
    rejected: List[str] = []
    seen = set()
    for factor, agg in _CANDIDATES:
        count = min(len(f), int(math.ceil(factor * triangles)))
        if (count, agg) in seen:
            continue
        seen.add((count, agg))
        label = f"{count:,} triangles, agg {agg:g}"
        floor = cache.get(("floor", agg))
        if floor is not None and floor > _SHORT_STOP * count:  # known to stop short: skip the work
            rejected.append(f"{label}: decimation stops at {floor:,} triangles")
            continue
        if count >= len(f):
            sv, sf, problems = v, f, []
        else:
            key = (count, agg)
            if key not in cache:
                cache[key] = _decimate(simplify, v, f, count, agg)
            sv, sf, problems = cache[key]
            if len(sf) > _SHORT_STOP * count:
                cache[("floor", agg)] = min(len(sf), cache.get(("floor", agg), len(sf)))
        if problems:
            rejected.append(f"{label}: {'; '.join(problems)}")
            continue
        try:
            nodes, elems = _run_tetgen(sv, sf, bound, quality, "")
        except MeshError as exc:
            rejected.append(f"{label}: {exc}")
            continue
        return sv, sf, nodes, elems, tuple(rejected)
    raise MeshError(
        f"{where}cannot decimate the surface to about {triangles:,} triangles into one TetGen can fill: "
        + " | ".join(rejected)
        + ". Try a larger target_tets"
    )


def tetrahedralize_to_size(
    surface_or_path,
    *,
    target_tets: int,
    max_tets: Optional[int] = None,
    quality: Optional[float] = None,
) -> SizedMesh:
    """Fill a closed surface with about ``target_tets`` tetrahedra, decimating it first (TetGen).

    A dense surface (a scan of 80k triangles) cannot become a small mesh by a volume bound alone: TetGen keeps
    every surface triangle, so it gives several tets per triangle whatever the bound. Here the surface is
    decimated with quadric error metrics (``fast-simplification``; closed and manifold afterwards, checked),
    then filled with TetGen under a volume bound. The size ``h`` starts from the enclosed volume ``V``:
    ``h^3 = 6 sqrt(2) V / target_tets`` (the edge of a regular tet of volume ``V / target_tets``), giving a
    surface of ``0.5 A / (sqrt(3)/4 h^2)`` triangles (``A`` the area) and a bound of ``3 h^3 / (6 sqrt(2))``
    (both calibrated by measuring, see the module source). Each pass measures the tet count ``n`` and scales
    ``h`` by ``(n / target)^(1/3)``, until ``n`` is within :data:`SIZE_TOLERANCE` of the target and at most
    ``max_tets`` (at most :data:`MAX_SIZING_PASSES` passes; then the closest one is taken). Every step is
    deterministic: the same input gives the same mesh.

    Parameters
    ----------
    surface_or_path : str, os.PathLike or (vertices, triangles)
        As for :func:`tetrahedralize`: a closed, manifold surface (units are kept).
    target_tets : int
        The number of tets to aim at, >= 1.
    max_tets : int, optional
        A hard upper bound, >= ``target_tets``: a mesh with more tets is never returned (the passes aim
        below it, and if none of them gets there a ``MeshError`` says so).
    quality : float, optional
        TetGen's radius-edge ratio bound, > 1 (default 2.0), as for :func:`tetrahedralize`.

    Returns
    -------
    SizedMesh
        ``.mesh`` the :class:`~fepr.TetMesh` (positively oriented tets, no unreferenced vertices); the input
        and decimated triangle counts and enclosed volumes (``.volume_change``), and the passes made.
        ``str()`` of it is a one-line summary. A :class:`UserWarning` is issued when decimation changed the
        volume by more than :data:`VOLUME_CHANGE_WARNING` (5%): the target is too small for the shape's detail.

    Raises
    ------
    ConfigError
        ``target_tets`` or ``max_tets`` is not a positive whole number, ``max_tets < target_tets``, or
        ``quality`` is not > 1.
    MeshError
        The surface cannot be read, is not closed and manifold, or encloses no volume; no decimated surface
        could be filled; or no pass gave at most ``max_tets`` tets. Messages name the input and the counts.
    MissingDependencyError
        ``tetgen`` or ``fast-simplification`` is missing (``pip install "fepr[mesh]"``).
    """
    from .io.surface import surface_volume

    target = _tet_count(target_tets, "target_tets")
    limit = None if max_tets is None else _tet_count(max_tets, "max_tets")
    if limit is not None and limit < target:
        raise ConfigError(f"max_tets ({limit:,}) must be >= target_tets ({target:,})")
    q = 2.0 if quality is None else real(quality, "quality", lo=1.0, lo_open=True)
    v, f, source, _ = _checked_surface(surface_or_path, "tetgen", repair_hint=False)
    where = f"{source}: "
    simplify = _decimator(where)
    volume_in = float(surface_volume(v, f) or 0.0)
    area = _surface_area(v, f)
    if not abs(volume_in) > 0.0:
        raise MeshError(f"{where}the surface encloses no volume (its {len(f):,} triangles are flat)")

    # Accept counts within SIZE_TOLERANCE of the target and not over max_tets; aim at the middle of that window.
    low = target * (1.0 - SIZE_TOLERANCE)
    high = target * (1.0 + SIZE_TOLERANCE) if limit is None else min(target * (1.0 + SIZE_TOLERANCE), limit)
    aim = 0.5 * (low + high)
    h = (_REGULAR_TET * abs(volume_in) / aim) ** (1.0 / 3.0)
    cache: Dict = {}
    passes: List[SizingPass] = []
    best = None
    for _ in range(MAX_SIZING_PASSES):
        triangles = int(round(_SURFACE_SHARE * area / (_EQUILATERAL * h * h)))
        triangles = max(_MIN_TRIANGLES, min(len(f), triangles))
        bound = _BOUND_PER_TET * h**3 / _REGULAR_TET
        try:
            sv, sf, nodes, elems, rejected = _fill(simplify, v, f, triangles, bound, q, where, cache)
        except MeshError:
            if not passes:
                raise
            break  # a coarser surface cannot be made: keep the closest of the passes so far
        n = len(elems)
        passes.append(SizingPass(len(sf), bound, n, rejected))
        allowed = limit is None or n <= limit
        miss = abs(math.log(max(n, 1) / target))
        if allowed and (best is None or miss < best[0]):
            best = (miss, sv, sf, nodes, elems)
        if low <= n <= high:
            break
        previous = passes[-2] if len(passes) > 1 else None
        if previous is not None and (previous.surface_triangles, previous.tets) == (len(sf), n):
            break  # the size is pinned (at the fewest triangles, or the surface as given): no pass changes it
        # n scales about as h^-3; the clamp keeps one odd pass (a fallback surface) from overshooting.
        h *= min(2.0, max(0.5, (max(n, 1) / aim) ** (1.0 / 3.0)))
    if best is None:
        tries = ", ".join(f"{p.surface_triangles:,} triangles -> {p.tets:,} tets" for p in passes)
        fewest = min(p.tets for p in passes)
        raise MeshError(
            f"{where}no mesh with at most max_tets={limit:,} tets after {len(passes)} passes ({tries}); the "
            f"fewest were {fewest:,}: give a larger max_tets"
        )
    _, sv, sf, nodes, elems = best
    nodes, tets = _normalise(nodes, elems)
    decimated = len(sf) != len(f) or sv is not v
    volume_out = float(surface_volume(sv, sf) or 0.0)
    label = f"tetgen, decimated to {len(sf):,} triangles" if decimated else "tetgen"
    result = SizedMesh(
        mesh=TetMesh(nodes, tets, source=f"{source} ({label})"),
        target_tets=target,
        max_tets=limit,
        input_triangles=len(f),
        surface_triangles=len(sf),
        input_volume=volume_in,
        surface_volume=volume_out,
        decimated=decimated,
        passes=passes,
    )
    if abs(result.volume_change) > VOLUME_CHANGE_WARNING:
        warnings.warn(
            f"{where}decimating the surface to {len(sf):,} triangles changed its volume by "
            f"{100.0 * result.volume_change:+.1f}%: {target:,} tets are too few for the shape's detail",
            UserWarning,
            stacklevel=2,
        )
    return result
