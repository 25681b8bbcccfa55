"""The world around a body: obstacles and kinematic pins (SI units: metres, seconds, hertz, radians).

Obstacles are passed to :class:`fepr.Simulation` as ``obstacles=[...]``; the free vertices collide with them
(vertex contact with restitution and Coulomb friction). An obstacle is static, or moves along a prescribed
rigid motion (``motion=fepr.ObstacleMotion(...)``: a platform, a piston, a turning drum). Kinematic pins
(``kinematic_pins=[...]``) move groups of vertices along a prescribed path. The energy that contacts remove and
the work the pins do enter each step's energy budget (history columns ``budget``, ``work_contact``,
``work_pins``), so FEPR conserves ``H_0 + budget_total`` instead of undoing them. Bodies of a
:class:`fepr.MultiBody` also collide with each other (see :mod:`fepr.multibody`).
"""

from __future__ import annotations

import math
import os
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


class _Analytic:
    """What the analytic obstacles share: the core's tuple of their coefficients, (no) triangles and motion."""

    def _common(self):
        motion = None if self.motion is None else self.motion._core()
        return float(self.restitution), float(self.friction), [], motion


def _check_motion(motion, what: str) -> None:
    if motion is not None and not isinstance(motion, ObstacleMotion):
        raise ConfigError(f"{what} motion must be a fepr.ObstacleMotion or None, got {motion!r}")


@dataclass(frozen=True)
class Plane(_Analytic):
    """The half-space below the plane through ``point`` (m) with outward ``normal``; the solid is on the side
    opposite the normal. ``restitution`` in [0, 1] (1: elastic bounce), ``friction``: Coulomb coefficient.
    Every obstacle takes ``motion`` (:class:`ObstacleMotion`, None: static); its geometry is where it is at
    ``t = 0``."""

    point: Vec3 = (0.0, 0.0, 0.0)
    normal: Vec3 = (0.0, 0.0, 1.0)
    restitution: float = 1.0
    friction: float = 0.0
    motion: Optional[ObstacleMotion] = None

    def __post_init__(self):
        object.__setattr__(self, "point", _vec3(self.point, "Plane point"))
        n = _vec3(self.normal, "Plane normal")
        if math.hypot(*n) < 1e-12:
            raise ConfigError("Plane normal must not be the zero vector")
        object.__setattr__(self, "normal", n)
        _coefficients(self.restitution, self.friction, "Plane")
        _check_motion(self.motion, "Plane")

    def _core(self):
        return ("plane", [*self.point, *self.normal], *self._common())


@dataclass(frozen=True)
class Sphere(_Analytic):
    """A solid ball of ``radius`` (m) about ``center`` (m)."""

    center: Vec3
    radius: float
    restitution: float = 1.0
    friction: float = 0.0
    motion: Optional[ObstacleMotion] = None

    def __post_init__(self):
        object.__setattr__(self, "center", _vec3(self.center, "Sphere center"))
        object.__setattr__(self, "radius", _length(self.radius, "Sphere radius"))
        _coefficients(self.restitution, self.friction, "Sphere")
        _check_motion(self.motion, "Sphere")

    def _core(self):
        return ("sphere", [*self.center, self.radius], *self._common())


@dataclass(frozen=True)
class Box(_Analytic):
    """A solid box with ``half_extents`` (m) about ``center`` (m); ``rotation`` is a 3x3 rotation matrix whose
    rows are the box's local axes in world coordinates (None: axis-aligned)."""

    center: Vec3
    half_extents: Vec3
    rotation: Optional[Tuple[Vec3, Vec3, Vec3]] = None
    restitution: float = 1.0
    friction: float = 0.0
    motion: Optional[ObstacleMotion] = None

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
        _check_motion(self.motion, "Box")

    def _core(self):
        rot = self.rotation if self.rotation is not None else ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        params = [*self.center, *self.half_extents, *[c for row in rot for c in row]]
        return ("box", params, *self._common())


