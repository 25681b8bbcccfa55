"""Energy and momentum plots of a comparison (matplotlib, off-screen ``Agg`` back end).

``energy.png``: total energy H(t) (J) and the energy error against the books |H - (H0 + budget)| / |H0|
(log scale; :func:`fepr.report.metrics.energy_error_series`), one curve per run.
``momentum.png``: |P(t)| (kg m/s) and |L(t)| about the centre of mass (kg m^2/s), one curve per run.
Colours follow :mod:`fepr.report.style`: warm with FEPR (solid), cool without (dashed). A run that ran away is
marked with a cross where it stopped, and the axes are scaled to the runs that did not.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import MissingDependencyError
from .metrics import energy_error_series, length_scale
from .runs import RecordedRun

__all__ = ["energy_plot", "momentum_plot"]


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt
    except ImportError:
        raise MissingDependencyError(
            'plots need matplotlib: pip install "fepr[compare]" (or pip install matplotlib)'
        ) from None
    return plt


def _style(ax, title: str, ylabel: str) -> None:
    ax.set_title(title, fontsize=12, loc="left")
    ax.set_xlabel("time (s)", fontsize=11)
    ax.set_ylabel(ylabel, fontsize=11)
    ax.grid(True, color="#dee2e6", linewidth=0.8)
    ax.tick_params(labelsize=10)
    for side in ("top", "right"):
        ax.spines[side].set_visible(False)


def _label(run: RecordedRun) -> str:
    if run.runaway_step is not None:
        return f"{run.spec.label} (runaway at step {run.runaway_step})"
    return run.spec.label


def _limits(values: List[np.ndarray], log: bool) -> Optional[Tuple[float, float]]:
    v = np.concatenate([a[np.isfinite(a)] for a in values]) if values else np.zeros(0)
    if log:
        v = v[v > 0]
    if v.size == 0:
        return None
    lo, hi = float(v.min()), float(v.max())
    if log:
        return lo / 3.0, hi * 3.0
    pad = 0.08 * (hi - lo) if hi > lo else max(abs(hi) * 0.05, 1e-12)
    return lo - pad, hi + pad


def _panel(
    ax,
    runs: Sequence[RecordedRun],
    series: Callable[[RecordedRun], np.ndarray],
    log: bool,
    min_span: Optional[float] = None,
) -> None:
    """One curve per run; linear panels span at least ``min_span`` (so a conserved quantity reads as flat)."""
    sane = []
    for run in runs:
        t = run.history["time"]
        y = series(run)
        ls = "-" if run.spec.projection else "--"
        ax.plot(t, y, ls, color=run.spec.color, linewidth=2.0, label=_label(run))
        if run.runaway_step is not None:
            ax.plot(t[-1:], y[-1:], "x", color=run.spec.color, markersize=9, markeredgewidth=2.5)
        else:
            sane.append(y)
    everything = [series(r) for r in runs]
    lim = _limits(everything if log else (sane or everything), log)
    if not log and lim is not None and min_span is not None:
        mid = 0.5 * (lim[0] + lim[1])
        half = max(0.5 * (lim[1] - lim[0]), 0.5 * min_span)
        lim = (mid - half, mid + half)
        ax.ticklabel_format(axis="y", useOffset=False)
    if log:
        ax.set_yscale("log")
    if lim is not None:
        ax.set_ylim(*lim)


def _finish(fig, axes, path: Path, title: str) -> Path:
    handles, labels = axes[0].get_legend_handles_labels()
    fig.suptitle(title, fontsize=13, x=0.01, ha="left", fontweight="bold")
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=10, frameon=False)
    fig.tight_layout(rect=(0, 0.1 + 0.04 * ((len(labels) - 1) // 4), 1, 0.95))
    fig.savefig(path, dpi=110, facecolor="white")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _span(runs: Sequence[RecordedRun], series: Callable[[RecordedRun], np.ndarray]) -> float:
    """10% of the largest initial value (at least a tiny positive number)."""
    return max(0.1 * max(abs(float(series(r)[0])) for r in runs), 1e-12)


def energy_plot(runs: Sequence[RecordedRun], path, *, title: str = "") -> Path:
    """Write ``energy.png``: H(t) in J and the energy error against the books on a log scale, one curve per
    run. Returns the path."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))

    def total(r: RecordedRun) -> np.ndarray:
        return r.history["total"]

    def rel(r: RecordedRun) -> np.ndarray:
        err = energy_error_series(
            r.history, total_mass=r.total_mass, gravity=r.gravity, length_scale=length_scale(r.rest_positions)
        )
        return np.maximum(err, 1e-17)

    h0 = max(abs(float(r.history["total"][0])) for r in runs)
    _panel(axes[0], runs, total, log=False, min_span=0.1 * h0)
    _style(axes[0], "total energy H = K + U", "H (J)")
    _panel(axes[1], runs, rel, log=True)
    _style(axes[1], "energy error against the books", "|H - (H0 + budget)| / |H0|")
    return _finish(fig, axes, Path(path), title or "energy")


#: A momentum panel whose every run stays within this share of its scale of its initial value shows a line saying
#: so instead of a curve (a curve would only draw round-off, on an axis scaled to it).
CONSERVED = 1e-9


def momentum_plot(runs: Sequence[RecordedRun], path, *, title: str = "") -> Path:
    """Write ``momentum.png``: |P(t)| and |L(t)| (about the centre of mass), one curve per run. A quantity that no
    run changes beyond round-off (within :data:`CONSERVED` of its scale: the largest |P| of the runs, and that times
    the body's size for |L|) is not drawn: its panel says that it is conserved, and to how much."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))

    def p(r: RecordedRun) -> np.ndarray:
        return np.linalg.norm(np.stack([r.history[c] for c in ("px", "py", "pz")], axis=1), axis=1)

    def ang(r: RecordedRun) -> np.ndarray:
        return np.linalg.norm(np.stack([r.history[c] for c in ("lx", "ly", "lz")], axis=1), axis=1)

    sane = [r for r in runs if r.runaway_step is None] or list(runs)
    p_scale = max(max(float(np.nanmax(p(r))) for r in sane), 1e-300)
    size = max(length_scale(r.rest_positions) for r in runs)
    panels = (
        (axes[0], p, "linear momentum |P|", "|P| (kg m/s)", "kg m/s", p_scale),
        (axes[1], ang, "angular momentum |L| (about the centre of mass)", "|L| (kg m²/s)", "kg m²/s", size * p_scale),
    )
    for ax, series, name, ylabel, unit, scale in panels:
        drift = max(float(np.nanmax(np.abs(series(r) - series(r)[0]))) for r in sane)
        if drift <= CONSERVED * scale:
            for r in runs:  # the legend still lists every run
                ax.plot([], [], "-" if r.spec.projection else "--", color=r.spec.color, linewidth=2.0, label=_label(r))
            ax.text(0.5, 0.5, f"conserved in every run:\nchanges by at most {drift:.1e} {unit}\n(round-off)",
                    ha="center", va="center", transform=ax.transAxes, fontsize=11, color="0.3")  # fmt: skip
            ax.set_yticks([])
            ax.set_xticks([])
            _style(ax, name, "")
            continue
        _panel(ax, runs, series, log=False, min_span=_span(runs, series))
        if ax.get_ylim()[0] < 0:  # a magnitude: the axis starts at 0
            ax.set_ylim(bottom=0.0)
        _style(ax, name, ylabel)
    pinned = any(r.pinned for r in runs)
    note = " (pinned: the supports exchange momentum with the body)" if pinned else ""
    return _finish(fig, axes, Path(path), (title or "momentum") + note)
