"""Obstacles on prescribed rigid motions (fepr.ObstacleMotion): a rising platform carries a body and books its
work, a thin plate swept at 10 m/s pushes a body instead of passing through it, a turntable turns a body with
it, scene files read the motion, bad motions are named. Also Projective Dynamics in a corner of two obstacles,
whose contact constraints held the face along the wall in free fall."""

from pathlib import Path

import numpy as np
import pytest

import fepr
import fepr.scene
from fepr.errors import ConfigError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

INTEGRATORS = {
    "BE": fepr.ImplicitEuler,
    "PD": fepr.ProjectiveDynamics,
    "XPBD": fepr.Xpbd,
}


def _box(center, size=0.2):
    return fepr.meshes.builtin("box", size=size, resolution=3, center=center)


def _box_sim(center, obstacles, integrator=None, gravity=True, **kw):
    """The 0.2 m Neo-Hookean box (1e5 / 0.3, 1000 kg/m^3) at ``center`` among ``obstacles``, at dt = 1/60 (Projective
    Dynamics unless ``integrator`` is given), under gravity unless ``gravity`` is False."""
    return fepr.Simulation(
        _box(center),
        material=fepr.NeoHookean(1e5, 0.3),
        density=kw.pop("density", 1000),
        integrator=integrator or fepr.ProjectiveDynamics(),
        dt=1 / 60,
        obstacles=obstacles,
        gravity=(0, 0, -9.81) if gravity else (0, 0, 0),
        **kw,
    )


def _books(h):
    """Largest |total - (H0 + budget_total)| over the run, relative to the largest |total|."""
    gap = h["total"] - (h["total"][0] + h["budget_total"])
    return float(np.abs(gap).max() / np.abs(h["total"]).max())


@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_a_rising_platform_carries_a_box_and_books_its_work(name):
    # The plane z = 0 rises 0.5 m between t = 0.5 s and 1.5 s, under a box of 8 kg resting on it.
    lift = fepr.ObstacleMotion(translation=fepr.Keyframes(times=[0.5, 1.5], offsets=[[0, 0, 0], [0, 0, 0.5]]))
    sim = _box_sim((0.0, 0.0, 0.1001), [fepr.Plane(restitution=0.0, friction=0.5, motion=lift)], INTEGRATORS[name]())
    sim.step(150)
    h = sim.history
    z = sim.positions[:, 2]
    edge = 0.2 / 3
    # On the platform's final height, no vertex inside it (exact: the plane is z = 0.5 now).
    assert z.min() >= 0.5 - 0.01 * edge, z.min()
    assert z.min() <= 0.5 + 0.01 * edge, z.min()
    # The platform's work is booked: the box's potential energy rose by m g 0.5 = 39.2 J (and its kinetic energy
    # while carried went back to the platform when it stopped).
    assert 39.2 * 0.95 <= h["work_contact"].sum() <= 39.2 * 1.1, h["work_contact"].sum()
    assert h["work_contact"].max() > 0
    assert _books(h) <= 1e-8
    assert h["min_j"].min() > 0.5
    assert h["proj_converged"][1:].mean() >= 0.9


@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_a_thin_plate_swept_at_10_m_per_s_pushes_a_box_instead_of_passing_through(name):
    # A 1 cm plate moving at 10 m/s (17 cm per step at dt = 1/60) into a box floating in space.
    sweep = fepr.ObstacleMotion(translation=fepr.Keyframes(times=[0, 0.1], offsets=[[0, 0, 0], [1.0, 0, 0]]))
    plate = fepr.Box(center=(-0.5, 0, 0), half_extents=(0.005, 0.3, 0.3), restitution=0.5, motion=sweep)
    sim = _box_sim((0.0, 0.0, 0.0), [plate], INTEGRATORS[name](), gravity=False)
    sim.step(18)
    x = sim.positions
    # The plate stopped at x = 0.5 (its front face at 0.505): every vertex is in front of it, and the box left
    # faster than the plate (10 m/s, up to 15 m/s for restitution 0.5 against an infinitely heavy plate).
    assert x[:, 0].min() > 0.505, x[:, 0].min()
    v = float(sim.velocities[:, 0].mean())
    assert 10.0 <= v <= 16.0, v
    assert _books(sim.history) <= 1e-8


