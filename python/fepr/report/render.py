"""Off-screen side-by-side video of a comparison: polyscope on EGL (Mesa's software renderer works), no display.

Each run is one panel: rows are integrators, columns are FEPR on / off; every panel uses the same camera (framing
every frame inside the band the overlays leave free), a ground grid only where the scene has a floor, and carries
the run's label, a frame counter and an energy readout (the energy error against the books,
:func:`fepr.report.metrics.energy_error_series`, and H/H0). Frames go to
``side_by_side.mp4`` (H.264 via imageio-ffmpeg) and ``side_by_side.gif`` (Pillow, scaled to at most
:data:`GIF_MAX_WIDTH` pixels wide).

Panel sizes are rounded down to multiples of 16 pixels so the video encoder does not rescale.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import FeprError, MissingDependencyError
from ..export.surface import boundary_surface
from .metrics import energy_error_series, format_value, length_scale
from .runs import RecordedRun
from .style import rgb

__all__ = ["RenderUnavailable", "VideoResult", "grid_layout", "render_video"]

_PS_STATE = {"ready": False, "error": None}
#: The GIF is scaled down to at most this width (pixels) to keep it small; the MP4 keeps the full size.
GIF_MAX_WIDTH = 720
_RUNAWAY_RGB = (224, 49, 49)


class RenderUnavailable(FeprError):
    """Off-screen rendering cannot start here (polyscope or an EGL driver is missing); the message says why."""


def _polyscope():
    """Import polyscope and initialise its EGL back end once per process."""
    if _PS_STATE["error"] is not None:
        raise RenderUnavailable(_PS_STATE["error"])
    try:
        import polyscope as ps
    except ImportError:
        msg = 'videos need polyscope and imageio-ffmpeg: pip install "fepr[compare]"'
        _PS_STATE["error"] = msg
        raise MissingDependencyError(msg) from None
    if not _PS_STATE["ready"]:
        try:
            ps.set_allow_headless_backends(True)
            ps.set_use_prefs_file(False)  # no .polyscope.ini in the working folder
            ps.set_program_name("fepr")
            ps.set_verbosity(0)
            ps.set_print_prefix("[polyscope] ")
            ps.init("openGL3_egl")
        except Exception as exc:  # polyscope raises RuntimeError subclasses from C++
            _PS_STATE["error"] = (
                f"polyscope could not open an off-screen EGL context ({exc}); on Debian/Ubuntu install "
                "libegl1 libegl-mesa0 libgl1-mesa-dri"
            )
            raise RenderUnavailable(_PS_STATE["error"]) from None
        ps.set_up_dir("z_up")
        ps.set_front_dir("neg_y_front")
        ps.set_ground_plane_height_mode("manual")
        ps.set_shadow_darkness(0.35)
        ps.set_background_color((1.0, 1.0, 1.0))
        ps.set_SSAA_factor(1)
        _PS_STATE["ready"] = True
    return ps


def _imageio_writer(path: Path, fps: float):
    try:
        import imageio.v2 as iio
    except ImportError:
        raise MissingDependencyError('videos need imageio and imageio-ffmpeg: pip install "fepr[compare]"') from None
    return iio.get_writer(
        str(path),
        fps=fps,
        codec="libx264",
        quality=7,
        macro_block_size=16,
        pixelformat="yuv420p",
        ffmpeg_log_level="error",
    )


class VideoResult:
    """What :func:`render_video` wrote: paths, frame count, size (pixels) and mean render time per frame (ms)."""

    def __init__(self, mp4: Path, gif: Path, frames: int, size: Tuple[int, int], ms_per_frame: float):
        self.mp4, self.gif, self.frames, self.size, self.ms_per_frame = mp4, gif, frames, size, ms_per_frame


def grid_layout(runs: Sequence[RecordedRun]) -> List[List[Optional[RecordedRun]]]:
    """Panels as rows (one per integrator, in comparison order) and columns (FEPR on, then off)."""
    integrators = sorted({r.spec.index for r in runs})
    cols = [p for p in (True, False) if any(r.spec.projection is p for r in runs)]
    grid: List[List[Optional[RecordedRun]]] = []
    for idx in integrators:
        row = []
        for proj in cols:
            match = [r for r in runs if r.spec.index == idx and r.spec.projection is proj]
            row.append(match[0] if match else None)
        grid.append(row)
    return grid


#: Polyscope's default vertical field of view, degrees.
FOV_DEG = 45.0
#: The share of the panel's height the body may fill (the overlays take the rest) and where its middle lies,
#: as a share of the height below the panel's centre.
FREE_BAND = 0.70
BAND_CENTRE_BELOW = 0.06


def _camera(center: np.ndarray, radius: float) -> Tuple[np.ndarray, np.ndarray]:
    """Eye and target that show a sphere of ``radius`` about ``center`` inside the free band of the panel."""
    half = np.radians(0.5 * FOV_DEG)
    distance = radius / np.sin(half) / FREE_BAND
    direction = np.array([0.5, -1.0, 0.35])
    direction /= np.linalg.norm(direction)
    # Aiming above the centre moves the body down in the image (away from the labels at the top).
    shift = 2.0 * BAND_CENTRE_BELOW * distance * np.tan(half)
    target = center + np.array([0.0, 0.0, shift])
    return target + direction * distance, target


def _sane_box(runs: Sequence[RecordedRun]) -> Tuple[np.ndarray, np.ndarray]:
    """Bounding box of every frame that stays within a few body sizes of the initial shapes (runaways excluded)."""
    first = np.concatenate([r.frames[0] for r in runs])
    lo0, hi0 = first.min(axis=0), first.max(axis=0)
    c0, r0 = 0.5 * (lo0 + hi0), max(0.5 * float(np.linalg.norm(hi0 - lo0)), 1e-9)
    lo, hi = lo0.copy(), hi0.copy()
    for run in runs:
        for x in run.frames:
            if np.all(np.isfinite(x)) and np.max(np.linalg.norm(x - c0, axis=1)) < 8.0 * r0:
                lo, hi = np.minimum(lo, x.min(axis=0)), np.maximum(hi, x.max(axis=0))
    return lo, hi


def _fonts(height: int):
    from PIL import ImageFont

    size = max(11, int(round(height / 24)))
    try:
        return ImageFont.load_default(size=size), ImageFont.load_default(size=int(size * 0.85))
    except TypeError:  # Pillow < 10.1: fixed bitmap font
        f = ImageFont.load_default()
        return f, f


def _boxed(d, xy, text: str, font, fill, pad: int = 3) -> None:
    """Text on a translucent white box (readable over the ground grid)."""
    x, y = xy
    left, top, right, bottom = d.textbbox((x, y), text, font=font)
    d.rounded_rectangle([left - pad, top - pad, right + pad, bottom + pad], radius=pad, fill=(255, 255, 255, 190))
    d.text((x, y), text, font=font, fill=fill + (255,))


def _overlay(img: np.ndarray, run: RecordedRun, k: int, nframes: int, fonts) -> np.ndarray:
    """Draw the run label, energy readout and frame counter onto an (h, w, 3) uint8 panel."""
    from PIL import Image, ImageDraw

    big, small = fonts
    im = Image.fromarray(img).convert("RGBA")
    layer = Image.new("RGBA", im.size, (0, 0, 0, 0))
    d = ImageDraw.Draw(layer)
    w, h = im.size
    pad = max(6, h // 60)
    step = int(run.frame_steps[k])
    hist = run.history
    row = min(step, len(hist["total"]) - 1)
    color = rgb(run.spec.color)
    line = int((big.size if hasattr(big, "size") else 12) * 1.45)
    sq = int(line * 0.55)
    d.rectangle([pad, pad + 4, pad + sq, pad + 4 + sq], fill=color + (255,))
    _boxed(d, (pad + sq + 8, pad), run.spec.label, big, color)
    h0 = hist["total"][0]
    H = hist["total"][row]
    ratio = H / h0 if h0 != 0 else float("nan")
    ratio_text = f"{ratio:.6f}" if abs(ratio) < 1e3 else f"{ratio:.2e}"
    K = hist["kinetic"][row]
    books = energy_error_series(
        hist, total_mass=run.total_mass, gravity=run.gravity, length_scale=length_scale(run.rest_positions)
    )[row]
    _boxed(d, (pad, pad + line), f"energy error {format_value('energy_error', books)}", big, (33, 37, 41))
    energies = f"H/H0 = {ratio_text}   K = {K:.3g} J   U = {H - K:.3g} J"
    _boxed(d, (pad, pad + 2 * line), energies, small, (52, 58, 64))
    times = hist["time"]
    dt = float(times[1] - times[0]) if len(times) > 1 else 0.0
    t = float(times[0]) + step * dt
    _boxed(d, (pad, h - pad - line), f"frame {k + 1}/{nframes}   step {step}   t = {t:.2f} s", small, (52, 58, 64))
    if run.runaway_step is not None and step >= run.runaway_step:
        msg = f"runaway at step {run.runaway_step}: the state became non-finite"
        tw = d.textlength(msg, font=small)
        _boxed(d, ((w - tw) / 2, h / 2 - line / 2), msg, small, _RUNAWAY_RGB)
    return np.asarray(Image.alpha_composite(im, layer).convert("RGB"))


def render_video(
    runs: Sequence[RecordedRun],
    out_dir,
    *,
    size: Tuple[int, int] = (640, 480),
    fps: float = 24.0,
    gif: bool = True,
    on_frame: Optional[Callable[[int], None]] = None,
    ground: Optional[float] = None,
) -> VideoResult:
    """Render the runs side by side into ``out_dir/side_by_side.mp4`` (and ``.gif``).

    Parameters
    ----------
    runs : sequence of RecordedRun
        Runs with the same frame steps (as :func:`fepr.cli.compare.compare` records them).
    size : (int, int)
        Width and height of one panel in pixels (rounded down to multiples of 16, at least 64).
    fps : float
        Frames per second of the videos.
    on_frame : callable, optional
        Called with 1 after each composite frame (progress).
    ground : float, optional
        The height (m) of the scene's floor, drawn as a grid; None (default): no floor.

    Raises
    ------
    RenderUnavailable, MissingDependencyError
        When polyscope, an EGL driver or imageio-ffmpeg is missing.
    """
    out_dir = Path(out_dir)
    pw, ph = (max(64, int(s) // 16 * 16) for s in size)
    ps = _polyscope()
    from PIL import Image

    grid = grid_layout(runs)
    nrows, ncols = len(grid), len(grid[0])
    nframes = min(len(r.frames) for r in runs)
    surf = boundary_surface(runs[0].tets)
    lo, hi = _sane_box(runs)
    center = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    ps.remove_all_structures()
    ps.set_window_size(pw, ph)
    # A floor only where the scene has one (a body falling in space over a grid looks as if it landed on it).
    if ground is None:
        ps.set_ground_plane_mode("none")
    else:
        ps.set_ground_plane_mode("tile")
        ps.set_ground_plane_height(float(ground))
    # Framing: the bounding sphere of every frame inside the band the overlays leave free (the labels take the
    # top sixth of the panel, the frame counter the bottom line), with polyscope's 45 degree vertical field of view.
    eye, target = _camera(center, radius)
    ps.look_at(tuple(eye), tuple(target))
    mesh = ps.register_surface_mesh("body", runs[0].frames[0], surf.faces, smooth_shade=False)
    mesh.set_edge_width(0.8)
    mesh.set_edge_color((0.15, 0.15, 0.15))
    fonts = _fonts(ph)
    mp4 = out_dir / "side_by_side.mp4"
    gif_path = out_dir / "side_by_side.gif"
    writer = _imageio_writer(mp4, fps)
    gif_frames = []
    blank = np.full((ph, pw, 3), 233, dtype=np.uint8)
    render_s = 0.0
    try:
        for k in range(nframes):
            t0 = time.perf_counter()
            canvas = np.full((nrows * ph, ncols * pw, 3), 255, dtype=np.uint8)
            for i, row in enumerate(grid):
                for j, run in enumerate(row):
                    if run is None:
                        panel = blank
                    else:
                        x = run.frames[k]
                        visible = bool(np.all(np.isfinite(x))) and float(np.max(np.abs(x - center))) < 50 * radius
                        mesh.set_enabled(visible)
                        if visible:
                            mesh.update_vertex_positions(x)
                            mesh.set_color(tuple(c / 255.0 for c in rgb(run.spec.color)))
                        shot = ps.screenshot_to_buffer(transparent_bg=False)
                        panel = _overlay(np.ascontiguousarray(shot[:ph, :pw, :3]), run, k, nframes, fonts)
                    canvas[i * ph : (i + 1) * ph, j * pw : (j + 1) * pw] = panel
            # thin separators between panels
            for j in range(1, ncols):
                canvas[:, j * pw - 1 : j * pw + 1] = 180
            for i in range(1, nrows):
                canvas[i * ph - 1 : i * ph + 1, :] = 180
            render_s += time.perf_counter() - t0
            writer.append_data(canvas)
            if gif:
                im = Image.fromarray(canvas)
                if im.width > GIF_MAX_WIDTH:
                    scale = GIF_MAX_WIDTH / im.width
                    im = im.resize((GIF_MAX_WIDTH, int(round(im.height * scale))), Image.LANCZOS)
                gif_frames.append(im.quantize(colors=128, method=Image.Quantize.FASTOCTREE))
            if on_frame is not None:
                on_frame(1)
    finally:
        writer.close()
        ps.remove_all_structures()
    if gif and gif_frames:
        gif_frames[0].save(
            gif_path,
            save_all=True,
            append_images=gif_frames[1:],
            duration=int(round(1000.0 / fps)),
            loop=0,
            optimize=False,
        )
    return VideoResult(mp4, gif_path, nframes, (ncols * pw, nrows * ph), 1e3 * render_s / max(nframes, 1))
