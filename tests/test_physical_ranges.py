"""Physically absurd parameters: values beyond what double precision can compute with (density 1e300 kg/m^3: before,
it ran and every projection failed, exit 0) are a ConfigError naming the parameter (and in a scene the section);
implausible but computable ones (density 1e7 kg/m^3, dt 2 s, E 1e15 Pa) an ImplausibleValueWarning with the reason.
Numbers in these messages are compact (``1e+300``, never 301 digits)."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest

import fepr
from fepr._validate import COMPUTABLE, compact_numbers, shown
from fepr.cli import EXIT_INVALID, main
from fepr.errors import ConfigError, ImplausibleValueWarning
from fepr.scene import scene_from_dict

MESH = fepr.meshes.builtin("box", size=0.1, resolution=1)
SOFT = fepr.NeoHookean(youngs_modulus=1e5, poisson_ratio=0.3)


def sim(**kw):
    args = dict(material=SOFT, density=1000.0, dt=1e-3)
    args.update(kw)
    return fepr.Simulation(MESH, **args)


# ----------------------------------------------------------------------------------------------------
# Errors: cannot be computed


@pytest.mark.parametrize(
    "kw, text",
    [
        (dict(density=1e300), "density = 1e+300 kg/m^3"),
        (dict(density=1e-300), "density = 1e-300 kg/m^3"),
        (dict(density=None, node_mass=1e120), "node_mass = 1e+120 kg"),
        (dict(dt=1e300), "dt = 1e+300 s"),
        (dict(dt=1e-150), "dt = 1e-150 s"),
        (dict(density=np.float64(1e200)), "density = 1e+200 kg/m^3"),
    ],
)
def test_api_rejects_values_that_cannot_be_computed(kw, text):
    with pytest.raises(ConfigError) as info:
        sim(**kw)
    msg = str(info.value)
    assert msg.startswith(f"{text} is outside the range fepr can compute with (1e-100 to 1e+100"), msg
    assert "overflow or vanish in double precision" in msg
    assert len(msg) < 300


@pytest.mark.parametrize("e", [1e300, 1e-300])
def test_material_rejects_youngs_modulus_that_cannot_be_computed(e):
    with pytest.raises(ConfigError, match=r"^youngs_modulus = 1e[-+]300 Pa is outside the range fepr can compute with"):
        fepr.StableNeoHookean(youngs_modulus=e, poisson_ratio=0.3)


def test_edges_of_the_computable_range_are_accepted():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ImplausibleValueWarning)
        sim(density=COMPUTABLE[1])
        fepr.NeoHookean(youngs_modulus=COMPUTABLE[0], poisson_ratio=0.3)


# ----------------------------------------------------------------------------------------------------
# Warnings: implausible


@pytest.mark.parametrize(
    "make, parameter, text",
    [
        (
            lambda: sim(density=1e7),
            "density",
            "density = 1e+07 kg/m^3 is implausible (above 1e+06 kg/m^3): real solids",
        ),
        (lambda: sim(density=1e-4), "density", "density = 0.0001 kg/m^3 is implausible (below 0.001 kg/m^3)"),
        (lambda: sim(dt=2.0), "dt", "dt = 2 s is implausible (above 1 s): time steps of elastic simulations"),
        (lambda: sim(dt=1e-10), "dt", "dt = 1e-10 s is implausible (below 1e-09 s)"),
        (
            lambda: fepr.NeoHookean(1e15, 0.3),
            "youngs_modulus",
            "youngs_modulus = 1e+15 Pa is implausible (above 1e+13 Pa)",
        ),
        (lambda: fepr.Arap(0.5, 0.3), "youngs_modulus", "youngs_modulus = 0.5 Pa is implausible (below 1 Pa)"),
    ],
)
def test_api_warns_about_implausible_values(make, parameter, text):
    with pytest.warns(ImplausibleValueWarning) as record:
        make()
    assert len(record) == 1
    w = record[0]
    assert str(w.message).startswith(text), str(w.message)
    assert "check the value and its units" in str(w.message)
    assert w.message.parameter == parameter
    assert w.filename == __file__  # points at the caller, not into fepr


def test_typical_values_do_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for density in (0.01, 1.0, 1000.0, 2.3e4):
            sim(density=density)
        for dt in (1e-6, 1 / 60, 1.0):
            sim(dt=dt)
        for e in (1.0, 1e3, 2e11, 1e13):
            fepr.NeoHookean(youngs_modulus=e, poisson_ratio=0.3)


# ----------------------------------------------------------------------------------------------------
# Scenes: the same bounds, naming the file and the section

BASE = {
    "mesh": {"builtin": "box", "size": 0.1, "resolution": 1},
    "material": {"youngs_modulus": 1e5, "poisson_ratio": 0.3},
    "mass": {"density": 1000.0},
    "integrator": {"dt": 1e-3},
}


def scene_dict(section, key, value):
    d = copy.deepcopy(BASE)
    if key == "node_mass":
        d["mass"] = {}
    d[section][key] = value
    return d


@pytest.mark.parametrize(
    "section, key, value, text",
    [
        ("mass", "density", 1e300, "scene.toml: [mass] density = 1e+300 kg/m^3 is outside the range"),
        ("mass", "node_mass", 1e-200, "scene.toml: [mass] node_mass = 1e-200 kg is outside the range"),
        ("material", "youngs_modulus", 1e120, "scene.toml: [material] youngs_modulus = 1e+120 Pa is outside the range"),
        ("integrator", "dt", 1e300, "scene.toml: [integrator] dt = 1e+300 s is outside the range"),
    ],
)
def test_scene_rejects_values_that_cannot_be_computed(section, key, value, text):
    with pytest.raises(ConfigError) as info:
        scene_from_dict(scene_dict(section, key, value), source="scene.toml")
    assert str(info.value).startswith(text), str(info.value)


def test_multibody_scene_names_the_body():
    body = {k: copy.deepcopy(BASE[k]) for k in ("mesh", "material", "mass")}
    body["mass"]["density"] = 1e300
    with pytest.raises(
        ConfigError, match=r"^scene\.toml: \[\[bodies\]\] #1 \[mass\] density = 1e\+300 kg/m\^3 is outside"
    ):
        scene_from_dict({"bodies": [body]}, source="scene.toml")


@pytest.mark.parametrize(
    "section, key, value, text",
    [
        ("mass", "density", 1e7, "scene.toml: [mass] density = 1e+07 kg/m^3 is implausible"),
        ("material", "youngs_modulus", 1e15, "scene.toml: [material] youngs_modulus = 1e+15 Pa is implausible"),
        ("integrator", "dt", 5.0, "scene.toml: [integrator] dt = 5 s is implausible"),
    ],
)
def test_scene_build_warns_with_the_section(section, key, value, text):
    scene = scene_from_dict(scene_dict(section, key, value), source="scene.toml")
    with pytest.warns(ImplausibleValueWarning) as record:
        scene.build()
    messages = [str(w.message) for w in record if issubclass(w.category, ImplausibleValueWarning)]
    assert messages and all(m.startswith(text) for m in messages), messages


def test_cli_refuses_density_1e300(tmp_path, capsys):
    path = tmp_path / "heavy.toml"
    path.write_text(
        '[mesh]\nbuiltin = "box"\nsize = 0.1\nresolution = 1\n[material]\nyoungs_modulus = 1e5\npoisson_ratio = 0.3\n'
        "[mass]\ndensity = 1e300\n[world]\ngravity = [0.0, 0.0, -9.81]\n[run]\nsteps = 3\n"
    )
    code = main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == EXIT_INVALID
    assert "heavy.toml: [mass] density = 1e+300 kg/m^3 is outside the range fepr can compute with" in err, err


# ----------------------------------------------------------------------------------------------------
# Compact numbers in messages


def test_core_message_with_a_huge_number_is_compact():
    """The core prints f64 with Rust's ``{}`` (301 digits for 1e300); the Python message shortens it."""
    with pytest.raises(ConfigError) as info:
        fepr.NeoHookean(youngs_modulus=-1e300, poisson_ratio=0.3)
    msg = str(info.value)
    assert msg.endswith("got -1e+300"), msg
    assert len(msg) < 120


