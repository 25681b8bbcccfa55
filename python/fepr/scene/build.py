"""Validated settings -> objects: meshes, materials, integrators, the projection, world objects, simulations.

The ``make``/``build`` methods of the settings in :mod:`fepr.scene.schema` call these functions. This module
imports the schema for type hints only, so the dependency runs one way (schema -> build) and the settings stay
plain data that any module can import. Every error names the scene file and the section (``[mesh]``,
``[[bodies]] #2 [material]``, ``[[world.obstacles]] #1:``), as the parser's do.
"""

from __future__ import annotations

import contextlib
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from .._validate import _user_stacklevel
from ..errors import ConfigError, ImplausibleValueWarning, MeshError

if TYPE_CHECKING:
    from .schema import (
        BodySettings,
        InitialSettings,
        IntegratorSettings,
        KinematicPinSettings,
        ObstacleSettings,
        PinBelow,
        ProjectionSettings,
        Scene,
        Vec3,
    )

# The options each integrator takes from ``[integrator]`` (the others take none).
_INTEGRATOR_OPTIONS = {
    "implicit_euler": ("tolerance", "max_iterations"),
    "projective_dynamics": ("iterations",),
    "xpbd": ("iterations", "substeps"),
}


# --------------------------------------------------------------------------------------------------------
# One setting, one object
# --------------------------------------------------------------------------------------------------------


def make_integrator(s: IntegratorSettings):
    """The integrator object of ``[integrator]`` (its name for an integrator without options); a ConfigError
    names an option the integrator lacks."""
    import fepr

    given = {
        k: getattr(s, k) for k in ("tolerance", "max_iterations", "iterations", "substeps") if getattr(s, k) is not None
    }
    extra = sorted(set(given) - set(_INTEGRATOR_OPTIONS.get(s.name, ())))
    if extra:
        raise ConfigError(f"[integrator] {', '.join(extra)} is not an option of {s.name!r}")
    types = {
        "implicit_euler": fepr.ImplicitEuler,
        "projective_dynamics": fepr.ProjectiveDynamics,
        "xpbd": fepr.Xpbd,
    }
    return types[s.name](**given) if s.name in types else s.name


def make_projection(s: ProjectionSettings):
    """``False`` when ``[projection]`` is disabled, else a :class:`fepr.Projection` with the given options."""
    if not s.enabled:
        return False
    import fepr

    return fepr.Projection(**s.options())


def make_obstacle(o: ObstacleSettings):
    """The obstacle object of one ``[[world.obstacles]]`` entry (:class:`fepr.Plane`, ...)."""
    from .. import world

    try:
        motion = None if o.motion is None else make_obstacle_motion(o.motion)
        if o.type == "mesh":
            g = o.geometry
            if "terrain" in g:
                terrain = world.MeshObstacle.terrain(
                    **g["terrain"], restitution=o.restitution, friction=o.friction, motion=motion
                )
                if not g.get("flip_normals"):
                    return terrain
                return world.MeshObstacle(
                    (terrain.vertices, terrain.triangles), o.restitution, o.friction, flip_normals=True, motion=motion
                )
            return world.MeshObstacle(
                g["path"], o.restitution, o.friction, flip_normals=g.get("flip_normals", False), motion=motion
            )
        cls = {"plane": world.Plane, "sphere": world.Sphere, "box": world.Box, "capsule": world.Capsule}[o.type]
        return cls(**o.geometry, restitution=o.restitution, friction=o.friction, motion=motion)
    except MeshError as exc:
        raise MeshError(f"{o.label}: {exc}") from None
    except (ConfigError, ValueError, TypeError) as exc:
        raise ConfigError(f"{o.label}: {exc}") from None


def make_obstacle_motion(m: Dict[str, Any]):
    """The :class:`fepr.ObstacleMotion` of an obstacle's parsed ``motion`` table."""
    from .. import world

    kind = m.get("translation")
    if kind == "sinusoidal":
        path = world.Sinusoid(amplitude=m["amplitude"], frequency=m["frequency"], phase=m["phase"])
    elif kind == "keyframes":
        path = world.Keyframes(
            times=np.asarray(m["times"], dtype=np.float64), offsets=np.asarray(m["offsets"], dtype=np.float64)
        )
    else:
        path = None
    return world.ObstacleMotion(
        translation=path,
        angular_velocity=m["angular_velocity"],
        pivot=m["pivot"],
        orientation_times=m.get("orientation_times", ()),
        orientations=m.get("orientations", ()),
    )


