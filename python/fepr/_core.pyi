"""Type stubs of the compiled extension ``fepr._core`` (thin bindings of the Rust crate fepr-core).

The public API is in :mod:`fepr`; these functions are its building blocks. SI units throughout. Every class,
method and argument of ``crates/fepr-python/src/lib.rs`` is declared here; ``tests/test_core_stub.py`` checks
the names, kinds and argument lists against the compiled module.
"""

from typing import Dict, List, Optional, Sequence, Tuple, TypedDict, Union

import numpy as np
import numpy.typing as npt

__version__: str
# The name lists, each defined once in the Rust core (``tests/test_core_contract.py`` checks that the Python
# package uses them).
#: Names of the base integrators, as used in scene files and by ``Simulation(integrator=...)``.
INTEGRATORS: List[str]
#: Names of the material models (``fepr.NeoHookean.model``, ...; ``fepr_core::material::MATERIAL_NAMES``).
MATERIALS: List[str]
#: ``Projection(rows=...)`` choices (``fepr_core::projection::ROW_NAMES``).
PROJECTION_ROWS: List[str]
#: ``Projection(metric=...)`` choices (``fepr_core::projection::METRIC_NAMES``).
METRICS: List[str]
#: Keys of the projection settings dict (``fepr.Projection``'s fields; ``[projection]`` keys but ``enabled``).
PROJECTION_KEYS: List[str]
#: ``Projection(slack=...)`` choices (``fepr_core::projection::SLACK_NAMES``).
SLACK_MODES: List[str]
#: Named ``Projection(warm_start=...)`` modes besides a number and None (``fepr_core::projection::WARM_START_MODES``).
WARM_START_MODES: List[str]
#: Column names of ``Simulation.history()``, in order (``fepr_core::simulation::HISTORY_COLUMNS``).
HISTORY_COLUMNS: List[str]
#: The history columns that hold counts or 0/1 flags (``fepr_core::simulation::HISTORY_INTEGER_COLUMNS``).
HISTORY_INTEGER_COLUMNS: List[str]
#: Keys of ``Simulation.last_projection()`` (``fepr_core::projection::REPORT_FIELDS``).
PROJECTION_REPORT_FIELDS: List[str]
#: Warm-start thresholds of ``warm_start="auto"`` after Projective Dynamics and after XPBD
#: (``fepr_core::simulation::PD_WARM_START``, ``XPBD_WARM_START``).
PD_WARM_START: float
XPBD_WARM_START: float

class _MaterialSettings(TypedDict, total=False):
    """A material for the core: ``model`` (one of :data:`MATERIALS`), ``youngs_modulus`` Pa, ``poisson_ratio``,
    ``j0`` (neo_hookean only, default 0.1)."""

    model: str
    youngs_modulus: float
    poisson_ratio: float
    j0: float

class _IntegratorSettings(TypedDict, total=False):
    """An integrator for the core: ``name`` (one of :data:`INTEGRATORS`) and that integrator's settings
    (implicit_euler: tolerance, max_iterations; projective_dynamics: iterations; xpbd: substeps, iterations)."""

    name: str
    tolerance: float
    max_iterations: int
    iterations: int
    substeps: int

class _ProjectionSettings(TypedDict, total=False):
    """The projection for the core: the fields of ``fepr.Projection`` (absent keys take its defaults)."""

    tolerance: float
    max_iterations: int
    rows: str
    c_eps: float
    regularization: float
    max_halvings: int
    impact_bound: Optional[float]
    slack: str
    warm_start: Union[float, str, None]
    metric: str
    quality_guard: bool
    quality_margin: float

class _MassSettings(TypedDict, total=False):
    """Exactly one of ``density`` kg/m^3, ``node_mass`` kg per vertex, ``node_masses`` (m,) kg."""

    density: float
    node_mass: float
    node_masses: npt.NDArray[np.float64]

class _WorldSettings(TypedDict, total=False):
    """``gravity`` (3,) m/s^2, ``pinned`` vertex indices, ``damping`` velocity damping factor per step in [0, 1)."""

    gravity: Tuple[float, float, float]
    pinned: Sequence[int]
    damping: float