def test_numpy_scalars_in_messages_read_as_numbers():
    with pytest.raises(ConfigError) as info:
        sim(dt=np.float64(-1e300))
    msg = str(info.value)
    assert msg.endswith("got -1e+300") and "np.float64" not in msg, msg


def test_scene_message_cuts_a_huge_value():
    d = copy.deepcopy(BASE)
    d["integrator"]["dt"] = list(range(100_000))
    with pytest.raises(ConfigError) as info:
        scene_from_dict(d, source="scene.toml")
    msg = str(info.value)
    assert msg.startswith("scene.toml: [integrator] dt must be a number, got [0, 1, 2,") and msg.endswith("..."), msg
    assert len(msg) < 200


@pytest.mark.parametrize(
    "value, text",
    [
        (1e300, "1e+300"),
        (np.float64(0.25), "0.25"),
        (10**400, "1e+400"),
        (-(12345678901234567890), "-1.23456e+19"),
        (7, "7"),
    ],
)
def test_shown(value, text):
    assert shown(value) == text


def test_compact_numbers():
    long = "1" + "0" * 300
    tiny = "0." + "0" * 299 + "1"
    msg = f"step 3 (t = {long}.000000 s): the step of dt = {tiny} s; vertex 12345 of tets [1, 2]; 3.5; "
    msg += "18446744073709551615"
    assert compact_numbers(msg) == (
        "step 3 (t = 1e+300 s): the step of dt = 1e-300 s; vertex 12345 of tets [1, 2]; 3.5; 18446744073709551615"
    )