def kinematic_pin_indices(kp: KinematicPinSettings, rest_vertices: np.ndarray) -> np.ndarray:
    """Sorted vertex indices (int64) of a kinematic pin for a mesh with these rest vertices (m)."""
    m = len(rest_vertices)
    if kp.vertices is not None:
        for i in kp.vertices:
            if not 0 <= i < m:
                raise ConfigError(f"{kp.label}: vertices: vertex index {i} out of range (mesh has {m} vertices)")
        return np.unique(np.asarray(kp.vertices, dtype=np.int64))
    assert kp.below is not None
    return vertices_below(rest_vertices, kp.below, f"{kp.label}: below")


def make_motion(kp: KinematicPinSettings):
    """The motion of a kinematic pin (:class:`fepr.Sinusoid` or :class:`fepr.Keyframes`)."""
    from .. import world

    try:
        if kp.motion == "sinusoidal":
            return world.Sinusoid(amplitude=kp.amplitude, frequency=kp.frequency, phase=kp.phase)
        return world.Keyframes(
            times=np.asarray(kp.times, dtype=np.float64), offsets=np.asarray(kp.offsets, dtype=np.float64)
        )
    except (ConfigError, ValueError, TypeError) as exc:
        raise ConfigError(f"{kp.label}: {exc}") from None


def make_kinematic_pins(kp: KinematicPinSettings, rest_vertices: np.ndarray):
    """The :class:`fepr.KinematicPins` of one entry for a mesh with these rest vertices (m)."""
    idx = kinematic_pin_indices(kp, rest_vertices)
    from .. import world

    try:
        return world.KinematicPins(vertices=idx, motion=make_motion(kp))
    except (ConfigError, ValueError, TypeError) as exc:
        raise ConfigError(f"{kp.label}: {exc}") from None


# --------------------------------------------------------------------------------------------------------
# One body: mesh, material, pins, initial state
# --------------------------------------------------------------------------------------------------------


def load_body_mesh(scene: Scene, body: BodySettings):
    """The rest mesh (:class:`fepr.TetMesh`) of a body after its ``[mesh]`` load options."""
    import fepr

    m = body.mesh
    where = scene._where()
    sec = body.section("mesh")
    if m.path is not None:
        try:
            return fepr.load_mesh(str(m.path), **m.load_options())
        except MeshError as exc:
            msg = str(exc)
            if str(m.path) not in msg and m.path.name not in msg:
                msg = f"{m.path}: {msg}"
            raise MeshError(f"{where}{sec} {msg}") from None
    assert m.builtin is not None
    try:
        from .. import meshes

        mesh = meshes.builtin(m.builtin, **m.builtin_options)
    except (ConfigError, MeshError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{where}{sec} builtin {m.builtin!r}: {exc}") from None
    if m.load_options():
        from ..io import transform_mesh

        try:
            mesh = transform_mesh(mesh, **m.load_options())
        except ConfigError as exc:
            raise ConfigError(f"{where}{sec} {exc}") from None
    return mesh


def make_body_material(scene: Scene, body: BodySettings):
    """The material object of a body (:class:`fepr.NeoHookean`, :class:`fepr.StableNeoHookean`, ...)."""
    import fepr

    mat = body.material
    try:
        kw: Dict[str, Any] = {}
        if mat.j0 is not None:
            kw["j0"] = mat.j0
        cls = fepr.materials.MATERIAL_TYPES[mat.model]
        with located_warnings(scene, body):
            return cls(youngs_modulus=mat.youngs_modulus, poisson_ratio=mat.poisson_ratio, **kw)
    except ConfigError as exc:
        raise ConfigError(f"{scene._where()}{body.section('material')} {exc}") from None


@contextlib.contextmanager
def located_warnings(scene: Scene, body: BodySettings) -> Iterator[None]:
    """Re-issue the :class:`~fepr.errors.ImplausibleValueWarning` of the block with the scene file and the section of
    the parameter in front (``scene.toml: [mass] density = 1e+07 kg/m^3 is implausible ...``); other warnings pass
    through unchanged."""
    sections = {
        "density": body.section("mass"),
        "node_mass": body.section("mass"),
        "youngs_modulus": body.section("material"),
        "dt": "[integrator]",
    }
    with warnings.catch_warnings(record=True) as caught:
        yield
    for w in caught:
        if issubclass(w.category, ImplausibleValueWarning):
            parameter = getattr(w.message, "parameter", "")
            section = sections.get(parameter)
            label = f"{section} " if section else ""
            again = ImplausibleValueWarning(f"{scene._where()}{label}{w.message}")
            again.parameter = parameter
            warnings.warn(again, stacklevel=_user_stacklevel())
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)


