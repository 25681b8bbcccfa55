"""Surface colouring for the viewer: per-tet fields (J, energy density) on the boundary triangles, in bins.

The boundary triangles of a tet mesh each belong to one tet; a field per tet (``J = det F``, or the energy
density ``Psi(F)`` in J/m^3) gives each triangle a value, and the triangles are grouped into :data:`NUM_BINS`
colour bins so that each bin can be drawn as one single-coloured mesh (cheap to update in the browser).
"""

from __future__ import annotations

import functools
from typing import List, Tuple

import numpy as np

from ..export.fields import TetKinematics
from ..export.surface import face_use

__all__ = ["COLOR_MODES", "NUM_BINS", "SurfaceColoring", "boundary_faces_with_tets"]

#: Colour modes of the viewer.
COLOR_MODES = ("solid", "J (volume change)", "energy density")
NUM_BINS = 9

#: The colour maps (matplotlib's): diverging for J (compressed blue .. unchanged light .. stretched red),
#: perceptually uniform for the energy density (low dark violet .. high yellow).
J_COLORMAP = "RdBu_r"
PSI_COLORMAP = "viridis"


@functools.cache
def palette(name: str, bins: int = NUM_BINS) -> Tuple[Tuple[int, int, int], ...]:
    """``bins`` colours sampled evenly from matplotlib's colour map ``name``, RGB 0..255 (matplotlib is imported
    when a field is first coloured, so the viewer starts without it)."""
    from matplotlib import colormaps

    cmap = colormaps[name]
    return tuple(tuple(int(round(255 * c)) for c in cmap(k / (bins - 1))[:3]) for k in range(bins))


def boundary_faces_with_tets(tets) -> Tuple[np.ndarray, np.ndarray]:
    """Boundary triangles (f, 3) with outward normals and the index (f,) of the tet each belongs to."""
    faces, use, _ = face_use(tets)  # face j of tet e at row 4e + j
    once = np.flatnonzero(use == 1)
    return faces[once], once // 4


class SurfaceColoring:
    """Bins the boundary triangles by a per-tet field of the current positions.

    Parameters
    ----------
    rest_positions : (m, 3) float
        Rest positions, m.
    tets : (k, 4) int
        Tets.
    material : fepr material, optional
        For the energy density (``material.energy_density(F)``, J/m^3).
    """

    def __init__(self, rest_positions, tets, material=None):
        self.faces, self.face_tets = boundary_faces_with_tets(tets)
        self.kinematics = TetKinematics(rest_positions, tets)
        self.material = material

    def field(self, mode: str, positions) -> np.ndarray:
        """The per-tet field of ``mode`` at ``positions`` (m, 3): J, or the energy density in J/m^3."""
        F = self.kinematics.deformation_gradients(positions)
        if mode == COLOR_MODES[1] or self.material is None:
            return np.linalg.det(F)
        return np.asarray(self.material.energy_density(F), dtype=np.float64).reshape(-1)

    def bins(self, mode: str, positions) -> Tuple[List[np.ndarray], Tuple[Tuple[int, int, int], ...], str]:
        """Faces per colour bin, the palette, and a legend line for ``mode`` (not ``"solid"``)."""
        values = self.field(mode, positions)[self.face_tets]
        if mode == COLOR_MODES[1]:
            lo, hi = 0.5, 1.5
            colors = palette(J_COLORMAP)
            legend = "J: blue < 1 (compressed), light = 1, red > 1 (stretched); range 0.5 .. 1.5"
        else:
            lo = 0.0
            finite = values[np.isfinite(values)]
            hi = float(np.percentile(finite, 98)) if finite.size else 1.0
            hi = hi if hi > 0 else 1.0
            colors = palette(PSI_COLORMAP)
            legend = f"energy density: dark 0 .. yellow {hi:.3g} J/m³"
        with np.errstate(invalid="ignore"):
            idx = np.clip(((values - lo) / (hi - lo) * NUM_BINS).astype(np.int64), 0, NUM_BINS - 1)
        idx[~np.isfinite(values)] = NUM_BINS - 1
        return [self.faces[idx == b] for b in range(NUM_BINS)], colors, legend
