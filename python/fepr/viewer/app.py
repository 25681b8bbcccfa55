"""The browser side of the viewer: a viser server showing a :class:`~fepr.viewer.session.ViewerSession`.

The simulation runs in the session's background thread; this module's loop (the caller's thread) pushes the
latest snapshot to the browser about 30 times a second: the surface (solid, or coloured by J or the energy
density), the drag spring, a status panel (with the run's summary from :mod:`fepr.report.metrics`, the numbers
``fepr run`` prints), and live plots of K, U, H and of |P|, |L|.
"""

from __future__ import annotations

import signal
import threading
import time
from typing import Callable, Optional

import numpy as np

from .. import _core
from ..errors import ConfigError, MissingDependencyError
from ..report.style import rgb, run_color
from .colors import COLOR_MODES, NUM_BINS, SurfaceColoring
from .session import ViewerSession

__all__ = ["ViewerApp"]

PACES = ("real time", "as fast as possible")
_FRAME_S = 1.0 / 30.0
_PLOT_S = 0.25


def _viser():
    try:
        import viser
    except ImportError:
        raise MissingDependencyError('the viewer needs viser: pip install "fepr[view]"') from None
    return viser



def _port_in_use(host: str, port: int) -> str:
    return f"port {port} on {host} is in use: give another --port, or --port 0 for any free port"


def _check_port(host: str, port: int) -> int:
    """``port`` if it can be bound on ``host`` now, else a ConfigError naming it."""
    import socket

    if not 0 < int(port) < 65536:
        raise ConfigError(f"port must be in 1..65535 (or 0 for any free port), got {port}")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, int(port)))
        except OSError:
            raise ConfigError(_port_in_use(host, port)) from None
    return int(port)


def _free_port(host: str) -> int:
    """A port that is free on ``host`` now."""
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])

