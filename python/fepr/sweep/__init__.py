"""Many simulations: parameter sweeps and datasets, on Ray or a local process pool.

A sweep is a base scene plus the parameters to vary, as a grid, seeded random samples and cases
(:mod:`~fepr.sweep.spec`). Every run gets a stable id from what it simulates (:mod:`~fepr.sweep.plan`) and its
own folder with diagnostics, the final state and frames of positions and velocities (:mod:`~fepr.sweep.runner`);
the sweep gets an index, one row per run with its parameters, status and summary metrics
(:mod:`~fepr.sweep.index`), and on request a dataset for a learned simulator (:mod:`~fepr.sweep.dataset`).
Runs are Ray tasks, or processes of a local pool without Ray (:mod:`~fepr.sweep.backends`); a run's results are
bit-identical wherever it runs, and ``fepr run`` on its ``scene.toml`` gives them too. A sweep run again skips what
finished and continues what did not from its checkpoints.

Example::

    import fepr.sweep

    index = fepr.sweep.run_sweep("examples/sweeps/material_study.toml", "out/material_study")
    print(index[["material.youngs_modulus", "projection.enabled", "energy_error", "min_j"]])

``fepr.sweep(...)`` (the module called) is :func:`run_sweep`. The command is ``fepr sweep SWEEP.toml --out DIR``
(``docs/sweeps.md``).
"""

import sys
import types

from .dataset import write_dataset
from .driver import run_sweep, summary_line
from .index import read_index
from .plan import RunPlan, plan_runs
from .spec import SweepSpec, load_sweep, sweep_from_dict

__all__ = [
    "RunPlan",
    "SweepSpec",
    "load_sweep",
    "plan_runs",
    "read_index",
    "run_sweep",
    "summary_line",
    "sweep_from_dict",
    "write_dataset",
]


class _CallableModule(types.ModuleType):
    """The package itself is callable, so that ``fepr.sweep(SWEEP, OUT)`` runs a sweep while ``fepr.sweep.*`` stays
    the package (one name for the feature, as the issue asks, without hiding the submodules)."""

    def __call__(self, *args, **kwargs):
        return run_sweep(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