def body_pinned(scene: Scene, body: BodySettings, rest_vertices: np.ndarray) -> Optional[np.ndarray]:
    """Sorted indices of a body's pinned vertices (``pinned`` and ``pin_below``), or ``None``."""
    where = scene._where()
    label = body.pins_label()
    m = len(rest_vertices)
    idx: List[int] = []
    for i in body.pinned:
        if not 0 <= i < m:
            raise ConfigError(f"{where}{label} pinned: vertex index {i} out of range (mesh has {m} vertices)")
        idx.append(i)
    if body.pin_below is not None:
        idx.extend(int(i) for i in vertices_below(rest_vertices, body.pin_below, f"{where}{label} pin_below"))
    if not idx:
        return None
    return np.unique(np.asarray(idx, dtype=np.int64))


def check_pin_overlap(scene: Scene, body: BodySettings, rest_vertices: np.ndarray) -> None:
    """Raise a ConfigError naming both keys if a vertex is held by a static pin (``pinned``, ``pin_below``) and
    moved by a kinematic pin, or moved by two kinematic pins: a vertex cannot both stay where it is and follow a
    path (before, the kinematic pin silently won)."""
    if not body.kinematic_pins:
        return
    where = scene._where()
    label = body.pins_label()
    m = len(rest_vertices)
    static: List[Tuple[str, np.ndarray]] = []
    if body.pinned:
        static.append(("pinned", np.unique(np.asarray([i for i in body.pinned if 0 <= i < m], dtype=np.int64))))
    if body.pin_below is not None:
        pb = body.pin_below
        static.append(
            (f"pin_below ({pb.axis} <= {pb.value:g})", vertices_below(rest_vertices, pb, f"{where}{label} pin_below"))
        )
    groups: List[Tuple[str, np.ndarray]] = []
    for kp in body.kinematic_pins:
        try:
            idx = kinematic_pin_indices(kp, rest_vertices)
        except ConfigError as exc:
            raise ConfigError(f"{where}{exc}") from None
        for key, other in static:
            both = np.intersect1d(idx, other)
            if both.size:
                raise ConfigError(
                    f"{where}{kp.label}: {_vertices_text(both)} also held by {label} {key}: a vertex cannot both stay "
                    f"fixed (a static pin) and follow a path (a kinematic pin); remove {_it(both)} from one of the two"
                )
        for other_label, other in groups:
            both = np.intersect1d(idx, other)
            if both.size:
                raise ConfigError(
                    f"{where}{kp.label}: {_vertices_text(both)} also moved by {other_label}: a vertex can follow "
                    f"only one path; remove {_it(both)} from one of the two"
                )
        groups.append((kp.label, idx))


def _it(idx: np.ndarray) -> str:
    return "it" if idx.size == 1 else "them"


def _vertices_text(idx: np.ndarray) -> str:
    """``vertex 3 is`` or ``4 vertices (3, 7, 8, 9) are`` (at most 5 listed)."""
    if idx.size == 1:
        return f"vertex {int(idx[0])} is"
    shown = ", ".join(str(int(i)) for i in idx[:5]) + (", ..." if idx.size > 5 else "")
    return f"{idx.size} vertices ({shown}) are"


def vertices_below(rest_vertices: np.ndarray, pb: PinBelow, label: str) -> np.ndarray:
    """Indices (int64) of the vertices whose rest coordinate along ``pb.axis`` is ``<= pb.value``; a ConfigError
    starting with ``label`` when there is none."""
    # The parser accepts only "x", "y" and "z".
    coord = np.asarray(rest_vertices)[:, "xyz".index(pb.axis)]
    below = np.flatnonzero(coord <= pb.value)
    if below.size == 0:
        raise ConfigError(f"{label}: no vertex has {pb.axis} <= {pb.value} (lowest {pb.axis} is {coord.min():.6g})")
    return below.astype(np.int64)


