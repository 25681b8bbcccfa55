"""Hyperelastic materials (SI units: Young's modulus in Pa, dimensionless Poisson ratio).

Each material evaluates, through the Rust core, its energy density ``Psi(F)`` (J/m^3), first Piola-Kirchhoff
stress ``P = dPsi/dF`` (Pa) and stress derivative ``dP/dF`` (Pa, 9x9 with row-major flattening of F), all
analytic and gated by finite-difference tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _core
from ._validate import check_magnitude, compact_numbers
from .errors import ConfigError


def _set_elastic(material) -> None:
    """Check the material in the core (``_core.check_material``: the messages name the key as
    ``material.key``) and store its numbers as floats on the frozen dataclass. Young's modulus is also checked for
    magnitude (:func:`fepr._validate.check_magnitude`): outside 1e-100..1e100 Pa a ConfigError, outside
    1..1e13 Pa an :class:`~fepr.errors.ImplausibleValueWarning`."""
    try:
        _core.check_material(material._settings())
    except ValueError as exc:
        raise ConfigError(compact_numbers(str(exc))) from None
    for name in ("youngs_modulus", "poisson_ratio", "j0"):
        if hasattr(material, name):
            object.__setattr__(material, name, float(getattr(material, name)))
    # magnitude: an error beyond what double precision can compute with, a warning when implausible
    check_magnitude(material.youngs_modulus, "youngs_modulus")


class _Material:
    model: str = ""
    youngs_modulus: float
    poisson_ratio: float

    @property
    def _j0(self) -> float:
        return 0.1

    def _settings(self) -> dict:
        """The material as the core reads it (``_core.Simulation(material=...)``)."""
        return {
            "model": self.model,
            "youngs_modulus": self.youngs_modulus,
            "poisson_ratio": self.poisson_ratio,
            "j0": self._j0,
        }

    @property
    def mu(self) -> float:
        """First Lame parameter (shear modulus), Pa."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lam(self) -> float:
        """Second Lame parameter, Pa."""
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    def _eval(self, F, derivative: bool):
        f = np.asarray(F, dtype=np.float64)
        if f.ndim < 2 or f.shape[-2:] != (3, 3):
            raise ConfigError(f"F must have shape (..., 3, 3), got {f.shape}")
        batch = f.shape[:-2]
        flat = np.ascontiguousarray(f.reshape(-1, 3, 3))
        psi, p, d = _core.material_eval(self.model, self.youngs_modulus, self.poisson_ratio, self._j0, flat, derivative)
        psi = psi.reshape(batch)
        p = p.reshape(batch + (3, 3))
        d = None if d is None else d.reshape(batch + (9, 9))
        if not batch:
            return float(psi), p, d
        return psi, p, d

    def energy_density(self, F) -> np.ndarray:
        """Energy density Psi(F) in J/m^3. ``F``: (3, 3) or (n, 3, 3); returns a float or (n,)."""
        return self._eval(F, False)[0]

    def first_piola(self, F) -> np.ndarray:
        """First Piola-Kirchhoff stress dPsi/dF in Pa, shape like ``F``."""
        return self._eval(F, False)[1]

    def stress_derivative(self, F) -> np.ndarray:
        """dP/dF in Pa: (9, 9) for one F or (n, 9, 9); index ``3*i + j`` is ``F[i, j]``."""
        return self._eval(F, True)[2]


@dataclass(frozen=True)
class NeoHookean(_Material):
    """The seed's log Neo-Hookean: ``Psi = mu/2 (tr F^T F - 3) - mu l(J) + lambda/2 l(J)^2``.

    ``l(J) = log J`` for ``J >= j0`` and its C2 quadratic extension below ``j0`` (fepr-spec section 4), so
    that energy and forces stay finite and restoring for inverted elements.

    Parameters
    ----------
    youngs_modulus : float
        Young's modulus E, Pa (> 0).
    poisson_ratio : float
        Poisson ratio nu, -1 < nu < 0.5.
    j0 : float
        Extension threshold, 0 < j0 <= 1 (default 0.1).
    """

    youngs_modulus: float
    poisson_ratio: float
    j0: float = 0.1
    model = "neo_hookean"

    def __post_init__(self):
        _set_elastic(self)

    @property
    def _j0(self) -> float:
        return self.j0


@dataclass(frozen=True)
class StableNeoHookean(_Material):
    """Stable Neo-Hookean (Smith, de Goes, Kim 2018), shifted so that Psi(I) = 0.

    ``Psi = mu'/2 (I_C - 3) + lambda'/2 (J - alpha)^2 - mu'/2 log(I_C + 1) - Psi0`` with ``mu' = 4/3 mu``,
    ``lambda' = lambda + 5/6 mu``, ``alpha = 1 + mu'/lambda' - mu'/(4 lambda')``. Defined for inverted F.

    Parameters
    ----------
    youngs_modulus : float
        Young's modulus E, Pa (> 0).
    poisson_ratio : float
        Poisson ratio nu, -1 < nu < 0.5.
    """

    youngs_modulus: float
    poisson_ratio: float
    model = "stable_neo_hookean"

    def __post_init__(self):
        _set_elastic(self)


@dataclass(frozen=True)
class Arap(_Material):
    """The Projective Dynamics strain energy (as-rigid-as-possible): ``Psi = mu |F - R(F)|_F^2``.

    ``R(F)`` is the rotation of the polar decomposition. This is the energy the ``"projective_dynamics"``
    integrator minimises (Bouaziz et al. 2014), so with FEPR it is the energy that is conserved. Only the shear
    modulus ``mu = E / (2 (1 + nu))`` enters; the energy has no volume term.

    Parameters
    ----------
    youngs_modulus : float
        Young's modulus E, Pa (> 0).
    poisson_ratio : float
        Poisson ratio nu, -1 < nu < 0.5.
    """

    youngs_modulus: float
    poisson_ratio: float
    model = "arap"

    def __post_init__(self):
        _set_elastic(self)


@dataclass(frozen=True)
class ConstraintNeoHookean(_Material):
    """The Neo-Hookean energy of XPBD's constraints (Macklin and Mueller 2021), shifted so that Psi(I) = 0.

    ``Psi = mu/2 (I_C - 3) + lambda'/2 (J - alpha)^2 - lambda'/2 (alpha - 1)^2`` with ``lambda' = lambda + mu``
    (matching linear elasticity at rest) and ``alpha = 1 + mu / lambda'``. It is the sum of the energies of the
    per-tet deviatoric constraint ``sqrt(I_C)`` (compliance ``1/(mu V)``) and hydrostatic constraint ``J - alpha``
    (compliance ``1/(lambda' V)``) that the ``"xpbd"`` integrator solves, so with FEPR it is the energy that is
    conserved. Defined for inverted F.

    Parameters
    ----------
    youngs_modulus : float
        Young's modulus E, Pa (> 0).
    poisson_ratio : float
        Poisson ratio nu, -1 < nu < 0.5.
    """

    youngs_modulus: float
    poisson_ratio: float
    model = "constraint_neo_hookean"

    def __post_init__(self):
        _set_elastic(self)


Material = _Material

#: The material classes by model name (the names are the core's ``fepr._core.MATERIALS``; a test checks both agree).
MATERIAL_TYPES = {cls.model: cls for cls in (NeoHookean, StableNeoHookean, Arap, ConstraintNeoHookean)}
