"""Built-in procedural tetrahedral meshes (no files needed): box, ell, sphere, cylinder.

Each mesh is a union of axis-aligned grid cells, every cell split into 6 tetrahedra along its main diagonal
(the Kuhn / Freudenthal split). The split is the same in every cell, so neighbouring cells share their faces'
diagonals and the mesh is conforming; vertices are shared, never duplicated, and all tets are positively
oriented. The sphere and the cylinder map such a grid smoothly onto the ball and the disc (see
:func:`sphere`, :func:`cylinder`).

Example
-------
>>> from fepr import meshes
>>> m = meshes.box(size=(2.0, 1.0, 1.0), resolution=(4, 2, 2))    # doctest: +SKIP
>>> m.num_vertices, m.num_tets                                    # doctest: +SKIP
(45, 96)
>>> meshes.builtin("ell", size=0.5).num_tets                      # doctest: +SKIP
30
"""

from __future__ import annotations

import inspect
import math
import numbers
from itertools import permutations
from typing import Callable, Dict, Sequence, Tuple, Union

import numpy as np

from ._validate import real
from .errors import ConfigError
from .mesh import TetMesh

__all__ = ["BUILTIN", "box", "builtin", "cylinder", "ell", "sphere"]

#: Upper bound on the number of tets a built-in mesh may have (guards against accidental huge resolutions).
MAX_TETS = 20_000_000

Float3 = Union[float, Sequence[float]]
Int3 = Union[int, Sequence[int]]


def _kuhn_offsets() -> np.ndarray:
    """The 6 Kuhn tets of the unit cube as corner offsets, shape (6, 4, 3), all positively oriented."""
    tets = []
    for perm in permutations(range(3)):
        corner = np.zeros(3, dtype=np.int64)
        path = [corner.copy()]
        for axis in perm:
            corner[axis] += 1
            path.append(corner.copy())
        a, b, c, d = path
        # det[e_p0, e_p0 + e_p1, e_p0 + e_p1 + e_p2] = sign(perm); swap two vertices for odd permutations.
        if np.linalg.det(np.stack([b - a, c - a, d - a], axis=1).astype(float)) < 0:
            c, d = d, c
        tets.append([a, b, c, d])
    return np.array(tets, dtype=np.int64)


_KUHN = _kuhn_offsets()


