"""The simulation API: :class:`Simulation`, :class:`Projection`, energies and per-step diagnostics.

Units are SI throughout: metres, seconds, kilograms, joules. Arrays are NumPy ``float64``; positions and
velocities have shape ``(m, 3)``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from . import _core
from ._validate import compact_numbers, float_array, integer, real
from .errors import ConfigError, SimulationError
from .history import History, HistoryStore
from .materials import MATERIAL_TYPES, _Material
from .mesh import TetMesh
from .world import OBSTACLE_TYPES, KinematicPins, Obstacle

# The name lists are the core's (``fepr._core``); the settings objects below are checked there too
# (``_core.check_projection``, ``_core.check_integrator``), with messages that name the key.
ROWS = tuple(_core.PROJECTION_ROWS)
METRICS = tuple(_core.METRICS)
SLACK_MODES = tuple(_core.SLACK_MODES)


def _checked(check, settings: dict) -> None:
    """Run one of the core's settings checks, raising its ValueError as ConfigError."""
    try:
        check(settings)
    except ValueError as exc:
        raise ConfigError(compact_numbers(str(exc))) from None


def _fields(obj) -> dict:
    return {f: getattr(obj, f) for f in obj.__dataclass_fields__}


@dataclass(frozen=True)
class Projection:
    """Settings of the FEPR projection (fepr-spec sections 2-3).

    Parameters
    ----------
    tolerance : float
        Relative per-row tolerance (default 1e-10): ``|c_H| <= tol * H_scale``, ``|c_P| <= tol * m r / h``,
        ``|c_L| <= tol * m r^2 / h``, ``|c_C| <= tol * r``.
    max_iterations : int
        Iterations per step before falling back (default 20).
    rows : str
        Active constraint rows: ``"auto"`` (all 10 rows for a free body, energy only with pinned vertices),
        ``"energy"``, ``"energy_momentum"`` (the paper's 7 rows), ``"all"`` (plus the centre of mass).
    c_eps : float
        Weight of the slack variables s, t: ``eps = c_eps * m_tot * r^2`` (default 0.01).
    regularization : float
        Relative diagonal regularisation of the small system (default 1e-12).
    max_halvings : int
        Step halvings per iteration when a full step increases the residual (default 4).
    impact_bound : float or None
        Optional cap on the D-norm of the total correction as a fraction of ``sqrt(m_tot) * r`` (the seed's
        "upper bound on FEPR impact"). When it bites, conservation is not exact and the report says so.
    slack : str
        When the slack variables s and t may move: ``"auto"`` (only in steps with impulsive events whose
        impulses are uncertain, such as contact), ``"on"`` or ``"off"``. With slack the projection may keep part
        of the base step's own momentum change instead of the target.
    warm_start : float, "auto", "off" or None
        Scaled energy error above which (and above ``tolerance``) the projection first moves the velocities
        alone to the closest point with the positions held: the rigid part goes to the momentum targets (whole
        body free, no slack) and the deformational rest is scaled to meet the energy. Then it iterates (usually
        nothing is left to do). It suits dissipative steps; the result is then the closest point among the
        states with the base step's positions rather than the closest state overall, and the base step's
        positions are kept. ``"auto"`` (default): always after Projective Dynamics (0), above 0.05 after XPBD,
        off after the other integrators. PD at dt = 1/30 loses 10-90% of H per step on the bunny; with the warm
        start its projection costs one energy + gradient evaluation instead of 5.6 iterations and never has to
        restart around tets it would have inverted (a third of the steps without it). XPBD loses a quarter of H
        per step on sliver-rich meshes; with the warm start every projection of a 10 s bunny run converges.
        ``None`` or ``"off"``: off. The thresholds of ``"auto"`` are the core's (``fepr._core.PD_WARM_START``,
        ``XPBD_WARM_START``).
    metric : str
        Position block W of the projection's metric ``D = diag(W, h^2 M, eps, eps)``: ``"mass"`` (W = M,
        fepr-spec section 3), ``"stiffness"`` (W = M + h^2 diag(K_0), K_0 the rest-state stiffness: stiff local
        modes such as sliver tets become expensive to move, so an energy deficit is restored through the
        velocities and the smooth modes) or ``"auto"`` (default: stiffness after an implicit base integrator,
        mass after symplectic Euler; after Projective Dynamics, where the energy is the only row (pinned bodies)
        and no vertex is in contact, PD's own prefactored matrix, W = M + h^2 L, which moves the positions as a
        global step would). Under ``"auto"``, a projection in the diagonal stiffness metric that stalls (its
        residual does not halve in an iteration after the first, as when a falling body needs a rigid
        correction) restarts from the base step's state in the mass metric (``metric_switched`` in the report).
    quality_guard : bool
        The quality guard (default on): restoring energy the base step lost may not move any tet's volume
        ratio J = det F, at the end of the step or one step ahead at the new velocities (``x + dt v``), by more
        than ``quality_margin`` from what the base step gave it, nor invert a tet. Where restoring the whole
        deficit would, the projection restores the largest fraction that keeps within it and books the rest
        as unresolved energy (history ``work_unresolved``, part of ``budget_total``): at a large time step the
        modes the step cannot resolve (the breathing of a stiff body, sliver tets) lose their energy instead
        of inverting the mesh. ``False``: restore everything (the model's own dynamics; on meshes with sliver
        tets at large steps that inverts them).
    quality_margin : float
        The largest change of a tet's volume ratio the restoration may cause (default 0.05), in (0, 1].
    """

    tolerance: float = 1e-10
    max_iterations: int = 20
    rows: str = "auto"
    c_eps: float = 0.01
    regularization: float = 1e-12
    max_halvings: int = 4
    impact_bound: Optional[float] = None
    slack: str = "auto"
    warm_start: Union[float, str, None] = "auto"
    metric: str = "auto"
    quality_guard: bool = True
    quality_margin: float = 0.05

    def __post_init__(self):
        # The names are case-insensitive ("ALL", "Mass", "Auto"), as everywhere in fepr.
        for name in ("rows", "slack", "metric", "warm_start"):
            value = getattr(self, name)
            if isinstance(value, str):
                object.__setattr__(self, name, value.strip().lower())
        _checked(_core.check_projection, self._settings())

    def _settings(self) -> dict:
        """The settings as the core reads them (``_core.Simulation(projection=...)``)."""
        return _fields(self)


