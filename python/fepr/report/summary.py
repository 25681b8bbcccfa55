"""``summary.md`` and ``summary.json`` of a comparison: one table row per run (numbers from the diagnostics).

The numbers are those of :func:`fepr.report.metrics.compute_metrics`; each cell is formatted by
:func:`format_cell`, so a test (or a reader) can recompute them from ``diagnostics.csv``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from .metrics import RunMetrics

__all__ = ["COLUMNS", "format_cell", "summary_json", "summary_markdown", "table_rows"]

#: (key, header) of the summary table; keys of :class:`RunMetrics` plus ``run``, ``integrator``, ``fepr``.
COLUMNS = (
    ("run", "run"),
    ("integrator", "integrator"),
    ("fepr", "FEPR"),
    ("steps", "steps"),
    ("final_h_ratio", "final H/H0"),
    ("max_dh", "max |dH|/H0"),
    ("p_drift", "P drift"),
    ("l_drift", "L drift"),
    ("min_j", "min J"),
    ("mean_iterations", "mean proj. iters"),
    ("ms_per_step", "ms/step"),
)

LEGEND = (
    "- **final H/H0**: total energy at the end over the initial one; **max |dH|/H0**: largest relative energy "
    "error over the run.",
    "- **P drift**: largest |P - P0 - M g t| relative to the momentum scale; **L drift**: largest |L - L0| "
    "(about the centre of mass) relative to its scale; n/a when vertices are pinned (the supports exchange "
    "momentum with the body).",
    "- **min J**: smallest volume ratio det F over all tets and steps (J <= 0: inverted).",
    "- **mean proj. iters**: FEPR iterations per step; **ms/step**: mean of the base step's and the "
    "projection's own wall time (`base_ms + proj_ms` in the diagnostics).",
)


def format_cell(key: str, value: Any) -> str:
    """The text of one summary cell (``n/a`` for a missing value, ``-`` for no projection)."""
    if value is None:
        return "-" if key == "mean_iterations" else "n/a"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, int) or key == "steps":
        return str(value)
    if isinstance(value, str):
        return value
    v = float(value)
    if not math.isfinite(v):
        return str(v)
    if key == "final_h_ratio":
        return f"{v:.9f}" if abs(v) < 1e6 else f"{v:.3e}"
    if key in ("mean_iterations",):
        return f"{v:.2f}"
    if key == "ms_per_step":
        return f"{v:.3f}"
    if key == "min_j":
        return f"{v:.4g}"
    return f"{v:.2e}"


def table_rows(runs: Sequence[Any], metrics: Sequence[RunMetrics]) -> List[Dict[str, str]]:
    """One dict of formatted cells per run (keys of :data:`COLUMNS`)."""
    rows = []
    for run, m in zip(runs, metrics):
        values: Dict[str, Any] = m.as_dict()
        values.update(run=run.spec.label, integrator=run.spec.integrator, fepr=run.spec.projection)
        cells = {k: format_cell(k, values[k]) for k, _ in COLUMNS}
        if m.runaway_step is not None:
            cells["steps"] = f"{m.steps} (runaway at {m.runaway_step})"
        rows.append(cells)
    return rows


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def summary_markdown(title: str, description: str, setup: str, rows: Sequence[Dict[str, str]]) -> str:
    """The Markdown text of ``summary.md``: a heading, the set-up line, the table and its legend."""
    lines = [f"# {title}", ""]
    if description:
        lines += [description, ""]
    if setup:
        lines += [setup, ""]
    lines.append("| " + " | ".join(_md_escape(h) for _, h in COLUMNS) + " |")
    lines.append("|" + "|".join("---" if i < 3 else "---:" for i in range(len(COLUMNS))) + "|")
    for r in rows:
        lines.append("| " + " | ".join(_md_escape(r[k]) for k, _ in COLUMNS) + " |")
    lines += [""] + list(LEGEND) + [""]
    return "\n".join(lines)


def summary_json(
    path,
    *,
    scene: str,
    setup: Dict[str, Any],
    runs: Sequence[Any],
    metrics: Sequence[RunMetrics],
    video: Optional[Dict[str, Any]] = None,
) -> Path:
    """Write the summary as JSON (full precision): scene, set-up (M, g, R, dt, ...), one entry per run."""
    data = {
        "scene": scene,
        "setup": setup,
        "runs": [
            {
                "label": r.spec.label,
                "integrator": r.spec.integrator,
                "projection": r.spec.projection,
                "folder": r.spec.folder,
                "color": r.spec.color,
                **m.as_dict(),
            }
            for r, m in zip(runs, metrics)
        ],
        "video": video,
    }
    path = Path(path)
    path.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n")
    return path
