"""Colours and labels shared by the plots, the video panels, the viewer and the HTML report.

Projection on is drawn in warm colours, projection off in cool ones; within each family the shade follows the
integrator's position in the comparison, so a run has the same colour in every figure and in the video.
Runs with FEPR are solid lines, runs without are dashed.
"""

from __future__ import annotations

from typing import Tuple

__all__ = ["OFF_COLORS", "ON_COLORS", "run_color", "run_label", "rgb"]

#: Warm shades for runs with the projection (hex RGB).
ON_COLORS = ("#e8590c", "#c2255c", "#f08c00", "#a61e4d", "#d9480f")
#: Cool shades for runs without the projection (hex RGB).
OFF_COLORS = ("#1c7ed6", "#0b7285", "#5f3dc4", "#364fc7", "#495057")


def run_color(projection: bool, index: int = 0) -> str:
    """Hex colour of a run: warm with projection, cool without; ``index`` is the integrator's position."""
    family = ON_COLORS if projection else OFF_COLORS
    return family[index % len(family)]


def rgb(hex_color: str) -> Tuple[int, int, int]:
    """``"#rrggbb"`` as an ``(r, g, b)`` tuple of ints in 0..255."""
    h = hex_color.lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


def run_label(integrator: str, projection: bool) -> str:
    """Human-readable name of a run, e.g. ``"implicit_euler + FEPR"``."""
    return f"{integrator} + FEPR" if projection else f"{integrator}, no projection"
