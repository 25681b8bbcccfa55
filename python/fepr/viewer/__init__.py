"""Interactive viewer in the browser (viser): ``fepr view SCENE.toml | MESH`` and :func:`view`.

Play, pause, single step and reset; FEPR on or off live; integrator and dt; real-time or as-fast-as-possible
pace; live plots of K, U, H and |P|, |L|; colour by J (volume change) or energy density; drag a vertex with a
spring (its work enters the energy the projection conserves). Bound to 127.0.0.1 unless told otherwise.

Example::

    import fepr
    from fepr.viewer import view
    sim = fepr.Simulation(fepr.meshes.ell(), material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
                          node_mass=5.0, dt=1 / 30)
    sim.positions = 1.5 * sim.rest_positions
    view(sim)            # prints the URL; Ctrl-C stops

Needs the ``view`` extra: ``pip install "fepr[view]"``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np

from .. import _core
from ..errors import ConfigError
from .session import ViewerSession

__all__ = ["ViewerSession", "scene_builder", "serve_target", "simulation_builder", "view"]

#: Built-in mesh names accepted by ``fepr view``.
BUILTINS = ("ell", "box", "sphere", "cylinder")


def scene_builder(scene) -> Callable[[str, float, bool], object]:
    """``build(integrator, dt, projection)`` for a :class:`fepr.scene.Scene` (its initial state each time)."""
    from ..report.runs import scene_with_integrator

    def build(integrator: str, dt: float, projection: bool):
        sc = scene_with_integrator(scene, integrator)
        sc = dataclasses.replace(sc, integrator=dataclasses.replace(sc.integrator, dt=float(dt)))
        build_one = sc.build_multibody if sc.is_multibody else sc.build
        sim = build_one(projection=None if projection else False)
        first = sim.bodies[0] if sc.is_multibody else sim
        if projection and first.projection is None:
            sim = build_one(projection=True)
        return sim

    return build


def simulation_builder(sim) -> Callable[[str, float, bool], object]:
    """``build(integrator, dt, projection)`` for an existing :class:`fepr.Simulation`: same mesh, material,
    masses, gravity, pins and damping, started from ``sim``'s state at the time of this call."""
    import fepr

    x0, v0 = np.array(sim.positions), np.array(sim.velocities)
    masses = np.array(sim.masses)
    pinned = np.flatnonzero(np.asarray(sim.pinned))
    settings = sim.projection

    def build(integrator: str, dt: float, projection: bool):
        new = fepr.Simulation(
            sim.mesh,
            material=sim.material,
            node_mass=masses,
            integrator=integrator,
            dt=dt,
            projection=(settings or True) if projection else False,
            gravity=tuple(sim.gravity),
            pinned=pinned if len(pinned) else None,
            damping=sim.damping,
        )
        new.positions = x0
        new.velocities = v0
        return new

    return build


def _mesh_scene(target: str):
    """A scene for a bare mesh (a file or a builtin name): Neo-Hookean E = 1e4 Pa, nu = 0.3, 100 kg/m^3,
    stretched 1.2x about its centre of mass and released, no gravity."""
    from ..scene import scene_from_dict

    mesh = {"builtin": target} if target in BUILTINS else {"path": str(Path(target).resolve())}
    name = target if target in BUILTINS else Path(target).stem
    default = "implicit_euler" if "implicit_euler" in _core.INTEGRATORS else _core.INTEGRATORS[0]
    return scene_from_dict(
        {
            "scene": {"name": name, "description": "mesh stretched 1.2x and released"},
            "mesh": mesh,
            "material": {"model": "neo_hookean", "youngs_modulus": 1e4, "poisson_ratio": 0.3},
            "mass": {"density": 100.0},
            "initial": {"scale": 1.2, "scale_about": "centroid"},
            "integrator": {"name": default, "dt": 1.0 / 60.0},
            "world": {"gravity": [0.0, 0.0, 0.0]},
        },
        ".",
        source=str(target),
    )


def _load_target(target: Union[str, Path]):
    from ..scene import load_scene

    text = str(target)
    if text in BUILTINS:
        return _mesh_scene(text)
    path = Path(text)
    if not path.exists() and not Path(text + ".node").exists():
        raise ConfigError(
            f"not found: {text} (give a scene file .toml, a mesh file, or a builtin mesh: {', '.join(BUILTINS)})"
        )
    if path.suffix.lower() == ".toml":
        return load_scene(path)
    return _mesh_scene(text)


def view(
    target,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    integrator: Optional[str] = None,
    dt: Optional[float] = None,
    projection: Optional[bool] = None,
    paused: bool = False,
    block: bool = True,
    max_seconds: Optional[float] = None,
    log: Callable[[str], None] = print,
):
    """Open the interactive viewer for a simulation, a scene, or a scene/mesh file, and print its URL.

    Parameters
    ----------
    target : fepr.Simulation, fepr.scene.Scene, str or Path
        What to show. A simulation starts from its current state; a scene or a file from its initial state.
    host : str
        Address to bind (default ``127.0.0.1``: this machine only; ``0.0.0.0`` for every interface).
    port : int
        Port (0: a free one).
    integrator, dt, projection : optional
        Start with these instead of the target's own (integrator names from ``fepr._core.INTEGRATORS``;
        dt in s).
    paused : bool
        Start paused.
    block : bool
        Serve until Ctrl-C (default). With ``False`` the app is returned with its simulation thread running;
        call ``app.update()`` to push frames, and ``app.close()`` when done.
    max_seconds : float, optional
        Stop serving after this many seconds (``block=True`` only).

    Returns
    -------
    ViewerApp
    """
    from ..scene import Scene
    from ..simulation import Simulation
    from .app import ViewerApp

    if isinstance(target, Simulation):
        build = simulation_builder(target)
        name, start_int, start_dt = "simulation", target.integrator, target.dt
        start_proj = target.projection is not None
    else:
        scene = target if isinstance(target, Scene) else _load_target(target)
        build = scene_builder(scene)
        name, start_int, start_dt = scene.name, scene.integrator.name, scene.integrator.dt
        start_proj = scene.projection.enabled
    session = ViewerSession(
        build,
        integrator=integrator or start_int,
        dt=float(dt or start_dt),
        projection=start_proj if projection is None else bool(projection),
        running=not paused,
        log=lambda line: log(f"fepr view: {line}"),
    )
    app = ViewerApp(session, title=name, host=host, port=port, log=lambda line: log(f"fepr view: {line}"))
    log(f"fepr view: serving {name} at {app.url}  (Ctrl-C to stop)")
    if host not in ("127.0.0.1", "localhost", "::1"):
        log(f"fepr view: bound to {host}: other machines on the network can open it")
    if not block:
        session.start()
        return app
    app.run(max_seconds=max_seconds)
    return app


def serve_target(
    target: str,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    integrator: Optional[str] = None,
    dt: Optional[float] = None,
    paused: bool = False,
    max_seconds: Optional[float] = None,
) -> int:
    """What ``fepr view`` does: load the target, serve until Ctrl-C, return the exit status 0."""
    if integrator is not None and integrator not in _core.INTEGRATORS:
        raise ConfigError(f"unknown integrator {integrator!r} (known: {', '.join(_core.INTEGRATORS)})")
    scene = _load_target(target)

    def log(line: str) -> None:
        print(line, flush=True)

    view(scene, host=host, port=port, integrator=integrator, dt=dt, paused=paused, max_seconds=max_seconds, log=log)
    log("fepr view: stopped")
    return 0
