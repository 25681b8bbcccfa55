"""Surface sequences: one OBJ (text) or PLY (binary) file per frame with the boundary surface.

Each file holds the boundary vertices only (compactly numbered, the same numbering in every frame) and the
boundary triangles, counter-clockwise seen from outside (outward normals). Coordinates are the simulation's,
in metres, not rotated: +Z stays up (importers that assume +Y up, such as Blender's OBJ importer by default,
need "Up Axis: Z").
"""

from __future__ import annotations

from pathlib import Path
from typing import List

import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_path
from .base import FrameWriter, PathLike
from .fields import Frame
from .surface import vertex_normals

__all__ = ["ObjSequence", "PlySequence", "read_ply"]


class _SurfaceSequence(FrameWriter):
    suffix = ""

    def __init__(self, sim, directory: PathLike, name: str = "frame", *, normals: bool = False, **kw):
        super().__init__(sim, **kw)
        self.directory = Path(directory)
        self.name = name
        self.normals = bool(normals)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._paths: List[Path] = []

    per_frame = True

    def _adopt(self, frame: Frame) -> None:
        path = self.directory / f"{self.name}_{self.num_frames:05d}{self.suffix}"
        if not path.is_file():
            raise ConfigError(f"cannot resume the export: the earlier frame {path} is missing")
        self._paths.append(path)

    def _write(self, frame: Frame) -> None:
        s = self.surface
        pts = frame.positions[s.vertices]
        nrm = vertex_normals(pts, s.local_faces) if self.normals else None
        path = self.directory / f"{self.name}_{self.num_frames:05d}{self.suffix}"
        with atomic_path(path) as tmp:  # renamed when complete: never a truncated frame
            self._write_file(Path(tmp), frame, pts, nrm)
        self._paths.append(path)

    def _write_file(self, path: Path, frame: Frame, pts: np.ndarray, nrm) -> None:  # pragma: no cover
        raise NotImplementedError

    def paths(self) -> List[Path]:
        return list(self._paths)


class ObjSequence(_SurfaceSequence):
    """Wavefront OBJ surface sequence ``directory/name_00000.obj``, ``name_00001.obj``, ...

    Parameters
    ----------
    sim : fepr.Simulation
        The simulation to record.
    directory : str or Path
        Output folder (created if needed).
    name : str
        File name prefix.
    normals : bool
        Also write area-weighted vertex normals (``vn``; faces as ``f a//a b//b c//c``).
    """

    format = "obj"
    suffix = ".obj"

    def _write_file(self, path: Path, frame: Frame, pts: np.ndarray, nrm) -> None:
        faces = self.surface.local_faces + 1
        with open(path, "w", encoding="ascii", newline="\n") as fh:
            fh.write(f"# fepr boundary surface: frame {frame.index}, step {frame.step}, time {frame.time!r} s\n")
            fh.write(f"# {len(pts)} vertices, {len(faces)} triangles, metres, +Z up, outward normals\n")
            fh.write(f"o {self.name}\n")
            np.savetxt(fh, pts, fmt="v %.9g %.9g %.9g")
            if nrm is not None:
                np.savetxt(fh, nrm, fmt="vn %.6f %.6f %.6f")
                np.savetxt(fh, np.repeat(faces, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")
            else:
                np.savetxt(fh, faces, fmt="f %d %d %d")


class PlySequence(_SurfaceSequence):
    """Binary little-endian PLY surface sequence ``directory/name_00000.ply``, ... (written by meshio: float64
    vertices, triangle faces; with ``normals``, ``nx ny nz`` per vertex)."""

    format = "ply"
    suffix = ".ply"

    def _write_file(self, path: Path, frame: Frame, pts: np.ndarray, nrm) -> None:
        import meshio

        point_data = {} if nrm is None else {"nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2]}
        mesh = meshio.Mesh(
            np.asarray(pts, dtype=np.float64), [("triangle", self.surface.local_faces)], point_data=point_data
        )
        meshio.write(str(path), mesh, file_format="ply", binary=True)


def read_ply(path: PathLike):
    """Read a surface PLY (as :class:`PlySequence` writes them, through meshio): ``(points (n, 3) float64,
    faces (f, 3) int64)``."""
    import meshio

    mesh = meshio.read(str(path), file_format="ply")
    return np.asarray(mesh.points, dtype=np.float64), np.asarray(mesh.cells_dict["triangle"], dtype=np.int64)