def initial_state(
    ini: InitialSettings,
    rest_vertices: np.ndarray,
    masses: np.ndarray,
    pinned: Optional[np.ndarray],
    where: str,
    kinematic: Sequence[np.ndarray] = (),
) -> Tuple[np.ndarray, np.ndarray]:
    """Initial positions and velocities, each (m, 3) float64 (see :class:`fepr.scene.InitialSettings`). Pinned
    and kinematically pinned vertices start at rest (a kinematic pin then moves them)."""
    rest = np.asarray(rest_vertices, dtype=np.float64)
    m = len(rest)
    w = _vertex_masses(masses, m)
    x = rest.copy()
    if ini.scale != 1.0:
        if ini.scale_about is None:
            about = np.zeros(3)
        elif isinstance(ini.scale_about, str):
            about = _centre_of_mass(rest, w)
        else:
            about = np.asarray(ini.scale_about, dtype=np.float64)
        x = about + ini.scale * (rest - about)
    if ini.translate is not None:
        x = x + np.asarray(ini.translate, dtype=np.float64)
    v = np.zeros_like(x)
    if ini.velocity is not None:
        v += np.asarray(ini.velocity, dtype=np.float64)
    if ini.angular_velocity is not None:
        c = _centre_of_mass(x, w)
        v += np.cross(np.asarray(ini.angular_velocity, dtype=np.float64), x - c)
    if ini.velocities is not None:
        v += _load_velocities(ini.velocities, m, where)
    if ini.alternating_velocity is not None:
        v[0::2] += np.asarray(ini.alternating_velocity, dtype=np.float64)
    if pinned is not None and len(pinned):
        v[pinned] = 0.0
    for k in kinematic:
        v[k] = 0.0
    return x, v


def _vertex_masses(masses: np.ndarray, m: int) -> np.ndarray:
    w = np.asarray(masses, dtype=np.float64)
    if w.ndim == 2:  # per-coordinate masses (m, 3)
        w = w[:, 0]
    if w.ndim == 0:
        w = np.full(m, float(w))
    return w