@dataclass(frozen=True)
class Capsule(_Analytic):
    """The solid within ``radius`` (m) of the segment from ``a`` to ``b`` (m)."""

    a: Vec3
    b: Vec3
    radius: float
    restitution: float = 1.0
    friction: float = 0.0
    motion: Optional[ObstacleMotion] = None

    def __post_init__(self):
        object.__setattr__(self, "a", _vec3(self.a, "Capsule a"))
        object.__setattr__(self, "b", _vec3(self.b, "Capsule b"))
        object.__setattr__(self, "radius", _length(self.radius, "Capsule radius"))
        _coefficients(self.restitution, self.friction, "Capsule")
        _check_motion(self.motion, "Capsule")

    def _core(self):
        return ("capsule", [*self.a, *self.b, self.radius], *self._common())


class MeshObstacle:
    """A triangle mesh the free vertices collide with: a scanned floor, a bowl, a terrain (static, or moving with
    ``motion``).

    Parameters
    ----------
    source : str, os.PathLike, or (vertices, triangles)
        An OBJ, OFF, STL or PLY file (see :func:`fepr.io.read_surface`), or arrays: ``vertices`` (n, 3)
        float64 in m and ``triangles`` (k, 3) int vertex indices.
    restitution : float in [0, 1]
        Normal velocity after an impact is ``-restitution`` times the one before.
    friction : float >= 0
        Coulomb coefficient.
    flip_normals : bool
        Reverse every triangle's winding (for an open mesh whose normals point into the solid).
    motion : ObstacleMotion or None
        A prescribed rigid motion (None: static); the mesh as given is where it is at ``t = 0``.

    The solid is on the side opposite the triangle normals (right-hand rule on the listed corners). A closed
    mesh (every edge shared by two triangles) wound inside-out is turned outward automatically; an open mesh is
    one-sided: everything behind its normals counts as solid, so its winding must point to the free side (use
    ``flip_normals``). Distances are exact point-triangle distances (signed with angle-weighted
    pseudo-normals), so contact is as accurate as with the analytic shapes; a vertex cannot cross a triangle
    within a step (segments are ray-cast against the mesh).

    Raises :class:`~fepr.errors.MeshError` for a file that cannot be read, and :class:`~fepr.errors.ConfigError`
    for arrays that are not a triangle mesh (wrong shapes, NaN, empty, an index out of range, a triangle with
    no area); the message names the vertex or triangle.
    """

    def __init__(
        self,
        source,
        restitution: float = 1.0,
        friction: float = 0.0,
        flip_normals: bool = False,
        motion: Optional[ObstacleMotion] = None,
    ):
        if isinstance(source, (str, os.PathLike)):
            from .io.surface import read_surface

            vertices, triangles = read_surface(source)
            self.path: Optional[str] = os.fspath(source)
        else:
            if not isinstance(source, (tuple, list)) or len(source) != 2:
                raise ConfigError(
                    "MeshObstacle source must be a file path or (vertices (n, 3), triangles (k, 3)), "
                    f"got {type(source).__name__}"
                )
            vertices, triangles = source
            self.path = None
        what = f"MeshObstacle {self.path}" if self.path else "MeshObstacle"
        v = float_array(vertices, f"{what} vertices", "(n, 3)")
        if v.ndim != 2 or v.shape[1] != 3:
            raise ConfigError(f"{what} vertices must have shape (n, 3), got {v.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(v), axis=1))
        if bad.size:
            raise ConfigError(f"{what}: vertex {int(bad[0])} is not finite: {v[bad[0]].tolist()}")
        t = np.asarray(triangles)
        if t.size == 0:
            raise ConfigError(f"{what} has no triangles")
        if t.ndim != 2 or t.shape[1] != 3:
            raise ConfigError(
                f"{what} triangles must have shape (k, 3) (a triangle mesh; got shape {t.shape}: "
                "tets, quads or lines are not a surface)"
            )
        if not np.issubdtype(t.dtype, np.integer):
            raise ConfigError(f"{what} triangles must be integer vertex indices, got dtype {t.dtype}")
        out = np.flatnonzero((t < 0).any(axis=1) | (t >= len(v)).any(axis=1))
        if out.size:
            raise ConfigError(
                f"{what}: triangle {int(out[0])} refers to vertex {t[out[0]].tolist()} but there are {len(v)} vertices"
            )
        t = t.astype(np.int64)
        if flip_normals:
            t = t[:, [0, 2, 1]]
        self.vertices = v.copy()
        self.vertices.flags.writeable = False
        self.triangles = t
        self.triangles.flags.writeable = False
        self.restitution, self.friction = _coefficients(restitution, friction, what)
        self.flip_normals = bool(flip_normals)
        _check_motion(motion, what)
        self.motion = motion
        # Validates now (degenerate triangles named by index), not at the first step.
        from ._core import check_mesh_obstacle

        try:
            self.closed = check_mesh_obstacle(self.vertices.ravel().tolist(), self.triangles.ravel().tolist())
        except ValueError as e:
            raise ConfigError(f"{what}: {e}") from None

    @classmethod
    def terrain(
        cls,
        size: float = 4.0,
        cells: int = 32,
        height: float = 0.1,
        wavelength: float = 1.0,
        center: Vec3 = (0.0, 0.0, 0.0),
        depth: Optional[float] = None,
        restitution: float = 1.0,
        friction: float = 0.0,
        motion: Optional[ObstacleMotion] = None,
    ) -> MeshObstacle:
        """A built-in bumpy ground, needing no file: a square slab of edge ``size`` (m) about ``center`` whose top
        is a height field ``z = center_z + height * b(x, y)`` over ``cells`` x ``cells`` squares (two triangles
        each), with smooth bumps ``b`` in [-1, 1] of about ``wavelength`` (m); its flat bottom lies ``depth`` (m,
        default ``size / 4``) below the lowest possible point of the top. A closed mesh, so it bounds a solid
        exactly (and the solve skips the vertices it provably cannot reach)."""
        size = _length(size, "terrain size")
        height = _length(height, "terrain height")
        wavelength = _length(wavelength, "terrain wavelength")
        depth = 0.25 * size if depth is None else _length(depth, "terrain depth")
        if isinstance(cells, bool) or not isinstance(cells, (int, np.integer)) or not 1 <= int(cells) <= 1000:
            raise ConfigError(f"terrain cells must be an integer in [1, 1000], got {cells!r}")
        c = _vec3(center, "terrain center")
        n = int(cells)
        u = np.linspace(-0.5 * size, 0.5 * size, n + 1)
        x, y = np.meshgrid(u, u, indexing="ij")
        k = 2.0 * math.pi / wavelength
        bumps = 0.6 * np.sin(k * x) * np.cos(k * y) + 0.4 * np.sin(0.61 * k * (x + 0.7 * y) + 1.3)
        top = np.stack([x.ravel() + c[0], y.ravel() + c[1], c[2] + height * bumps.ravel()], axis=1)
        bottom = top.copy()
        bottom[:, 2] = c[2] - height - depth
        vertices = np.concatenate([top, bottom])
        off = (n + 1) ** 2

        def at(i, j):
            return i * (n + 1) + j  # grid corner (i, j), x index major

        i, j = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
        a, b, d, e = at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)
        quads = [np.stack([a, b, d], 1), np.stack([a, d, e], 1)]  # counter-clockwise seen from +z: normal up
        faces = quads + [q[:, [0, 2, 1]] + off for q in quads]  # the bottom, normal down
        # The rim, counter-clockwise seen from +z; each wall quad (top p, top q, bottom q, bottom p) faces out.
        r = np.arange(n)
        ring = np.concatenate([at(r, 0), at(n, r), at(n - r, n), at(0, n - r)])
        p, q = ring, np.roll(ring, -1)
        faces += [np.stack([p, p + off, q + off], 1), np.stack([p, q + off, q], 1)]
        triangles = np.concatenate(faces)
        return cls((vertices, triangles), restitution=restitution, friction=friction, motion=motion)

    def __repr__(self) -> str:
        src = self.path or "arrays"
        return (
            f"MeshObstacle({src}, vertices={len(self.vertices)}, triangles={len(self.triangles)}, "
            f"restitution={self.restitution}, friction={self.friction}"
            + ("" if self.motion is None else f", motion={self.motion!r}")
            + ")"
        )

    def _core(self):
        return (
            "mesh",
            self.vertices.ravel().tolist(),
            float(self.restitution),
            float(self.friction),
            self.triangles.ravel().tolist(),
            None if self.motion is None else self.motion._core(),
        )