def _grid_tets(cells: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Kuhn-split the integer lattice cells ``cells`` (c, 3) (lower corners).

    Returns the used lattice points (m, 3) int64, ordered with x fastest then y then z, and the tets (6c, 4)
    as indices into them.
    """
    corners = cells[:, None, None, :] + _KUHN[None, :, :, :]  # (c, 6, 4, 3)
    extent = corners.reshape(-1, 3).max(axis=0) + 1
    keys = corners[..., 0] + extent[0] * (corners[..., 1] + extent[1] * corners[..., 2])  # (c, 6, 4)
    unique, inverse = np.unique(keys.ravel(), return_inverse=True)
    lattice = np.stack(
        [unique % extent[0], (unique // extent[0]) % extent[1], unique // (extent[0] * extent[1])], axis=1
    )
    tets = inverse.reshape(-1, 4).astype(np.int64)
    return lattice.astype(np.int64), tets


def _check_tets_budget(name: str, ntets: int) -> None:
    if ntets > MAX_TETS:
        raise ConfigError(
            f"{name}: resolution too large: the mesh would have {ntets:,} tets (the limit is {MAX_TETS:,})"
        )


def _positive_float(value, param: str) -> float:
    return real(value, param, unit="metres", lo=0, lo_open=True)


def _positive_int(value, param: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ConfigError(f"{param} must be an integer >= 1, got {value!r}")
    out = int(value)
    if out < 1:
        raise ConfigError(f"{param} must be an integer >= 1, got {value!r}")
    return out


def _triple(value, param: str, check) -> tuple:
    if isinstance(value, (str, bytes)):
        raise ConfigError(f"{param} must be a number or 3 numbers, got {value!r}")
    if isinstance(value, (numbers.Number, np.generic)) and not isinstance(value, np.ndarray):
        item = check(value, param)
        return (item, item, item)
    try:
        items = list(value)
    except TypeError:
        raise ConfigError(f"{param} must be a number or 3 numbers, got {value!r}") from None
    if len(items) != 3:
        raise ConfigError(f"{param} must be a number or 3 numbers, got {len(items)} values: {value!r}")
    return tuple(check(v, f"{param}[{i}]") for i, v in enumerate(items))


def _finite_float(value, param: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ConfigError(f"{param} must be a number (metres), got {value!r}")
    out = float(value)
    if not math.isfinite(out):
        raise ConfigError(f"{param} must be finite, got {value!r}")
    return out


def box(
    size: Float3 = (1.0, 1.0, 1.0), resolution: Int3 = (2, 2, 2), center: Sequence[float] = (0.0, 0.0, 0.0)
) -> TetMesh:
    """An axis-aligned box split into ``nx * ny * nz`` cells of 6 tets each.

    Parameters
    ----------
    size : float or 3 floats
        Edge lengths (x, y, z) in metres, each > 0; a single number gives a cube.
    resolution : int or 3 ints
        Number of cells along x, y, z, each >= 1.
    center : 3 floats
        Centre of the box in metres.

    Returns
    -------
    TetMesh
        ``(nx+1)(ny+1)(nz+1)`` vertices (x fastest, then y, then z) and ``6 nx ny nz`` positively oriented
        tets.

    Raises
    ------
    ConfigError
        If a parameter is invalid (the message names it).
    """
    sizes = np.array(_triple(size, "size", _positive_float))
    res = _triple(resolution, "resolution", _positive_int)
    if isinstance(center, (str, bytes)) or isinstance(center, numbers.Number):
        raise ConfigError(f"center must be 3 numbers (metres), got {center!r}")
    try:
        center_items = list(center)
    except TypeError:
        raise ConfigError(f"center must be 3 numbers (metres), got {center!r}") from None
    if len(center_items) != 3:
        raise ConfigError(f"center must be 3 numbers (metres), got {len(center_items)} values")
    mid = np.array([_finite_float(v, f"center[{i}]") for i, v in enumerate(center_items)])
    _check_tets_budget("box", 6 * res[0] * res[1] * res[2])

    cells = np.stack(
        np.meshgrid(np.arange(res[0]), np.arange(res[1]), np.arange(res[2]), indexing="ij"), axis=-1
    ).reshape(-1, 3)
    lattice, tets = _grid_tets(cells.astype(np.int64))
    lower = mid - 0.5 * sizes
    vertices = lower + sizes * (lattice / np.array(res, dtype=np.float64))
    return TetMesh(vertices, tets, source="builtin:box")


#: Unit cells of the "L": the footprint [0,2]x[0,2] minus [1,2]x[1,2], height 1, plus a 1x1x2 column over the
#: cell [0,1]x[1,2] from z = 1 to z = 3 (the geometry of the seed project's ``ellell.1`` TetGen mesh).
_ELL_CELLS = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 1, 1), (0, 1, 2)], dtype=np.int64)


def ell(size: float = 1.0, resolution: int = 1) -> TetMesh:
    """The seed project's "L" body, built on a regular grid.

    An L-shaped footprint (the square [0,2]x[0,2] minus the corner cell [1,2]x[1,2]) of height 1, plus a
    1x1x2 column on the cell [0,1]x[1,2] from z = 1 to z = 3, all in units of ``size`` metres, with the corner
    at the origin: the geometry of the seed's ``ellell.1`` mesh. Volume ``5 size^3``, bounding box
    ``[0,2]x[0,2]x[0,3] * size``.

    Parameters
    ----------
    size : float
        Edge length of one unit cube in metres (> 0).
    resolution : int
        Cells per unit-cube edge (>= 1); the mesh has ``30 resolution^3`` tets.

    Raises
    ------
    ConfigError
        If a parameter is invalid (the message names it).
    """
    unit = _positive_float(size, "size")
    r = _positive_int(resolution, "resolution")
    _check_tets_budget("ell", 6 * len(_ELL_CELLS) * r**3)
    sub = np.stack(np.meshgrid(np.arange(r), np.arange(r), np.arange(r), indexing="ij"), axis=-1).reshape(-1, 3)
    cells = (_ELL_CELLS[:, None, :] * r + sub[None, :, :]).reshape(-1, 3)
    lattice, tets = _grid_tets(cells)
    vertices = unit * (lattice / float(r))
    return TetMesh(vertices, tets, source="builtin:ell")


def _mirrored_kuhn(lower: np.ndarray, n: Sequence[int]) -> Tuple[np.ndarray, np.ndarray]:
    """Kuhn-split the lattice cells ``lower`` (c, 3) of the grid ``0..n`` with the split mirrored per octant.

    In every cell the split's main diagonal points away from the grid's centre, so the mesh has the symmetry
    of the cube (no preferred diagonal direction). Mirroring a cell along an axis keeps the diagonals of the
    faces normal to that axis, so neighbouring cells still share their face diagonals: the mesh is conforming.
    Returns the used lattice points (m, 3) int64 and the tets (6c, 4), all positively oriented.
    """
    centre2 = np.asarray(n, dtype=np.int64)  # twice the grid centre
    mirrored = (2 * lower + 1) < centre2  # (c, 3): cell centre on the low side of the middle plane
    off = np.where(mirrored[:, None, None, :], 1 - _KUHN[None], _KUHN[None])  # (c, 6, 4, 3)
    corners = lower[:, None, None, :] + off
    odd = mirrored.sum(axis=1) % 2 == 1
    corners[odd] = corners[odd][:, :, [0, 1, 3, 2], :]  # an odd number of mirrors flips the orientation
    extent = np.asarray(n, dtype=np.int64) + 1
    keys = corners[..., 0] + extent[0] * (corners[..., 1] + extent[1] * corners[..., 2])
    unique, inverse = np.unique(keys.ravel(), return_inverse=True)
    lattice = np.stack(
        [unique % extent[0], (unique // extent[0]) % extent[1], unique // (extent[0] * extent[1])], axis=1
    )
    return lattice.astype(np.int64), inverse.reshape(-1, 4).astype(np.int64)


def _center3(center, name: str = "center") -> np.ndarray:
    if isinstance(center, (str, bytes)) or isinstance(center, numbers.Number):
        raise ConfigError(f"{name} must be 3 numbers (metres), got {center!r}")
    try:
        items = list(center)
    except TypeError:
        raise ConfigError(f"{name} must be 3 numbers (metres), got {center!r}") from None
    if len(items) != 3:
        raise ConfigError(f"{name} must be 3 numbers (metres), got {len(items)} values")
    return np.array([_finite_float(v, f"{name}[{i}]") for i, v in enumerate(items)])


def sphere(radius: float = 0.5, resolution: int = 8, center: Sequence[float] = (0.0, 0.0, 0.0)) -> TetMesh:
    """A ball, built procedurally (no mesher needed): a cube grid mapped smoothly onto the ball.

    The cube ``[-1, 1]^3`` is split into ``resolution^3`` cells of 6 tets each (the Kuhn split, mirrored per
    octant so the mesh has the cube's symmetry), and every grid point ``(x, y, z)`` is moved by the
    cube-to-ball map ``x' = x sqrt(1 - y^2/2 - z^2/2 + y^2 z^2/3)`` (and likewise for y', z'), which sends
    the cube's surface onto the sphere and is smooth inside. The boundary vertices lie exactly on the sphere,
    so the volume is a little below ``4/3 pi radius^3`` (1.6% below at resolution 8).

    Parameters
    ----------
    radius : float
        Radius in metres (> 0).
    resolution : int
        Cells across the diameter (>= 1): ``(resolution+1)^3`` vertices and ``6 resolution^3`` tets.
    center : 3 floats
        Centre in metres.

    Raises
    ------
    ConfigError
        If a parameter is invalid (the message names it).
    """
    r = _positive_float(radius, "radius")
    n = _positive_int(resolution, "resolution")
    mid = _center3(center)
    _check_tets_budget("sphere", 6 * n**3)
    lower = np.stack(np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij"), axis=-1).reshape(-1, 3)
    lattice, tets = _mirrored_kuhn(lower.astype(np.int64), (n, n, n))
    u = 2.0 * lattice / n - 1.0
    x2, y2, z2 = u[:, 0] ** 2, u[:, 1] ** 2, u[:, 2] ** 2
    ball = np.stack(
        [
            u[:, 0] * np.sqrt(1.0 - y2 / 2 - z2 / 2 + y2 * z2 / 3),
            u[:, 1] * np.sqrt(1.0 - z2 / 2 - x2 / 2 + z2 * x2 / 3),
            u[:, 2] * np.sqrt(1.0 - x2 / 2 - y2 / 2 + x2 * y2 / 3),
        ],
        axis=1,
    )
    return TetMesh(mid + r * ball, tets, source="builtin:sphere")


def cylinder(
    radius: float = 0.25,
    height: float = 1.0,
    resolution: int = 8,
    center: Sequence[float] = (0.0, 0.0, 0.0),
) -> TetMesh:
    """A solid circular cylinder along z, built procedurally (no mesher needed).

    A square grid of ``resolution x resolution`` cells is mapped onto the disc by
    ``x' = x sqrt(1 - y^2/2)``, ``y' = y sqrt(1 - x^2/2)`` (the square's edge goes onto the circle) and
    extruded along z in ``nz = max(1, round(resolution * height / (2 radius)))`` layers, so cells are about as
    tall as they are wide. Every cell is split into 6 tets (the Kuhn split, mirrored per quadrant).

    Parameters
    ----------
    radius : float
        Radius in metres (> 0).
    height : float
        Length along z in metres (> 0); the cylinder spans ``center[2] +- height / 2``.
    resolution : int
        Cells across the diameter (>= 1): ``6 resolution^2 nz`` tets.
    center : 3 floats
        Centre in metres.

    Raises
    ------
    ConfigError
        If a parameter is invalid (the message names it).
    """
    r = _positive_float(radius, "radius")
    h = _positive_float(height, "height")
    n = _positive_int(resolution, "resolution")
    mid = _center3(center)
    ratio = n * h / (2.0 * r)
    if ratio > MAX_TETS:
        raise ConfigError(f"cylinder: height / radius too large for resolution {n} (over {MAX_TETS:,} tets)")
    nz = max(1, int(round(ratio)))
    _check_tets_budget("cylinder", 6 * n * n * nz)
    lower = np.stack(np.meshgrid(np.arange(n), np.arange(n), np.arange(nz), indexing="ij"), axis=-1).reshape(-1, 3)
    lattice, tets = _mirrored_kuhn(lower.astype(np.int64), (n, n, nz))
    u = 2.0 * lattice[:, 0] / n - 1.0
    w = 2.0 * lattice[:, 1] / n - 1.0
    z = (lattice[:, 2] / nz - 0.5) * h
    disc = np.stack([u * np.sqrt(1.0 - w * w / 2), w * np.sqrt(1.0 - u * u / 2)], axis=1)
    return TetMesh(mid + np.column_stack([r * disc, z]), tets, source="builtin:cylinder")


#: Built-in meshes by name.
BUILTIN: Dict[str, Callable[..., TetMesh]] = {"box": box, "ell": ell, "sphere": sphere, "cylinder": cylinder}


def builtin(name: str, **kwargs) -> TetMesh:
    """Build the built-in mesh ``name`` (a key of :data:`BUILTIN`) with keyword arguments ``kwargs``.

    Raises
    ------
    ConfigError
        If the name is unknown (the message lists the known ones) or an argument is unknown or invalid.
    """
    func = BUILTIN.get(name) if isinstance(name, str) else None
    if func is None:
        raise ConfigError(f"unknown built-in mesh {name!r}; known: {', '.join(sorted(BUILTIN))}")
    params = inspect.signature(func).parameters
    unknown = [k for k in kwargs if k not in params]
    if unknown:
        raise ConfigError(
            f"built-in mesh {name!r} has no parameter {', '.join(map(repr, unknown))}; "
            f"its parameters are: {', '.join(params)}"
        )
    return func(**kwargs)
