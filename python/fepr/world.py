"""The world around a body: static obstacles and kinematic pins (SI units: metres, seconds, hertz, radians).

Obstacles are passed to :class:`fepr.Simulation` as ``obstacles=[...]``; the free vertices collide with them
(vertex contact with restitution and Coulomb friction). Kinematic pins (``kinematic_pins=[...]``) move groups
of vertices along a prescribed path. The energy that contacts remove and the work the pins do enter each
step's energy budget (history columns ``budget``, ``work_contact``, ``work_pins``), so FEPR conserves
``H_0 + budget_total`` instead of undoing them. Bodies of a :class:`fepr.MultiBody` do not collide with each
other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple, Union

import numpy as np

from ._validate import float_array
from .errors import ConfigError

Vec3 = Tuple[float, float, float]


def _vec3(value, name: str) -> Vec3:
    a = np.asarray(value, dtype=float) if not isinstance(value, str) else None
    if a is None or a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{name} must be 3 finite numbers, got {value!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


def _length(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ConfigError(f"{name} must be a number (m), got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ConfigError(f"{name} must be a positive length in m, got {value!r}")
    return v


def _coefficients(restitution, friction, what: str) -> Tuple[float, float]:
    for name, value in (("restitution", restitution), ("friction", friction)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
            raise ConfigError(f"{what}: {name} must be a number, got {value!r}")
    e, mu = float(restitution), float(friction)
    if not (math.isfinite(e) and 0.0 <= e <= 1.0):
        raise ConfigError(f"{what}: restitution must be in [0, 1], got {restitution!r}")
    if not (math.isfinite(mu) and mu >= 0.0):
        raise ConfigError(f"{what}: friction must be a finite coefficient >= 0, got {friction!r}")
    return e, mu


@dataclass(frozen=True)
class Plane:
    """The half-space below the plane through ``point`` (m) with outward ``normal``; the solid is on the side
    opposite the normal. ``restitution`` in [0, 1] (1: elastic bounce), ``friction``: Coulomb coefficient."""

    point: Vec3 = (0.0, 0.0, 0.0)
    normal: Vec3 = (0.0, 0.0, 1.0)
    restitution: float = 1.0
    friction: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "point", _vec3(self.point, "Plane point"))
        n = _vec3(self.normal, "Plane normal")
        if math.hypot(*n) < 1e-12:
            raise ConfigError("Plane normal must not be the zero vector")
        object.__setattr__(self, "normal", n)
        _coefficients(self.restitution, self.friction, "Plane")

    def _core(self):
        return ("plane", [*self.point, *self.normal], float(self.restitution), float(self.friction))


@dataclass(frozen=True)
class Sphere:
    """A solid ball of ``radius`` (m) about ``center`` (m)."""

    center: Vec3
    radius: float
    restitution: float = 1.0
    friction: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(self.center, "Sphere center"))
        object.__setattr__(self, "radius", _length(self.radius, "Sphere radius"))
        _coefficients(self.restitution, self.friction, "Sphere")

    def _core(self):
        return ("sphere", [*self.center, self.radius], float(self.restitution), float(self.friction))


@dataclass(frozen=True)
class Box:
    """A solid box with ``half_extents`` (m) about ``center`` (m); ``rotation`` is a 3x3 rotation matrix whose
    rows are the box's local axes in world coordinates (None: axis-aligned)."""

    center: Vec3
    half_extents: Vec3
    rotation: Optional[Tuple[Vec3, Vec3, Vec3]] = None
    restitution: float = 1.0
    friction: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(self.center, "Box center"))
        h = _vec3(self.half_extents, "Box half_extents")
        if min(h) <= 0:
            raise ConfigError(f"Box half_extents must be positive lengths in m, got {self.half_extents!r}")
        object.__setattr__(self, "half_extents", h)
        if self.rotation is not None:
            r = float_array(self.rotation, "Box rotation", "(3, 3)")
            if r.shape != (3, 3):
                raise ConfigError(f"Box rotation must be a 3x3 matrix, got shape {r.shape}")
            if not (np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0):
                raise ConfigError("Box rotation must be a rotation matrix (orthonormal rows, determinant +1)")
            object.__setattr__(self, "rotation", tuple(tuple(float(c) for c in row) for row in r))
        _coefficients(self.restitution, self.friction, "Box")

    def _core(self):
        rot = self.rotation if self.rotation is not None else ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        params = [*self.center, *self.half_extents, *[c for row in rot for c in row]]
        return ("box", params, float(self.restitution), float(self.friction))


