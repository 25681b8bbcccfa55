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
    """Binary little-endian PLY surface sequence ``directory/name_00000.ply``, ... (float32 vertices,
    ``uchar``-counted ``int`` face lists; with ``normals``, ``nx ny nz`` per vertex)."""

    format = "ply"
    suffix = ".ply"

    def _write_file(self, path: Path, frame: Frame, pts: np.ndarray, nrm) -> None:
        faces = self.surface.local_faces
        props = ["property float x", "property float y", "property float z"]
        cols = [pts]
        if nrm is not None:
            props += ["property float nx", "property float ny", "property float nz"]
            cols.append(nrm)
        header = "\n".join(
            [
                "ply",
                "format binary_little_endian 1.0",
                f"comment fepr boundary surface: frame {frame.index}, step {frame.step}, time {frame.time!r} s",
                f"element vertex {len(pts)}",
                *props,
                f"element face {len(faces)}",
                "property list uchar int vertex_indices",
                "end_header",
                "",
            ]
        )
        verts = np.ascontiguousarray(np.hstack(cols), dtype="<f4")
        rec = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
        rec["n"] = 3
        rec["v"] = faces
        with open(path, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(verts.tobytes())
            fh.write(rec.tobytes())


def read_ply(path: PathLike):
    """Read a PLY written by :class:`PlySequence`: ``(points (n, 3) float32, faces (f, 3) int32)``."""
    data = Path(path).read_bytes()
    head_len = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:head_len].decode("ascii").splitlines()
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    nprops = sum(1 for h in header if h.startswith("property float"))
    verts = np.frombuffer(data, dtype="<f4", count=nv * nprops, offset=head_len).reshape(nv, nprops)
    rec = np.frombuffer(data, dtype=[("n", "u1"), ("v", "<i4", (3,))], count=nf, offset=head_len + 4 * nv * nprops)
    return verts[:, :3], rec["v"]
