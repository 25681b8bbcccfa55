"""A vertex held by a static pin (``pinned``, ``pin_below``) and moved by a kinematic pin, or moved by two kinematic
pins, is a ConfigError naming both scene keys (before, the kinematic pin silently won)."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from fepr.errors import ConfigError
from fepr.scene import scene_from_dict

SHAKE = {"motion": "sinusoidal", "amplitude": [0.01, 0.0, 0.0], "frequency": 1.0}
BASE = {
    "mesh": {"builtin": "box", "size": 0.1, "resolution": 2},  # 27 vertices, z in {-0.05, 0, 0.05}
    "material": {"youngs_modulus": 1e5, "poisson_ratio": 0.3},
    "mass": {"density": 1000.0},
    "integrator": {"dt": 1e-3},
}


def scene(**world):
    d = copy.deepcopy(BASE)
    d["world"] = world
    return scene_from_dict(d, source="pins.toml")


def test_vertex_in_pinned_and_kinematic_pin():
    s = scene(pinned=[0, 1, 5], kinematic_pins=[{"vertices": [5, 6], **SHAKE}])
    with pytest.raises(ConfigError) as info:
        s.build()
    assert str(info.value) == (
        "pins.toml: [[world.kinematic_pins]] #1: vertex 5 is also held by [world] pinned: a vertex cannot both stay "
        "fixed (a static pin) and follow a path (a kinematic pin); remove it from one of the two"
    )


def test_vertices_in_pin_below_and_kinematic_below():
    s = scene(pin_below={"axis": "z", "value": 0.0}, kinematic_pins=[{"below": {"axis": "z", "value": -0.04}, **SHAKE}])
    with pytest.raises(ConfigError) as info:
        s.build()
    msg = str(info.value)
    assert msg.startswith(
        "pins.toml: [[world.kinematic_pins]] #1: 9 vertices (0, 1, 2, 3, 4, ...) are also held by "
    ), msg
    assert "[world] pin_below (z <= 0)" in msg


def test_vertex_in_two_kinematic_pins():
    s = scene(kinematic_pins=[{"vertices": [5, 6], **SHAKE}, {"vertices": [7, 6], **SHAKE}])
    with pytest.raises(ConfigError) as info:
        s.build()
    assert str(info.value).startswith(
        "pins.toml: [[world.kinematic_pins]] #2: vertex 6 is also moved by [[world.kinematic_pins]] #1: a vertex can "
        "follow only one path"
    )


def test_multibody_names_the_body():
    d = {
        "integrator": {"dt": 1e-3},
        "bodies": [
            {**copy.deepcopy({k: BASE[k] for k in ("mesh", "material", "mass")}), "name": "a"},
            {
                **copy.deepcopy({k: BASE[k] for k in ("material", "mass")}),
                "mesh": {"builtin": "box", "size": 0.1, "resolution": 2, "center": [1.0, 0.0, 0.0]},
                "name": "b",
                "pinned": [3],
                "kinematic_pins": [{"vertices": [2, 3], **SHAKE}],
            },
        ],
    }
    with pytest.raises(
        ConfigError,
        match=r"^pins\.toml: \[\[bodies\]\] #2 \[\[kinematic_pins\]\] #1: vertex 3 is also "
        r"held by \[\[bodies\]\] #2: pinned",
    ):
        scene_from_dict(d, source="pins.toml").build_bodies()


def test_disjoint_pins_still_build():
    sim = scene(pinned=[0, 1], kinematic_pins=[{"vertices": [25, 26], **SHAKE}, {"vertices": [24], **SHAKE}]).build()
    pinned = np.flatnonzero(np.asarray(sim.pinned))
    assert {0, 1, 24, 25, 26} <= set(pinned.tolist())


def test_the_python_api_refuses_a_vertex_both_pinned_and_kinematic():
    import fepr

    mat = fepr.NeoHookean(youngs_modulus=1e4, poisson_ratio=0.3)
    kp = fepr.KinematicPins([3, 4], fepr.Sinusoid(amplitude=(0.01, 0.0, 0.0), frequency=1.0))
    with pytest.raises(fepr.ConfigError, match=r"kinematic_pins\[0\]: vertex 4 is also in pinned"):
        fepr.Simulation(fepr.meshes.box(), material=mat, density=100.0, dt=0.01, pinned=[4, 7], kinematic_pins=[kp])