def check_material(material: _MaterialSettings) -> None:
    """Check a material in the core; raises ValueError naming the key (``material.youngs_modulus ...``)."""

def check_integrator(integrator: _IntegratorSettings) -> None:
    """Check an integrator's settings in the core; raises ValueError naming the key (``integrator.substeps ...``)."""

def check_projection(projection: _ProjectionSettings) -> None:
    """Check projection settings in the core; raises ValueError naming the key (``projection.tolerance ...``)."""

def conserved_material(integrator: str) -> Optional[str]:
    """The material model whose energy the integrator minimises and the projection therefore conserves
    ("arap" for projective_dynamics, "constraint_neo_hookean" for xpbd), or None: any material."""

def warm_start_threshold(integrator: str) -> float:
    """The projection's warm-start threshold under ``warm_start="auto"`` after ``integrator`` (inf: off)."""

def step_bodies(
    sims: Sequence[Simulation],
    n: int,
    coefficients: Sequence[Tuple[float, float]],
    max_seconds: Optional[float] = None,
) -> int:
    """Advance the bodies ``sims`` (same dt) up to ``n`` steps together with contact between them (with
    ``max_seconds``: stop after the first step that ends later than that); ``coefficients`` holds each body's
    ``(restitution, friction)``. Returns the steps taken. On a failure raises RuntimeError with args ``(body
    index, message)``; the steps completed before it stay."""

def bench_body_detection(sims: Sequence[Simulation], repeats: int) -> float:
    """Seconds per detection pass of contact between ``sims`` at their current states (nothing changes), the
    mean over ``repeats``."""

def check_mesh_obstacle(vertices: Sequence[float], triangles: Sequence[int]) -> bool:
    """Validate a triangle-mesh obstacle (``vertices`` (n * 3) m and ``triangles`` (k * 3), flattened); returns
    whether it is closed. Raises ValueError naming the vertex or triangle at fault."""

# An obstacle's motion: (translation kind ("none", "sinusoid", "keyframes"), its parameters, keyframe times (s),
# angular velocity (3) rad/s, pivot (3) m, orientation times (k) s, orientations flattened (k * 3 rotation
# vectors, rad)).
ObstacleMotionArgs = Tuple[
    str, Sequence[float], Sequence[float], Sequence[float], Sequence[float], Sequence[float], Sequence[float]
]

def obstacle_placement(
    motion: ObstacleMotionArgs, t: float
) -> Tuple[Tuple[Tuple[float, float, float], ...], Tuple[float, float, float]]:
    """Where an obstacle with ``motion`` is at time ``t`` (s), as contact places it: ``(R (3, 3) rows, offset (3,)
    m)`` with ``x = R p + offset`` for a point ``p`` of the obstacle as given. Raises ValueError for a bad motion."""

def validate_mesh(
    vertices: npt.NDArray[np.float64], tets: npt.NDArray[np.int64]
) -> Tuple[npt.NDArray[np.int64], int, int]:
    """Validate a mesh (vertices (m, 3) m, tets (k, 4)); returns (positively oriented tets (k, 4) int64,
    number flipped, number of unreferenced vertices). Raises ValueError naming the tet or vertex."""

def material_eval(
    model: str,
    youngs_modulus: float,
    poisson_ratio: float,
    j0: float,
    f: npt.NDArray[np.float64],
    derivative: bool = True,
) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], Optional[npt.NDArray[np.float64]]]:
    """Evaluate material ``model`` ("neo_hookean", "stable_neo_hookean", "arap", "constraint_neo_hookean";
    Young's modulus in Pa) at deformation gradients ``f`` (n, 3, 3): energy densities (n,) J/m^3, first Piola
    stresses (n, 3, 3) Pa and, if ``derivative``, stress derivatives (n, 9, 9) Pa (row-major flattening of F),
    else None. ``j0`` is used by "neo_hookean" only."""

