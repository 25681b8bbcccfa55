"""Type stubs of the compiled extension ``fepr._core`` (thin bindings of the Rust crate fepr-core).

The public API is in :mod:`fepr`; these functions are its building blocks. SI units throughout. Every class,
method and argument of ``crates/fepr-python/src/lib.rs`` is declared here; ``tests/test_core_stub.py`` checks
the names, kinds and argument lists against the compiled module.
"""

from typing import List, Optional, Sequence, Tuple, TypedDict

import numpy as np
import numpy.typing as npt

__version__: str
#: Names of the base integrators, as used in scene files and by ``Simulation(integrator=...)``.
INTEGRATORS: List[str]

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
    region that every thread must join, with no work in it and the threads kept awake, seconds per cache-line
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

class Simulation:
    """The simulation: model, state, integrator and projection (see ``fepr.Simulation`` for the documented
    API). It runs on the mesh renumbered in a locality order; every per-vertex array and vertex index in and out
    is in the caller's numbering."""

    def __init__(
        self,
        vertices: npt.NDArray[np.float64],
        tets: npt.NDArray[np.int64],
        *,
        material: str,
        youngs_modulus: float,
        poisson_ratio: float,
        j0: float,
        mass_kind: str,
        mass_value: float,
        node_masses: Optional[npt.NDArray[np.float64]],
        integrator: str,
        dt: float,
        projection: bool,
        tolerance: float,
        max_iterations: int,
        rows: str,
        c_eps: float,
        regularization: float,
        max_halvings: int,
        impact_bound: Optional[float],
        gravity: Tuple[float, float, float],
        pinned: Sequence[int],
        damping: float,
        threads: Optional[int],
        slack: str = "auto",
        newton_tolerance: float = 1e-6,
        newton_max_iterations: int = 20,
        pd_iterations: int = 10,
        warm_start_threshold: float = ...,
        metric: str = "auto",
        xpbd_substeps: int = 20,
        xpbd_iterations: int = 1,
        quality_margin: Optional[float] = 0.05,
    ) -> None:
        """``mass_kind``: "density" (``mass_value`` kg/m^3) or "node_mass" (``mass_value`` kg per vertex, or
        ``node_masses`` (m,) kg). ``warm_start_threshold`` defaults to infinity (no warm start);
        ``quality_margin`` None turns the projection's quality guard off."""

    def step(self, n: int) -> int:
        """Take ``n`` steps with the GIL released; returns the number taken. Raises RuntimeError (naming the
        step) on a runaway to a non-finite state."""

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
        batch's mean); with ``awake`` the pool's threads poll between evaluations, as in a step: (seconds per
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

    def set_obstacles(self, obstacles: Sequence[Tuple[str, Sequence[float], float, float]]) -> None:
        """Obstacles as ``(kind, params, restitution, friction)``: "plane" [point (3), normal (3)], "sphere"
        [center (3), radius], "box" [center (3), half extents (3), 9 rotation entries (rows)], "capsule" [a (3),
        b (3), radius]; lengths in m. Replaces the previous list. Raises ValueError for a bad obstacle."""

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
        """The per-step diagnostics as a (rows, columns) float64 array (row 0: the initial state)."""