def test_a_turntable_turns_a_box_resting_on_it():
    # A wide slab spinning about z at 1 rad/s, the box's centre 0.5 m off the axis, friction 0.8.
    table = fepr.Box(
        center=(0, 0, -0.05),
        half_extents=(1, 1, 0.05),
        restitution=0.0,
        friction=0.8,
        motion=fepr.ObstacleMotion(angular_velocity=(0, 0, 1.0)),
    )
    sim = _box_sim((0.5, 0.0, 0.1), [table])
    sim.step(180)
    c = sim.positions.mean(axis=0)
    assert abs(np.arctan2(c[1], c[0]) - 3.0) < 0.1, np.arctan2(c[1], c[0])
    assert abs(np.hypot(c[0], c[1]) - 0.5) < 0.05
    assert sim.positions[:, 2].min() >= -1e-3 * 0.2 / 3
    assert _books(sim.history) <= 1e-8


@pytest.mark.parametrize("tilt_deg, slides", [(15, False), (45, True)])
def test_a_platform_tilted_by_keyframed_orientations_holds_or_sheds_a_box(tilt_deg, slides):
    # A slab tilted about the y axis through the origin between t = 0.2 and 1.2 s; friction 0.5 holds the box up
    # to atan(0.5) = 26.6 degrees.
    tilt = np.radians(tilt_deg)
    slab = fepr.Box(
        center=(0, 0, -0.05),
        half_extents=(2, 1, 0.05),
        restitution=0.0,
        friction=0.5,
        motion=fepr.ObstacleMotion(orientation_times=[0.2, 1.2], orientations=[[0, 0, 0], [0, tilt, 0]]),
    )
    sim = _box_sim((0.0, 0.0, 0.1001), [slab])
    sim.step(120)
    r, offset = slab.motion.placement(sim.time)
    # The box's centre in the slab's frame: along the slope (x) it stays near where it stood, or slides down.
    c = r.T @ (sim.positions.mean(axis=0) - offset)
    slid = abs(c[0]) > 0.1
    assert slid == slides, c
    # Never inside the slab: every vertex above its top face (its own frame).
    local = (sim.positions - offset) @ r
    assert local[:, 2].min() >= -1e-3 * 0.2 / 3, local[:, 2].min()
    assert _books(sim.history) <= 1e-8


@pytest.mark.parametrize("sliding", [False, True])
def test_projective_dynamics_in_a_corner_does_not_make_elastic_energy(sliding):
    # A box on a floor against a wall (resting there, or sliding into it at 1 m/s, restitution 0): without FEPR
    # the energy can only fall. The contact constraints used to hold the face along the wall where the
    # inertial prediction put it (in free fall): 36 J of elastic energy from 2 J of kinetic.
    wall = fepr.Box(center=(0.15 if sliding else 0.1301, 0, 0.1), half_extents=(0.03, 0.3, 0.2), restitution=0.0)
    sim = _box_sim((0.0, 0.0, 0.1), [fepr.Plane(restitution=0.0), wall], density=500, projection=False)
    if sliding:
        v = np.zeros_like(sim.positions)
        v[:, 0] = 1.0
        sim.velocities = v
    sim.step(60)
    h = sim.history
    assert h["total"].max() <= h["total"][0] * (1 + 1e-6), (h["total"].max(), h["total"][0])
    assert h["elastic"].max() < 0.5
    assert h["min_j"].min() > 0.8


