"""A run's frames: positions (and velocities) every ``frames_every`` steps, as ``.npy`` arrays that survive a kill.

The arrays are NumPy ``.npy`` files of their final shape, made when the run starts and filled as it goes
(memory-mapped): ``positions.npy`` (frames, m, 3) float64 in m, ``velocities.npy`` (frames, m, 3) in m/s and
``frame_times.npy`` (frames,) in s, frame ``j`` being the state after ``j * frames_every`` steps (frame 0 the
initial state). While the run goes they have temporary names (``.positions.npy.part``, ...); :meth:`finish`
renames them.

Why memory maps: a resumed run needs the frames recorded before its checkpoint. The frames are flushed to the
files before each checkpoint is written, so the files always hold every frame up to the last checkpoint; frames
recorded after it are written again, with the same values, by the resumed run (results are bit-identical). Memory
stays at one frame whatever the length of the run, and no frame is copied at the end.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, List

import numpy as np

__all__ = ["FrameStore", "frame_count"]


def frame_count(steps: int, every: int) -> int:
    """Frames of a run of ``steps`` steps recorded every ``every`` steps (0: none): steps 0, every, 2 every, ..."""
    return steps // every + 1 if every else 0


class FrameStore:
    """The frame arrays of one run in ``folder`` (see the module docs).

    Parameters
    ----------
    folder : Path
        The run's folder.
    frames : int
        Frames of the whole run (:func:`frame_count`).
    vertices : int
        Vertices ``m`` of the simulation (all bodies').
    velocities : bool
        Also record the velocities.
    """

    NAMES = ("positions", "velocities", "frame_times")

    def __init__(self, folder: Path, frames: int, vertices: int, velocities: bool):
        self.folder, self.frames, self.vertices, self.with_velocities = Path(folder), frames, vertices, velocities
        self.arrays: Dict[str, np.memmap] = {}

    def _names(self) -> List[str]:
        return [n for n in self.NAMES if n != "velocities" or self.with_velocities]

    def part(self, name: str) -> Path:
        return self.folder / f".{name}.npy.part"

    def final(self, name: str) -> Path:
        return self.folder / f"{name}.npy"

    def _shape(self, name: str) -> tuple:
        return (self.frames,) if name == "frame_times" else (self.frames, self.vertices, 3)

    def create(self) -> None:
        """New, zero-filled arrays (a fresh run)."""
        for name in self._names():
            self.arrays[name] = np.lib.format.open_memmap(
                self.part(name), mode="w+", dtype=np.float64, shape=self._shape(name)
            )

    def reopen(self) -> bool:
        """The arrays of an earlier attempt, to continue; False if any is missing or of another shape."""
        for name in self._names():
            p = self.part(name)
            try:
                a = np.lib.format.open_memmap(p, mode="r+")
            except (OSError, ValueError):
                self.arrays.clear()
                return False
            if a.shape != self._shape(name) or a.dtype != np.float64:
                self.arrays.clear()
                return False
            self.arrays[name] = a
        return True

    def record(self, index: int, positions: np.ndarray, velocities: np.ndarray, time: float) -> None:
        """Frame ``index``: positions (m, 3) m, velocities (m, 3) m/s, at ``time`` s."""
        self.arrays["positions"][index] = positions
        if self.with_velocities:
            self.arrays["velocities"][index] = velocities
        self.arrays["frame_times"][index] = time

    def flush(self) -> None:
        """Write what is recorded to the files (before a checkpoint that counts on them)."""
        for a in self.arrays.values():
            a.flush()

    def finish(self, recorded: int) -> List[Path]:
        """Close the arrays and give them their names; with ``recorded`` frames fewer than planned (a run that
        ran away), the arrays are cut to those frames. Returns the files."""
        out = []
        for name in self._names():
            a = self.arrays.pop(name)
            a.flush()
            if recorded < self.frames:
                kept = np.array(a[:recorded])  # a copy: the map holds the file it is rewritten to
                del a
                with open(self.part(name), "wb") as fh:
                    np.save(fh, kept)
            else:
                del a
            os.replace(self.part(name), self.final(name))
            out.append(self.final(name))
        return out

    def discard(self) -> None:
        """Remove the temporary files (a run that starts again from scratch)."""
        self.arrays.clear()
        for name in self.NAMES:
            if self.part(name).exists():
                self.part(name).unlink()