@dataclass(frozen=True)
class SymplecticEuler:
    """Symplectic (semi-implicit) Euler, the seed's integrator: ``v += h M^-1 f(x)``, ``x += h v``.

    Conditionally stable: a step size above the stability limit runs away (and FEPR does not change that).
    """

    name = "symplectic_euler"

    def _settings(self) -> dict:
        return {"name": self.name}


@dataclass(frozen=True)
class ImplicitEuler:
    """Backward Euler as minimisation of ``1/(2h^2)|x - x_n - h v_n|_M^2 + U(x)`` by Newton's method.

    Each Newton iteration factorises the exact Hessian and falls back to element Hessians projected to positive
    semi-definite only when that is not positive definite; the sparse Cholesky symbolic analysis is done once
    per simulation, and a backtracking line search keeps every step a descent. Unconditionally stable but
    numerically dissipative; FEPR on top restores the energy.

    Parameters
    ----------
    tolerance : float
        Stop when the Newton decrement falls below this fraction of its first value (default 1e-6).
    max_iterations : int
        Newton iterations per step (default 20).
    """

    tolerance: float = 1e-6
    max_iterations: int = 20
    name = "implicit_euler"

    def __post_init__(self):
        _checked(_core.check_integrator, self._settings())

    def _settings(self) -> dict:
        return {"name": self.name, **_fields(self)}


@dataclass(frozen=True)
class ProjectiveDynamics:
    """Projective Dynamics (Bouaziz et al. 2014): local rotations per tet + one prefactored global solve.

    It minimises the ARAP energy ``mu |F - R|^2`` (:class:`fepr.Arap`); a simulation with this integrator uses
    that energy (built from the given material's Young's modulus and Poisson ratio), so FEPR conserves the
    energy the solver minimises. Stable and fast at large steps, numerically dissipative alone.

    Parameters
    ----------
    iterations : int
        Local/global iterations per step (default 10).
    """

    iterations: int = 10
    name = "projective_dynamics"

    def __post_init__(self):
        _checked(_core.check_integrator, self._settings())

    def _settings(self) -> dict:
        return {"name": self.name, **_fields(self)}


@dataclass(frozen=True)
class Xpbd:
    """XPBD (Macklin et al. 2016) with the Neo-Hookean constraints of Macklin and Mueller 2021.

    Per tet a deviatoric constraint ``sqrt(I_C)`` and a hydrostatic constraint ``J - alpha`` with compliances
    ``1/(mu V)`` and ``1/(lambda' V)``, solved by Gauss-Seidel sweeps (colour by colour, in parallel and
    bit-identical for any thread count). A simulation with this integrator uses the energy those compliances
    encode (:class:`fepr.ConstraintNeoHookean`, built from the given material's Young's modulus and Poisson
    ratio), so FEPR conserves it. Stable at large steps; with few sweeps per (sub)step, numerically dissipative.

    Parameters
    ----------
    substeps : int
        Substeps per step (default 20: "small steps", Macklin et al. 2019; few large substeps diverge on stiff
        elements because XPBD's local solves ignore the constraints' curvature).
    iterations : int
        Gauss-Seidel sweeps per substep (default 1).
    """

    substeps: int = 20
    iterations: int = 1
    name = "xpbd"

    def __post_init__(self):
        _checked(_core.check_integrator, self._settings())

    def _settings(self) -> dict:
        return {"name": self.name, **_fields(self)}


#: The integrator classes by name (the names are the core's ``fepr._core.INTEGRATORS``; a test checks both agree).
INTEGRATOR_TYPES = {cls.name: cls for cls in (SymplecticEuler, ImplicitEuler, ProjectiveDynamics, Xpbd)}


class Energy(NamedTuple):
    """Energies of a state, J."""

    kinetic: float
    elastic: float
    gravitational: float
    total: float


