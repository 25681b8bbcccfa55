"""The :class:`Recorder`: every k-th step of a simulation to several export formats at once."""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from .._validate import integer
from ..errors import ConfigError
from ..io.atomic import atomic_path
from .base import FrameWriter, PathLike
from .fields import Frame, TetKinematics
from .gltf import GlbWriter
from .sequence import ObjSequence, PlySequence
from .surface import boundary_surface
from .usd import UsdWriter, require_usd
from .vtk import VtuSeries

__all__ = ["DEFAULT_FORMATS", "FORMATS", "Recorder", "parse_formats", "run_with_export"]

#: Export formats: ``vtu`` (+ ``.pvd``, ParaView), ``obj`` and ``ply`` (surface sequences), ``glb`` (glTF
#: binary, Blender), ``usd`` (needs ``usd-core``).
FORMATS: Tuple[str, ...] = ("vtu", "obj", "ply", "glb", "usd")
#: What :class:`Recorder` writes when no formats are given (no optional dependency needed).
DEFAULT_FORMATS: Tuple[str, ...] = ("vtu", "obj", "glb")

Formats = Union[str, Sequence[str]]


def parse_formats(formats: Formats) -> Tuple[str, ...]:
    """Export format names from ``"vtu,glb"`` or ``["vtu", "glb"]``: lower-cased, without repeats, in order.

    Raises
    ------
    ConfigError
        If a name is unknown or none is given.
    """
    if isinstance(formats, str):
        items = formats.split(",")
    else:
        try:
            items = list(formats)
        except TypeError:
            raise ConfigError(f"export formats must be names such as 'vtu,glb', got {formats!r}") from None
    out: List[str] = []
    for f in items:
        if not isinstance(f, str):
            raise ConfigError(f"export formats must be strings (known: {', '.join(FORMATS)}), got {f!r}")
        name = f.strip().lower().lstrip(".")
        if not name:
            continue
        if name not in FORMATS:
            raise ConfigError(f"unknown export format {f.strip()!r} (known: {', '.join(FORMATS)})")
        if name not in out:
            out.append(name)
    if not out:
        raise ConfigError(f"no export format given (known: {', '.join(FORMATS)})")
    return tuple(out)