def _centre_of_mass(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    return (w[:, None] * x).sum(axis=0) / w.sum()


def _load_velocities(path: Path, m: int, where: str) -> np.ndarray:
    # Memory-mapped first: the shape in the .npy header is checked (against the file's size by numpy, then against
    # the mesh here) before anything is read, so a header declaring 1e10 rows cannot allocate 224 GiB.
    try:
        arr = np.load(path, allow_pickle=False, mmap_mode="r")
    except (OSError, ValueError, MemoryError) as exc:
        raise ConfigError(f"{where} velocities: cannot read {path}: {exc}") from None
    if isinstance(arr, np.lib.npyio.NpzFile):
        arr.close()
    if not isinstance(arr, np.ndarray):
        raise ConfigError(f"{where} velocities: {path} must hold one array (a .npy file)")
    if arr.shape != (m, 3):
        raise ConfigError(f"{where} velocities: {path} has shape {arr.shape}, expected ({m}, 3)")
    try:
        arr = np.array(arr, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where} velocities: {path} must hold numbers, got dtype {arr.dtype}: {exc}") from None
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{where} velocities: {path} contains NaN or infinite values")
    return arr


# --------------------------------------------------------------------------------------------------------
# The scene: one simulation per body
# --------------------------------------------------------------------------------------------------------


def build_multibody(scene: Scene, projection=None):
    """A :class:`fepr.multibody.MultiBody` of :func:`build_bodies`, named after the bodies."""
    from ..multibody import MultiBody

    bodies = scene.body_settings()
    return MultiBody(
        build_bodies(scene, projection),
        names=[b.name for b in bodies],
        restitution=[b.restitution for b in bodies],
        friction=[b.friction for b in bodies],
    )


def build_bodies(scene: Scene, projection=None) -> list:
    """One :class:`fepr.Simulation` per body (:meth:`fepr.scene.Scene.body_settings`), each in its initial state.

    ``projection`` overrides ``[projection]``. The shared settings (integrator, projection, gravity, damping,
    obstacles, run threads) are the same for every body; ``[world] force`` is split over the free vertices of
    all bodies in proportion to mass.
    """
    if projection is None:
        try:
            projection = scene.projection.make()
        except ConfigError as exc:
            raise ConfigError(f"{scene._where()}[projection] {exc}") from None
    obstacles = [o.make() for o in scene.world.obstacles]
    sims = []
    free_masks = []
    for body in scene.body_settings():
        sim, free = _build_body(scene, body, projection, obstacles)
        sims.append(sim)
        free_masks.append(free)
    force = scene.world.force
    if force is not None and any(c != 0.0 for c in force):
        for sim, f in zip(sims, distribute_force(force, sims, free_masks)):
            sim.set_external_forces(f)
    return sims


def _build_body(scene: Scene, body: BodySettings, projection, obstacles: list) -> Tuple[Any, np.ndarray]:
    """The :class:`fepr.Simulation` of one body in its initial state, and its free-vertex mask (not pinned,
    not kinematically pinned) for spreading ``[world] force``."""
    import fepr

    where = scene._where()
    world = scene.world
    mesh = load_body_mesh(scene, body)
    material = make_body_material(scene, body)
    rest = np.asarray(mesh.vertices, dtype=np.float64)
    pinned = body_pinned(scene, body, rest)
    check_pin_overlap(scene, body, rest)
    kin = []
    for kp in body.kinematic_pins:
        try:
            kin.append(kp.make(rest))
        except ConfigError as exc:
            raise ConfigError(f"{where}{exc}") from None
    kwargs: Dict[str, Any] = {}
    if body.mass.node_mass is not None:
        kwargs["node_mass"] = body.mass.node_mass
    else:
        kwargs["density"] = body.mass.density
    if scene.run.threads is not None:
        kwargs["threads"] = scene.run.threads
    # The world options are passed only when used, so scenes without them need nothing new.
    if obstacles:
        kwargs["obstacles"] = obstacles
    if kin:
        kwargs["kinematic_pins"] = kin
    if world.air_damping:
        kwargs["air_damping"] = world.air_damping
    if world.rayleigh_damping:
        kwargs["rayleigh_damping"] = world.rayleigh_damping
    if body.self_contact is not None:
        kwargs["self_contact"] = body.self_contact
    try:
        with located_warnings(scene, body):
            sim = fepr.Simulation(
                mesh,
                material=material,
                integrator=scene.integrator.make(),
                dt=scene.integrator.dt,
                projection=projection,
                gravity=world.gravity,
                pinned=pinned,
                damping=world.damping,
                **kwargs,
            )
    except ConfigError as exc:
        label = f"{body.label}: " if body.label else ""
        raise ConfigError(f"{where}{label}{exc}") from None
    kinematic = [np.asarray(k.vertices, dtype=np.int64) for k in kin]
    if not body.initial.is_rest():
        x, v = initial_state(
            body.initial,
            np.asarray(sim.rest_positions),
            np.asarray(sim.masses),
            pinned,
            where + body.section("initial"),
            kinematic=kinematic,
        )
        if body.initial.moves_positions():
            sim.positions = x
        if np.any(v):
            sim.velocities = v
    free = np.ones(len(rest), dtype=bool)
    if pinned is not None:
        free[pinned] = False
    for k in kinematic:
        free[k] = False
    return sim, free


def distribute_force(force: Vec3, sims: Sequence[Any], free_masks: Sequence[np.ndarray]) -> list:
    """Per-body (m, 3) force arrays (N) that spread the total ``force`` (N) over the free vertices of all bodies
    in proportion to their masses: ``f_i = m_i force / m_free``."""
    masses = [_vertex_masses(np.asarray(s.masses), len(free)) for s, free in zip(sims, free_masks)]
    # > 0: fepr.Simulation rejects a body whose vertices are all pinned.
    m_free = float(sum(float(w[free].sum()) for w, free in zip(masses, free_masks)))
    a = np.asarray(force, dtype=np.float64) / m_free
    out = []
    for w, free in zip(masses, free_masks):
        f = np.zeros((len(free), 3))
        f[free] = w[free, None] * a
        out.append(f)
    return out
