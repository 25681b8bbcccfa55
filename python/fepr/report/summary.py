"""``summary.md`` and ``summary.json`` of a comparison: one table row per run (numbers from the diagnostics).

The numbers are those of :func:`fepr.report.metrics.compute_metrics`; each cell is formatted by
:meth:`fepr.report.metrics.RunMetrics.cell` (:func:`format_cell` for one value), so a test (or a reader) can
recompute them from ``diagnostics.csv``. Under the table, each run's problems (a runaway, inverted tets at the
end, unconverged projections) and notes are listed.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from .metrics import FIELDS, LEGEND, RunMetrics, format_value

__all__ = ["COLUMNS", "LEGEND", "format_cell", "summary_json", "summary_markdown", "table_rows"]

#: (key, header) of the summary table: ``run``, ``integrator``, ``fepr`` and the keys of
#: :data:`fepr.report.metrics.FIELDS`.
COLUMNS = (("run", "run"), ("integrator", "integrator"), ("fepr", "FEPR")) + FIELDS


def format_cell(key: str, value: Any) -> str:
    """The text of one summary value (:func:`fepr.report.metrics.format_value`)."""
    return format_value(key, value)


def table_rows(runs: Sequence[Any], metrics: Sequence[RunMetrics]) -> List[Dict[str, str]]:
    """One dict of formatted cells per run (keys of :data:`COLUMNS`, plus ``problems`` and ``notes``: the
    run's phrases joined by ``"; "``, empty when none)."""
    rows = []
    for run, m in zip(runs, metrics):
        cells = {k: m.cell(k) for k, _ in FIELDS}
        cells.update(
            run=run.spec.label,
            integrator=run.spec.integrator,
            fepr=format_value("fepr", run.spec.projection),
            problems="; ".join(m.problems()),
            notes="; ".join(m.notes()),
        )
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
    flagged = [r for r in rows if r.get("problems") or r.get("notes")]
    if flagged:
        lines.append("")
        for r in flagged:
            parts = []
            if r.get("problems"):
                parts.append(f"**problems**: {r['problems']}")
            if r.get("notes"):
                parts.append(f"notes: {r['notes']}")
            lines.append(f"- {r['run']}: " + "; ".join(parts))
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
                "problems": m.problems(),
                "notes": m.notes(),
                "summary": m.summary_line(r.spec.label),
            }
            for r, m in zip(runs, metrics)
        ],
        "video": video,
    }
    path = Path(path)
    path.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n")
    return path
