"""The index of a sweep: one row per run (its parameters, status and summary metrics), as a pandas DataFrame
written to ``DIR/index.parquet``.

Columns, in this order:

- ``run_id`` (16 hex digits), ``number`` (position in the sweep, from 0), ``sample`` (the random draw, or -1);
- one column per varied parameter, named by its path (``material.youngs_modulus``): numbers, strings and
  booleans as they are, vectors as lists, tables (a whole ``mesh``) as JSON text; ``params`` is all of them as
  one JSON text;
- ``status``: ``complete``, ``runaway`` (the simulation ran away: a result, not retried), ``failed`` (after the
  retries; ``error`` says why) or ``pending`` (not run: the sweep was stopped); ``error``; ``attempts``;
  ``resumed`` (continued from a checkpoint); ``skipped`` (complete before this invocation);
- ``steps``, ``steps_completed``, ``frames``, ``mesh_id``, ``vertices``, ``tets``;
- the summary metrics (:mod:`fepr.report.metrics`): ``energy_error`` (the energy-book gap, ``|H - (H0 +
  budget)|`` over the energy scale, largest over the run), ``final_energy_error``, ``unresolved`` (energy booked as
  unresolved, same scale), ``p_drift`` and ``l_drift`` (largest momentum drift from the targets; NaN with pins),
  ``min_j``, ``inverted`` (most inverted tets in a step), ``final_inverted``, ``unconverged`` (projections),
  ``mean_iterations``, ``substeps``, ``ms_per_step``, ``runaway_step``, ``problems``;
- ``wall_s`` (the run's stepping time, s, over all its attempts), ``host``, ``result_sha256`` (the digest of
  the results, :func:`fepr.sweep.runner.result_digest`: equal digests are bit-identical results), ``path`` (the
  run's folder, relative to the sweep's).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from ..errors import MissingDependencyError
from .plan import RunPlan, canonical_json

__all__ = ["INDEX", "METRIC_COLUMNS", "build_index", "read_index", "require_pandas", "write_index"]

INDEX = "index.parquet"
METRIC_COLUMNS = (
    "energy_error",
    "final_energy_error",
    "unresolved",
    "p_drift",
    "l_drift",
    "min_j",
    "inverted",
    "final_inverted",
    "unconverged",
    "mean_iterations",
    "substeps",
    "ms_per_step",
)


def require_pandas():
    """pandas, with pyarrow for Parquet; a :class:`fepr.MissingDependencyError` saying what to install."""
    try:
        import pandas
        import pyarrow  # noqa: F401
    except ImportError:
        raise MissingDependencyError(
            'fepr sweep writes its index with pandas and pyarrow: pip install "fepr[sweep]" (or pandas pyarrow)'
        ) from None
    return pandas


def _scalar(v: Any) -> bool:
    return isinstance(v, (bool, int, float, str))


def _param_column(values: List[Any]) -> List[Any]:
    """A parameter's values as one column: scalars of one kind as they are (ints and floats as floats), lists of
    numbers as lists, anything else (tables, mixed kinds) as canonical JSON text."""
    present = [v for v in values if v is not None]
    kinds = {bool if isinstance(v, bool) else (float if isinstance(v, (int, float)) else type(v)) for v in present}
    if len(kinds) == 1 and all(_scalar(v) for v in present):
        kind = kinds.pop()
        return [float(v) if kind is float and v is not None else v for v in values]
    if present and all(isinstance(v, list) and all(isinstance(c, (int, float)) for c in v) for v in present):
        return [None if v is None else [float(c) for c in v] for v in values]
    return [None if v is None else canonical_json(v) for v in values]


def _optional_int(v: Any) -> Optional[int]:
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else int(v)


def _nan_if_none(v: Any) -> Any:
    return float("nan") if v is None else v


def build_index(plans: Sequence[RunPlan], records: Dict[str, Dict[str, Any]], sweep_dir: Path):
    """The index DataFrame (see the module docs) of ``plans``, from each run's record (``status.json``
    content, plus ``skipped``; a plan without a record is ``pending``)."""
    pd = require_pandas()
    names: List[str] = []
    for p in plans:
        names.extend(k for k in p.params if k not in names)
    rows: List[Dict[str, Any]] = []
    for p in plans:
        rec = records.get(p.run_id, {})
        m = rec.get("metrics") or {}
        row: Dict[str, Any] = {"run_id": p.run_id, "number": p.number, "sample": -1 if p.sample is None else p.sample}
        rows.append(row)
        row["params"] = canonical_json(p.params)
        row["status"] = rec.get("status", "pending")
        row["error"] = rec.get("error")
        row["attempts"] = int(rec.get("attempts", 0))
        row["resumed"] = any(a.get("resumed_from") is not None for a in rec.get("attempt_log", []))
        row["skipped"] = bool(rec.get("skipped", False))
        row["steps"] = p.steps
        row["steps_completed"] = int(rec.get("steps_completed", 0) or 0)
        row["frames"] = int(rec.get("frames", 0) or 0)
        row["mesh_id"] = rec.get("mesh_id")
        row["vertices"] = int(rec.get("vertices", 0) or 0)
        row["tets"] = int(rec.get("tets", 0) or 0)
        for c in METRIC_COLUMNS:
            row[c] = _nan_if_none(m.get(c))
        row["runaway_step"] = rec.get("runaway_step")
        row["problems"] = "; ".join(rec.get("problems", []) or [])
        row["wall_s"] = _nan_if_none(rec.get("wall_s"))
        row["host"] = rec.get("host")
        row["result_sha256"] = rec.get("result_sha256")
        row["path"] = f"runs/{p.run_id}"
    df = pd.DataFrame(rows)
    for k, name in enumerate(names):
        df.insert(3 + k, name, _param_column([p.params.get(name) for p in plans]))
    # Counts that may be missing (a run that never ran, a projection that was off) as nullable integers.
    for c in ("runaway_step", "inverted", "final_inverted", "unconverged", "substeps"):
        df[c] = pd.array([_optional_int(r[c]) for r in rows], dtype="Int64")
    return df


def write_index(df, sweep_dir: Path) -> Path:
    """``DIR/index.parquet``, written atomically."""
    from ..io.atomic import atomic_path

    path = Path(sweep_dir) / INDEX
    with atomic_path(path) as tmp:
        df.to_parquet(tmp, index=False)
    return path


def read_index(sweep_dir) -> Any:
    """The index of the sweep in ``sweep_dir`` (``index.parquet``) as a DataFrame."""
    pd = require_pandas()
    path = Path(sweep_dir) / INDEX
    if not path.is_file():
        from ..errors import ConfigError

        raise ConfigError(f"{path}: no sweep index there (run fepr sweep SWEEP.toml --out {sweep_dir})")
    return pd.read_parquet(path)