Obstacle = Union[Plane, Sphere, Box, Capsule, MeshObstacle]
OBSTACLE_TYPES = (Plane, Sphere, Box, Capsule, MeshObstacle)


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
class ObstacleMotion:
    """A prescribed rigid motion of an obstacle (a moving platform, a piston, a turning drum or paddle).

    At time ``t`` (s) the point ``p`` of the obstacle as given is at
    ``R(angular_velocity * t) Q(t) (p - pivot) + pivot + d(t)``: ``translation`` is the displacement ``d``
    (:class:`Sinusoid`, :class:`Keyframes`, or None: no translation), ``angular_velocity`` (3,) rad/s a constant
    rotation (its direction the axis, right-hand rule) and ``Q`` keyframed orientations (``orientation_times``
    (k,) s strictly increasing, ``orientations`` (k, 3) rotation vectors in rad; slerp between them, held before
    the first and after the last), both about ``pivot`` (3,) m, which travels with ``d``.

    The body's contact with a moving obstacle answers its velocity relative to the obstacle's surface
    (restitution and friction act on the relative velocity), and the work the obstacle does on the body is
    booked in ``work_contact`` (it can be positive: a platform lifting a body), so FEPR keeps
    ``H_0 + budget_total`` instead of taking that energy back. Each step places the obstacle where it is at the
    step's end (XPBD: at each substep's end); a vertex cannot pass through it within a step (the crossing test
    follows the obstacle from the step's start to its end).
    """

    translation: Optional[Motion] = None
    angular_velocity: Vec3 = (0.0, 0.0, 0.0)
    pivot: Vec3 = (0.0, 0.0, 0.0)
    orientation_times: Sequence[float] = ()
    orientations: Sequence[Vec3] = ()

    def __post_init__(self):
        if self.translation is not None and not isinstance(self.translation, (Sinusoid, Keyframes)):
            raise ConfigError(
                f"ObstacleMotion translation must be fepr.Sinusoid, fepr.Keyframes or None, got {self.translation!r}"
            )
        object.__setattr__(self, "angular_velocity", _vec3(self.angular_velocity, "ObstacleMotion angular_velocity"))
        object.__setattr__(self, "pivot", _vec3(self.pivot, "ObstacleMotion pivot"))
        t = float_array(self.orientation_times, "ObstacleMotion orientation_times", "(k,)").reshape(-1)
        r = float_array(self.orientations, "ObstacleMotion orientations", "(k, 3)")
        if r.size == 0:
            r = r.reshape(0, 3)
        if r.shape != (t.size, 3):
            raise ConfigError(
                f"ObstacleMotion orientations must have shape ({t.size}, 3) (one rotation vector per time), "
                f"got {r.shape}"
            )
        if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
            raise ConfigError(f"ObstacleMotion orientation_times must be finite and strictly increasing, got {list(t)}")
        if not np.all(np.isfinite(r)):
            raise ConfigError("ObstacleMotion orientations must be finite (rotation vectors, rad)")
        object.__setattr__(self, "orientation_times", tuple(float(x) for x in t))
        object.__setattr__(self, "orientations", tuple(tuple(float(c) for c in row) for row in r))

    def _core(self):
        kind, params, times = ("none", [], []) if self.translation is None else self.translation._core()
        turns = [c for row in self.orientations for c in row]
        return kind, params, times, list(self.angular_velocity), list(self.pivot), list(self.orientation_times), turns

    def placement(self, t: float) -> Tuple[np.ndarray, np.ndarray]:
        """Where the obstacle is at time ``t`` (s): ``(R (3, 3), offset (3,) m)`` with ``x = R @ p + offset`` for
        a point ``p`` of the obstacle as given (for drawing it, or placing a copy of its mesh in an export): the
        core's own placement, the one contact uses."""
        from . import _core

        r, offset = _core.obstacle_placement(self._core(), float(t))
        return np.asarray(r, dtype=float), np.asarray(offset, dtype=float)


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
