"""The simulation side of the viewer: a :class:`ViewerSession` steps a :class:`fepr.Simulation` in a background
thread, takes commands from the GUI (play, pause, step, reset, projection, integrator, dt, pace, drag), and
publishes snapshots (positions and a time series of energies and momenta) for the GUI to draw.

No viser here: the session is plain Python and testable on its own.

Drag spring. While a vertex ``i`` is dragged towards an anchor ``a`` (m), the simulation carries a spring
(:meth:`fepr.Simulation.set_drag`): a force ``F = k (a - x_i)`` (N), evaluated at the start of each step and
applied by the integrator like any external force. Its work ``W = F . (x_i* - x_i)`` (J, ``x_i*`` the base
step's result) enters the step's energy budget (history column ``work_forces``), so FEPR conserves the energy
*including* the spring's work instead of undoing the pull; :attr:`Snapshot.drag_work` sums ``work_forces`` over
the steps taken while dragging (with a constant scene ``force``, its work in those steps is included). Releasing calls
:meth:`fepr.Simulation.clear_drag`. The stiffness is ``k = min(20 M, m_i / (2 h^2))`` (N/m, M the total mass),
below the explicit stability limit of the spring alone. Pinned vertices cannot be dragged.

Summary. :attr:`Snapshot.metrics` is the run's summary (:func:`fepr.report.metrics.simulation_metrics`, the
numbers ``fepr run`` prints: energy error against the books, unresolved energy, P and L drift against the
targets, min J, inverted tets, unconverged projections) since the last reset or rebuild (projection, integrator
or dt change). It reads the whole history, so it is recomputed in the simulation thread at most every
:data:`METRICS_EVERY_S` seconds and within :data:`METRICS_BUDGET` of the wall time, and whenever the session is
paused or stepped by hand; in between, snapshots carry the last one.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from .. import _core
from ..errors import ConfigError, SimulationError
from ..report.metrics import RunMetrics, simulation_metrics

__all__ = ["Builder", "Snapshot", "ViewerSession"]

#: ``build(integrator, dt, projection)`` returns a fresh :class:`fepr.Simulation` in the initial state.
Builder = Callable[[str, float, bool], object]

SERIES = ("t", "kinetic", "potential", "total", "p", "l")

#: The live summary is recomputed at most this often (s of wall time) ...
METRICS_EVERY_S = 0.25
#: ... and takes at most this share of the wall time (a long history takes longer to read).
METRICS_BUDGET = 0.05


@dataclass
class Snapshot:
    """What the GUI draws: positions (m, 3) in m, the latest numbers, and the time series (each a list)."""

    version: int
    positions: np.ndarray
    time: float
    steps: int
    running: bool
    projection: bool
    integrator: str
    dt: float
    kinetic: float
    potential: float
    total: float
    momentum: float
    angular_momentum: float
    iterations: Optional[int]
    ms_per_step: float
    drag_work: float
    dragging: Optional[int]
    error: Optional[str]
    series: Dict[str, List[float]] = field(default_factory=dict)
    metrics: Optional[RunMetrics] = None


class ViewerSession:
    """A simulation stepped in a background thread.

    Parameters
    ----------
    build : callable
        ``build(integrator, dt, projection)`` -> a new :class:`fepr.Simulation` in its initial state.
    integrator : str
        Base integrator at start (one of ``fepr._core.INTEGRATORS``).
    dt : float
        Time step, s.
    projection : bool
        FEPR on at start.
    realtime : bool
        Pace simulated time to wall time (else step as fast as possible).
    max_points : int
        Length of the plotted time series (older points are dropped).
    log : callable, optional
        Called with one line of text for every command that changes the simulation (the CLI prints them).
    """

    def __init__(
        self,
        build: Builder,
        *,
        integrator: str,
        dt: float,
        projection: bool = True,
        realtime: bool = True,
        running: bool = True,
        max_points: int = 2000,
        log: Optional[Callable[[str], None]] = None,
    ):
        self._build = build
        self._check_integrator(integrator)
        self.integrator = integrator
        self.dt = float(dt)
        self.projection = bool(projection)
        self.realtime = bool(realtime)
        self.running = bool(running)
        self.max_points = int(max_points)
        self._log = log or (lambda line: None)
        self._commands: queue.Queue[Tuple[str, object]] = queue.Queue()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._version = 0
        self._error: Optional[str] = None
        self._drag: Optional[Tuple[int, np.ndarray]] = None
        self._sim = self._build(self.integrator, self.dt, self.projection)
        self._reset_counters()
        self._snapshot = self._take_snapshot()

    # ---- commands (any thread) --------------------------------------------------------------------------
    @staticmethod
    def _check_integrator(name: str) -> None:
        if name not in _core.INTEGRATORS:
            raise ConfigError(f"unknown integrator {name!r} (known: {', '.join(_core.INTEGRATORS)})")

    def play(self) -> None:
        self._commands.put(("running", True))

    def pause(self) -> None:
        self._commands.put(("running", False))

    def step_once(self) -> None:
        self._commands.put(("step", 1))

    def reset(self) -> None:
        self._commands.put(("reset", None))

    def set_projection(self, on: bool) -> None:
        self._commands.put(("projection", bool(on)))

    def set_integrator(self, name: str) -> None:
        self._check_integrator(name)
        self._commands.put(("integrator", name))

    def set_dt(self, dt: float) -> None:
        if not (dt > 0 and np.isfinite(dt)):
            raise ConfigError(f"dt must be a positive number of seconds, got {dt!r}")
        self._commands.put(("dt", float(dt)))

    def set_realtime(self, on: bool) -> None:
        self._commands.put(("realtime", bool(on)))

    def grab(self, point) -> int:
        """Start dragging the surface vertex nearest to ``point`` (m); returns its index."""
        x = self.snapshot().positions
        i = int(np.argmin(np.linalg.norm(x - np.asarray(point, dtype=np.float64), axis=1)))
        self._commands.put(("drag", (i, np.array(x[i]))))
        return i

    def drag_to(self, anchor) -> None:
        """Move the anchor of the drag spring to ``anchor`` (m)."""
        self._commands.put(("anchor", np.asarray(anchor, dtype=np.float64)))

    def release(self) -> None:
        self._commands.put(("release", None))

    # ---- snapshots ----------------------------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        with self._lock:
            return self._snapshot

    @property
    def simulation(self):
        """The current simulation (replaced when the integrator, dt or projection changes)."""
        return self._sim

    # ---- thread -------------------------------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="fepr-viewer-sim", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def run_pending(self) -> None:
        """Apply queued commands and take one step if running (what the thread does; for tests without it)."""
        self._apply_commands()
        if self.running or self._pending_steps:
            self._advance()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._apply_commands()
            if not (self.running or self._pending_steps) or self._error:
                self._pending_steps = 0
                time.sleep(0.01)
                continue
            self._advance()
            if self.realtime and self.running:
                lag = self._sim_time - (time.perf_counter() - self._wall0)
                if lag > 0:
                    time.sleep(min(lag, 0.1))
                elif lag < -0.25:  # too slow for real time: do not try to catch up
                    self._wall0 = time.perf_counter() - self._sim_time
            else:
                time.sleep(0)  # let the GUI thread in

    # ---- internals (simulation thread) --------------------------------------------------------------------
    def _reset_counters(self) -> None:
        self._series: Dict[str, List[float]] = {k: [] for k in SERIES}
        self._t_offset = 0.0
        self._sim_time = 0.0
        self._steps = 0
        self._drag_work = 0.0
        self._pending_steps = 0
        self._iterations: Optional[int] = None
        self._ms = 0.0
        self._wall0 = time.perf_counter()
        self._error = None
        self._metrics: Optional[RunMetrics] = None
        self._metrics_next = 0.0

    def _rebuild(self, keep_state: bool) -> None:
        x, v = np.array(self._sim.positions), np.array(self._sim.velocities)
        t = self._t_offset + float(self._sim.time)
        self._sim = self._build(self.integrator, self.dt, self.projection)
        if keep_state:
            self._sim.positions = x
            self._sim.velocities = v
            self._t_offset = t
        self._sync_drag()
        self._wall0 = time.perf_counter() - self._sim_time
        self._metrics_next = 0.0  # a new simulation: a new history

    def _apply_commands(self) -> None:
        changed = False
        while True:
            try:
                kind, value = self._commands.get_nowait()
            except queue.Empty:
                break
            changed = True
            if kind == "running":
                self.running = bool(value)
                self._wall0 = time.perf_counter() - self._sim_time
                self._log(f"running: {'yes' if self.running else 'no'}")
            elif kind == "step":
                self.running = False
                self._pending_steps += int(value)
            elif kind == "reset":
                self._sim = self._build(self.integrator, self.dt, self.projection)
                self._reset_counters()
                self._drag = None
                self._log("reset")
            elif kind == "projection":
                if bool(value) != self.projection:
                    self.projection = bool(value)
                    self._rebuild(keep_state=True)
                self._log(f"projection: {'on' if self.projection else 'off'}")
            elif kind == "integrator":
                if value != self.integrator:
                    self.integrator = str(value)
                    self._rebuild(keep_state=True)
                self._log(f"integrator: {self.integrator}")
            elif kind == "dt":
                if value != self.dt:
                    self.dt = float(value)
                    self._rebuild(keep_state=True)
                self._log(f"dt: {self.dt:g} s")
            elif kind == "realtime":
                self.realtime = bool(value)
                self._wall0 = time.perf_counter() - self._sim_time
                self._log(f"pace: {'real time' if self.realtime else 'as fast as possible'}")
            elif kind == "drag":
                i, anchor = value
                self._drag = (int(i), anchor)
                self._sync_drag()
                self._log(f"drag: vertex {i}")
            elif kind == "anchor":
                if self._drag is not None:
                    self._drag = (self._drag[0], value)
                    self._sync_drag()
            elif kind == "release":
                if self._drag is not None:
                    self._log(f"drag released: work {self._drag_work:.6g} J")
                self._drag = None
                self._sync_drag()
        if changed:
            self._publish()

    def _drag_stiffness(self, i: int) -> float:
        """``k = min(20 M, m_i / (2 h^2))``, N/m (see the module docstring)."""
        sim = self._sim
        h = float(sim.dt)
        return min(20.0 * float(sim.total_mass), 0.5 * float(sim.masses[i]) / (h * h))

    def _dragged(self) -> Optional[int]:
        """The vertex the spring pulls now (None: no drag, or a pinned vertex)."""
        if self._drag is None or bool(self._sim.pinned[self._drag[0]]):
            return None
        return self._drag[0]

    def _sync_drag(self) -> None:
        """Give the simulation the session's drag spring (or release it)."""
        i = self._dragged()
        if i is None:
            self._sim.clear_drag()
        else:
            self._sim.set_drag(i, self._drag[1], self._drag_stiffness(i))

    def _advance(self) -> None:
        sim = self._sim
        t0 = time.perf_counter()
        dragging = self._dragged() is not None
        try:
            sim.step(1)
        except (SimulationError, ConfigError) as exc:
            self._error = str(exc)
            self.running = False
            self._log(f"stopped: {exc}")
            self._publish()
            return
        if self._pending_steps:
            self._pending_steps -= 1
        if dragging:  # the spring's work, as the simulation put it into this step's budget
            self._drag_work += float(sim.last["work_forces"])
        self._steps += 1
        self._sim_time += float(sim.dt)
        rep = sim.last_projection
        self._iterations = None if rep is None else int(rep.iterations)
        self._ms = 1e3 * (time.perf_counter() - t0)
        self._publish()

    def _update_metrics(self) -> None:
        """Recompute the summary when it is due (see the module docstring), in the simulation thread."""
        now = time.perf_counter()
        if self.running and not self._pending_steps and now < self._metrics_next:
            return
        try:
            self._metrics = simulation_metrics(self._sim)
        except (KeyError, ValueError, IndexError):  # an unusual simulation (no history columns): no summary
            self._metrics = None
        cost = time.perf_counter() - now
        self._metrics_next = now + max(METRICS_EVERY_S, cost / METRICS_BUDGET)

    def _take_snapshot(self) -> Snapshot:
        sim = self._sim
        self._update_metrics()
        e = sim.energy()
        p = float(np.linalg.norm(sim.linear_momentum()))
        ang = float(np.linalg.norm(sim.angular_momentum()))
        t = self._t_offset + float(sim.time)
        s = self._series
        if not s["t"] or t != s["t"][-1]:
            for key, val in zip(SERIES, (t, e.kinetic, e.elastic + e.gravitational, e.total, p, ang)):
                s[key].append(float(val))
                if len(s[key]) > self.max_points:
                    del s[key][0]
        self._version += 1
        return Snapshot(
            version=self._version,
            positions=np.array(sim.positions),
            time=t,
            steps=self._steps,
            running=self.running,
            projection=self.projection,
            integrator=self.integrator,
            dt=self.dt,
            kinetic=float(e.kinetic),
            potential=float(e.elastic + e.gravitational),
            total=float(e.total),
            momentum=p,
            angular_momentum=ang,
            iterations=self._iterations,
            ms_per_step=self._ms,
            drag_work=self._drag_work,
            dragging=None if self._drag is None else self._drag[0],
            error=self._error,
            series={k: list(v) for k, v in s.items()},
            metrics=self._metrics,
        )

    def _publish(self) -> None:
        snap = self._take_snapshot()
        with self._lock:
            self._snapshot = snap