@dataclass(frozen=True)
class ProjectionReport:
    """What the last projection did.

    ``residual`` and ``initial_residual`` are the largest scaled constraint residuals (compare with the
    tolerance) after and before the projection; ``correction`` is the D-norm of the change (sqrt(kg) m);
    ``fallback`` means it did not converge and kept the best iterate or the base step's state.
    ``stiffness_metric`` and ``system_metric`` say which position metric it used (neither: the mass metric):
    ``W = M + h^2 diag(K_0)``, or the base integrator's own matrix (after Projective Dynamics with the energy as
    the only row, the default with pins: ``W = M + h^2 L``, PD's global matrix times ``h^2``).
    ``gap`` is the step's energy gap ``H_target - H(x*, v*)`` (J; positive: the base step lost energy),
    ``restored`` the fraction of it the projection closed and ``unresolved`` the rest, booked as unresolved energy
    (J; see :class:`Projection`'s ``quality_guard``); ``quality_excess`` the largest change of a tet's volume ratio
    as a fraction of what the guard allows (0 where it did not run); ``trials`` the projections the step tried;
    ``metric_switched``: the stiffness metric stalled and the step was projected in the mass metric;
    ``translated``: the body was first translated onto its centre-of-mass target.
    ``stood_down``: a step of resting contact on which the projection stood down (no iteration; the base step's
    state, its residual booked as contact work; see ``docs/world.md``); not counted as unconverged.
    """

    iterations: int
    converged: bool
    residual: float
    initial_residual: float
    correction: float
    s: float
    t: float
    fallback: bool
    bound_hit: bool
    least_squares_solves: int
    halvings: int
    active_rows: int
    base_energy: float
    warm_start: bool
    stiffness_metric: bool
    system_metric: bool
    restarts: int
    frozen_vertices: int
    evaluations: int
    restored: float = 1.0
    unresolved: float = 0.0
    gap: float = 0.0
    translated: bool = False
    trials: int = 1
    metric_switched: bool = False
    quality_excess: float = 0.0
    stood_down: bool = False


