"""Several bodies stepped together, touching each other: :class:`MultiBody`.

Each body is its own :class:`fepr.Simulation` (its own mesh, material, masses, pins and FEPR projection); the
bodies share the time step. With ``contact=True`` (the default) a step of the scene is every body's base step,
then contact between the bodies (``fepr_core::world::resolve_body_contacts``: each surface vertex of one body
against the other's surface triangles, equal and opposite impulses with restitution and Coulomb friction), then
every body's projection onto targets that include what the contact exchanged with it, so the scene's total energy,
momentum and angular momentum are conserved when nothing outside acts on it. With ``contact=False`` the bodies
pass through each other and each steps on its own (its trajectory bit-identical to running it alone).

:attr:`MultiBody.history` holds the totals of the system (energies summed, linear momentum summed, angular
momentum of the whole system about its centre of mass, energy budgets summed). Units are SI: m, s, kg, J.

Example::

    import fepr
    from fepr.multibody import MultiBody

    mat = fepr.NeoHookean(youngs_modulus=1e4, poisson_ratio=0.3)
    a = fepr.Simulation(fepr.meshes.box(), material=mat, density=100.0, dt=0.01)
    b = fepr.Simulation(fepr.meshes.ell(), material=mat, density=100.0, dt=0.01)
    system = MultiBody([a, b], names=["box", "ell"])
    system.step(100)
    print(system.history["total"][-1])           # J, the sum of both bodies' energies
    system.save_diagnostics("diagnostics.csv")
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np

from ._validate import compact_numbers
from .errors import ConfigError, SimulationError
from .simulation import Energy, History, Simulation, _read_only

__all__ = ["MultiBody", "TOTAL_COLUMNS"]

#: Columns of :attr:`MultiBody.history` summed over the bodies (when every body's history has them).
SUM_COLUMNS: Tuple[str, ...] = (
    "kinetic",
    "elastic",
    "gravitational",
    "total",
    "px",
    "py",
    "pz",
    "budget",
    "budget_total",
    "work_contact",
    "work_damping",
    "work_pins",
    "work_forces",
    "work_deferred",
    "contacts",
    "inverted",
    "base_ms",
    "proj_ms",
)
#: Columns of :attr:`MultiBody.history` that are the largest value over the bodies.
MAX_COLUMNS: Tuple[str, ...] = (
    "penetration",
    "proj_iterations",
    "proj_residual",
    "proj_initial_residual",
    "proj_fallback",
    "proj_bound_hit",
    "base_iterations",
    "base_energy_error",
    "runaway",
)
#: Columns of :attr:`MultiBody.history` that are the smallest value over the bodies.
MIN_COLUMNS: Tuple[str, ...] = ("min_j", "proj_converged")
#: Every column :attr:`MultiBody.history` can have, in order (``lx, ly, lz``: angular momentum of the system
#: about its centre of mass ``cx, cy, cz``).
TOTAL_COLUMNS: Tuple[str, ...] = (
    ("step", "time")
    + SUM_COLUMNS[:7]
    + ("lx", "ly", "lz", "cx", "cy", "cz")
    + SUM_COLUMNS[7:]
    + MAX_COLUMNS
    + MIN_COLUMNS
)


class MultiBody:
    """Several independent :class:`fepr.Simulation` bodies stepped together, with the totals of the system.

    Parameters
    ----------
    bodies : sequence of fepr.Simulation
        The bodies (at least one), all with the same time step ``dt`` (s) and at the same step and time.
    names : sequence of str, optional
        One unique name per body (default ``body1``, ``body2``, ...); used by :func:`fepr.scene.run_scene` in
        file names (``diagnostics_<name>.csv``).

    Notes
    -----
    contact : bool
        Whether the bodies collide with each other (default True); each always collides with its own obstacles.
    restitution, friction : float or sequence of float
        Each body's coefficients for contact with the other bodies (restitution in [0, 1], Coulomb friction >= 0;
        one number for all bodies). A pair takes the smaller restitution and the geometric mean of the frictions.

    Each body is projected separately, onto targets that include what contact with the other bodies did to it
    (its impulse, the moment of that impulse, its share of the kinetic energy): the impulses are equal and
    opposite at one point, so the bodies' targets add up to the scene's conserved totals. When every body uses
    Projective Dynamics, the bodies take their iterations together and contact between them is held inside their
    joint solve (constraints with equal and opposite forces); when every body uses backward Euler, they minimise
    their objectives together with the contact (penalty and friction rows) in one Newton solve; when every body
    uses XPBD, contact is answered after each substep; otherwise it is answered after the base step. An impact
    left deeper than a tenth of the finer body's mean edge is redone in up to 16 parts (history column
    ``base_substeps``). Bodies that start inside each other deeper than that are a :class:`SimulationError`
    naming both.

    Raises
    ------
    ConfigError
        For no bodies, an object that is not a :class:`fepr.Simulation`, the same simulation twice, different
        ``dt`` or start times, or bad names.
    """

    def __init__(
        self,
        bodies: Sequence[Simulation],
        names: Optional[Sequence[str]] = None,
        contact: bool = True,
        restitution: Union[float, Sequence[float]] = 1.0,
        friction: Union[float, Sequence[float]] = 0.0,
    ):
        if isinstance(bodies, Simulation):
            raise ConfigError("bodies must be a sequence of fepr.Simulation; got one Simulation (wrap it in a list)")
        bodies = list(bodies)
        if not bodies:
            raise ConfigError("MultiBody needs at least one body")
        for k, b in enumerate(bodies):
            if not isinstance(b, Simulation):
                raise ConfigError(f"bodies[{k}] must be a fepr.Simulation, got {type(b).__name__}")
        ids = [id(b) for b in bodies]
        if len(set(ids)) != len(ids):
            k = next(k for k, i in enumerate(ids) if ids.index(i) != k)
            raise ConfigError(f"bodies[{k}] is the same Simulation as bodies[{ids.index(ids[k])}]")
        if names is None:
            names = [f"body{k + 1}" for k in range(len(bodies))]
        else:
            if isinstance(names, str):
                raise ConfigError(f"names must be a sequence of strings, got the string {names!r}")
            names = list(names)
            if len(names) != len(bodies):
                raise ConfigError(f"names has {len(names)} entries but there are {len(bodies)} bodies")
            for k, n in enumerate(names):
                if not isinstance(n, str) or not n:
                    raise ConfigError(f"names[{k}] must be a non-empty string, got {n!r}")
            dup = [n for k, n in enumerate(names) if n in names[:k]]
            if dup:
                raise ConfigError(f"names must be unique; {dup[0]!r} is given twice")
        dt0 = bodies[0].dt
        for k, b in enumerate(bodies[1:], 1):
            if not math.isclose(b.dt, dt0, rel_tol=1e-12, abs_tol=0.0):
                raise ConfigError(
                    f"all bodies must have the same dt: {names[0]!r} has dt = {dt0!r} s, {names[k]!r} has {b.dt!r} s"
                )
            if b.num_steps != bodies[0].num_steps or b.time != bodies[0].time:
                raise ConfigError(
                    f"all bodies must start at the same step and time: {names[0]!r} is at step "
                    f"{bodies[0].num_steps} (t = {bodies[0].time!r} s), {names[k]!r} at step {b.num_steps} "
                    f"(t = {b.time!r} s)"
                )
        self._bodies: Tuple[Simulation, ...] = tuple(bodies)
        self._names: Tuple[str, ...] = tuple(names)
        if not isinstance(contact, bool):
            raise ConfigError(f"contact must be True or False, got {contact!r}")
        self.contact: bool = contact
        self._coefficients = [
            (e, mu)
            for e, mu in zip(
                _per_body(restitution, "restitution", self._names, 0.0, 1.0),
                _per_body(friction, "friction", self._names, 0.0, math.inf),
            )
        ]

    # --- the bodies --------------------------------------------------------------------------------------
    @property
    def bodies(self) -> Tuple[Simulation, ...]:
        """The bodies, in order."""
        return self._bodies

    @property
    def names(self) -> Tuple[str, ...]:
        """The body names, in order."""
        return self._names

    def __len__(self) -> int:
        return len(self._bodies)

    def __getitem__(self, key: Union[int, str]) -> Simulation:
        """A body by index or by name."""
        if isinstance(key, str):
            try:
                return self._bodies[self._names.index(key)]
            except ValueError:
                raise KeyError(f"no body named {key!r} (names: {', '.join(self._names)})") from None
        return self._bodies[key]

    @property
    def dt(self) -> float:
        """Time step, s (the same for every body)."""
        return float(self._bodies[0].dt)

    @property
    def num_steps(self) -> int:
        """Steps every body has completed."""
        return min(int(b.num_steps) for b in self._bodies)

    @property
    def time(self) -> float:
        """Simulated time every body has reached, s."""
        return min(float(b.time) for b in self._bodies)

    @property
    def offsets(self) -> np.ndarray:
        """Where each body's vertices start in the concatenated arrays, (bodies + 1,) int64."""
        counts = [len(b.rest_positions) for b in self._bodies]
        return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)

    @property
    def positions(self) -> np.ndarray:
        """Positions of all bodies concatenated in order, (n, 3) float64, m (a read-only copy). Setting it sets
        every body's positions from its rows (each body re-measures its references, as
        :attr:`Simulation.positions`)."""
        return _read_only(np.concatenate([np.asarray(b.positions) for b in self._bodies]))

    @positions.setter
    def positions(self, x) -> None:
        for b, part in zip(self._bodies, self._split(x, "positions")):
            b.positions = part

    @property
    def velocities(self) -> np.ndarray:
        """Velocities of all bodies concatenated in order, (n, 3) float64, m/s (a read-only copy); settable as
        :attr:`positions`."""
        return _read_only(np.concatenate([np.asarray(b.velocities) for b in self._bodies]))

    @velocities.setter
    def velocities(self, v) -> None:
        for b, part in zip(self._bodies, self._split(v, "velocities")):
            b.velocities = part

    def _split(self, a, what: str) -> list:
        """``a`` ((n, 3), the concatenated vertices) cut into the bodies' rows."""
        arr = np.asarray(a, dtype=np.float64)
        offs = self.offsets
        if arr.shape != (int(offs[-1]), 3):
            raise ConfigError(f"{what} must have shape ({int(offs[-1])}, 3) (all bodies' vertices), got {arr.shape}")
        return [arr[offs[k] : offs[k + 1]] for k in range(len(self._bodies))]

    def _body_of(self, vertex: int) -> Tuple[int, int]:
        """``(body, its vertex)`` of a vertex of the concatenated arrays."""
        offs = self.offsets
        if not 0 <= int(vertex) < int(offs[-1]):
            raise ConfigError(f"vertex {vertex} is out of range: the bodies have {int(offs[-1])} vertices")
        k = int(np.searchsorted(offs, int(vertex), side="right")) - 1
        return k, int(vertex) - int(offs[k])

    @property
    def pinned(self) -> np.ndarray:
        """Pinned-vertex mask of all bodies concatenated in order, (n,) bool."""
        return np.concatenate([np.asarray(b.pinned, dtype=bool) for b in self._bodies])

    def set_drag(self, vertex: int, target, stiffness: float) -> None:
        """Pull ``vertex`` (an index into the concatenated arrays) towards ``target`` ((3,) m) with a spring of
        ``stiffness`` N/m (the viewer's mouse drag); the other bodies are released."""
        k, i = self._body_of(vertex)
        for j, b in enumerate(self._bodies):
            if j == k:
                b.set_drag(i, target, stiffness)
            else:
                b.clear_drag()

    def clear_drag(self) -> None:
        """Release the drag spring."""
        for b in self._bodies:
            b.clear_drag()

    @property
    def last_projection(self):
        """The last step's projection report of the body that iterated most, or None (no projection)."""
        reports = [r for r in (b.last_projection for b in self._bodies) if r is not None]
        return max(reports, key=lambda r: r.iterations) if reports else None

    @property
    def rest_positions(self) -> np.ndarray:
        """Rest positions of all bodies concatenated in order, (n, 3) float64, m."""
        return np.concatenate([np.asarray(b.rest_positions) for b in self._bodies])

    @property
    def tets(self) -> np.ndarray:
        """Tets of all bodies, indices into the concatenated vertex arrays, (k, 4) int64."""
        offs = self.offsets
        return np.concatenate([np.asarray(b.tets, dtype=np.int64) + offs[k] for k, b in enumerate(self._bodies)])

    @property
    def masses(self) -> np.ndarray:
        """Lumped vertex masses of all bodies concatenated in order, (n,) float64, kg."""
        return np.concatenate([_vertex_masses(b) for b in self._bodies])

    @property
    def total_mass(self) -> float:
        """Total mass of the system, kg."""
        return float(sum(float(b.total_mass) for b in self._bodies))

    # --- stepping ----------------------------------------------------------------------------------------
    def step(self, n: int = 1, callback=None) -> int:
        """Advance every body ``n`` steps (each body in turn; the GIL is released while each steps); returns the
        steps taken. ``callback(system)`` as for :meth:`fepr.Simulation.step` (called after every batch; True
        stops). Ctrl-C stops at a step boundary that every body has reached.

        Raises
        ------
        SimulationError
            If a body runs away; the message names the body, ``err.body`` is its name and ``err.step`` the step
            that failed. The bodies after it in the list are not stepped, so the bodies before it are ahead:
            :attr:`num_steps` and :attr:`history` then cover the steps every body completed.
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ConfigError(f"n must be a non-negative integer, got {n!r}")
        if callback is not None and not callable(callback):
            raise ConfigError(f"callback must be callable, got {callback!r}")
        if self.contact and len(self._bodies) > 1:
            return self._step_together(int(n), callback)
        start = self.num_steps
        remaining = int(n)
        while remaining:
            # Rounds of one batch of the first body and as many steps of each other, so that the bodies stand at
            # the same step whenever control returns (a Ctrl-C during a round is raised after it).
            k, interrupted = None, None
            for name, b in zip(self._names, self._bodies):
                before = b.num_steps
                try:
                    if k is None:
                        try:
                            b.step(remaining, lambda _: True)  # one batch: the round's length
                        except KeyboardInterrupt as exc:
                            interrupted = exc
                        k = b.num_steps - before
                    else:
                        interrupted = self._catch_up(b, k) or interrupted
                except SimulationError as exc:
                    err = SimulationError(f"body {name!r}: {exc}")
                    err.step = getattr(exc, "step", None)  # type: ignore[attr-defined]
                    err.body = name  # type: ignore[attr-defined]
                    raise err from None
            if interrupted is not None:
                raise interrupted
            remaining -= k
            if callback is not None and callback(self) is True:
                break
        return self.num_steps - start

    @staticmethod
    def _catch_up(body: Simulation, k: int) -> Optional[KeyboardInterrupt]:
        """``k`` steps of ``body``, finished even through Ctrl-C (returned, for the caller to raise after the
        round), so that every body stands at the same step."""
        target = body.num_steps + k
        interrupted = None
        while body.num_steps < target:
            try:
                body.step(target - body.num_steps)
            except KeyboardInterrupt as exc:
                interrupted = exc
        return interrupted

    def _step_together(self, n: int, callback=None) -> int:
        """``n`` steps of all bodies at once, with contact between them (``fepr._core.step_bodies``), in batches
        of at most :attr:`fepr.Simulation.BATCH_SECONDS` (signals are handled between them)."""
        from . import _core

        remaining = n
        while remaining:
            before = [b.num_steps for b in self._bodies]
            try:
                remaining -= _core.step_bodies(
                    [b._sim for b in self._bodies], remaining, self._coefficients, Simulation.BATCH_SECONDS
                )
            except RuntimeError as exc:
                k, message = exc.args if len(exc.args) == 2 else (0, str(exc))
                message = compact_numbers(message)
                name = self._names[k]
                # The core numbers the bodies; the user named them.
                message = re.sub(r"\bbody (\d+)\b", lambda m: f"body {self._names[int(m.group(1))]!r}", message)
                err = SimulationError(message if message.startswith("body ") else f"body {name!r}: {message}")
                err.step = self._bodies[k].num_steps + 1  # type: ignore[attr-defined]
                err.body = name  # type: ignore[attr-defined]
                raise err from None
            finally:
                for b, k in zip(self._bodies, before):
                    b._after_batch(k)
            if callback is not None and callback(self) is True:
                break
        return n - remaining

    @property
    def coefficients(self) -> Tuple[Tuple[float, float], ...]:
        """Each body's ``(restitution, friction)`` for contact between bodies (a pair uses the smaller restitution
        and the geometric mean of the frictions)."""
        return tuple(self._coefficients)

    # --- measurements ------------------------------------------------------------------------------------
    def energy(self) -> Energy:
        """Kinetic, elastic, gravitational and total energy of the system (sums over the bodies), J."""
        parts = [b.energy() for b in self._bodies]
        return Energy(*(float(sum(getattr(e, f) for e in parts)) for f in Energy._fields))

    def linear_momentum(self) -> np.ndarray:
        """Total linear momentum, (3,) float64, kg m/s."""
        return np.sum([np.asarray(b.linear_momentum(), dtype=np.float64) for b in self._bodies], axis=0)

    def center_of_mass(self) -> np.ndarray:
        """Centre of mass of the system, (3,) float64, m."""
        w = self.masses
        return (w[:, None] * self.positions).sum(axis=0) / w.sum()

    def angular_momentum(self) -> np.ndarray:
        """Angular momentum of the system about its centre of mass, (3,) float64, kg m^2/s.

        ``L = sum_i (x_i - C) x m_i v_i`` over the vertices of all bodies, ``C`` the system centre of mass.
        """
        w, x, v = self.masses, self.positions, self.velocities
        c = (w[:, None] * x).sum(axis=0) / w.sum()
        return np.cross(x - c, w[:, None] * v).sum(axis=0)

    @property
    def history(self) -> History:
        """Per-step totals of the system (row 0: the initial state), as a :class:`fepr.History`.

        Columns (see :data:`TOTAL_COLUMNS`): ``step`` and ``time`` (s); ``kinetic``, ``elastic``,
        ``gravitational`` and ``total`` (J) and ``px, py, pz`` (kg m/s) summed; ``lx, ly, lz`` the angular
        momentum of the system about its centre of mass ``cx, cy, cz`` (kg m^2/s, m), from each body's
        momenta and centre of mass: ``L = sum_b [L_b + (c_b - C) x P_b]`` with ``L_b`` about ``c_b``. Where
        the bodies' histories have them: the energy budgets ``budget`` and ``budget_total`` (J), the work
        breakdown ``work_*`` (J), ``contacts``, ``inverted`` and the wall times ``base_ms``, ``proj_ms`` summed;
        ``penetration`` (m), ``proj_iterations``, residuals, ``base_energy_error`` and the flags ``runaway``,
        ``proj_fallback`` the largest over the bodies; ``min_j`` and ``proj_converged`` the smallest. Rows are
        the steps every body completed.
        """
        return self._history_slice(0, None)

    def _history_slice(self, start: int, stop: Optional[int]) -> History:
        """:attr:`history`'s rows ``[start, stop)`` (``stop`` None: the rows every body has), reading only those
        rows of the bodies' histories."""
        hs = [b.history for b in self._bodies]
        rows = min(len(h) for h in hs)
        stop = rows if stop is None else min(stop, rows)
        start = min(start, stop)
        sources = [lambda name, h=h: h._slice(name, start, stop) for h in hs]
        return self._totals(sources, [h.columns for h in hs], stop - start)

    def _totals(self, sources, columns, rows: int) -> History:
        """The system's columns from each body's (``sources[k](name)``: a (rows,) array of that column)."""
        common = set(columns[0])
        for c in columns[1:]:
            common &= set(c)
        cols: Dict[str, np.ndarray] = {}

        def stack(name: str) -> np.ndarray:
            return np.stack([np.asarray(src(name), dtype=np.float64) for src in sources])  # (bodies, rows)

        cols["step"] = np.asarray(sources[0]("step"), dtype=np.float64)
        cols["time"] = np.asarray(sources[0]("time"), dtype=np.float64)
        for name in SUM_COLUMNS[:7]:
            cols[name] = stack(name).sum(axis=0)
        masses = np.array([float(b.total_mass) for b in self._bodies])
        com = np.stack([stack("cx"), stack("cy"), stack("cz")], axis=-1)  # (bodies, rows, 3)
        mom = np.stack([stack("px"), stack("py"), stack("pz")], axis=-1)
        ang = np.stack([stack("lx"), stack("ly"), stack("lz")], axis=-1)
        c_sys = (masses[:, None, None] * com).sum(axis=0) / masses.sum()  # (rows, 3)
        l_sys = (ang + np.cross(com - c_sys[None], mom)).sum(axis=0)
        for a, axis in enumerate("xyz"):
            cols[f"l{axis}"] = l_sys[:, a]
        for a, axis in enumerate("xyz"):
            cols[f"c{axis}"] = c_sys[:, a]
        for name in SUM_COLUMNS[7:]:
            if name in common:
                cols[name] = stack(name).sum(axis=0)
        for name in MAX_COLUMNS:
            if name in common:
                cols[name] = stack(name).max(axis=0)
        for name in MIN_COLUMNS:
            if name in common:
                cols[name] = stack(name).min(axis=0)
        names = [c for c in TOTAL_COLUMNS if c in cols]
        data = np.stack([cols[c] for c in names], axis=1) if rows else np.zeros((0, len(names)))
        return History(data, names)

    def save_diagnostics(self, path: Union[str, Path]) -> None:
        """Write :attr:`history` (the totals) as CSV (one row per step, header of column names)."""
        self.history.to_csv(path)

    def save_checkpoint(self, path: Union[str, Path], *, history: bool = True) -> None:
        """Write every body's checkpoint (:meth:`fepr.Simulation.save_checkpoint`) and the system's names, contact
        switch and coefficients to one ``.npz`` file, atomically; :meth:`load_checkpoint` resumes it bit for bit."""
        from .checkpoint import save_multibody

        for b in self._bodies:
            b._take_history()
        save_multibody(self, path, history=history)

    @classmethod
    def load_checkpoint(cls, path: Union[str, Path], *, threads: Optional[int] = None) -> MultiBody:
        """A system resumed from :meth:`save_checkpoint`'s file (its next steps are the saved system's, bit for
        bit). Raises :class:`fepr.errors.CheckpointError` for a file that is not a multi-body checkpoint."""
        from .checkpoint import load_multibody

        return load_multibody(path, threads=threads)

    @property
    def last(self) -> Dict[str, float]:
        """The last row of :attr:`history` as ``{column: value}``, from each body's last row (O(1) in the
        steps)."""
        rows = [b.last for b in self._bodies]
        if len({r["step"] for r in rows}) > 1:  # the bodies stand at different steps (a body failed)
            return self.history.last
        return self._totals([lambda name, r=r: np.array([r[name]]) for r in rows], [list(r) for r in rows], 1).last

    @classmethod
    def from_scene(cls, scene, *, projection=None, base_dir: Union[str, Path, None] = None) -> MultiBody:
        """The system a scene with ``[[bodies]]`` describes (a path, a dict of sections or a
        :class:`fepr.scene.Scene`), as :meth:`fepr.Simulation.from_scene`."""
        from .scene import load_scene_from

        return load_scene_from(scene, base_dir).build_multibody(projection=projection)

    def to_meshio(self):
        """The bodies' current states concatenated as one ``meshio.Mesh`` (see :meth:`fepr.Simulation.to_meshio`;
        body ``b`` is points ``offsets[b]:offsets[b+1]``)."""
        from .interop import to_meshio

        return to_meshio(self)

    def to_pyvista(self):
        """:meth:`to_meshio` as a ``pyvista.UnstructuredGrid`` (needs ``pip install pyvista``)."""
        from .interop import to_pyvista

        return to_pyvista(self)

    def save_state(self, path: Union[str, Path]) -> None:
        """Write the system to a NumPy ``.npz`` file.

        Arrays: ``positions``, ``velocities``, ``rest_positions`` (n, 3), ``tets`` (k, 4) and ``masses`` (n,)
        of all bodies concatenated (as the properties of the same names), ``offsets`` (bodies + 1,): body ``b``
        is rows ``offsets[b]:offsets[b+1]``, ``names`` (bodies,) and ``time`` (s). The archive is written to exactly
        ``path`` (no ``.npz`` is appended to another suffix), atomically (:func:`fepr.io.npz.save_npz`).
        """
        from .io.npz import save_npz

        save_npz(
            path,
            dict(
                positions=self.positions,
                velocities=self.velocities,
                rest_positions=self.rest_positions,
                tets=self.tets,
                masses=self.masses,
                offsets=self.offsets,
                names=np.array(self._names),
                time=np.float64(self.time),
            ),
        )

    def __repr__(self) -> str:
        parts = ", ".join(f"{n}: {len(b.rest_positions)} vertices" for n, b in zip(self._names, self._bodies))
        return f"MultiBody({len(self)} bodies [{parts}], dt={self.dt}, t={self.time:.4g} s)"


def _per_body(value, name: str, names: Sequence[str], lo: float, hi: float) -> list:
    """One coefficient per body from a number or a sequence, each checked to lie in [lo, hi]."""
    values = list(value) if isinstance(value, (list, tuple, np.ndarray)) else [value] * len(names)
    if len(values) != len(names):
        raise ConfigError(f"{name} has {len(values)} entries but there are {len(names)} bodies")
    out = []
    for body, v in zip(names, values):
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float, np.integer, np.floating))
            or not (lo <= float(v) <= hi)
        ):
            bound = f"in [{lo:g}, {hi:g}]" if math.isfinite(hi) else f"a finite number >= {lo:g}"
            raise ConfigError(f"{name} of body {body!r} must be {bound}, got {v!r}")
        if not math.isfinite(float(v)):
            raise ConfigError(f"{name} of body {body!r} must be finite, got {v!r}")
        out.append(float(v))
    return out


def _vertex_masses(sim: Simulation) -> np.ndarray:
    w = np.asarray(sim.masses, dtype=np.float64)
    m = len(sim.rest_positions)
    if w.ndim == 2:
        w = w[:, 0]
    if w.ndim == 0:
        w = np.full(m, float(w))
    return w
