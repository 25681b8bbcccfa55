"""VTU files (one per frame, via meshio, binary) and a ParaView ``.pvd`` collection with their times."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Tuple
from xml.etree import ElementTree
from xml.sax.saxutils import quoteattr

import meshio

from ..errors import ConfigError
from ..io.atomic import atomic_path
from .base import FrameWriter, PathLike
from .fields import Frame

__all__ = ["VtuSeries", "read_pvd"]


class VtuSeries(FrameWriter):
    """A VTU file per frame and a ``.pvd`` collection that lists them with their times (ParaView).

    Each ``.vtu`` holds the tet mesh at the frame's positions, binary (zlib-compressed, written by meshio),
    with point data ``velocity`` (m/s) and ``displacement`` (m, from the rest positions) and cell data ``J``
    (``det F``) and ``energy_density`` (J/m^3, the material's ``Psi(F)``).

    Parameters
    ----------
    sim : fepr.Simulation
        The simulation to record.
    pvd_path : str or Path
        The collection file, written by :meth:`close`.
    frames_dir : str or Path, optional
        Folder of the ``.vtu`` files (default: ``vtu`` beside the ``.pvd``); the ``.pvd`` refers to them by
        relative path, so the folder can be moved as a whole.
    name : str, optional
        File name prefix of the frames (default: the ``.pvd`` file's stem): ``name_00000.vtu``, ...
    """

    format = "vtu"
    per_frame = True

    def __init__(self, sim, pvd_path: PathLike, *, frames_dir: Optional[PathLike] = None, name=None, **kw):
        super().__init__(sim, **kw)
        self.pvd_path = Path(pvd_path)
        self.frames_dir = Path(frames_dir) if frames_dir is not None else self.pvd_path.parent / "vtu"
        self.name = name or self.pvd_path.stem
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        self.pvd_path.parent.mkdir(parents=True, exist_ok=True)
        self._entries: List[Tuple[float, Path]] = []

    def _frame_path(self) -> Path:
        return self.frames_dir / f"{self.name}_{self.num_frames:05d}.vtu"

    def _adopt(self, frame: Frame) -> None:
        path = self._frame_path()
        if not path.is_file():
            raise ConfigError(f"cannot resume the export: the earlier frame {path} is missing")
        self._entries.append((frame.time, path))

    def _write(self, frame: Frame) -> None:
        path = self._frame_path()
        mesh = meshio.Mesh(
            frame.positions,
            [("tetra", frame.tets)],
            point_data={"velocity": frame.velocities, "displacement": frame.displacement},
            cell_data={"J": [frame.volume_ratio], "energy_density": [frame.energy_density]},
        )
        # A temporary name, renamed when complete: a run stopped mid-frame leaves no truncated .vtu.
        with atomic_path(path) as tmp:
            meshio.write(tmp, mesh, file_format="vtu", binary=True)
        self._entries.append((frame.time, path))

    def _finish(self) -> None:
        base = self.pvd_path.parent.resolve()
        lines = [
            '<?xml version="1.0"?>',
            '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
            "  <Collection>",
        ]
        for t, path in self._entries:
            try:
                rel = path.resolve().relative_to(base).as_posix()
            except ValueError:
                rel = path.resolve().as_posix()
            lines.append(f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(rel)}/>')
        lines += ["  </Collection>", "</VTKFile>", ""]
        with atomic_path(self.pvd_path) as tmp:
            Path(tmp).write_text("\n".join(lines), encoding="utf-8")

    def paths(self) -> List[Path]:
        return [self.pvd_path] + [p for _, p in self._entries]


def read_pvd(path: PathLike) -> List[Tuple[float, Path]]:
    """The ``(time, file)`` entries of a ``.pvd`` collection, files resolved against the ``.pvd``'s folder.

    Raises
    ------
    ConfigError
        If the file is not a VTK collection.
    """
    p = Path(path)
    try:
        root = ElementTree.parse(p).getroot()
    except (ElementTree.ParseError, OSError) as exc:
        raise ConfigError(f"{p}: not a readable .pvd file: {exc}") from None
    coll = root.find("Collection")
    if root.tag != "VTKFile" or root.get("type") != "Collection" or coll is None:
        raise ConfigError(f"{p}: not a VTK collection (.pvd) file")
    out = []
    for ds in coll.findall("DataSet"):
        out.append((float(ds.get("timestep", "nan")), p.parent / ds.get("file", "")))
    return out
