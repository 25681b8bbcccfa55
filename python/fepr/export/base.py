"""Common base of the frame writers: frames from a simulation, frame counting, closing."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Union

from ..errors import ConfigError
from .fields import Frame, TetKinematics
from .surface import BoundarySurface, boundary_surface

__all__ = ["FrameWriter", "PathLike"]

PathLike = Union[str, "Path"]


class FrameWriter:
    """Base class of the writers: ``add_frame(sim)`` after the steps to record, then ``close()``.

    Parameters
    ----------
    sim : fepr.Simulation
        The simulation whose states are written; its rest positions, tets and material are read once here.
    surface : BoundarySurface, optional
        The boundary surface of ``sim.tets`` (computed when not given; pass it to share it between writers).
    kinematics : TetKinematics, optional
        The rest shape of ``sim`` (computed when not given).

    A writer is also a context manager that closes itself.
    """

    #: Format name, as in :data:`fepr.export.FORMATS`.
    format = ""

    def __init__(self, sim, *, surface: Optional[BoundarySurface] = None, kinematics: Optional[TetKinematics] = None):
        self.kinematics = kinematics if kinematics is not None else TetKinematics(sim.rest_positions, sim.tets)
        self.surface = surface if surface is not None else boundary_surface(self.kinematics.tets)
        self.material = getattr(sim, "material", None)
        self.num_frames = 0
        self.closed = False

    def frame(self, sim_or_frame) -> Frame:
        """``sim_or_frame`` as a :class:`Frame` (a simulation's current state, numbered as the next frame)."""
        if isinstance(sim_or_frame, Frame):
            return sim_or_frame
        return Frame.from_simulation(sim_or_frame, self.kinematics, index=self.num_frames)

    def add_frame(self, sim_or_frame) -> None:
        """Write (or keep, for the files written at :meth:`close`) the current state of a simulation.

        ``sim_or_frame`` is a :class:`fepr.Simulation` or a :class:`Frame` built by the caller.
        """
        if self.closed:
            raise ConfigError(f"the {self.format} writer is closed; no frame can be added")
        frame = self.frame(sim_or_frame)
        if frame.positions.shape != self.kinematics.rest_positions.shape:
            raise ConfigError(
                f"frame positions have shape {frame.positions.shape}, expected {self.kinematics.rest_positions.shape}"
            )
        self._write(frame)
        self.num_frames += 1

    def _write(self, frame: Frame) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    #: The writer writes a file per frame (its earlier frames stay on disk when a run is resumed).
    per_frame = False

    def resume_frame(self, frame: Frame) -> None:
        """A frame an earlier part of a resumed run recorded: a writer with a file per frame takes the file it
        wrote then (it must still be there), a writer that writes at :meth:`close` takes the frame's data
        (its surface rows: what such writers read)."""
        if self.closed:
            raise ConfigError(f"the {self.format} writer is closed; no frame can be added")
        if self.per_frame:
            self._adopt(frame)
        else:
            self._write(frame)
        self.num_frames += 1

    def _adopt(self, frame: Frame) -> None:  # pragma: no cover - per-frame writers
        raise NotImplementedError

    def close(self) -> List[Path]:
        """Finish the files; returns the paths written (the collection file first, where there is one)."""
        if self.closed:
            return self.paths()
        self._finish()
        self.closed = True
        return self.paths()

    def _finish(self) -> None:
        pass

    def paths(self) -> List[Path]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
