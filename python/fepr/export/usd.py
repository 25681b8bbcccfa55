"""USD (``.usdc``, ``.usda`` or ``.usd``): the boundary surface as a Mesh prim with time-sampled points.

Needs the optional ``usd-core`` package (``pip install "fepr[export-usd]"``). The stage is +Z up with
``metersPerUnit = 1``; time code ``i`` is frame ``i`` and ``timeCodesPerSecond`` (and ``framesPerSecond``) is
the number of frames per simulated second, so playback is in real time. The Mesh prim ``/fepr/<name>`` (the
default prim ``/fepr`` is an Xform) has the triangles (``faceVertexCounts`` all 3, ``faceVertexIndices``,
right-handed, outward), no subdivision, and per time code ``points`` (m), ``velocities`` (m/s) and ``extent``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import List, Optional

import numpy as np

from ..errors import ConfigError, MissingDependencyError
from ..io.atomic import atomic_path
from .base import FrameWriter, PathLike
from .fields import Frame

__all__ = ["UsdWriter", "require_usd", "usd_available"]


def usd_available() -> bool:
    """Whether ``usd-core`` (the ``pxr`` module) can be imported."""
    try:
        import pxr  # noqa: F401
    except ImportError:
        return False
    return True


def require_usd():
    """Import and return ``(Usd, UsdGeom, Vt)`` from ``pxr``.

    Raises
    ------
    fepr.MissingDependencyError
        If ``usd-core`` is not installed (the message says what to install).
    """
    try:
        from pxr import Usd, UsdGeom, Vt
    except ImportError:
        raise MissingDependencyError(
            'USD export needs the usd-core package: pip install "fepr[export-usd]" (or pip install usd-core)'
        ) from None
    return Usd, UsdGeom, Vt


def _prim_name(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_]", "_", name) or "fepr"
    return s if not s[0].isdigit() else "_" + s


class UsdWriter(FrameWriter):
    """Writes a USD stage with the boundary surface, one time sample per frame; saved at :meth:`close`.

    Parameters
    ----------
    sim : fepr.Simulation
        The simulation to record.
    path : str or Path
        ``.usdc`` (binary), ``.usda`` (text) or ``.usd``.
    fps : float, optional
        Frames per simulated second, the stage's ``timeCodesPerSecond``; default ``1 / sim.dt`` (a frame per
        step). :class:`fepr.export.Recorder` passes ``1 / (every * dt)``.
    name : str, optional
        Name of the Mesh prim (default the file's stem, made a valid prim name); Blender names the object
        after it.

    Raises
    ------
    fepr.MissingDependencyError
        If ``usd-core`` is not installed.
    """

    format = "usd"

    def __init__(self, sim, path: PathLike, *, fps: Optional[float] = None, name: Optional[str] = None, **kw):
        Usd, UsdGeom, Vt = require_usd()
        super().__init__(sim, **kw)
        self._Usd, self._UsdGeom, self._Vt = Usd, UsdGeom, Vt
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fps = float(fps) if fps is not None else 1.0 / float(sim.dt)
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ConfigError(f"fps must be a positive number, got {fps!r}")
        root = "/fepr"
        # In memory, exported at close through a temporary name: the file on disk is complete or absent.
        self.stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(self.stage, 1.0)
        self.stage.SetTimeCodesPerSecond(self.fps)
        self.stage.SetFramesPerSecond(self.fps)
        xform = UsdGeom.Xform.Define(self.stage, root)
        self.stage.SetDefaultPrim(xform.GetPrim())
        self.mesh = UsdGeom.Mesh.Define(self.stage, root + "/" + _prim_name(name or self.path.stem))
        faces = self.surface.local_faces
        self.mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
        self.mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.reshape(-1).tolist()))
        self.mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        self.mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        self.mesh.CreateDoubleSidedAttr(False)
        self._points = self.mesh.CreatePointsAttr()
        self._velocities = self.mesh.CreateVelocitiesAttr()
        self._extent = self.mesh.CreateExtentAttr()
        self._times: List[float] = []

    def _write(self, frame: Frame) -> None:
        Vt, Usd = self._Vt, self._Usd
        code = Usd.TimeCode(float(self.num_frames))
        pts = np.ascontiguousarray(frame.positions[self.surface.vertices], dtype=np.float32)
        vel = np.ascontiguousarray(frame.velocities[self.surface.vertices], dtype=np.float32)
        self._points.Set(Vt.Vec3fArray.FromNumpy(pts), code)
        self._velocities.Set(Vt.Vec3fArray.FromNumpy(vel), code)
        self._extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([pts.min(axis=0), pts.max(axis=0)])), code)
        self._times.append(frame.time)

    def _finish(self) -> None:
        self.stage.SetStartTimeCode(0.0)
        self.stage.SetEndTimeCode(float(max(self.num_frames - 1, 0)))
        self.stage.GetRootLayer().customLayerData = {
            "fepr:frames": self.num_frames,
            "fepr:first_time_s": float(self._times[0]) if self._times else 0.0,
        }
        with atomic_path(self.path, suffix=self.path.suffix) as tmp:
            if not self.stage.GetRootLayer().Export(tmp):
                raise OSError(f"USD could not write {self.path}")

    def paths(self) -> List[Path]:
        return [self.path]