def test_the_moving_obstacles_example_runs_with_closed_books():
    scene = fepr.scene.load_scene(EXAMPLES / "moving_obstacles.toml")
    assert [o.motion is not None for o in scene.world.obstacles] == [True, True]
    sim = scene.build()
    sim.step(150)
    h = sim.history
    assert _books(h) <= 1e-8
    assert h["work_contact"].max() > 0  # the platform lifts the box
    assert h["cz"][-1] > 0.35  # carried up 0.3 m from 0.1
    assert int(h["inverted"][-1]) == 0


def test_obstacle_motion_placement_and_bad_motions():
    m = fepr.ObstacleMotion(
        translation=fepr.Keyframes(times=[0, 2], offsets=[[0, 0, 0], [2, 0, 0]]),
        angular_velocity=(0, 0, np.pi / 2),
        pivot=(1, 0, 0),
    )
    r, offset = m.placement(1.0)
    # The pivot moved 1 m along x; a point 1 m along x from it turned a quarter turn about z.
    assert np.allclose(r @ np.array([1.0, 0, 0]) + offset, [2, 0, 0])
    assert np.allclose(r @ np.array([2.0, 0, 0]) + offset, [2, 1, 0])
    # Keyframed orientations about the pivot: halfway between an eighth and three eighths of a turn about x
    # (slerp) is a quarter turn, the last held after its time; the placement is the core's, a proper rotation.
    turned = fepr.ObstacleMotion(orientation_times=[0, 2], orientations=[[np.pi / 4, 0, 0], [3 * np.pi / 4, 0, 0]])
    r, offset = turned.placement(1.0)
    assert np.allclose(r, [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12) and np.allclose(offset, 0, atol=1e-12)
    r, _ = turned.placement(5.0)
    c, s = np.cos(3 * np.pi / 4), np.sin(3 * np.pi / 4)
    assert np.allclose(r, [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-12)
    assert abs(np.linalg.det(r) - 1) < 1e-12
    with pytest.raises(ConfigError, match="angular_velocity"):
        fepr.ObstacleMotion(angular_velocity=(0, np.nan, 0))
    with pytest.raises(ConfigError, match="translation"):
        fepr.ObstacleMotion(translation=(1, 2, 3))
    with pytest.raises(ConfigError, match="Plane motion"):
        fepr.Plane(motion="up")
    with pytest.raises(ConfigError, match="strictly increasing"):
        fepr.Keyframes(times=[0, 0], offsets=[[0, 0, 0], [1, 0, 0]])


@pytest.mark.parametrize(
    "motion, message",
    [
        ("{ }", "give 'translation'"),
        ("{ spin = [0, 0, 1] }", "unknown key 'spin'"),
        ("{ times = [0, 1], offsets = [[0, 0, 0], [1, 0, 0]] }", "times needs 'translation'"),
        ("{ translation = 'keyframes', times = [0, 1] }", "missing required key 'offsets'"),
        ("{ translation = 'sinusoidal', amplitude = [0, 0, 1], frequency = 1, times = [0] }", "times does not apply"),
        ("{ angular_velocity = [0, 1] }", "angular_velocity must be a list of 3 numbers"),
        ("[1, 2]", "motion must be a table"),
        ("{ orientations = [[0, 0, 1]] }", "together"),
        ("{ orientations = [[0, 0, 1]], orientation_times = [0, 1] }", "as many"),
        ("{ orientations = [[0, 0], [0, 0, 1]], orientation_times = [0, 1] }", "orientations #1 must be"),
    ],
)
def test_a_bad_obstacle_motion_in_a_scene_is_named(tmp_path, motion, message):
    text = (EXAMPLES / "drop_box.toml").read_text()
    text = text.replace("friction = 0.0              # Coulomb coefficient (0: frictionless)", f"motion = {motion}")
    path = tmp_path / "scene.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        fepr.scene.load_scene(path)
    assert "[[world.obstacles]] #1" in str(err.value) and message in str(err.value), str(err.value)
