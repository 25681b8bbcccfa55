"""Exports of a simulation run: ParaView (VTU + PVD), OBJ/PLY surface sequences, glTF binary (Blender), USD.

Every format except VTU writes the boundary surface of the tet mesh (:func:`boundary_surface`): the triangles
used by exactly one tet, with outward normals. VTU files hold the whole tet mesh with point data ``velocity``
(m/s) and ``displacement`` (m) and cell data ``J`` (``det F``) and ``energy_density`` (J/m^3).

Example
-------
>>> import fepr
>>> from fepr.export import Recorder, run_with_export
>>> sim = fepr.Simulation(fepr.meshes.ell(), material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
...                       node_mass=5.0, dt=1 / 30)                                  # doctest: +SKIP
>>> sim.positions = 1.5 * sim.rest_positions                                        # doctest: +SKIP
>>> with Recorder(sim, "out", formats="vtu,glb", every=2) as rec:                   # doctest: +SKIP
...     run_with_export(sim, 60, rec)      # frames at steps 0, 2, ..., 60: out/frame.pvd, out/frame.glb

Writers for one format each (:class:`VtuSeries`, :class:`ObjSequence`, :class:`PlySequence`,
:class:`GlbWriter`, :class:`UsdWriter`) have the same ``add_frame(sim)`` / ``close()`` interface.
See ``docs/blender-paraview.md`` for opening the files.
"""

from .base import FrameWriter
from .fields import Frame, TetKinematics, deformation_gradients
from .gltf import Z_UP_TO_Y_UP, GlbWriter, glb_accessor, read_glb, write_glb
from .recorder import DEFAULT_FORMATS, FORMATS, Recorder, parse_formats, run_with_export
from .sequence import ObjSequence, PlySequence, read_ply
from .surface import BoundarySurface, boundary_surface, enclosed_volume, vertex_normals
from .usd import UsdWriter, usd_available
from .vtk import VtuSeries, read_pvd

__all__ = [
    "DEFAULT_FORMATS",
    "FORMATS",
    "BoundarySurface",
    "Frame",
    "FrameWriter",
    "GlbWriter",
    "ObjSequence",
    "PlySequence",
    "Recorder",
    "TetKinematics",
    "UsdWriter",
    "VtuSeries",
    "Z_UP_TO_Y_UP",
    "boundary_surface",
    "deformation_gradients",
    "enclosed_volume",
    "glb_accessor",
    "parse_formats",
    "read_glb",
    "read_ply",
    "read_pvd",
    "run_with_export",
    "usd_available",
    "vertex_normals",
    "write_glb",
]