#: The projection's warm-start thresholds of ``Projection(warm_start="auto")`` (the core's policy,
#: ``fepr_core::simulation::auto_warm_start_threshold``): after Projective Dynamics always (any energy error above
#: the tolerance), after XPBD above 5% of the energy scale.
PD_WARM_START = _core.PD_WARM_START
#: The history's ``step`` column (the store's rows are found by it).
_STEP_COLUMN = list(_core.Simulation.history_columns()).index("step")
XPBD_WARM_START = _core.XPBD_WARM_START


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a`` (a fresh copy from the core) marked read-only: editing it in place could only edit the copy."""
    a.flags.writeable = False
    return a


def _as_float3(value, name: str) -> tuple:
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be three numbers, got {value!r}") from None
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{name} must be three finite numbers, got {value!r}")
    return tuple(float(x) for x in a)


def _positive(value, name: str, unit: str) -> float:
    return real(value, name, unit=unit, lo=0, lo_open=True)


class Simulation:
    """A deformable body: mesh, material, masses, a base integrator and the FEPR projection.

    Parameters
    ----------
    mesh : TetMesh
        The rest shape (metres).
    material : NeoHookean, StableNeoHookean, Arap or ConstraintNeoHookean
        Material, SI units (Young's modulus in Pa, Poisson ratio). Projective Dynamics conserves the ARAP energy
        and XPBD the constraint Neo-Hookean energy: with those integrators the material is converted to that
        model with the same moduli (``sim.material`` shows the one in use).
    node_mass : float or array_like (m,), optional
        Mass per vertex, kg (as the seed used). Exactly one of ``node_mass`` and ``density``.
    density : float, optional
        Density, kg/m^3, lumped: a quarter of each tet's mass to each of its vertices.
    integrator : str or SymplecticEuler, ImplicitEuler, ProjectiveDynamics or Xpbd
        Base integrator: a name (``"symplectic_euler"``, ``"implicit_euler"``, ``"projective_dynamics"``,
        ``"xpbd"``; case-insensitive) or an integrator object with settings, e.g.
        ``fepr.ImplicitEuler(tolerance=1e-8)``, ``fepr.ProjectiveDynamics(iterations=20)``,
        ``fepr.Xpbd(substeps=20)``. Projective Dynamics uses the ARAP energy and XPBD the constraint Neo-Hookean
        energy built from the material's Young's modulus and Poisson ratio (see ``sim.material``).
    dt : float
        Time step, s (> 0).
    projection : bool or Projection
        ``True`` for FEPR with default settings, ``False`` for the bare integrator, or a :class:`Projection`.
    gravity : (3,) float
        Gravitational acceleration, m/s^2; gravity is potential energy and part of the conserved H.
    pinned : array_like of int or bool mask (m,), optional
        Vertices held fixed at their position.
    damping : float
        The seed's velocity damping factor per step, ``v <- (1 - damping) v``, in [0, 1); the energy it
        removes enters the step's energy budget, so the projection does not undo it.
    threads : int, optional
        Worker threads (default: all cores). Results are bit-identical for any thread count. With 1, the steps
        run on the calling thread itself, without a thread pool (no thread to wake for each ``step`` call).
    obstacles : sequence of Plane, Sphere, Box, Capsule or MeshObstacle, optional
        Static obstacles the free vertices collide with (restitution and Coulomb friction per obstacle). The
        kinetic energy a contact removes enters the step's budget, its impulses the momentum targets, and the
        projection does not move the positions of vertices in contact.
    kinematic_pins : sequence of KinematicPins, optional
        Groups of vertices that follow a prescribed path (they are pinned too); their work enters the budget.
    self_contact : bool or (restitution, friction), optional
        Contact of the body with its own surface (a fold, a limb pressed against the torso): ``True`` for
        restitution 1 and no friction, or the two coefficients; off by default. The impulses are internal
        (momenta unchanged); the kinetic energy they remove enters the budget (``work_contact``).
    air_damping : float
        Mass-proportional damping rate ``a`` in 1/s (``dv/dt = -a v``, applied exactly per step).
    rayleigh_damping : float
        Stiffness-proportional damping coefficient ``b`` in s (force ``-b K(x) v``, applied implicitly: one
        sparse factorisation per step).
    external_forces : array_like (m, 3), optional
        Constant force on each vertex, N (see :meth:`set_external_forces`).

    Raises
    ------
    ConfigError
        For invalid parameters (the message names the parameter).
    """

    def __init__(
        self,
        mesh: TetMesh,
        *,
        material: _Material,
        node_mass=None,
        density: Optional[float] = None,
        integrator: Union[str, SymplecticEuler, ImplicitEuler, ProjectiveDynamics, Xpbd] = "symplectic_euler",
        dt: float,
        projection: Union[bool, Projection] = True,
        gravity=(0.0, 0.0, 0.0),
        pinned=None,
        damping: float = 0.0,
        threads: Optional[int] = None,
        obstacles: Sequence[Obstacle] = (),
        kinematic_pins: Sequence[KinematicPins] = (),
        air_damping: float = 0.0,
        rayleigh_damping: float = 0.0,
        external_forces=None,
        self_contact: Union[bool, Tuple[float, float]] = False,
    ):
        if not isinstance(mesh, TetMesh):
            raise ConfigError(f"mesh must be a fepr.TetMesh, got {type(mesh).__name__}")
        if not isinstance(material, tuple(MATERIAL_TYPES.values())):
            raise ConfigError(
                "material must be fepr.NeoHookean(...), fepr.StableNeoHookean(...), fepr.Arap(...) or "
                f"fepr.ConstraintNeoHookean(...), got {material!r}"
            )
        m = mesh.num_vertices
        node_masses = None
        if (node_mass is None) == (density is None):
            raise ConfigError("give exactly one of node_mass (kg per vertex) and density (kg/m^3)")
        if density is not None:
            mass_kind, mass_value = "density", _positive(density, "density", "kg/m^3")
        elif np.ndim(node_mass) == 0:
            mass_kind, mass_value = "node_mass", _positive(node_mass, "node_mass", "kg")
        else:
            node_masses = float_array(node_mass, "node_mass", f"({m},)")
            if node_masses.shape != (m,):
                raise ConfigError(f"node_mass array must have shape ({m},), got {node_masses.shape}")
            bad = np.flatnonzero(~(np.isfinite(node_masses) & (node_masses > 0)))
            if bad.size:
                raise ConfigError(f"node_mass of vertex {bad[0]} is {node_masses[bad[0]]}; masses must be positive")
            mass_kind, mass_value = "node_mass", 0.0
        dt = _positive(dt, "dt", "seconds")
        if isinstance(integrator, str):
            integrator = integrator.strip().lower()  # names are case-insensitive
            if integrator not in _core.INTEGRATORS or integrator not in INTEGRATOR_TYPES:
                raise ConfigError(f"unknown integrator {integrator!r} (known: {', '.join(_core.INTEGRATORS)})")
            integrator = INTEGRATOR_TYPES[integrator]()
        elif not isinstance(integrator, tuple(INTEGRATOR_TYPES.values())):
            raise ConfigError(f"integrator must be a name or an integrator object, got {integrator!r}")
        # PD minimises the ARAP energy, XPBD's constraints encode the constraint Neo-Hookean energy: H must be
        # that energy (fepr-spec section 5). The core's policy says which; ``sim.material`` shows it.
        conserved = _core.conserved_material(integrator.name)
        if conserved is not None and material.model != conserved:
            material = MATERIAL_TYPES[conserved](material.youngs_modulus, material.poisson_ratio)
        if projection is True:
            proj = Projection()
        elif projection is False or projection is None:
            proj = None
        elif isinstance(projection, Projection):
            proj = projection
        else:
            raise ConfigError(f"projection must be True, False or fepr.Projection(...), got {projection!r}")
        gravity = _as_float3(gravity, "gravity")
        pinned_idx = self._pinned_indices(pinned, m)
        obstacles = list(obstacles or ())
        for k, ob in enumerate(obstacles):
            if not isinstance(ob, OBSTACLE_TYPES):
                raise ConfigError(
                    f"obstacles[{k}] must be fepr.Plane, Sphere, Box, Capsule or MeshObstacle, got {ob!r}"
                )
        kinematic = list(kinematic_pins or ())
        groups = []
        for k, kp in enumerate(kinematic):
            if not isinstance(kp, KinematicPins):
                raise ConfigError(f"kinematic_pins[{k}] must be fepr.KinematicPins(vertices, motion), got {kp!r}")
            groups.append(kp.indices(m))
        seen: set = set()
        static = set(pinned_idx)
        for k, g in enumerate(groups):
            if seen & set(g):
                raise ConfigError(f"kinematic_pins[{k}]: vertex {min(seen & set(g))} is in more than one group")
            if static & set(g):
                raise ConfigError(
                    f"kinematic_pins[{k}]: vertex {min(static & set(g))} is also in pinned: a vertex cannot both stay "
                    "fixed (pinned) and follow a path (a kinematic pin); remove it from one of the two"
                )
            seen |= set(g)
        pinned_idx = sorted(set(pinned_idx) | seen)
        air_damping = real(air_damping, "air_damping", lo=0)
        rayleigh_damping = real(rayleigh_damping, "rayleigh_damping", lo=0)
        damping = real(damping, "damping", lo=0, hi=1, hi_open=True)
        if threads is not None:
            threads = integer(threads, "threads", lo=1, hi=4096)
        try:
            self._sim = _core.Simulation(
                mesh.vertices,
                mesh.tets,
                material=material._settings(),
                mass={"node_masses": node_masses} if node_masses is not None else {mass_kind: mass_value},
                integrator=integrator._settings(),
                dt=dt,
                projection=None if proj is None else proj._settings(),
                world={"gravity": gravity, "pinned": pinned_idx, "damping": float(damping)},
                threads=threads,
            )
        except ValueError as exc:
            raise ConfigError(compact_numbers(str(exc))) from None
        try:
            self._sim.set_obstacles([ob._core() for ob in obstacles])
            self._sim.set_kinematic_pins([(g, *kp.motion._core()) for g, kp in zip(groups, kinematic)])
            self._sim.set_damping(float(air_damping), float(rayleigh_damping))
            self._sim.set_self_contact(_self_contact(self_contact))
        except ValueError as exc:
            raise ConfigError(compact_numbers(str(exc))) from None
        self.self_contact = _self_contact(self_contact)
        self.obstacles: tuple = tuple(obstacles)
        self.kinematic_pins: tuple = tuple(kinematic)
        self.air_damping = float(air_damping)
        self.rayleigh_damping = float(rayleigh_damping)
        self.mesh = mesh
        if external_forces is not None:
            self.set_external_forces(external_forces)
        self.material = material
        self.projection: Optional[Projection] = proj
        self.integrator_settings = integrator
        self.gravity = np.array(gravity)
        self.damping = float(damping)
        self._warned_runaway = False
        self._warned_unconverged = False
        self._warned_unresolved = False
        self._history = HistoryStore(_core.Simulation.history_columns())
        # What a checkpoint needs to build this simulation again (fepr.checkpoint), as the caller gave it.
        self._recipe = dict(
            mesh=mesh,
            material=material,
            node_mass=node_masses if node_masses is not None else (mass_value if mass_kind == "node_mass" else None),
            density=mass_value if mass_kind == "density" else None,
            integrator=integrator,
            dt=dt,
            projection=proj if proj is not None else False,
            gravity=tuple(gravity),
            pinned=[int(i) for i in self._pinned_indices(pinned, m)],
            damping=float(damping),
            obstacles=list(obstacles),
            kinematic_pins=list(kinematic),
            self_contact=self.self_contact if self.self_contact is not None else False,
            air_damping=self.air_damping,
            rayleigh_damping=self.rayleigh_damping,
        )

    @staticmethod
    def _pinned_indices(pinned, m: int) -> List[int]:
        if pinned is None:
            return []
        a = np.asarray(pinned)
        if a.dtype == bool:
            if a.shape != (m,):
                raise ConfigError(f"pinned mask must have shape ({m},), got {a.shape}")
            return [int(i) for i in np.flatnonzero(a)]
        if a.size == 0:
            return []
        if not np.issubdtype(a.dtype, np.integer) or a.ndim != 1:
            raise ConfigError("pinned must be a 1-D array of vertex indices or a boolean mask of shape (m,)")
        bad = a[(a < 0) | (a >= m)]
        if bad.size:
            raise ConfigError(f"pinned vertex {int(bad[0])} is out of range: the mesh has {m} vertices")
        return sorted({int(i) for i in a})

    # --- state -------------------------------------------------------------------------------------------
    @property
    def positions(self) -> np.ndarray:
        """Current positions, (m, 3) float64, m: a read-only copy (an in-place edit such as
        ``sim.positions[:, 2] += 1`` raises instead of silently editing a copy). To change the state, assign:
        ``x = sim.positions.copy(); x[:, 2] += 1; sim.positions = x`` (assigning resets the projection's
        references)."""
        return _read_only(self._sim.positions)

    @positions.setter
    def positions(self, x) -> None:
        self._set_state_array("positions", x)

    @property
    def velocities(self) -> np.ndarray:
        """Current velocities, (m, 3) float64, m/s: a read-only copy, as :attr:`positions` (assign to change;
        pinned rows stay zero)."""
        return _read_only(self._sim.velocities)

    @velocities.setter
    def velocities(self, v) -> None:
        self._set_state_array("velocities", v)

    def _set_state_array(self, name: str, value) -> None:
        a = float_array(value, name, "(m, 3)")
        m = self.mesh.num_vertices
        if a.shape != (m, 3):
            raise ConfigError(f"{name} must have shape ({m}, 3), got {a.shape}")
        try:
            setattr(self._sim, name, a)
        except ValueError as exc:
            raise ConfigError(compact_numbers(str(exc))) from None
        if self.num_steps == 0:
            self._history.clear()  # row 0 describes the state the run starts from: taken again at the first step

    @property
    def rest_positions(self) -> np.ndarray:
        """Rest positions, (m, 3) float64, m (read-only)."""
        return _read_only(self._sim.rest_positions)

    @property
    def tets(self) -> np.ndarray:
        """Tets, (k, 4) int64, positively oriented."""
        return self.mesh.tets

    @property
    def masses(self) -> np.ndarray:
        """Lumped vertex masses, (m,) float64, kg (read-only)."""
        return _read_only(self._sim.masses)

    @property
    def total_mass(self) -> float:
        return self._sim.total_mass

    @property
    def pinned(self) -> np.ndarray:
        """Pinned-vertex mask, (m,) bool (read-only)."""
        return _read_only(self._sim.pinned)

    @property
    def time(self) -> float:
        """Simulated time, s."""
        return self._sim.time

    @property
    def num_steps(self) -> int:
        return self._sim.num_steps

    @property
    def dt(self) -> float:
        """Time step, s."""
        return self._sim.dt

    @property
    def integrator(self) -> str:
        return self._sim.integrator

    # --- stepping ----------------------------------------------------------------------------------------
    #: Longest stretch of stepping, s, before control comes back to Python (signals such as Ctrl-C are handled
    #: there, and the history rows are taken from the core): a run stops within this plus one step.
    BATCH_SECONDS = 0.05

    def step(self, n: int = 1, callback: Optional[Callable[[Simulation], Optional[bool]]] = None) -> int:
        """Advance ``n`` steps (the GIL is released while stepping); returns the steps taken.

        The steps run in batches of at most :attr:`BATCH_SECONDS` of wall time; between batches Python handles
        signals, so Ctrl-C (``KeyboardInterrupt``) stops a long ``step(n)`` within about 0.05 s plus one step, at
        a step boundary: the state, the history and :attr:`num_steps` then describe the steps completed.
        ``callback(sim)``, if given, is called after every batch (progress bars, live plots); when it returns
        True, stepping stops there (fewer than ``n`` steps are taken).

        Raises
        ------
        SimulationError
            If the state becomes non-finite (runaway of an unstable step size). The state is left at the last
            finite step and the history keeps every completed step.
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ConfigError(f"n must be a non-negative integer, got {n!r}")
        if callback is not None and not callable(callback):
            raise ConfigError(f"callback must be callable, got {callback!r}")
        remaining = int(n)
        while remaining:
            before = self.num_steps
            try:
                remaining -= self._sim.step(remaining, self.BATCH_SECONDS)
            except RuntimeError as exc:
                err = SimulationError(compact_numbers(str(exc)))
                err.step = self.num_steps + 1  # the step that failed
                raise err from None
            finally:
                self._after_batch(before)
            if callback is not None and callback(self) is True:
                break
        return int(n) - remaining

    def _after_batch(self, before: int) -> None:
        """After a batch of steps from step ``before``: the warnings, then the new history rows into the store
        (the core keeps only its last row)."""
        self._check_runaway(before)
        self._check_projection(before)
        self._take_history()

    def _take_history(self) -> None:
        """Move the core's history rows that the store does not hold yet into it."""
        last = self._history.last
        after = -1 if last is None else int(last[_STEP_COLUMN])
        rows = self._sim.history_after(after)
        if len(rows):
            self._history.append(rows)
        self._sim.trim_history()

    #: Unresolved energy (a share of the run's initial energy scale) above which :meth:`step` warns, once.
    UNRESOLVED_WARNING = 1e-3

    def _check_projection(self, before: int) -> None:
        """Warn (once per simulation each) about energy booked as unresolved and unconverged projections."""
        if self.projection is None or self.num_steps == before:
            return
        if not self._warned_unconverged:
            k = self._sim.first_unconverged(before + 1)
            if k is not None:
                self._warned_unconverged = True
                warnings.warn(
                    f"the FEPR projection did not converge in step {k}: that step keeps the best state it found, off "
                    "its energy and momentum targets by the residual in history['proj_residual'] "
                    "(history['proj_converged'] marks every such step)",
                    RuntimeWarning,
                    stacklevel=3,
                )
        if not self._warned_unresolved:
            unresolved, lost, scale = self._sim.unresolved_energy()
            if -unresolved > self.UNRESOLVED_WARNING * scale:
                self._warned_unresolved = True
                warnings.warn(self._unresolved_message(-unresolved, lost), RuntimeWarning, stacklevel=3)

    def _unresolved_message(self, unresolved: float, lost: float) -> str:
        share = f"{unresolved / lost:.0%} of the energy the base integrator lost" if lost > 0 else "energy"
        dt_res = self._sim.resolving_time_step()
        if self.integrator == "symplectic_euler":
            cause = (
                f"symplectic Euler at dt = {self.dt:.3g} s is at or beyond its stability limit in the states this "
                "motion reaches (its own energy errors: history['base_energy_error']); a smaller dt keeps its steps "
                "stable"
            )
        elif self.dt > dt_res:
            cause = (
                f"dt = {self.dt:.3g} s does not resolve this body's fast elastic modes (a pressure wave crosses it "
                f"in {10 * dt_res:.3g} s); dt <= {dt_res:.2g} s resolves them"
            )
        else:
            cause = (
                f"the motion strains some tets hard (dt = {self.dt:.3g} s resolves this body's pressure waves, so "
                "this is the mesh: sliver tets whose motion the restoration would have amplified)"
            )
        return (
            f"FEPR could not restore {share} ({unresolved:.3g} J of {lost:.3g} J so far) without moving tets' "
            f"volume ratios by more than the quality guard allows (margin {self.projection.quality_margin}): it is "
            f"booked as unresolved energy (history['work_unresolved'], part of budget_total). Cause: {cause}. "
            "Projection(quality_guard=False) restores everything instead (the model's own dynamics, which can "
            "invert sliver tets)."
        )

    def _check_runaway(self, before: int) -> None:
        if self._warned_runaway or self.num_steps == before:
            return
        k = self._sim.first_runaway(before + 1)
        if k is not None:
            self._warned_runaway = True
            warnings.warn(
                f"runaway detected at step {k}: the base integrator's energy error exceeded 100% of the energy "
                f"scale (dt = {self.dt} s is unstable for this material and mesh; see history['base_energy_error'])",
                RuntimeWarning,
                stacklevel=3,
            )

    # --- the world: forces and the drag spring ------------------------------------------------------------
    def set_external_forces(self, forces) -> None:
        """Set a constant force on each vertex, ``(m, 3)`` float64 in N, or ``(3,)`` for the same force on
        every vertex; ``None`` removes it. Forces on pinned vertices are ignored (the support takes them).
        Their work ``sum f . (x_{n+1} - x_n)`` enters each step's budget (history column ``work_forces``)."""
        m = self.mesh.num_vertices
        if forces is None:
            self._sim.set_external_forces(None)
            return
        f = float_array(forces, "external_forces", "(m, 3) or (3,)")
        if f.shape == (3,):
            f = np.tile(f, (m, 1))
        if f.shape != (m, 3):
            raise ConfigError(f"external_forces must have shape ({m}, 3) or (3,), got {f.shape}")
        try:
            self._sim.set_external_forces(np.ascontiguousarray(f))
        except ValueError as exc:
            raise ConfigError(compact_numbers(str(exc))) from None

    def set_drag(self, vertex: int, target, stiffness: float) -> None:
        """Pull ``vertex`` towards ``target`` ((3,) m) with a spring of ``stiffness`` N/m (the viewer's mouse
        drag). The force is evaluated at the start of each step; its work enters the budget."""
        vertex = integer(vertex, "vertex", lo=0, hi=self.mesh.num_vertices - 1)
        target = _as_float3(target, "target")
        stiffness = real(stiffness, "stiffness", lo=0)
        try:
            self._sim.set_drag((vertex, target, float(stiffness)))
        except ValueError as exc:
            raise ConfigError(compact_numbers(str(exc))) from None

    def clear_drag(self) -> None:
        """Release the drag spring."""
        self._sim.set_drag(None)

    # --- measurements ------------------------------------------------------------------------------------
    def energy(self) -> Energy:
        """Kinetic, elastic, gravitational and total energy of the current state, J."""
        k, e, g, t, _, _ = self._sim.measure()
        return Energy(k, e, g, t)

    def linear_momentum(self) -> np.ndarray:
        """Linear momentum, (3,) float64, kg m/s."""
        return np.array(self._sim.momenta()[0])

    def angular_momentum(self) -> np.ndarray:
        """Angular momentum about the centre of mass, (3,) float64, kg m^2/s."""
        return np.array(self._sim.momenta()[1])

    def center_of_mass(self) -> np.ndarray:
        """Centre of mass, (3,) float64, m."""
        return np.array(self._sim.momenta()[2])

    def min_volume_ratio(self) -> float:
        """Smallest J = det F over all tets (J <= 0: inverted)."""
        return self._sim.measure()[4]

    def elastic_energy_gradient(self, x=None):
        """Elastic energy (J) and its gradient ((m, 3) float64, J/m) at positions ``x`` (default: current)."""
        x = self.positions if x is None else float_array(x, "x", "(m, 3)")
        try:
            return self._sim.elastic_energy_gradient(x)
        except ValueError as exc:
            raise ConfigError(compact_numbers(str(exc))) from None

    @property
    def last_projection(self) -> Optional[ProjectionReport]:
        """Report of the last step's projection, or None (no projection, or no step yet)."""
        d = self._sim.last_projection()
        return None if d is None else ProjectionReport(**d)

    @property
    def history(self) -> History:
        """Per-step diagnostics (row 0: the initial state), a snapshot (later steps do not change it). Reading a
        column reads only that column; :attr:`last` gives the last row without building anything."""
        self._take_history()
        return History(self._history, self._history.columns)

    @property
    def last(self) -> Dict[str, float]:
        """The last row of the history as ``{column: value}`` (O(1), whatever the number of steps)."""
        self._take_history()
        return dict(zip(self._history.columns, self._history.last.tolist()))

    @property
    def history_memory_rows(self) -> Optional[int]:
        """Rows of history kept in memory (default :data:`fepr.history.DEFAULT_MEMORY_ROWS`, about 8 MB); older
        rows go to a temporary folder and are read back when a column is read. ``None``: keep every row in
        memory."""
        return self._history.memory_rows

    @history_memory_rows.setter
    def history_memory_rows(self, rows: Optional[int]) -> None:
        self._history.memory_rows = rows

    def save_diagnostics(self, path: Union[str, Path]) -> None:
        """Write :attr:`history` as CSV (one row per step, header of column names), atomically (a temporary file
        in the same folder, renamed)."""
        from .io.atomic import atomic_path

        with atomic_path(path) as tmp:
            self.history.to_csv(tmp)

    def save_checkpoint(self, path: Union[str, Path], *, history: bool = True) -> None:
        """Write everything the next steps depend on to ``path`` (a NumPy ``.npz`` file, written atomically):
        the settings this simulation was built with (mesh, material, masses, integrator, projection, obstacles,
        pins), the state, time and step count, the projection's running references and books, the kinematic
        pins' anchors, the forces and damping set since, and (``history=True``) the history so far.
        :meth:`load_checkpoint` builds a simulation whose next steps are this one's, bit for bit."""
        from .checkpoint import save_simulation

        self._take_history()
        save_simulation(self, path, history=history)

    @classmethod
    def load_checkpoint(cls, path: Union[str, Path], *, threads: Optional[int] = None) -> Simulation:
        """A simulation resumed from a checkpoint written by :meth:`save_checkpoint`: its next steps are the
        saved simulation's, bit for bit (any ``threads``). Raises :class:`fepr.errors.CheckpointError` for a file
        that is not a fepr checkpoint, is damaged, comes from another checkpoint version, or holds a multi-body
        system (use :meth:`fepr.MultiBody.load_checkpoint`)."""
        from .checkpoint import load_simulation

        return load_simulation(path, threads=threads)

    @classmethod
    def from_scene(cls, scene, *, projection=None, base_dir: Union[str, Path, None] = None) -> Simulation:
        """The simulation a one-body scene describes, in its initial state: ``scene`` a scene file (path), a dict
        of its sections (as the parsed TOML; relative paths against ``base_dir``, default the working folder), or
        a :class:`fepr.scene.Scene`. ``projection`` overrides ``[projection]`` (``False``: FEPR off).

        Raises
        ------
        ConfigError
            For an invalid scene (the message names the file, section and key), or a multi-body scene (use
            :meth:`fepr.MultiBody.from_scene`).
        """
        from .scene import load_scene_from

        return load_scene_from(scene, base_dir).build(projection=projection)

    def to_meshio(self):
        """The current state as a ``meshio.Mesh``: points at the current positions, ``tetra`` cells, point data
        ``velocity`` (m/s) and ``displacement`` (m), cell data ``J`` and ``energy_density`` (J/m^3)
        (:func:`fepr.interop.to_meshio`); ``meshio.write(path, sim.to_meshio())`` writes any format meshio knows."""
        from .interop import to_meshio

        return to_meshio(self)

    def to_pyvista(self):
        """The current state as a ``pyvista.UnstructuredGrid`` with the fields of :meth:`to_meshio` (needs
        ``pip install pyvista``)."""
        from .interop import to_pyvista

        return to_pyvista(self)

    def save_state(self, path: Union[str, Path]) -> None:
        """Write ``positions, velocities, rest_positions, tets, masses, time`` to a NumPy ``.npz`` archive at exactly
        ``path`` (no ``.npz`` is appended to another suffix), atomically (:func:`fepr.io.npz.save_npz`)."""
        from .io.npz import save_npz

        save_npz(
            path,
            dict(
                positions=self.positions,
                velocities=self.velocities,
                rest_positions=self.rest_positions,
                tets=self.tets,
                masses=self.masses,
                time=np.float64(self.time),
            ),
        )

    def __repr__(self) -> str:
        proj = "FEPR" if self.projection else "no projection"
        return (
            f"Simulation({self.mesh.num_vertices} vertices, {self.mesh.num_tets} tets, {self.integrator}, "
            f"dt={self.dt}, {proj}, t={self.time:.4g} s)"
        )


def _self_contact(value) -> Optional[Tuple[float, float]]:
    """``self_contact`` as ``(restitution, friction)`` or None (off)."""
    if value is False or value is None:
        return None
    if value is True:
        return (1.0, 0.0)
    if isinstance(value, (tuple, list)) and len(value) == 2:
        try:
            return (float(value[0]), float(value[1]))
        except (TypeError, ValueError):
            pass
    raise ConfigError(f"self_contact must be True, False or (restitution, friction), got {value!r}")