class ViewerApp:
    """A viser server bound to ``host:port`` that shows and drives a :class:`ViewerSession`.

    Parameters
    ----------
    session : ViewerSession
        The simulation (started by :meth:`run` if it is not running yet).
    title : str
        Shown at the top of the control panel.
    host : str
        Address to bind; ``"127.0.0.1"`` (default) serves this machine only.
    port : int
        Port; 0 picks a free one (see :attr:`url`). A port in use is an error (viser alone would move to the
        next free port, and the URL the user expects would show another program or nothing).
    log : callable
        Receives one line per event (the URL, and every change the GUI makes).
    """

    def __init__(
        self,
        session: ViewerSession,
        *,
        title: str = "fepr",
        host: str = "127.0.0.1",
        port: int = 8080,
        log: Callable[[str], None] = print,
    ):
        viser = _viser()
        self.session = session
        self.log = log
        port = _free_port(host) if port == 0 else _check_port(host, port)
        self.server = viser.ViserServer(host=host, port=port, label=f"fepr: {title}", verbose=False)
        self.host = host
        self.port = int(self.server.get_port())
        if self.port != port:  # taken between the check and the bind
            self.server.stop()
            raise ConfigError(_port_in_use(host, port))
        sim = session.simulation
        self.coloring = SurfaceColoring(sim.rest_positions, sim.tets, getattr(sim, "material", None))
        self._mode = COLOR_MODES[0]
        self._last_version = -1
        self._last_plot = 0.0
        self._stop = threading.Event()
        self._build_scene(np.asarray(session.snapshot().positions))
        self._build_gui(title)

    @property
    def url(self) -> str:
        shown = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{shown}:{self.port}"

    # ---- scene -------------------------------------------------------------------------------------------
    def _build_scene(self, x: np.ndarray) -> None:
        scene = self.server.scene
        scene.set_up_direction("+z")
        lo, hi = x.min(axis=0), x.max(axis=0)
        center = 0.5 * (lo + hi)
        radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
        size = float(max(10.0 * radius, 2.0))
        scene.add_grid(
            "/ground",
            width=size,
            height=size,
            plane="xy",
            cell_size=size / 40.0,
            section_size=size / 8.0,
            position=(float(center[0]), float(center[1]), float(lo[2]) - 1e-3 * radius),
        )
        self._solid = scene.add_mesh_simple(
            "/body/solid", x.astype(np.float32), self.coloring.faces.astype(np.uint32), color=self._solid_color()
        )
        self._bins = []
        for b in range(NUM_BINS):
            h = scene.add_mesh_simple(
                f"/body/bin{b}",
                x.astype(np.float32),
                self.coloring.faces[:1].astype(np.uint32),
                color=(200, 200, 200),
                visible=False,
            )
            self._bins.append(h)
        self._spring = scene.add_line_segments(
            "/drag/spring",
            points=np.zeros((1, 2, 3), dtype=np.float32),
            colors=(20, 20, 20),
            line_width=3.0,
            visible=False,
        )
        for handle in [self._solid] + self._bins:
            handle.on_drag("left")(self._on_drag)
        eye = center + radius * 3.0 * np.array([0.55, -1.0, 0.55])

        @self.server.on_client_connect
        def _(client) -> None:
            client.camera.position = tuple(float(c) for c in eye)
            client.camera.look_at = tuple(float(c) for c in center)
            client.camera.up_direction = (0.0, 0.0, 1.0)

    def _solid_color(self):
        return rgb(run_color(self.session.snapshot().projection))

    def _on_drag(self, event) -> None:
        if event.phase == "start":
            i = self.session.grab(event.start_position)
            self.session.drag_to(event.end_position)
            self.log(f"grab vertex {i}")
        elif event.phase == "update":
            self.session.drag_to(event.end_position)
        else:
            self.session.release()

    # ---- GUI ---------------------------------------------------------------------------------------------
    def _build_gui(self, title: str) -> None:
        gui = self.server.gui
        s = self.session
        snap = s.snapshot()
        gui.add_markdown(f"**fepr** · {title}")
        self._play = gui.add_button("Pause" if snap.running else "Play")
        step = gui.add_button("Step")
        reset = gui.add_button("Reset")
        self._proj = gui.add_checkbox("FEPR projection", initial_value=snap.projection)
        integ = gui.add_dropdown("Integrator", tuple(_core.INTEGRATORS), initial_value=snap.integrator)
        dt = gui.add_number("dt (s)", initial_value=float(snap.dt), min=1e-6, max=1.0, step=1e-4)
        pace = gui.add_dropdown("Pace", PACES, initial_value=PACES[0] if s.realtime else PACES[1])
        color = gui.add_dropdown("Colour", COLOR_MODES, initial_value=COLOR_MODES[0])
        self._legend = gui.add_markdown("")
        gui.add_markdown("Drag a vertex with the left mouse button to pull it with a spring.")
        self._status = gui.add_markdown("")
        series = ({"label": "t (s)"},)
        self._energy_plot = gui.add_uplot(
            data=(np.zeros(1),) * 4,
            series=series
            + (
                {"label": "K (J)", "stroke": "#1c7ed6", "width": 2},
                {"label": "U (J)", "stroke": "#2f9e44", "width": 2},
                {"label": "H (J)", "stroke": "#e8590c", "width": 2.5},
            ),
            scales={"x": {"time": False}},
            title="energy",
            aspect=1.6,
        )
        self._momentum_plot = gui.add_uplot(
            data=(np.zeros(1),) * 3,
            series=series
            + (
                {"label": "|P| (kg m/s)", "stroke": "#5f3dc4", "width": 2},
                {"label": "|L| (kg m²/s)", "stroke": "#c2255c", "width": 2},
            ),
            scales={"x": {"time": False}},
            title="momentum",
            aspect=1.6,
        )

        @self._play.on_click
        def _(_event) -> None:
            if s.snapshot().running:
                s.pause()
            else:
                s.play()

        @step.on_click
        def _(_event) -> None:
            s.step_once()

        @reset.on_click
        def _(_event) -> None:
            s.reset()

        @self._proj.on_update
        def _(_event) -> None:
            s.set_projection(bool(self._proj.value))

        @integ.on_update
        def _(_event) -> None:
            s.set_integrator(str(integ.value))

        @dt.on_update
        def _(_event) -> None:
            if dt.value and dt.value > 0:
                s.set_dt(float(dt.value))

        @pace.on_update
        def _(_event) -> None:
            s.set_realtime(pace.value == PACES[0])

        @color.on_update
        def _(_event) -> None:
            self._mode = str(color.value)
            self._last_version = -1  # redraw
            self.log(f"colour: {self._mode}")

    # ---- updates -----------------------------------------------------------------------------------------
    def update(self, force: bool = False) -> None:
        """Push the latest snapshot to the browser if it changed (call from one thread only)."""
        snap = self.session.snapshot()
        if snap.version == self._last_version and not force:
            return
        self._last_version = snap.version
        x = np.asarray(snap.positions)
        with np.errstate(over="ignore"):
            xf = x.astype(np.float32)
        # A run that blows up (an unprojected explicit step at a large dt) can leave positions that float32 cannot
        # hold: the body then stays where it was last drawn, but its colour and the status (FEPR off, the error)
        # still follow the run.
        drawable = bool(np.all(np.isfinite(xf)))
        if self._mode == COLOR_MODES[0] or not drawable:
            if drawable:
                self._solid.vertices = xf
            self._solid.color = rgb(run_color(snap.projection))
            self._solid.visible = True
            for h in self._bins:
                h.visible = False
            self._legend.content = ""
        else:
            faces, palette, legend = self.coloring.bins(self._mode, x)
            self._solid.visible = False
            for h, f, c in zip(self._bins, faces, palette):
                if len(f):
                    h.vertices = xf
                    h.faces = f.astype(np.uint32)
                    h.color = c
                    h.visible = True
                else:
                    h.visible = False
            self._legend.content = legend
        if snap.dragging is not None and self.session._drag is not None and drawable:
            anchor = np.asarray(self.session._drag[1], dtype=np.float32)
            self._spring.points = np.stack([xf[snap.dragging], anchor])[None]
            self._spring.visible = True
        else:
            self._spring.visible = False
        self._play.label = "Pause" if snap.running else "Play"
        now = time.perf_counter()
        if force or now - self._last_plot >= _PLOT_S:
            self._last_plot = now
            self._status.content = self._status_text(snap)
            ser = snap.series
            if ser["t"]:
                t = np.asarray(ser["t"])
                self._energy_plot.data = (
                    t,
                    np.asarray(ser["kinetic"]),
                    np.asarray(ser["potential"]),
                    np.asarray(ser["total"]),
                )
                self._momentum_plot.data = (t, np.asarray(ser["p"]), np.asarray(ser["l"]))

    @staticmethod
    def _status_text(snap) -> str:
        it = "-" if snap.iterations is None else str(snap.iterations)
        lines = [
            f"t = {snap.time:.3f} s · step {snap.steps} · {snap.integrator} · dt {snap.dt:g} s · "
            f"FEPR {'on' if snap.projection else 'off'}",
            f"H = {snap.total:.6g} J (K {snap.kinetic:.4g}, U {snap.potential:.4g})",
            f"|P| = {snap.momentum:.4g} kg m/s · |L| = {snap.angular_momentum:.4g} kg m²/s",
            f"projection iterations {it} · {snap.ms_per_step:.2f} ms/step · drag work {snap.drag_work:.4g} J",
        ]
        m = snap.metrics
        if m is not None:  # the summary fepr run prints (fepr.report.metrics), since the last reset or change
            lines.append(" · ".join(m.summary_parts()[1:-2]))
            if m.problems():
                lines.append("**problems:** " + ", ".join(m.problems()))
        if snap.error:
            lines.append(f"**stopped:** {snap.error}")
        return "  \n".join(lines)

    # ---- lifetime ----------------------------------------------------------------------------------------
    def run(self, max_seconds: Optional[float] = None) -> None:
        """Serve until Ctrl-C (or SIGTERM, or ``max_seconds``), then shut down cleanly."""
        self.session.start()
        previous = None
        if threading.current_thread() is threading.main_thread():
            previous = signal.getsignal(signal.SIGTERM)
            signal.signal(signal.SIGTERM, _raise_interrupt)
        start = time.perf_counter()
        try:
            while not self._stop.is_set():
                if max_seconds is not None and time.perf_counter() - start > max_seconds:
                    break
                self.update()
                time.sleep(_FRAME_S)
        except KeyboardInterrupt:
            self.log("shutting down")
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
            self.close()

    def stop(self) -> None:
        """Ask :meth:`run` to return (from another thread)."""
        self._stop.set()

    def close(self) -> None:
        self.session.stop()
        self.server.stop()


def _raise_interrupt(signum, frame):  # noqa: ARG001
    raise KeyboardInterrupt
