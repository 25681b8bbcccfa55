"""Scene files: validation (every key, every type), path resolution, builtin meshes, initial state."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

import fepr
from fepr import meshes
from fepr.cli.demo import DEMO_SCENES
from fepr.errors import ConfigError, FeprError
from fepr.scene import SCENE_KEYS, Scene, load_scene, scene_from_dict

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def minimal() -> dict:
    return {
        "mesh": {"builtin": "ell"},
        "material": {"youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 5.0},
    }


def with_(section: str, **keys) -> dict:
    d = minimal()
    d.setdefault(section, {}).update(keys)
    return d


def write_scene(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def write_tetgen(base: Path, mesh) -> None:
    """Write ``mesh`` as TetGen ``base.node`` / ``base.ele`` (1-based numbering, as TetGen writes)."""
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.tets)
    lines = [f"{len(v)} 3 0 0"] + [f"{i + 1} {x:.17g} {y:.17g} {z:.17g}" for i, (x, y, z) in enumerate(v)]
    Path(str(base) + ".node").write_text("\n".join(lines) + "\n")
    lines = [f"{len(t)} 4 0"] + [f"{i + 1} " + " ".join(str(j + 1) for j in tet) for i, tet in enumerate(t)]
    Path(str(base) + ".ele").write_text("\n".join(lines) + "\n")


# ---- defaults ------------------------------------------------------------------------------------------


def test_minimal_scene_has_documented_defaults():
    s = scene_from_dict(minimal(), ".")
    assert isinstance(s, Scene)
    assert s.material.model == "neo_hookean"
    assert s.integrator.name == "symplectic_euler"
    assert s.integrator.dt == pytest.approx(1.0 / 30.0)
    assert s.projection.enabled is True
    assert s.projection.options() == {}
    assert s.world.gravity == (0.0, 0.0, 0.0)
    assert s.world.pinned == () and s.world.pin_below is None
    assert s.world.damping == 0.0
    assert s.run.steps == 100
    assert s.initial.is_rest()


def test_integers_are_accepted_where_numbers_are_expected():
    d = with_("integrator", dt=1)
    d["material"]["youngs_modulus"] = 1000
    d["world"] = {"gravity": [0, 0, -10]}
    s = scene_from_dict(d, ".")
    assert s.integrator.dt == 1.0 and isinstance(s.integrator.dt, float)
    assert s.world.gravity == (0.0, 0.0, -10.0)


# ---- unknown keys and sections -------------------------------------------------------------------------


@pytest.mark.parametrize("section", sorted(SCENE_KEYS))
def test_unknown_key_in_each_section_is_named(section):
    d = with_(section, bogus_key=1)
    with pytest.raises(ConfigError) as info:
        scene_from_dict(d, ".", source="scene.toml")
    msg = str(info.value)
    assert msg.startswith("scene.toml: ")
    assert f"[{section}] unknown key 'bogus_key'" in msg
    assert "known: " + ", ".join(SCENE_KEYS[section]) in msg


def test_misspelled_key_lists_the_known_ones():
    d = minimal()
    d["material"]["youngs_modulu"] = d["material"].pop("youngs_modulus")
    with pytest.raises(ConfigError, match=r"\[material\] unknown key 'youngs_modulu' \(known: model, youngs_modulus"):
        scene_from_dict(d, ".", source="scene.toml")


def test_unknown_section_is_named():
    d = minimal()
    d["materials"] = {}
    with pytest.raises(ConfigError, match=r"unknown section \[materials\]"):
        scene_from_dict(d, ".")


def test_section_that_is_not_a_table():
    d = minimal()
    d["run"] = 5
    with pytest.raises(ConfigError, match=r"\[run\] must be a section"):
        scene_from_dict(d, ".")


@pytest.mark.parametrize("section", ["mesh", "material", "mass"])
def test_required_sections(section):
    d = minimal()
    del d[section]
    with pytest.raises(ConfigError, match=rf"missing section \[{section}\]"):
        scene_from_dict(d, ".")


@pytest.mark.parametrize("key", ["youngs_modulus", "poisson_ratio"])
def test_required_material_keys(key):
    d = minimal()
    del d["material"][key]
    with pytest.raises(ConfigError, match=rf"\[material\] missing required key '{key}'"):
        scene_from_dict(d, ".")


# ---- wrong types and values ----------------------------------------------------------------------------

BAD_VALUES = [
    ("integrator", "dt", "abc", "[integrator] dt must be a number, got 'abc'"),
    ("integrator", "dt", True, "[integrator] dt must be a number, got True"),
    ("integrator", "dt", 0.0, "[integrator] dt must be > 0"),
    ("integrator", "dt", -0.01, "[integrator] dt must be > 0"),
    ("integrator", "name", "runge_kutta", "[integrator] name must be one of"),
    ("integrator", "name", 3, "[integrator] name must be a string"),
    ("material", "youngs_modulus", "1e3", "[material] youngs_modulus must be a number, got '1e3'"),
    ("material", "youngs_modulus", 0.0, "[material] youngs_modulus must be > 0"),
    ("material", "youngs_modulus", float("inf"), "[material] youngs_modulus must be finite"),
    ("material", "poisson_ratio", 0.5, "[material] poisson_ratio must be in (-1.0, 0.5)"),
    ("material", "poisson_ratio", [0.3], "[material] poisson_ratio must be a number"),
    ("material", "model", "linear", "[material] model must be one of 'neo_hookean', 'stable_neo_hookean'"),
    ("material", "j0", 0.0, "[material] j0 must be > 0"),
    ("mass", "node_mass", -1.0, "[mass] node_mass must be > 0"),
    ("mass", "node_mass", "5", "[mass] node_mass must be a number"),
    ("projection", "enabled", "yes", "[projection] enabled must be true or false, got 'yes'"),
    ("projection", "enabled", 1, "[projection] enabled must be true or false, got 1"),
    ("projection", "tolerance", -1e-10, "[projection] tolerance must be > 0"),
    ("projection", "max_iterations", 2.5, "[projection] max_iterations must be an integer, got 2.5"),
    ("projection", "max_iterations", 0, "[projection] max_iterations must be >= 1"),
    (
        "projection",
        "rows",
        "some",
        "[projection] rows must be one of 'auto', 'energy', 'energy_momentum', 'all'",
    ),
    ("projection", "c_eps", "big", "[projection] c_eps must be a number"),
    ("projection", "impact_bound", 0, "[projection] impact_bound must be > 0"),
    ("world", "gravity", [0, -9.81], "[world] gravity must be a list of 3 numbers"),
    ("world", "gravity", "down", "[world] gravity must be a list of 3 numbers"),
    ("world", "gravity", [0, 0, "g"], "[world] gravity must be a list of 3 numbers"),
    ("world", "damping", -0.1, "[world] damping must be >= 0"),
    ("world", "pinned", [0, 1.5], "[world] pinned must be a list of vertex indices"),
    ("world", "pinned", 3, "[world] pinned must be a list of vertex indices"),
    ("world", "pinned", [-1], "[world] pinned: vertex indices must be >= 0"),
    ("world", "pin_below", 0.0, "[world] pin_below must be a table"),
    ("world", "pin_below", {"axis": "w", "value": 0.0}, "[world] pin_below.axis must be"),
    ("world", "pin_below", {"axis": "z"}, "[world] pin_below: missing required key 'value'"),
    ("world", "pin_below", {"axis": "z", "value": "low"}, "[world] pin_below.value must be a number"),
    ("world", "pin_below", {"axis": "z", "value": 0, "margin": 1}, "[world] pin_below: unknown key 'margin'"),
    ("run", "steps", 3.5, "[run] steps must be an integer, got 3.5"),
    ("run", "steps", "10", "[run] steps must be an integer, got '10'"),
    ("run", "steps", -1, "[run] steps must be >= 0"),
    ("run", "threads", 0, "[run] threads must be >= 1"),
    ("initial", "scale", 0.0, "[initial] scale must be > 0"),
    ("initial", "scale", "big", "[initial] scale must be a number"),
    ("initial", "scale_about", "middle", '[initial] scale_about must be [x, y, z] or "centroid"'),
    ("initial", "scale_about", [1, 2], '[initial] scale_about must be [x, y, z] or "centroid"'),
    ("initial", "velocity", "fast", "[initial] velocity must be a list of 3 numbers"),
    ("initial", "angular_velocity", [1, 2, 3, 4], "[initial] angular_velocity must be a list of 3 numbers"),
    ("initial", "alternating_velocity", [0, 0, None], "[initial] alternating_velocity must be a list of 3"),
    ("initial", "velocities", 5, "[initial] velocities must be a string"),
    ("mesh", "scale", -2.0, "[mesh] scale must be > 0"),
    ("mesh", "translate", [0, 0], "[mesh] translate must be a list of 3 numbers"),
    ("mesh", "resolution", 1.5, "[mesh] resolution must be an integer"),
    ("mesh", "resolution", 0, "[mesh] resolution must be >= 1"),
    ("mesh", "size", -1.0, "[mesh] size must be > 0"),
    ("mesh", "builtin", 7, "[mesh] builtin must be a string"),
    ("scene", "name", 5, "[scene] name must be a string"),
]


@pytest.mark.parametrize("section,key,value,fragment", BAD_VALUES, ids=[f"{s}.{k}={v!r}" for s, k, v, _ in BAD_VALUES])
def test_bad_value_is_named(section, key, value, fragment):
    d = with_(section, **{key: value})
    with pytest.raises(ConfigError) as info:
        scene_from_dict(d, ".", source="scene.toml")
    msg = str(info.value)
    assert msg.startswith("scene.toml: ")
    assert fragment in msg


def test_config_error_is_a_fepr_error_and_value_error():
    with pytest.raises(FeprError):
        scene_from_dict(with_("integrator", dt="abc"), ".")
    with pytest.raises(ValueError):
        scene_from_dict(with_("integrator", dt="abc"), ".")
    assert fepr.ConfigError is ConfigError


# ---- mass ----------------------------------------------------------------------------------------------


def test_node_mass_and_density_together_is_an_error():
    d = with_("mass", density=1000.0)
    with pytest.raises(ConfigError, match=r"\[mass\] give exactly one of 'node_mass'.*'density'"):
        scene_from_dict(d, ".")


def test_neither_node_mass_nor_density_is_an_error():
    d = minimal()
    d["mass"] = {}
    with pytest.raises(ConfigError, match=r"\[mass\] give exactly one of"):
        scene_from_dict(d, ".")


def test_density_gives_lumped_masses():
    d = minimal()
    d["mass"] = {"density": 100.0}
    d["mesh"] = {"builtin": "box", "size": 2.0, "resolution": 1}
    sim = scene_from_dict(d, ".").build()
    masses = np.asarray(sim.masses)
    if masses.ndim == 2:
        masses = masses[:, 0]
    assert masses.shape == (8,)
    assert masses.sum() == pytest.approx(100.0 * 8.0, rel=1e-12)


# ---- mesh ----------------------------------------------------------------------------------------------


def test_mesh_needs_exactly_one_source():
    d = with_("mesh", path="x.node")
    with pytest.raises(ConfigError, match=r"\[mesh\] give exactly one of 'path'"):
        scene_from_dict(d, ".")
    d = minimal()
    d["mesh"] = {"scale": 2.0}
    with pytest.raises(ConfigError, match=r"\[mesh\] give exactly one of 'path'"):
        scene_from_dict(d, ".")


def test_bad_mesh_path_names_the_path(tmp_path):
    scene = write_scene(
        tmp_path / "scene.toml",
        '[mesh]\npath = "no_such_mesh.1.node"\n[material]\nyoungs_modulus = 1e3\npoisson_ratio = 0.3\n'
        "[mass]\nnode_mass = 1.0\n",
    )
    with pytest.raises(ConfigError) as info:
        load_scene(scene)
    msg = str(info.value)
    assert str(tmp_path / "no_such_mesh.1.node") in msg
    assert str(scene) in msg and "[mesh] path" in msg


@pytest.mark.parametrize("given", ["cube.1.node", "cube.1", "meshes/../cube.1.ele"])
def test_mesh_path_is_relative_to_the_scene_file(tmp_path, monkeypatch, given):
    sub = tmp_path / "scenes"
    (sub / "meshes").mkdir(parents=True)
    write_tetgen(sub / "cube.1", meshes.box(size=(1.0, 2.0, 3.0), resolution=1))
    scene = write_scene(
        sub / "scene.toml",
        f'[mesh]\npath = "{given}"\nscale = 2.0\ntranslate = [1.0, 0.0, 0.0]\n'
        "[material]\nyoungs_modulus = 1e3\npoisson_ratio = 0.3\n[mass]\nnode_mass = 1.0\n",
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    s = load_scene(scene)
    assert s.mesh.path is not None and s.mesh.path.is_absolute()
    assert s.mesh.path.parent.resolve() in (sub.resolve(), (sub / "meshes").resolve())
    mesh = s.load_mesh()
    assert mesh.num_vertices == 8 and mesh.num_tets == 6
    lo, hi = mesh.bounding_box()
    np.testing.assert_allclose(lo, [0.0, -2.0, -3.0], atol=1e-12)
    np.testing.assert_allclose(hi, [2.0, 2.0, 3.0], atol=1e-12)
    sim = s.build()
    np.testing.assert_allclose(sim.positions, mesh.vertices)


def test_path_mesh_rejects_builtin_options(tmp_path):
    write_tetgen(tmp_path / "m", meshes.box(resolution=1))
    d = minimal()
    d["mesh"] = {"path": "m.node", "resolution": 2}
    with pytest.raises(ConfigError, match=r"\[mesh\] resolution applies to builtin meshes only"):
        scene_from_dict(d, tmp_path)


def test_builtin_box_options():
    d = minimal()
    d["mesh"] = {
        "builtin": "box",
        "size": [2.0, 1.0, 1.0],
        "resolution": [2, 1, 1],
        "center": [0.0, 0.0, 5.0],
    }
    mesh = scene_from_dict(d, ".").load_mesh()
    assert mesh.num_tets == 6 * 2
    lo, hi = mesh.bounding_box()
    np.testing.assert_allclose(lo, [-1.0, -0.5, 4.5])
    np.testing.assert_allclose(hi, [1.0, 0.5, 5.5])


def test_builtin_box_scalar_size_and_resolution():
    d = minimal()
    d["mesh"] = {"builtin": "box", "size": 0.5, "resolution": 3}
    mesh = scene_from_dict(d, ".").load_mesh()
    assert mesh.num_vertices == 4**3
    lo, hi = mesh.bounding_box()
    np.testing.assert_allclose(hi - lo, [0.5, 0.5, 0.5])


def test_builtin_ell_options_and_transform():
    d = minimal()
    d["mesh"] = {"builtin": "ell", "size": 0.5, "resolution": 2, "scale": 2.0, "translate": [0.0, 0.0, 1.0]}
    mesh = scene_from_dict(d, ".").load_mesh()
    ref = meshes.builtin("ell", size=0.5, resolution=2)
    assert mesh.num_tets == ref.num_tets
    np.testing.assert_allclose(mesh.vertices, 2.0 * ref.vertices + [0.0, 0.0, 1.0])


def test_builtin_option_that_does_not_apply():
    d = minimal()
    d["mesh"] = {"builtin": "ell", "center": [0.0, 0.0, 0.0]}
    with pytest.raises(ConfigError, match=r"\[mesh\] center does not apply to builtin 'ell'"):
        scene_from_dict(d, ".")


def test_unknown_builtin_lists_the_known_ones():
    d = minimal()
    d["mesh"] = {"builtin": "teapot"}
    known = r"\(known: box, cylinder, ell, sphere\)"
    with pytest.raises(ConfigError, match=r"\[mesh\] builtin: unknown built-in mesh 'teapot' " + known):
        scene_from_dict(d, ".")


# ---- files ---------------------------------------------------------------------------------------------


def test_missing_scene_file(tmp_path):
    with pytest.raises(ConfigError, match="scene file not found"):
        load_scene(tmp_path / "nope.toml")


def test_invalid_toml_names_the_file(tmp_path):
    p = write_scene(tmp_path / "broken.toml", "[mesh\nbuiltin = 'ell'\n")
    with pytest.raises(ConfigError, match=r"broken\.toml: invalid TOML"):
        load_scene(p)


def test_file_errors_start_with_the_file_name(tmp_path):
    p = write_scene(
        tmp_path / "scene.toml",
        '[mesh]\nbuiltin = "ell"\n[material]\nyoungs_modulus = 1e3\npoisson_ratio = 0.3\n'
        '[mass]\nnode_mass = 5.0\n[integrator]\ndt = "abc"\n',
    )
    with pytest.raises(ConfigError) as info:
        load_scene(p)
    assert str(info.value) == f"{p}: [integrator] dt must be a number, got 'abc'"


def test_scene_name_defaults_to_the_file_stem(tmp_path):
    p = write_scene(
        tmp_path / "my_scene.toml",
        '[mesh]\nbuiltin = "ell"\n[material]\nyoungs_modulus = 1e3\npoisson_ratio = 0.3\n[mass]\nnode_mass = 5.0\n',
    )
    assert load_scene(p).name == "my_scene"


# ---- building: material, projection, pins, initial state -----------------------------------------------


def test_build_passes_the_settings_on():
    d = minimal()
    d["integrator"] = {"dt": 0.01}
    d["world"] = {"gravity": [0.0, 0.0, -9.81]}
    sim = scene_from_dict(d, ".").build()
    assert sim.num_steps == 0
    np.testing.assert_allclose(sim.positions, meshes.builtin("ell").vertices)
    assert np.all(np.asarray(sim.velocities) == 0.0)
    sim.step(2)
    assert sim.time == pytest.approx(0.02)
    assert np.asarray(sim.velocities)[:, 2].mean() < 0  # falling


@pytest.mark.parametrize("model", ["neo_hookean", "stable_neo_hookean"])
def test_both_material_models_build(model):
    d = with_("material", model=model)
    d["initial"] = {"scale": 1.1}
    sim = scene_from_dict(d, ".").build()
    assert sim.energy().elastic > 0


def test_j0_is_for_neo_hookean_only():
    scene_from_dict(with_("material", j0=0.2), ".").build()
    with pytest.raises(ConfigError, match=r"\[material\] j0 applies to model 'neo_hookean' only"):
        scene_from_dict(with_("material", model="stable_neo_hookean", j0=0.2), ".")


def test_projection_override_and_options():
    d = with_("projection", tolerance=1e-9, max_iterations=7, rows="energy")
    d["initial"] = {"scale": 1.2}
    s = scene_from_dict(d, ".")
    assert s.projection.options() == {"tolerance": 1e-9, "max_iterations": 7, "rows": "energy"}
    sim = s.build()
    sim.step(1)
    assert sim.last_projection is not None
    assert sim.last_projection.iterations <= 7
    off = s.build(projection=False)
    off.step(1)
    assert off.last_projection is None


def test_projection_disabled_in_the_scene():
    d = with_("projection", enabled=False)
    d["initial"] = {"scale": 1.2}
    sim = scene_from_dict(d, ".").build()
    sim.step(1)
    assert sim.last_projection is None


def test_pinned_indices_and_pin_below():
    d = minimal()
    d["world"] = {"pinned": [0, 1], "pin_below": {"axis": "z", "value": 0.0}, "gravity": [0, 0, -9.81]}
    d["integrator"] = {"dt": 0.01}
    s = scene_from_dict(d, ".")
    rest = np.asarray(meshes.builtin("ell").vertices)
    idx = s.pinned_indices(rest)
    expected = np.union1d([0, 1], np.flatnonzero(rest[:, 2] <= 0.0))
    np.testing.assert_array_equal(idx, expected)
    sim = s.build()
    sim.step(3)
    np.testing.assert_allclose(np.asarray(sim.positions)[idx], rest[idx])
    free = np.setdiff1d(np.arange(len(rest)), idx)
    assert np.asarray(sim.positions)[free, 2].mean() < rest[free, 2].mean()  # the free part sags


def test_pinned_index_out_of_range():
    d = minimal()
    d["world"] = {"pinned": [0, 10_000]}
    with pytest.raises(ConfigError, match=r"\[world\] pinned: vertex index 10000 out of range"):
        scene_from_dict(d, ".", source="s.toml").build()


def test_pin_below_that_pins_nothing():
    d = minimal()
    d["world"] = {"pin_below": {"axis": "z", "value": -1.0}}
    with pytest.raises(ConfigError, match=r"\[world\] pin_below: no vertex has z <= -1"):
        scene_from_dict(d, ".").build()


def test_initial_scale_about_origin_and_centroid():
    s = scene_from_dict(with_("initial", scale=1.5), ".")
    rest = np.asarray(meshes.builtin("ell").vertices)
    sim = s.build()
    np.testing.assert_allclose(sim.positions, 1.5 * rest)
    np.testing.assert_allclose(sim.rest_positions, rest)
    s = scene_from_dict(with_("initial", scale=1.5, scale_about="centroid"), ".")
    x = np.asarray(s.build().positions)
    np.testing.assert_allclose(x.mean(axis=0), rest.mean(axis=0), atol=1e-12)
    s = scene_from_dict(with_("initial", scale=2.0, scale_about=[1.0, 1.0, 1.0]), ".")
    np.testing.assert_allclose(s.build().positions, 1.0 + 2.0 * (rest - 1.0))


def test_initial_spin_and_throw():
    s = scene_from_dict(with_("initial", angular_velocity=[0.0, 0.0, 2.0], velocity=[1.0, 0.0, 0.0]), ".")
    sim = s.build()
    x, v = np.asarray(sim.positions), np.asarray(sim.velocities)
    c = x.mean(axis=0)  # uniform node masses
    np.testing.assert_allclose(v, np.cross([0.0, 0.0, 2.0], x - c) + [1.0, 0.0, 0.0], atol=1e-12)
    m_tot = 5.0 * len(x)
    np.testing.assert_allclose(sim.linear_momentum(), [m_tot, 0.0, 0.0], atol=1e-9)
    r = x - c
    expected_L = 5.0 * np.cross(r, np.cross([0.0, 0.0, 2.0], r)).sum(axis=0)  # I omega about the CoM
    np.testing.assert_allclose(sim.angular_momentum(), expected_L, rtol=1e-12, atol=1e-9)
    assert expected_L[2] > 0


def test_initial_alternating_velocity():
    sim = scene_from_dict(with_("initial", alternating_velocity=[0.0, 0.0, -5.0]), ".").build()
    v = np.asarray(sim.velocities)
    np.testing.assert_array_equal(v[0::2], np.tile([0.0, 0.0, -5.0], (len(v[0::2]), 1)))
    np.testing.assert_array_equal(v[1::2], 0.0)


def test_initial_velocities_file_is_relative_to_the_scene(tmp_path):
    m = meshes.builtin("ell").num_vertices
    v = np.random.default_rng(0).normal(size=(m, 3))
    np.save(tmp_path / "v.npy", v)
    s = scene_from_dict(with_("initial", velocities="v.npy"), tmp_path)
    assert s.initial.velocities == tmp_path / "v.npy"
    np.testing.assert_allclose(s.build().velocities, v)


def test_initial_velocities_file_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"\[initial\] velocities: file not found: .*missing\.npy"):
        scene_from_dict(with_("initial", velocities="missing.npy"), tmp_path)
    np.save(tmp_path / "bad.npy", np.zeros((3, 3)))
    s = scene_from_dict(with_("initial", velocities="bad.npy"), tmp_path)
    with pytest.raises(ConfigError, match=r"bad\.npy has shape \(3, 3\), expected"):
        s.build()


def test_pinned_vertices_start_at_rest():
    d = with_("initial", velocity=[1.0, 0.0, 0.0])
    d["world"] = {"pinned": [0, 3]}
    v = np.asarray(scene_from_dict(d, ".").build().velocities)
    np.testing.assert_array_equal(v[[0, 3]], 0.0)
    assert np.all(v[[1, 2]][:, 0] == 1.0)


# ---- examples ------------------------------------------------------------------------------------------

EXAMPLE_FILES = sorted(EXAMPLES.glob("*.toml"))


def test_the_required_examples_exist():
    names = {p.name for p in EXAMPLE_FILES}
    assert {"seed_demo3_stretch.toml", "spinning_l_gravity.toml", "wobbly_box.toml"} <= names


@pytest.mark.parametrize("path", EXAMPLE_FILES, ids=[p.stem for p in EXAMPLE_FILES])
def test_example_loads_builds_and_steps(path):
    s = load_scene(path)
    assert all(b.mesh.builtin is not None for b in s.body_settings())  # examples use builtin meshes only
    sim = s.build_multibody() if s.is_multibody else s.build()
    sim.step(2)
    assert np.all(np.isfinite(sim.positions))


@pytest.mark.parametrize("name", sorted(set(DEMO_SCENES) & {p.stem for p in EXAMPLE_FILES}))
def test_example_files_match_the_demo_scenes(name):
    f = load_scene(EXAMPLES / f"{name}.toml")
    d = copy.deepcopy(DEMO_SCENES[name])
    s = scene_from_dict(d, ".")
    for section in ("material", "mass", "initial", "projection", "world", "run"):
        assert getattr(f, section) == getattr(s, section), section
    assert f.integrator.name == s.integrator.name
    assert f.integrator.dt == pytest.approx(s.integrator.dt, rel=1e-12)
    np.testing.assert_allclose(f.load_mesh().vertices, s.load_mesh().vertices)


def test_integrator_options_reach_the_integrator_and_foreign_options_are_named():
    from fepr.scene import scene_from_dict

    base = {
        "mesh": {"builtin": "ell"},
        "material": {"model": "neo_hookean", "youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 5.0},
        "projection": {"enabled": True, "slack": "off"},
    }
    sim = scene_from_dict(
        {**base, "integrator": {"name": "implicit_euler", "tolerance": 1e-8, "max_iterations": 7}}
    ).build()
    assert sim.integrator_settings == fepr.ImplicitEuler(tolerance=1e-8, max_iterations=7)
    assert sim.projection.slack == "off"
    sim = scene_from_dict({**base, "integrator": {"name": "projective_dynamics", "iterations": 4}}).build()
    assert sim.integrator_settings == fepr.ProjectiveDynamics(iterations=4)
    with pytest.raises(fepr.ConfigError, match="iterations is not an option of 'implicit_euler'"):
        scene_from_dict({**base, "integrator": {"name": "implicit_euler", "iterations": 4}}).build()
