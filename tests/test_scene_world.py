"""Scene files, the world part: obstacles, kinematic pins, damping, a constant force, ``[initial] translate`` and
several bodies (``[[bodies]]``); parsing, every validation error with its message, and building and running
scenes that use them."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import fepr
from fepr.errors import ConfigError
from fepr.scene import (
    BODY_KEYS,
    KinematicPinSettings,
    ObstacleSettings,
    load_scene,
    run_scene,
    scene_from_dict,
)

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def minimal() -> dict:
    return {
        "mesh": {"builtin": "box", "size": 0.4, "resolution": 2},
        "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.3},
        "mass": {"density": 100.0},
    }


def with_world(**keys) -> dict:
    d = minimal()
    d["world"] = keys
    return d


def body(name=None, **extra) -> dict:
    b = {
        "mesh": {"builtin": "box", "size": 0.4, "resolution": 2},
        "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.3},
        "mass": {"density": 100.0},
    }
    if name is not None:
        b["name"] = name
    b.update(extra)
    return b


def two_bodies(**world) -> dict:
    d = {
        "bodies": [
            body("a", initial={"velocity": [0.1, 0.0, 0.0]}),
            body("b", mesh={"builtin": "ell", "size": 0.2}, initial={"translate": [2.0, 0.0, 0.0]}),
        ],
        "integrator": {"dt": 0.01},
    }
    if world:
        d["world"] = world
    return d


def error_of(d: dict) -> str:
    with pytest.raises(ConfigError) as info:
        scene_from_dict(d, ".", source="scene.toml")
    return str(info.value)


# ---- parsing ---------------------------------------------------------------------------------------------


def test_obstacles_parse_with_defaults_and_geometry():
    s = scene_from_dict(
        with_world(
            obstacles=[
                {"type": "plane"},
                {"type": "sphere", "center": [0, 0, -1], "radius": 0.5, "restitution": 0.5, "friction": 0.2},
                {"type": "box", "center": [1, 0, 0], "size": [2.0, 1.0, 0.5], "rotate": [0, 0, 90]},
                {"type": "box", "center": [0, 0, 0], "half_extents": [1, 1, 1]},
                {"type": "capsule", "a": [0, 0, 0], "b": [1, 0, 0], "radius": 0.1},
            ]
        ),
        ".",
    )
    obs = s.world.obstacles
    assert [o.type for o in obs] == ["plane", "sphere", "box", "box", "capsule"]
    assert all(isinstance(o, ObstacleSettings) for o in obs)
    assert obs[0].geometry == {"point": (0.0, 0.0, 0.0), "normal": (0.0, 0.0, 1.0)}
    assert (obs[0].restitution, obs[0].friction) == (1.0, 0.0)
    assert (obs[1].restitution, obs[1].friction) == (0.5, 0.2)
    assert obs[1].geometry == {"center": (0.0, 0.0, -1.0), "radius": 0.5}
    assert obs[2].geometry["half_extents"] == (1.0, 0.5, 0.25)  # size is the full edge lengths
    rows = np.array(obs[2].geometry["rotation"])  # the box's axes in world coordinates (fepr.Box's convention)
    np.testing.assert_allclose(rows[0], [0.0, 1.0, 0.0], atol=1e-15)  # 90 degrees about z: local x -> world y
    np.testing.assert_allclose(rows[1], [-1.0, 0.0, 0.0], atol=1e-15)
    assert obs[3].geometry["rotation"] is None
    assert obs[4].geometry == {"a": (0.0, 0.0, 0.0), "b": (1.0, 0.0, 0.0), "radius": 0.1}
    assert [o.label for o in obs] == [f"[[world.obstacles]] #{k}" for k in range(1, 6)]


def test_world_damping_and_force_parse():
    s = scene_from_dict(with_world(air_damping=0.5, rayleigh_damping=0.01, force=[1, 0, -2]), ".")
    assert s.world.air_damping == 0.5 and s.world.rayleigh_damping == 0.01
    assert s.world.force == (1.0, 0.0, -2.0)
    d = scene_from_dict(minimal(), ".")
    assert (d.world.air_damping, d.world.rayleigh_damping, d.world.force) == (0.0, 0.0, None)
    assert d.world.obstacles == () and d.world.kinematic_pins == ()


def test_kinematic_pins_parse():
    s = scene_from_dict(
        with_world(
            kinematic_pins=[
                {"vertices": [0, 3], "motion": "sinusoidal", "amplitude": [0, 0, 0.1], "frequency": 2},
                {
                    "below": {"axis": "z", "value": -0.1},
                    "motion": "keyframes",
                    "times": [0, 1, 2],
                    "offsets": [[0, 0, 0], [0, 0, 1], [1, 0, 1]],
                },
            ]
        ),
        ".",
    )
    a, b = s.world.kinematic_pins
    assert isinstance(a, KinematicPinSettings)
    assert (a.vertices, a.motion, a.amplitude, a.frequency, a.phase) == (
        (0, 3),
        "sinusoidal",
        (0.0, 0.0, 0.1),
        2.0,
        0.0,
    )
    assert b.vertices is None and b.below.axis == "z" and b.below.value == -0.1
    assert b.times == (0.0, 1.0, 2.0) and b.offsets[2] == (1.0, 0.0, 1.0)
    assert a.label == "[[world.kinematic_pins]] #1"


def test_initial_translate_parses_and_is_not_rest():
    d = minimal()
    d["initial"] = {"translate": [0, 0, 1.5]}
    s = scene_from_dict(d, ".")
    assert s.initial.translate == (0.0, 0.0, 1.5)
    assert not s.initial.is_rest() and s.initial.moves_positions()


def test_bodies_parse_with_default_names_and_per_body_pins():
    d = {
        "bodies": [
            body(
                pinned=[0],
                kinematic_pins=[{"vertices": [1], "motion": "sinusoidal", "amplitude": [0, 0, 1], "frequency": 1}],
            ),
            body("ball", mesh={"builtin": "sphere", "radius": 0.2}, pin_below={"axis": "z", "value": -0.1}),
        ]
    }
    s = scene_from_dict(d, ".", source="two.toml")
    assert s.is_multibody and s.mesh is None and s.material is None
    names = [b.name for b in s.body_settings()]
    assert names == ["body1", "ball"]
    b1, b2 = s.bodies
    assert b1.pinned == (0,) and b1.kinematic_pins[0].label == "[[bodies]] #1 [[kinematic_pins]] #1"
    assert b2.pin_below.value == -0.1 and b2.mesh.builtin == "sphere"
    assert set(BODY_KEYS) == {
        "name",
        "mesh",
        "material",
        "mass",
        "initial",
        "pinned",
        "pin_below",
        "kinematic_pins",
        "restitution",
        "friction",
        "self_contact",
    }


def test_one_body_scene_is_its_own_single_body():
    d = with_world(
        pinned=[1], kinematic_pins=[{"vertices": [2], "motion": "sinusoidal", "amplitude": [0, 0, 1], "frequency": 1}]
    )
    s = scene_from_dict(d, ".", source="one.toml")
    (b,) = s.body_settings()
    assert not s.is_multibody and b.name == "one" and b.pinned == (1,) and len(b.kinematic_pins) == 1
    assert s.has_supports()


# ---- validation errors ---------------------------------------------------------------------------------

PLANE = {"type": "plane"}
SPHERE = {"type": "sphere", "center": [0, 0, 0], "radius": 1.0}
SINE = {"vertices": [0], "motion": "sinusoidal", "amplitude": [0, 0, 0.1], "frequency": 1.0}
KEYS = {"vertices": [0], "motion": "keyframes", "times": [0.0, 1.0], "offsets": [[0, 0, 0], [0, 0, 1]]}


def _with(base: dict, **changes) -> dict:
    out = copy.deepcopy(base)
    for k, v in changes.items():
        if v is None:
            out.pop(k, None)
        else:
            out[k] = v
    return out


WORLD_ERRORS = [
    (
        {"obstacles": [PLANE, _with(SPHERE, restitution=-0.5)]},
        "scene.toml: [[world.obstacles]] #2: restitution must be in [0, 1], got -0.5",
    ),
    ({"obstacles": [_with(PLANE, restitution=1.5)]}, "[[world.obstacles]] #1: restitution must be in [0, 1], got 1.5"),
    ({"obstacles": [_with(PLANE, friction=-0.1)]}, "[[world.obstacles]] #1: friction must be >= 0, got -0.1"),
    ({"obstacles": [_with(PLANE, friction="rough")]}, "[[world.obstacles]] #1: friction must be a number, got 'rough'"),
    (
        {"obstacles": [PLANE, PLANE, {"type": "cone"}]},
        "[[world.obstacles]] #3: unknown obstacle type 'cone' (known: 'plane', 'sphere', 'box', 'capsule', 'mesh')",
    ),
    ({"obstacles": [{"radius": 1.0}]}, "[[world.obstacles]] #1: missing required key 'type'"),
    ({"obstacles": [_with(SPHERE, radius=None)]}, "[[world.obstacles]] #1: missing required key 'radius'"),
    ({"obstacles": [_with(SPHERE, center=None)]}, "[[world.obstacles]] #1: missing required key 'center'"),
    ({"obstacles": [_with(SPHERE, radius=0.0)]}, "[[world.obstacles]] #1: radius must be > 0, got 0.0"),
    (
        {"obstacles": [{"type": "capsule", "a": [0, 0, 0], "radius": 0.1}]},
        "[[world.obstacles]] #1: missing required key 'b'",
    ),
    (
        {"obstacles": [{"type": "box", "center": [0, 0, 0]}]},
        "[[world.obstacles]] #1: give exactly one of 'half_extents' (m, half the edge lengths) and 'size'",
    ),
    (
        {"obstacles": [{"type": "box", "center": [0, 0, 0], "size": [1, 1, 1], "half_extents": [1, 1, 1]}]},
        "[[world.obstacles]] #1: give exactly one of 'half_extents'",
    ),
    (
        {"obstacles": [{"type": "box", "center": [0, 0, 0], "size": [1, -1, 1]}]},
        "[[world.obstacles]] #1: size must be > 0 in every component, got [1.0, -1.0, 1.0]",
    ),
    (
        {"obstacles": [{"type": "box", "center": [0, 0, 0], "size": [1, 1, 1], "rotate": [0, 90]}]},
        "[[world.obstacles]] #1: rotate must be 3 angles in degrees (about x, y, z) or a 3x3 rotation matrix",
    ),
    ({"obstacles": [_with(PLANE, normal=[0, 0, 0])]}, "[[world.obstacles]] #1: normal must not be the zero vector"),
    ({"obstacles": [_with(PLANE, normal=[0, 1])]}, "[[world.obstacles]] #1: normal must be a list of 3 numbers"),
    (
        {"obstacles": [_with(PLANE, radius=1.0)]},
        "[[world.obstacles]] #1: unknown key 'radius' (known: type, restitution, friction, motion, point, normal)",
    ),
    ({"obstacles": {"type": "plane"}}, "[world] obstacles must be a list of tables ([[world.obstacles]] entries)"),
    ({"air_damping": -1.0}, "[world] air_damping must be >= 0, got -1.0"),
    ({"rayleigh_damping": -0.01}, "[world] rayleigh_damping must be >= 0, got -0.01"),
    ({"force": [1, 2]}, "[world] force must be a list of 3 numbers, got [1, 2]"),
    ({"kinematic_pins": [SINE, _with(SINE, vertices=None)]}, "[[world.kinematic_pins]] #2: give exactly one of"),
    (
        {"kinematic_pins": [_with(SINE, below={"axis": "z", "value": 0})]},
        "[[world.kinematic_pins]] #1: give exactly one of 'vertices' (vertex indices) and 'below'",
    ),
    ({"kinematic_pins": [_with(SINE, vertices=[])]}, "[[world.kinematic_pins]] #1: vertices must not be empty"),
    (
        {"kinematic_pins": [_with(SINE, vertices=[-2])]},
        "[[world.kinematic_pins]] #1: vertices: vertex indices must be >= 0",
    ),
    ({"kinematic_pins": [_with(SINE, motion=None)]}, "[[world.kinematic_pins]] #1: missing required key 'motion'"),
    (
        {"kinematic_pins": [_with(SINE, motion="circle")]},
        "[[world.kinematic_pins]] #1: motion must be one of 'sinusoidal', 'keyframes'; got 'circle'",
    ),
    (
        {"kinematic_pins": [_with(SINE, frequency=None)]},
        "[[world.kinematic_pins]] #1: missing required key 'frequency'",
    ),
    ({"kinematic_pins": [_with(SINE, frequency=-1.0)]}, "[[world.kinematic_pins]] #1: frequency must be > 0, got -1.0"),
    ({"kinematic_pins": [_with(SINE, amplitude=[0, 1])]}, "[[world.kinematic_pins]] #1: amplitude must be a list of 3"),
    (
        {"kinematic_pins": [_with(SINE, times=[0, 1])]},
        "[[world.kinematic_pins]] #1: times does not apply to motion 'sinusoidal' (its keys: amplitude, frequency, ",
    ),
    (
        {"kinematic_pins": [_with(KEYS, times=[0.0, 1.0, 1.0], offsets=[[0, 0, 0]] * 3)]},
        "[[world.kinematic_pins]] #1: times must be strictly increasing, got [0.0, 1.0, 1.0]",
    ),
    (
        {"kinematic_pins": [_with(KEYS, times=[1.0, 0.5])]},
        "[[world.kinematic_pins]] #1: times must be strictly increasing, got [1.0, 0.5]",
    ),
    ({"kinematic_pins": [_with(KEYS, times=[])]}, "[[world.kinematic_pins]] #1: times must be a non-empty list"),
    (
        {"kinematic_pins": [_with(KEYS, offsets=[[0, 0, 0]])]},
        "[[world.kinematic_pins]] #1: offsets has 1 entries but times has 2",
    ),
    (
        {"kinematic_pins": [_with(KEYS, offsets=[[0, 0, 0], [0, 1]])]},
        "[[world.kinematic_pins]] #1: offsets #2 must be a list of 3 numbers (m), got [0, 1]",
    ),
    ({"kinematic_pins": [_with(KEYS, offsets=None)]}, "[[world.kinematic_pins]] #1: missing required key 'offsets'"),
    (
        {"kinematic_pins": [_with(KEYS, frequency=1.0)]},
        "[[world.kinematic_pins]] #1: frequency does not apply to motion 'keyframes' (its keys: times, offsets)",
    ),
    (
        {"kinematic_pins": [_with(SINE, speed=1.0)]},
        "[[world.kinematic_pins]] #1: unknown key 'speed' (known: vertices, below, motion,",
    ),
    (
        {"kinematic_pins": [_with(SINE, vertices=None, below={"axis": "q", "value": 0})]},
        '[[world.kinematic_pins]] #1: below.axis must be "x", "y" or "z"',
    ),
]


@pytest.mark.parametrize("world,fragment", WORLD_ERRORS, ids=[f[1].split(": ", 1)[-1][:60] for f in WORLD_ERRORS])
def test_world_validation_error_names_the_key_and_position(world, fragment):
    msg = error_of(with_world(**world))
    assert msg.startswith("scene.toml: ")
    assert fragment in msg


def test_initial_translate_must_be_a_vector():
    d = minimal()
    d["initial"] = {"translate": [0, 0]}
    assert "scene.toml: [initial] translate must be a list of 3 numbers, got [0, 0]" in error_of(d)


BODY_ERRORS = [
    (lambda d: d.update(mesh={"builtin": "box"}), "scene.toml: [mesh] is not allowed in a scene with [[bodies]]"),
    (lambda d: d.update(initial={"scale": 1.1}), "scene.toml: [initial] is not allowed in a scene with [[bodies]]"),
    (
        lambda d: d.update(world={"pinned": [0]}),
        "scene.toml: [world] pinned is per body in a scene with [[bodies]]: give it in the [[bodies]] tables",
    ),
    (
        lambda d: d.update(world={"kinematic_pins": [SINE]}),
        "scene.toml: [world] kinematic_pins is per body in a scene with [[bodies]]",
    ),
    (lambda d: d["bodies"][1].pop("mesh"), "scene.toml: [[bodies]] #2: missing required table 'mesh'"),
    (lambda d: d["bodies"][0].pop("mass"), "scene.toml: [[bodies]] #1: missing required table 'mass'"),
    (
        lambda d: d["bodies"][1].update(colour="red"),
        "scene.toml: [[bodies]] #2: unknown key 'colour' (known: name, mesh,",
    ),
    (
        lambda d: d["bodies"][1]["mesh"].update(foo=1),
        "scene.toml: [[bodies]] #2 [mesh] unknown key 'foo' (known: path, builtin,",
    ),
    (
        lambda d: d["bodies"][0]["material"].update(poisson_ratio=0.7),
        "scene.toml: [[bodies]] #1 [material] poisson_ratio must be in (-1.0, 0.5), got 0.7",
    ),
    (lambda d: d["bodies"][1].update(mass=5.0), "scene.toml: [[bodies]] #2: mass must be a table of keys, got 5.0"),
    (lambda d: d["bodies"][1].update(name="a"), "scene.toml: [[bodies]] #2: name 'a' is already used by [[bodies]] #1"),
    (lambda d: d["bodies"][0].update(name="my body"), "scene.toml: [[bodies]] #1: name must be letters, digits,"),
    (lambda d: d["bodies"][0].update(pinned=[-1]), "scene.toml: [[bodies]] #1: pinned: vertex indices must be >= 0"),
    (
        lambda d: d["bodies"][1].update(kinematic_pins=[_with(SINE, frequency=0.0)]),
        "scene.toml: [[bodies]] #2 [[kinematic_pins]] #1: frequency must be > 0, got 0.0",
    ),
    (lambda d: d.update(bodies=[]), "scene.toml: bodies must be a non-empty list of tables ([[bodies]] entries)"),
    (lambda d: d.update(bodies={"mesh": {}}), "scene.toml: bodies must be a non-empty list of tables"),
]


@pytest.mark.parametrize("change,fragment", BODY_ERRORS, ids=[f[1].split(": ", 1)[-1][:60] for f in BODY_ERRORS])
def test_bodies_validation_error_names_the_body(change, fragment):
    d = two_bodies()
    change(d)
    assert fragment in error_of(d)


def test_unknown_section_lists_bodies():
    d = minimal()
    d["body"] = {}
    assert "unknown section [body] (known: scene, mesh," in error_of(d)
    assert "[bodies]" in error_of(d)


# ---- errors found when building (they need the mesh) ---------------------------------------------------


def test_kinematic_pin_vertex_out_of_range_is_named_at_build():
    s = scene_from_dict(with_world(kinematic_pins=[SINE, _with(SINE, vertices=[999])]), ".", source="scene.toml")
    with pytest.raises(ConfigError) as info:
        s.build()
    m = len(s.load_mesh().vertices)
    assert str(info.value) == (
        f"scene.toml: [[world.kinematic_pins]] #2: vertices: vertex index 999 out of range (mesh has {m} vertices)"
    )


def test_kinematic_pin_below_that_selects_nothing_is_named_at_build():
    pin = _with(SINE, vertices=None, below={"axis": "z", "value": -5.0})
    s = scene_from_dict(with_world(kinematic_pins=[pin]), ".", source="scene.toml")
    with pytest.raises(
        ConfigError, match=r"scene.toml: \[\[world.kinematic_pins\]\] #1: below: no vertex has z <= -5.0"
    ):
        s.build()


def test_body_pin_out_of_range_is_named_at_build():
    d = two_bodies()
    d["bodies"][1]["pinned"] = [0, 10_000]
    s = scene_from_dict(d, ".", source="scene.toml")
    with pytest.raises(ConfigError, match=r"scene.toml: \[\[bodies\]\] #2: pinned: vertex index 10000 out of range"):
        s.build_bodies()


def test_build_of_a_multibody_scene_points_to_build_multibody():
    s = scene_from_dict(two_bodies(), ".", source="scene.toml")
    with pytest.raises(ConfigError, match=r"build\(\) needs a one-body scene; this scene has 2 \[\[bodies\]\]"):
        s.build()


# ---- building ------------------------------------------------------------------------------------------


def test_translate_moves_the_initial_positions_not_the_rest_shape():
    d = minimal()
    d["initial"] = {"translate": [0.0, 0.0, 2.0], "scale": 1.1, "scale_about": "centroid"}
    s = scene_from_dict(d, ".")
    sim = s.build()
    rest = np.asarray(s.load_mesh().vertices)
    np.testing.assert_array_equal(sim.rest_positions, rest)
    c = rest.mean(axis=0)  # uniform lumped masses of a regular box: the centroid
    np.testing.assert_allclose(sim.positions, c + 1.1 * (rest - c) + [0.0, 0.0, 2.0], atol=1e-12)
    assert sim.energy().gravitational == 0.0  # no gravity in this scene
    assert not np.any(sim.velocities)


def test_translate_alone_keeps_the_body_undeformed():
    d = minimal()
    d["initial"] = {"translate": [1.0, -2.0, 3.0]}
    d["world"] = {"gravity": [0.0, 0.0, -9.81]}
    sim = scene_from_dict(d, ".").build()
    np.testing.assert_allclose(sim.positions, np.asarray(sim.rest_positions) + [1.0, -2.0, 3.0], atol=1e-15)
    assert abs(sim.energy().elastic) < 1e-12
    sim.step(10)  # free fall: the centre of mass follows the exact parabola (FEPR's c_C row)
    t = sim.time
    c0 = np.asarray(sim.rest_positions).mean(axis=0) + [1.0, -2.0, 3.0]
    np.testing.assert_allclose(sim.center_of_mass(), c0 + [0.0, 0.0, -0.5 * 9.81 * t * t], atol=1e-9)


def test_build_passes_obstacles_pins_and_damping_to_the_simulation():
    d = with_world(
        gravity=[0.0, 0.0, -9.81],
        air_damping=0.3,
        rayleigh_damping=0.01,
        obstacles=[
            {"type": "plane", "point": [0, 0, -1], "restitution": 0.5, "friction": 0.2},
            {"type": "box", "center": [0, 0, -3], "size": [2, 4, 6], "rotate": [0, 0, 90]},
            {"type": "sphere", "center": [5, 0, 0], "radius": 0.5},
            {"type": "capsule", "a": [0, 5, 0], "b": [1, 5, 0], "radius": 0.25, "restitution": 0.0},
        ],
        kinematic_pins=[_with(KEYS, vertices=[0, 1])],
    )
    sim = scene_from_dict(d, ".").build()
    plane, box, sphere, capsule = sim.obstacles
    assert plane == fepr.Plane(point=(0, 0, -1), normal=(0, 0, 1), restitution=0.5, friction=0.2)
    assert isinstance(box, fepr.Box) and box.half_extents == (1.0, 2.0, 3.0)
    np.testing.assert_allclose(box.rotation, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
    assert sphere == fepr.Sphere(center=(5, 0, 0), radius=0.5)
    assert capsule == fepr.Capsule(a=(0, 5, 0), b=(1, 5, 0), radius=0.25, restitution=0.0)
    (kp,) = sim.kinematic_pins
    assert list(kp.vertices) == [0, 1] and kp.motion == fepr.Keyframes(times=[0.0, 1.0], offsets=[[0, 0, 0], [0, 0, 1]])
    assert sim.air_damping == 0.3 and sim.rayleigh_damping == 0.01
    assert bool(sim.pinned[0]) and bool(sim.pinned[1]) and not bool(sim.pinned[2])


def test_kinematic_pins_follow_their_translated_start_plus_the_motion():
    s = load_scene(EXAMPLES / "hanging_bar.toml")
    top = [32, 33, 34, 35]
    rest = np.asarray(s.load_mesh().vertices)
    assert np.all(rest[top, 2] == rest[:, 2].max())  # the example's comment: the top face
    s.initial = dataclasses.replace(s.initial, translate=(1.0, 0.0, 2.0))
    sim = s.build()
    x0 = np.asarray(sim.positions)[top]
    np.testing.assert_allclose(x0, rest[top] + [1.0, 0.0, 2.0], atol=1e-15)
    for _ in range(3):
        sim.step(13)
        d = np.array([0.05, 0.0, 0.0]) * math.sin(2 * math.pi * 1.0 * sim.time)
        np.testing.assert_allclose(np.asarray(sim.positions)[top], x0 + d, atol=1e-14)
    assert np.any(sim.history["work_pins"][1:] != 0.0)


def test_keyframed_pins_are_piecewise_linear_and_held_after_the_last_key():
    pin = {
        "below": {"axis": "z", "value": -0.19},
        "motion": "keyframes",
        "times": [0.0, 0.1],
        "offsets": [[0, 0, 0], [0.1, 0, 0]],
    }
    d = with_world(kinematic_pins=[pin])
    d["integrator"] = {"dt": 0.01}
    s = scene_from_dict(d, ".")
    sim = s.build()
    idx = s.world.kinematic_pins[0].indices(np.asarray(sim.rest_positions))
    assert len(idx) == 9  # the bottom face of the 2x2 box
    x0 = np.asarray(sim.positions)[idx]
    sim.step(5)
    np.testing.assert_allclose(np.asarray(sim.positions)[idx], x0 + [0.05, 0.0, 0.0], atol=1e-14)
    sim.step(10)
    np.testing.assert_allclose(np.asarray(sim.positions)[idx], x0 + [0.1, 0.0, 0.0], atol=1e-14)


def test_force_is_spread_over_the_free_vertices_of_all_bodies_by_mass():
    force = np.array([3.0, -1.0, 2.0])
    d = two_bodies(gravity=[0.0, 0.0, -9.81], force=list(force))
    d["bodies"][0]["pinned"] = [0]  # a pinned vertex carries no part of the force
    s = scene_from_dict(d, ".", source="scene.toml")
    a, b = s.build_bodies()
    pinned_mass = float(np.asarray(a.masses)[0])
    m_free = a.total_mass + b.total_mass - pinned_mass
    # The free body b accelerates by g + force / m_free exactly: P_b(t) = P_b(0) + m_b (g + force / m_free) t.
    p0 = b.linear_momentum()
    b.step(20)
    g = np.array([0.0, 0.0, -9.81])
    expected = p0 + b.total_mass * (g + force / m_free) * b.time
    np.testing.assert_allclose(b.linear_momentum(), expected, rtol=1e-8)  # the projection's tolerance
    assert b.history["work_forces"][1:].sum() != 0.0


def test_force_on_a_single_body_gives_the_exact_momentum_and_energy_budget():
    force = [0.5, 0.0, 0.0]
    d = with_world(force=force)
    d["initial"] = {"angular_velocity": [0.0, 0.0, 1.0]}
    # a stable step for symplectic Euler (at the default 1/30 s this box's steps are unstable and some projections
    # need more than 20 iterations)
    d["integrator"] = {"dt": 0.01}
    result = run_scene(scene_from_dict(d, ".", source="push.toml"), steps=120)
    assert result.momentum_error < 1e-10 and result.angular_momentum_error < 1e-10
    assert result.final_energy_error < 1e-9  # measured against H0 + budget_total
    h = result.simulation.history
    assert h["budget_total"][-1] > 0.0  # the push did positive work
    np.testing.assert_allclose(h["budget_total"], np.cumsum(h["budget"]), rtol=1e-12, atol=1e-15)


def test_air_damping_takes_energy_out_and_the_budget_accounts_for_it():
    d = with_world(air_damping=2.0)
    d["initial"] = {"velocity": [1.0, 0.0, 0.0]}
    result = run_scene(scene_from_dict(d, ".", source="drag.toml"), steps=30)
    h = result.simulation.history
    assert h["kinetic"][-1] < 0.5 * h["kinetic"][0]
    assert np.all(h["work_damping"][1:] < 0.0)
    assert result.final_energy_error < 1e-9
    # air drag takes momentum out: its impulses are in the momentum targets, so the drift is measured against them
    assert result.metrics.momentum_reference == "targets"
    assert result.momentum_error < 1e-10 and result.angular_momentum_error < 1e-10


def test_dropped_box_never_penetrates_the_ground():
    s = load_scene(EXAMPLES / "drop_box.toml")
    sim = s.build()
    assert np.asarray(sim.positions)[:, 2].min() == pytest.approx(1.0)  # translated 1 m up
    lowest = []
    for _ in range(s.run.steps):
        sim.step(1)
        lowest.append(float(np.asarray(sim.positions)[:, 2].min()))
    h = sim.history
    assert min(lowest) >= -1e-3
    assert h["penetration"].max() <= 1e-3
    assert h["contacts"].sum() > 0 and h["work_contact"].min() < 0.0  # it hit the ground, inelastically
    first = int(np.argmax(np.asarray(lowest) < 1e-3))
    assert max(lowest[first:]) > 0.05  # and bounced
    # FEPR holds H0 + the budget (the energy the impacts took out)
    err = np.abs(h["total"] - h["total"][0] - h["budget_total"]) / h["total"][0]
    assert err.max() < 1e-8


@pytest.mark.parametrize("name", ["drop_box", "hanging_bar", "two_bodies"])
def test_new_examples_run_and_keep_the_budgeted_energy(name, tmp_path):
    result = run_scene(load_scene(EXAMPLES / f"{name}.toml"), out_dir=tmp_path)
    assert not result.runaway and result.steps_completed == load_scene(EXAMPLES / f"{name}.toml").run.steps
    assert result.max_energy_error < 1e-8
    assert result.wall_s < 10.0
