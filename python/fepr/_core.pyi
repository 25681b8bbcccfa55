"""Type stubs of the compiled extension ``fepr._core`` (thin bindings of the Rust crate fepr-core).

The public API is in :mod:`fepr`; these functions are its building blocks.
"""

from typing import Dict, List, Optional, Tuple

import numpy as np
import numpy.typing as npt

__version__: str
INTEGRATORS: List[str]

def validate_mesh(
    vertices: npt.NDArray[np.float64], tets: npt.NDArray[np.int64]
) -> Tuple[npt.NDArray[np.int64], int, int]:
    """Validate a mesh; returns (positively oriented tets (k, 4), number flipped, number unreferenced).
    Raises ValueError naming the tet or vertex."""

def material_eval(
    model: str,
    youngs_modulus: float,
    poisson_ratio: float,
    j0: float,
    f: npt.NDArray[np.float64],
    derivative: bool = True,
) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], Optional[npt.NDArray[np.float64]]]:
    """Energy densities (n,), first Piola stresses (n, 3, 3) and stress derivatives (n, 9, 9) at F (n, 3, 3)."""

class Simulation:
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
        pinned: List[int],
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
    ) -> None: ...
    def step(self, n: int) -> int: ...
    positions: npt.NDArray[np.float64]
    velocities: npt.NDArray[np.float64]
    @property
    def time(self) -> float: ...
    @property
    def num_steps(self) -> int: ...
    @property
    def dt(self) -> float: ...
    @property
    def integrator(self) -> str: ...
    @property
    def masses(self) -> npt.NDArray[np.float64]: ...
    @property
    def total_mass(self) -> float: ...
    @property
    def length_scale(self) -> float: ...
    @property
    def rest_positions(self) -> npt.NDArray[np.float64]: ...
    @property
    def pinned(self) -> npt.NDArray[np.bool_]: ...
    def measure(self) -> Tuple[float, float, float, float, float, int]: ...
    def momenta(
        self,
    ) -> Tuple[Tuple[float, float, float], Tuple[float, float, float], Tuple[float, float, float]]: ...
    def elastic_energy_gradient(self, x: npt.NDArray[np.float64]) -> Tuple[float, npt.NDArray[np.float64]]: ...
    def bench_energy_gradient(self, repeats: int, threads: int) -> Tuple[float, int, int]: ...
    def last_projection(self) -> Optional[Dict[str, object]]: ...
    @staticmethod
    def history_columns() -> List[str]: ...
    def history(self) -> npt.NDArray[np.float64]: ...
