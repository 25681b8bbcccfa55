"""``report.html``: one self-contained page (images and videos linked by relative paths) per comparison, or one
page with a section per scene for ``fepr demo``."""

from __future__ import annotations

import html
from typing import Dict, Optional, Sequence

from .summary import COLUMNS, LEGEND

__all__ = ["report_page", "report_section"]

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2rem auto; max-width: 1280px;
       color: #212529; padding: 0 1rem; }
h1 { font-size: 1.7rem; } h2 { font-size: 1.3rem; margin-top: 2.5rem; border-bottom: 1px solid #dee2e6; }
video, img { max-width: 100%; border: 1px solid #dee2e6; border-radius: 4px; }
table { border-collapse: collapse; font-size: 0.9rem; margin: 1rem 0; }
th, td { padding: 0.3rem 0.6rem; border-bottom: 1px solid #e9ecef; text-align: right; white-space: nowrap; }
th:nth-child(-n+3), td:nth-child(-n+3) { text-align: left; }
th { background: #f8f9fa; }
.swatch { display: inline-block; width: 0.8rem; height: 0.8rem; border-radius: 2px; margin-right: 0.4rem;
          vertical-align: -1px; }
.note { color: #495057; font-size: 0.9rem; }
.problem { color: #c92a2a; }
.plots { display: flex; flex-direction: column; gap: 0.8rem; }
"""


def _table(rows: Sequence[Dict[str, str]], colors: Sequence[str]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h in COLUMNS)
    body = []
    for r, c in zip(rows, colors):
        cells = []
        for k, _ in COLUMNS:
            text = html.escape(r[k])
            if k == "run":
                text = f'<span class="swatch" style="background:{c}"></span>{text}'
            cells.append(f"<td>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _problems(rows: Sequence[Dict[str, str]]) -> str:
    """The runs' problems and notes (as under the table of ``summary.md``), or nothing."""
    items = []
    for r in rows:
        parts = []
        if r.get("problems"):
            parts.append(f'<strong class="problem">problems: {html.escape(r["problems"])}</strong>')
        if r.get("notes"):
            parts.append(f"notes: {html.escape(r['notes'])}")
        if parts:
            items.append(f"<li>{html.escape(r['run'])}: {'; '.join(parts)}</li>")
    return f'<ul class="note">{"".join(items)}</ul>' if items else ""


def report_section(
    title: str,
    *,
    description: str,
    setup: str,
    rows: Sequence[Dict[str, str]],
    colors: Sequence[str],
    prefix: str = "",
    video: bool = True,
    diagnostics: Sequence[str] = (),
    note: Optional[str] = None,
) -> str:
    """An HTML ``<section>`` for one comparison; file names are relative to the page, under ``prefix``."""
    p = html.escape(prefix)
    parts = [f"<section><h2>{html.escape(title)}</h2>"]
    if description:
        parts.append(f"<p>{html.escape(description)}</p>")
    if setup:
        parts.append(f'<p class="note">{html.escape(setup)}</p>')
    if video:
        parts.append(
            f'<video controls loop autoplay muted playsinline src="{p}side_by_side.mp4">'
            f'<img src="{p}side_by_side.gif" alt="side-by-side animation"></video>'
            f'<p class="note">Also as <a href="{p}side_by_side.gif">GIF</a>.</p>'
        )
    elif note:
        parts.append(f'<p class="note">{html.escape(note)}</p>')
    parts.append(_table(rows, colors))
    problems = _problems(rows)
    if problems:
        parts.append(problems)
    parts.append(
        f'<div class="plots"><img src="{p}energy.png" alt="energy over time">'
        f'<img src="{p}momentum.png" alt="momentum over time"></div>'
    )
    if diagnostics:
        links = ", ".join(f'<a href="{p}{html.escape(d)}">{html.escape(d)}</a>' for d in diagnostics)
        parts.append(
            f'<p class="note">Diagnostics (one row per step): {links}. Summary: '
            f'<a href="{p}summary.md">summary.md</a>.</p>'
        )
    parts.append("</section>")
    return "\n".join(parts)


def report_page(title: str, sections: Sequence[str], *, intro: str = "") -> str:
    """A complete HTML page from sections, with the legend of the table columns."""
    legend = "".join(f"<li>{html.escape(line[2:]).replace('**', '')}</li>" for line in LEGEND)
    intro_html = f"<p>{html.escape(intro)}</p>" if intro else ""
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>"
        f"<h1>{html.escape(title)}</h1>{intro_html}"
        + "\n".join(sections)
        + f'<h2>Columns</h2><ul class="note">{legend}</ul>'
        + '<p class="note">Warm colours: FEPR on; cool colours: projection off (the base integrator alone).</p>'
        + "</body></html>\n"
    )
