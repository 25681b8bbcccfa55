"""Per-frame data of an export: positions, velocity and displacement per vertex; J and energy density per tet.

The deformation gradient of a linear tet is ``F = D_s D_m^-1`` with the edge matrices
``D_m = [X_b - X_a, X_c - X_a, X_d - X_a]`` (rest) and ``D_s`` the same for the current positions; ``J = det F``
is the volume ratio (``<= 0``: inverted) and the energy density ``Psi(F)`` (J/m^3) comes from the simulation's
material (``sim.material.energy_density``), evaluated by the Rust core.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

__all__ = ["Frame", "TetKinematics", "deformation_gradients"]


def _edge_matrices(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = x[tets]  # (k, 4, 3)
    return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # columns are edges


class TetKinematics:
    """The rest shape of a tet mesh, for evaluating deformation gradients of many states.

    Parameters
    ----------
    rest_positions : (m, 3) float
        Rest positions, m.
    tets : (k, 4) int
        Tets (positively oriented at rest, so every ``det D_m > 0``).
    """

    def __init__(self, rest_positions, tets):
        self.rest_positions = np.ascontiguousarray(rest_positions, dtype=np.float64)
        self.tets = np.ascontiguousarray(tets, dtype=np.int64)
        self.dm_inv = np.linalg.inv(_edge_matrices(self.rest_positions, self.tets))  # (k, 3, 3)

    def deformation_gradients(self, positions) -> np.ndarray:
        """``F = D_s D_m^-1`` of every tet at ``positions`` (m, 3) (m): shape (k, 3, 3), dimensionless."""
        ds = _edge_matrices(np.asarray(positions, dtype=np.float64), self.tets)
        return np.matmul(ds, self.dm_inv)


def deformation_gradients(rest_positions, positions, tets) -> np.ndarray:
    """Deformation gradient ``F = D_s D_m^-1`` of every tet, shape (k, 3, 3).

    Parameters
    ----------
    rest_positions, positions : (m, 3) float
        Rest and current vertex positions, m.
    tets : (k, 4) int
        Tets, positively oriented at rest.
    """
    return TetKinematics(rest_positions, tets).deformation_gradients(positions)


@dataclass
class Frame:
    """One recorded state, with the fields the writers need (computed on first use and cached).

    ``index`` is the frame number in the export (0, 1, 2, ...), ``step`` the simulation step, ``time`` the
    simulated time (s). ``positions`` and ``velocities`` are (m, 3) float64 in m and m/s.
    """

    index: int
    step: int
    time: float
    positions: np.ndarray
    velocities: np.ndarray
    kinematics: TetKinematics
    material: Any = None
    _F: Optional[np.ndarray] = field(default=None, repr=False)
    _psi: Optional[np.ndarray] = field(default=None, repr=False)

    @classmethod
    def from_simulation(cls, sim, kinematics: Optional[TetKinematics] = None, index: int = 0) -> Frame:
        """The current state of a :class:`fepr.Simulation`."""
        if kinematics is None:
            kinematics = TetKinematics(sim.rest_positions, sim.tets)
        return cls(
            index=int(index),
            step=int(sim.num_steps),
            time=float(sim.time),
            positions=np.asarray(sim.positions, dtype=np.float64),
            velocities=np.asarray(sim.velocities, dtype=np.float64),
            kinematics=kinematics,
            material=getattr(sim, "material", None),
        )

    @property
    def rest_positions(self) -> np.ndarray:
        return self.kinematics.rest_positions

    @property
    def tets(self) -> np.ndarray:
        return self.kinematics.tets

    @property
    def displacement(self) -> np.ndarray:
        """``positions - rest_positions``, (m, 3) float64, m."""
        return self.positions - self.kinematics.rest_positions

    @property
    def deformation_gradient(self) -> np.ndarray:
        """F per tet, (k, 3, 3)."""
        if self._F is None:
            self._F = self.kinematics.deformation_gradients(self.positions)
        return self._F

    @property
    def volume_ratio(self) -> np.ndarray:
        """J = det F per tet, (k,) float64 (``<= 0``: inverted)."""
        return np.linalg.det(self.deformation_gradient)

    @property
    def energy_density(self) -> np.ndarray:
        """Elastic energy density Psi(F) per tet, (k,) float64, J/m^3 (NaN without a material)."""
        if self._psi is None:
            k = self.kinematics.tets.shape[0]
            if self.material is None or k == 0:
                self._psi = np.full(k, np.nan)
            else:
                self._psi = np.asarray(self.material.energy_density(self.deformation_gradient), dtype=np.float64)
        return self._psi