class Recorder:
    """Record every ``every``-th step of a simulation in several formats.

    Call :meth:`record` after stepping (and once before the first step for frame 0); it writes a frame when
    the number of steps since the recorder was made is a multiple of ``every``. :meth:`close` finishes the
    files that are written at the end (``.pvd``, ``.glb``, USD) and ``frames.csv``. A recorder is a context
    manager that closes itself.

    Parameters
    ----------
    sim : fepr.Simulation
        The simulation to record.
    out_dir : str or Path
        Output folder, created if needed. Layout, with ``name = "frame"``::

            frame.pvd            ParaView collection (vtu)     vtu/frame_00000.vtu, ...
            obj/frame_00000.obj  OBJ surface sequence (obj)    ply/frame_00000.ply, ... (ply)
            frame.glb            animated glTF binary (glb)    frame.usdc (usd)
            frames.csv           frame, step, time (s) of every frame

    formats : str or sequence of str
        Names from :data:`FORMATS` (``"vtu,glb"`` or ``("vtu", "glb")``); default :data:`DEFAULT_FORMATS`.
    every : int
        Record every ``every``-th step (>= 1).
    name : str
        File name prefix (letters, digits, ``_``, ``-``, ``.``); also the object name in Blender.
    normals : bool
        Write vertex normals into OBJ and PLY files.
    start_step : int, optional
        The step the cadence counts from (default: the simulation's current step).
    keep_frames : bool
        Keep each frame's positions and velocities until :meth:`take_frames` (a run that writes checkpoints
        saves them, so that a resumed run can :meth:`replay` them into the animation files).

    Raises
    ------
    ConfigError
        For an unknown format or a bad ``every`` or ``name``.
    fepr.MissingDependencyError
        For ``usd`` without ``usd-core`` installed.

    Example
    -------
    >>> rec = fepr.export.Recorder(sim, "out/export", formats="vtu,glb", every=2)   # doctest: +SKIP
    >>> fepr.export.run_with_export(sim, 100, rec)                                  # doctest: +SKIP
    >>> rec.close()                                                                 # doctest: +SKIP
    """

    def __init__(
        self,
        sim,
        out_dir: PathLike,
        formats: Formats = DEFAULT_FORMATS,
        *,
        every: int = 1,
        name: str = "frame",
        normals: bool = False,
        start_step: Optional[int] = None,
        keep_frames: bool = False,
    ):
        self.formats = parse_formats(formats)
        if "usd" in self.formats:
            require_usd()  # before any file is written
        self.every = integer(every, "export every", lo=1)
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.\-]+", name) or name in (".", ".."):
            raise ConfigError(f"export name must be letters, digits, '_', '-' or '.', got {name!r}")
        self.name = name
        self.sim = sim
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.start_step = int(sim.num_steps) if start_step is None else int(start_step)
        self.keep_frames = bool(keep_frames)
        self._kept: List[Frame] = []
        self.frames: List[Tuple[int, int, float]] = []
        self.closed = False
        #: Wall time spent computing and writing frames, s.
        self.write_s = 0.0
        kin = TetKinematics(sim.rest_positions, sim.tets)
        surf = boundary_surface(kin.tets)
        self.surface = surf
        self.kinematics = kin
        shared = {"surface": surf, "kinematics": kin}
        out = self.out_dir
        self.writers: Dict[str, FrameWriter] = {}
        for fmt in self.formats:
            if fmt == "vtu":
                w: FrameWriter = VtuSeries(sim, out / f"{name}.pvd", frames_dir=out / "vtu", name=name, **shared)
            elif fmt == "obj":
                w = ObjSequence(sim, out / "obj", name, normals=normals, **shared)
            elif fmt == "ply":
                w = PlySequence(sim, out / "ply", name, normals=normals, **shared)
            elif fmt == "glb":
                w = GlbWriter(sim, out / f"{name}.glb", name=name, **shared)
            else:
                w = UsdWriter(sim, out / f"{name}.usdc", fps=self.fps, name=name, **shared)
            self.writers[fmt] = w

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def fps(self) -> float:
        """Frames per simulated second, ``1 / (every * dt)`` (the USD stage's ``timeCodesPerSecond``)."""
        return 1.0 / (self.every * float(self.sim.dt))

    def _last_step(self) -> Optional[int]:
        return self.frames[-1][1] if self.frames else None

    def due(self) -> bool:
        """True when the simulation is at a step to record that has not been recorded yet."""
        n = int(self.sim.num_steps)
        return (n - self.start_step) % self.every == 0 and n != self._last_step()

    def steps_to_next(self) -> int:
        """Steps from now to the next step to record (1 to ``every``)."""
        r = (int(self.sim.num_steps) - self.start_step) % self.every
        return self.every - r

    def record(self, *, force: bool = False) -> bool:
        """Write the current state as a frame if it is due (or, with ``force``, if this step is not recorded
        yet). Returns whether a frame was written."""
        if self.closed:
            raise ConfigError("the recorder is closed")
        if not (force and int(self.sim.num_steps) != self._last_step()) and not self.due():
            return False
        t0 = time.perf_counter()
        frame = Frame.from_simulation(self.sim, self.kinematics, index=len(self.frames))
        self._add(frame)
        if self.keep_frames:
            self._kept.append(frame)
        self.write_s += time.perf_counter() - t0
        return True

    def _add(self, frame: Frame) -> None:
        for w in self.writers.values():
            w.add_frame(frame)
        self.frames.append((frame.index, frame.step, frame.time))

    def frame_files(self) -> List[Path]:
        """The files of the newest frame in the formats that write a file per frame (vtu, obj, ply)."""
        return [w.paths()[-1] for w in self.writers.values() if w.per_frame and w.num_frames]

    def take_frames(self) -> Dict[str, np.ndarray]:
        """The frames recorded since the last call (with ``keep_frames``), as arrays: ``steps`` (f,) int64,
        ``times`` (f,) s and, where a format writes its file at the end (glb, usd), the surface vertices'
        ``positions`` and ``velocities`` (f, s, 3) float64 (what those writers read; the per-frame formats'
        files are on disk already)."""
        kept, self._kept = self._kept, []
        rows = self.surface.vertices if any(not w.per_frame for w in self.writers.values()) else []
        out = {
            "steps": np.array([f.step for f in kept], dtype=np.int64),
            "times": np.array([f.time for f in kept], dtype=np.float64),
        }
        shape = (len(kept), len(rows), 3)
        out["positions"] = np.stack([f.positions[rows] for f in kept]) if kept else np.zeros(shape)
        out["velocities"] = np.stack([f.velocities[rows] for f in kept]) if kept else np.zeros(shape)
        return out

    def replay(self, steps, times, positions, velocities) -> None:
        """The frames an earlier part of a resumed run recorded (arrays as :meth:`take_frames` gave them): the
        per-frame formats take their files from disk, the others the surface rows, so that the collection and
        animation files hold the whole run."""
        m = len(self.kinematics.rest_positions)
        rows = self.surface.vertices if len(positions) and positions.shape[1] else None
        for k, (step, t) in enumerate(zip(steps, times)):
            x, v = np.zeros((m, 3)), np.zeros((m, 3))
            if rows is not None:
                x[rows], v[rows] = positions[k], velocities[k]
            frame = Frame(
                index=len(self.frames),
                step=int(step),
                time=float(t),
                positions=x,
                velocities=v,
                kinematics=self.kinematics,
                material=getattr(self.sim, "material", None),
            )
            for w in self.writers.values():
                w.resume_frame(frame)
            self.frames.append((frame.index, frame.step, frame.time))

    def close(self) -> Dict[str, List[Path]]:
        """Finish every file; returns the paths written per format (see :attr:`paths`)."""
        if not self.closed:
            t0 = time.perf_counter()
            self.closed = True
            for w in self.writers.values():
                w.close()
            with atomic_path(self.out_dir / "frames.csv") as tmp:
                with open(tmp, "w", encoding="ascii", newline="\n") as fh:
                    fh.write("frame,step,time\n")
                    for i, step, t in self.frames:
                        fh.write(f"{i},{step},{t!r}\n")
            self.write_s += time.perf_counter() - t0
        return self.paths

    @property
    def paths(self) -> Dict[str, List[Path]]:
        """Files per format; the collection or animation file first (``.pvd``, ``.glb``, ``.usdc``)."""
        return {fmt: w.paths() for fmt, w in self.writers.items()}

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"Recorder({str(self.out_dir)!r}, formats={','.join(self.formats)}, every={self.every}, "
            f"{len(self.frames)} frames{', closed' if self.closed else ''})"
        )


def run_with_export(sim, steps: int, recorder: Recorder) -> Recorder:
    """Advance ``sim`` by ``steps`` steps, recording every ``recorder.every``-th step (and the current state
    first, if it is due). Steps in chunks up to the next frame; the recorder stays open (call ``close``).

    Raises
    ------
    fepr.SimulationError
        As :meth:`fepr.Simulation.step`; the frames recorded so far are kept, close the recorder to write them.
    """
    n = integer(steps, "steps", lo=0)
    recorder.record()
    while n > 0:
        k = min(n, recorder.steps_to_next())
        sim.step(k)
        n -= k
        recorder.record()
    return recorder