@dataclass(frozen=True)
class Capsule:
    """The solid within ``radius`` (m) of the segment from ``a`` to ``b`` (m)."""

    a: Vec3
    b: Vec3
    radius: float
    restitution: float = 1.0
    friction: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "a", _vec3(self.a, "Capsule a"))
        object.__setattr__(self, "b", _vec3(self.b, "Capsule b"))
        object.__setattr__(self, "radius", _length(self.radius, "Capsule radius"))
        _coefficients(self.restitution, self.friction, "Capsule")

    def _core(self):
        return ("capsule", [*self.a, *self.b, self.radius], float(self.restitution), float(self.friction))


Obstacle = Union[Plane, Sphere, Box, Capsule]
OBSTACLE_TYPES = (Plane, Sphere, Box, Capsule)


@dataclass(frozen=True)
class Sinusoid:
    """Displacement ``d(t) = amplitude * (sin(2 pi frequency t + phase) - sin(phase))``: ``amplitude`` (3,) m,
    ``frequency`` Hz (>= 0), ``phase`` rad. ``d(0) = 0``."""

    amplitude: Vec3
    frequency: float
    phase: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "amplitude", _vec3(self.amplitude, "Sinusoid amplitude"))
        f = float(self.frequency)
        if not (math.isfinite(f) and f >= 0):
            raise ConfigError(f"Sinusoid frequency must be a finite number >= 0 (Hz), got {self.frequency!r}")
        if not math.isfinite(float(self.phase)):
            raise ConfigError(f"Sinusoid phase must be finite (rad), got {self.phase!r}")

    def _core(self):
        return "sinusoid", [*self.amplitude, float(self.frequency), float(self.phase)], []

    def displacement(self, t: float) -> np.ndarray:
        """``d(t)``, (3,) float64, m."""
        w = 2 * math.pi * float(self.frequency)
        return np.asarray(self.amplitude) * (math.sin(w * t + self.phase) - math.sin(self.phase))


@dataclass(frozen=True)
class Keyframes:
    """Piecewise-linear displacement through ``(times[k], offsets[k])``: ``times`` (k,) s strictly increasing,
    ``offsets`` (k, 3) m; held at the first offset before ``times[0]`` and at the last after ``times[-1]``."""

    times: Sequence[float]
    offsets: Sequence[Vec3]

    def __post_init__(self):
        t = float_array(self.times, "Keyframes times", "(k,)")
        o = float_array(self.offsets, "Keyframes offsets", "(k, 3)")
        if t.ndim != 1 or t.size == 0:
            raise ConfigError(f"Keyframes times must be a non-empty 1-D list of seconds, got shape {t.shape}")
        if o.shape != (t.size, 3):
            raise ConfigError(f"Keyframes offsets must have shape ({t.size}, 3), got {o.shape}")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ConfigError(f"Keyframes times must be finite and strictly increasing, got {list(t)}")
        if not np.all(np.isfinite(o)):
            raise ConfigError("Keyframes offsets must be finite")
        object.__setattr__(self, "times", tuple(float(x) for x in t))
        object.__setattr__(self, "offsets", tuple(tuple(float(c) for c in row) for row in o))

    def _core(self):
        return "keyframes", [c for row in self.offsets for c in row], list(self.times)

    def displacement(self, t: float) -> np.ndarray:
        """``d(t)``, (3,) float64, m."""
        o = np.asarray(self.offsets)
        return np.array([np.interp(t, self.times, o[:, a]) for a in range(3)])


Motion = Union[Sinusoid, Keyframes]


@dataclass(frozen=True)
class KinematicPins:
    """A group of vertices that follow ``x_i(t) = x_i(t_0) + d(t) - d(t_0)`` for the ``motion`` d: their
    initial positions plus the prescribed displacement. ``vertices``: indices, or a bool mask of shape (m,).
    They are pinned (excluded from the solve and the projection); the work they do enters the budget."""

    vertices: Union[Sequence[int], np.ndarray]
    motion: Motion

    def __post_init__(self):
        if not isinstance(self.motion, (Sinusoid, Keyframes)):
            raise ConfigError(f"KinematicPins motion must be fepr.Sinusoid or fepr.Keyframes, got {self.motion!r}")

    def indices(self, m: int) -> List[int]:
        """The vertex indices, validated against a mesh of ``m`` vertices."""
        a = np.asarray(self.vertices)
        if a.dtype == bool:
            if a.shape != (m,):
                raise ConfigError(f"KinematicPins mask must have shape ({m},), got {a.shape}")
            idx = np.flatnonzero(a)
        else:
            if a.size and (not np.issubdtype(a.dtype, np.integer) or a.ndim != 1):
                raise ConfigError("KinematicPins vertices must be a 1-D array of indices or a bool mask")
            idx = a.astype(np.int64).ravel()
        if idx.size == 0:
            raise ConfigError("KinematicPins has no vertices")
        bad = idx[(idx < 0) | (idx >= m)]
        if bad.size:
            raise ConfigError(f"KinematicPins vertex {int(bad[0])} is out of range: the mesh has {m} vertices")
        return sorted({int(i) for i in idx})
