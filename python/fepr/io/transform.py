"""Load options: place a mesh read from a file in fepr's frame (metres, Z up).

The options are applied in this fixed order, whatever order they are given in:

1. ``up_axis``: ``"y"`` turns a Y-up file into fepr's Z-up frame (a rotation by +90 degrees about x:
   ``(x, y, z) -> (x, -z, y)``); ``"z"`` (fepr's own convention) changes nothing.
2. ``rotate``: three angles in degrees about the x, y and z axes, applied in that order
   (``R = Rz @ Ry @ Rx``), or a 3x3 rotation matrix (orthonormal, determinant +1).
3. ``scale`` (a factor, e.g. 0.01 for centimetres) or ``fit`` (a size in metres: the largest extent of the
   bounding box after steps 1-2 becomes ``fit``); both scale about the origin, and at most one may be given.
4. ``center``: ``"bbox"`` (or ``True``) moves the centre of the bounding box to the origin, ``"centroid"``
   moves the centroid of the solid (volume-weighted centre of the tets) there.
5. ``translate``: a vector in metres added last.

Rotations and positive scales keep every tet's orientation. Every invalid option raises
:class:`~fepr.errors.ConfigError` naming the option.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

from .._validate import real, shown
from ..errors import ConfigError

__all__ = ["LoadOptions", "apply_load_options", "check_load_options", "rotation_matrix"]

#: Rotation taking a Y-up frame to fepr's Z-up frame: +90 degrees about x, (x, y, z) -> (x, -z, y).
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

CENTER_MODES = ("bbox", "centroid")


@dataclass(frozen=True)
class LoadOptions:
    """Validated load options (see the module docs for their meaning and order)."""

    scale: Optional[float] = None
    translate: Optional[np.ndarray] = None
    fit: Optional[float] = None
    rotate: Optional[np.ndarray] = None  # 3x3
    up_axis: Optional[str] = None
    center: Optional[str] = None  # "bbox" or "centroid"

    def is_identity(self) -> bool:
        return all(
            v is None for v in (self.scale, self.translate, self.fit, self.rotate, self.center)
        ) and self.up_axis in (None, "z")


def rotation_matrix(angles_deg) -> np.ndarray:
    """``Rz @ Ry @ Rx`` for angles (degrees) about x, y and z: rotate about x first, then y, then z."""
    ax, ay, az = (math.radians(float(a)) for a in angles_deg)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _vector(value, name: str) -> np.ndarray:
    if isinstance(value, (str, bytes)):
        raise ConfigError(f"{name} must be 3 numbers (metres), got {shown(value)}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be 3 numbers (metres), got {shown(value)}") from None
    if arr.shape != (3,):
        raise ConfigError(f"{name} must be 3 numbers (metres), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be finite, got {shown(value)}")
    return arr


def _rotation(value) -> np.ndarray:
    msg = "rotate must be 3 angles in degrees (about x, y, z) or a 3x3 rotation matrix"
    if isinstance(value, (str, bytes, bool, numbers.Number)):
        raise ConfigError(f"{msg}, got {shown(value)}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"{msg}, got {shown(value)}") from None
    if arr.dtype == object or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{msg} of finite numbers, got {shown(value)}")
    if arr.shape == (3,):
        return rotation_matrix(arr)
    if arr.shape == (3, 3):
        err = float(np.abs(arr @ arr.T - np.eye(3)).max())
        if err > 1e-6:
            raise ConfigError(f"rotate: the 3x3 matrix is not orthonormal (max |R R^T - I| = {err:.3g})")
        if np.linalg.det(arr) < 0:
            raise ConfigError("rotate: the 3x3 matrix has determinant -1 (a reflection, which would invert the tets)")
        return arr
    raise ConfigError(f"{msg}, got shape {arr.shape}")


def check_load_options(
    *,
    scale=None,
    translate=None,
    fit=None,
    rotate=None,
    up_axis=None,
    center=None,
) -> LoadOptions:
    """Validate the load options; raises :class:`~fepr.errors.ConfigError` naming the option."""
    s = None if scale is None else real(scale, "scale", lo=0, lo_open=True)
    f = None if fit is None else real(fit, "fit", unit="metres", lo=0, lo_open=True)
    if s is not None and f is not None:
        raise ConfigError("give at most one of scale and fit (fit sets the size; scale multiplies it)")
    t = None if translate is None else _vector(translate, "translate")
    r = None if rotate is None else _rotation(rotate)
    if up_axis is not None and (not isinstance(up_axis, str) or up_axis.lower() not in ("y", "z")):
        raise ConfigError(f'up_axis must be "y" or "z" (the file\'s up direction), got {shown(up_axis)}')
    up = None if up_axis is None else up_axis.lower()
    c: Optional[str]
    if center is None or center is False:
        c = None
    elif center is True:
        c = "bbox"
    elif isinstance(center, str) and center in CENTER_MODES:
        c = center
    else:
        raise ConfigError(f'center must be "bbox", "centroid", true or false, got {shown(center)}')
    return LoadOptions(scale=s, translate=t, fit=f, rotate=r, up_axis=up, center=c)


def _centroid(vertices: np.ndarray, tets: Optional[np.ndarray]) -> np.ndarray:
    if tets is not None and len(tets):
        t = np.asarray(tets, dtype=np.int64)
        if t.min() >= 0 and t.max() < len(vertices):
            p = vertices[t]
            d = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
            w = np.abs(np.linalg.det(d))
            if np.isfinite(w).all() and w.sum() > 0:
                return (w[:, None] * p.mean(axis=1)).sum(axis=0) / w.sum()
    return vertices.mean(axis=0)


def apply_load_options(
    vertices: np.ndarray, tets: Optional[np.ndarray], options: Union[LoadOptions, None]
) -> np.ndarray:
    """Vertices after the load options, in the documented order (a new array; the input is not changed).

    ``tets`` is used only for ``center="centroid"`` (the volume-weighted centroid; without tets the vertex
    mean).
    """
    v = np.asarray(vertices, dtype=np.float64)
    if options is None or options.is_identity():
        return v
    o = options
    if o.up_axis == "y":
        v = v @ Y_UP_TO_Z_UP.T
    if o.rotate is not None:
        v = v @ o.rotate.T
    if o.scale is not None:
        v = v * o.scale
    if o.fit is not None:
        extent = float((v.max(axis=0) - v.min(axis=0)).max()) if len(v) else 0.0
        if extent == 0.0:
            raise ConfigError("fit: the mesh has no extent to scale (all vertices coincide)")
        if math.isfinite(extent):  # a non-finite coordinate is reported by the mesh validation
            v = v * (o.fit / extent)
    if o.center == "bbox":
        v = v - 0.5 * (v.min(axis=0) + v.max(axis=0))
    elif o.center == "centroid":
        v = v - _centroid(v, tets)
    if o.translate is not None:
        v = v + o.translate
    return v