def bench_sync_floor(threads: int) -> Tuple[float, float]:
    """Measure what synchronising ``threads`` threads costs on this machine, in about 0.1 s: (seconds per parallel
    region that every thread must join, with no work in it (`rayon::broadcast`), seconds per cache-line
    round trip between two threads; NaN on a single CPU). ``fepr bench`` reports both with the machine."""

class _ProjectionReportDict(TypedDict):
    """What ``Simulation.last_projection()`` returns (the fields of ``fepr.ProjectionReport``)."""

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
    restored: float
    unresolved: float
    gap: float
    translated: bool
    trials: int
    metric_switched: bool
    quality_excess: float
    stood_down: bool

class Simulation:
    """The simulation: model, state, integrator and projection (see ``fepr.Simulation`` for the documented
    API). It runs on the mesh renumbered in a locality order; every per-vertex array and vertex index in and out
    is in the caller's numbering."""

    def __init__(
        self,
        vertices: npt.NDArray[np.float64],
        tets: npt.NDArray[np.int64],
        *,
        material: _MaterialSettings,
        mass: _MassSettings,
        integrator: _IntegratorSettings,
        dt: float,
        projection: Optional[_ProjectionSettings],
        world: _WorldSettings,
        threads: Optional[int] = None,
    ) -> None:
        """One settings dict per concern, each checked in the core (errors name ``section.key``); ``projection``
        None: no projection. Under projective_dynamics and xpbd the material is :func:`conserved_material`'s,
        built from the given moduli."""

    def step(self, n: int, max_seconds: Optional[float] = None) -> int:
        """Take up to ``n`` steps with the GIL released (with ``max_seconds``: stop after the first step that ends
        later than that); returns the number taken. Raises RuntimeError (naming the step) on a runaway to a
        non-finite state."""

    def carry(self) -> Dict[str, npt.NDArray[np.float64]]:
        """What the next steps depend on besides the settings, as named float64 arrays (internal vertex order)."""

    def resume(self, carry: Dict[str, Sequence[float]]) -> None:
        """Put back a :meth:`carry` of a simulation with the same settings; ValueError names what does not fit."""

    def history_after(self, step: int) -> npt.NDArray[np.float64]:
        """The history rows of the steps after ``step`` the core still holds, (rows, columns) float64."""

    def trim_history(self) -> None:
        """Drop every history row but the last."""

    @property
    def positions(self) -> npt.NDArray[np.float64]:
        """Positions (m, 3), m (a copy)."""

    @positions.setter
    def positions(self, x: npt.NDArray[np.float64]) -> None:
        """Set the positions (m, 3), m, finite; re-measures the running references."""

    @property
    def velocities(self) -> npt.NDArray[np.float64]:
        """Velocities (m, 3), m/s (a copy)."""

    @velocities.setter
    def velocities(self, v: npt.NDArray[np.float64]) -> None:
        """Set the velocities (m, 3), m/s, finite (pinned rows are set to zero); re-measures the references."""

    @property
    def time(self) -> float:
        """Simulated time, s."""

    @property
    def num_steps(self) -> int: ...
    @property
    def dt(self) -> float:
        """Time step, s."""

    @property
    def integrator(self) -> str: ...
    @property
    def masses(self) -> npt.NDArray[np.float64]:
        """Lumped vertex masses (m,), kg."""

    @property
    def total_mass(self) -> float:
        """kg."""

    @property
    def length_scale(self) -> float:
        """Half diagonal of the rest bounding box, m."""

    @property
    def rest_positions(self) -> npt.NDArray[np.float64]:
        """Rest positions (m, 3), m."""

    @property
    def pinned(self) -> npt.NDArray[np.bool_]:
        """Pinned-vertex mask (m,)."""

    def measure(self) -> Tuple[float, float, float, float, float, int]:
        """(kinetic, elastic, gravitational, total energy (J), smallest det F, number of inverted tets) of the
        current state."""

    def momenta(
        self,
    ) -> Tuple[Tuple[float, float, float], Tuple[float, float, float], Tuple[float, float, float]]:
        """(P kg m/s, L about the centre of mass kg m^2/s, centre of mass m)."""

    def elastic_energy_gradient(self, x: npt.NDArray[np.float64]) -> Tuple[float, npt.NDArray[np.float64]]:
        """Elastic energy (J) and its gradient (m, 3) J/m at positions ``x`` (m, 3)."""

    def bench_energy_gradient(self, repeats: int, threads: int, awake: bool = False) -> Tuple[float, int, int]:
        """Time ``repeats`` energy + gradient evaluations on ``threads`` threads, in up to ten batches (the best
        batch's mean); ``awake`` is kept for compatibility and has no effect (plain rayon): (seconds per
        evaluation, the energy's bits, a checksum of the gradient's bits)."""

    def bench_energy_gradient_apart(self, repeats: int, copies: int) -> float:
        """The same evaluation run by ``copies`` threads at once, each on its own one-thread pool and workspace,
        ``repeats`` evaluations each in up to ten batches started together: seconds per evaluation of the
        slowest copy in the best batch (``copies`` times one copy alone over this: the machine's ceiling over the
        speed-up)."""

    def last_projection(self) -> Optional[_ProjectionReportDict]:
        """The last step's projection report, or None (no projection, or no step yet)."""

    def first_runaway(self, start: int) -> Optional[int]:
        """First step at or after ``start`` whose ``runaway`` flag is set, or None."""

    def first_unconverged(self, start: int) -> Optional[int]:
        """First step at or after ``start`` whose projection did not converge, or None."""

    def unresolved_energy(self) -> Tuple[float, float, float]:
        """(unresolved, lost, scale), J: the energy booked as unresolved so far, the energy the base steps lost
        against their targets, and the run's initial energy scale."""

    def resolving_time_step(self) -> float:
        """A time step that resolves the body's fast elastic modes, s (a tenth of a pressure wave's crossing
        time)."""

    def set_obstacles(
        self,
        obstacles: Sequence[
            Tuple[
                str,
                Sequence[float],
                float,
                float,
                Sequence[int],
                Optional[ObstacleMotionArgs],
            ]
        ],
    ) -> None:
        """Obstacles as ``(kind, params, restitution, friction, triangles, motion)``: "plane" [point (3), normal
        (3)], "sphere" [center (3), radius], "box" [center (3), half extents (3), 9 rotation entries (rows)],
        "capsule" [a (3), b (3), radius], "mesh" [vertices flattened (n * 3)] with ``triangles`` flattened (k * 3;
        empty for the other kinds); lengths in m. ``motion``: None (static) or an :data:`ObstacleMotionArgs`.
        Replaces the previous list. Raises ValueError for a bad obstacle."""

    def set_self_contact(self, coefficients: Optional[Tuple[float, float]]) -> None:
        """Contact of the body with itself: ``(restitution, friction)``, or None for off. Raises ValueError for
        coefficients out of range."""

    def set_kinematic_pins(self, groups: Sequence[Tuple[Sequence[int], str, Sequence[float], Sequence[float]]]) -> None:
        """Kinematic pin groups ``(vertices, kind, params, times)``: "sinusoid" params [amplitude (3) m,
        frequency Hz, phase rad] (``times`` ignored); "keyframes" params = offsets flattened (k * 3) m with
        ``times`` (k,) s. The vertices must be pinned. Raises ValueError for a bad group."""

    def set_damping(self, air: float, rayleigh: float) -> None:
        """Air (mass-proportional, 1/s) and Rayleigh (stiffness-proportional, s) damping, each >= 0."""

    def set_external_forces(self, forces: Optional[npt.NDArray[np.float64]]) -> None:
        """Constant external force per vertex, (m, 3) N; None removes it."""

    def set_drag(self, drag: Optional[Tuple[int, Tuple[float, float, float], float]]) -> None:
        """The drag spring ``(vertex, target (3,) m, stiffness N/m)``, or None to release it."""

    @staticmethod
    def history_columns() -> List[str]:
        """Column names of :meth:`history`, in order."""

    def history(self) -> npt.NDArray[np.float64]:
        """The per-step diagnostics the core still holds (all of them unless trimmed) as a (rows, columns)
        float64 array."""
