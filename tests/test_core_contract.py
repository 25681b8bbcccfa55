"""One contract between Python and Rust: the name lists are the core's, and Python uses them.

Every name list (integrators, materials, projection rows, metrics, slack and warm-start modes, history
columns, projection-report fields) is defined once in the Rust core and exported by ``fepr._core``; these tests
check that what the Python package declares (classes per name, dataclass fields, ``_core.pyi``) is exactly
that list, and that validation and policy come from the core (messages naming ``section.key``).
"""

from __future__ import annotations

import ast
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

import fepr
from fepr import _core
from fepr import simulation as fsim
from fepr.materials import MATERIAL_TYPES

STUB = Path(fepr.__file__).with_name("_core.pyi")

NAME_LISTS = (
    "INTEGRATORS",
    "MATERIALS",
    "PROJECTION_ROWS",
    "METRICS",
    "SLACK_MODES",
    "WARM_START_MODES",
    "HISTORY_COLUMNS",
    "HISTORY_INTEGER_COLUMNS",
    "PROJECTION_REPORT_FIELDS",
)


@pytest.mark.parametrize("name", NAME_LISTS)
def test_name_lists_are_exported_distinct_strings_and_declared_in_the_stub(name):
    values = getattr(_core, name)
    assert values and all(isinstance(v, str) and v for v in values), name
    assert len(set(values)) == len(values), f"{name} repeats a name"
    stub = {n.target.id for n in ast.parse(STUB.read_text()).body if isinstance(n, ast.AnnAssign)}
    assert name in stub, f"{name} is not declared in _core.pyi"


def test_integrator_classes_are_the_cores_integrators():
    assert list(fsim.INTEGRATOR_TYPES) == list(_core.INTEGRATORS)
    for name, cls in fsim.INTEGRATOR_TYPES.items():
        assert cls.name == name
        assert getattr(fepr, cls.__name__) is cls


def test_material_classes_are_the_cores_materials():
    assert list(MATERIAL_TYPES) == list(_core.MATERIALS)
    for name, cls in MATERIAL_TYPES.items():
        assert cls.model == name
        assert getattr(fepr, cls.__name__) is cls


def test_projection_choices_are_the_cores():
    assert fsim.ROWS == tuple(_core.PROJECTION_ROWS)
    assert fsim.METRICS == tuple(_core.METRICS)
    assert fsim.SLACK_MODES == tuple(_core.SLACK_MODES)
    for rows in _core.PROJECTION_ROWS:
        fepr.Projection(rows=rows)
    for metric in _core.METRICS:
        fepr.Projection(metric=metric)
    for slack in _core.SLACK_MODES:
        fepr.Projection(slack=slack)
    for mode in _core.WARM_START_MODES:
        fepr.Projection(warm_start=mode)


def test_report_fields_are_the_cores():
    fields = [f.name for f in dataclasses.fields(fepr.ProjectionReport)]
    assert set(fields) == set(_core.PROJECTION_REPORT_FIELDS)
    stub = next(
        n for n in ast.parse(STUB.read_text()).body if isinstance(n, ast.ClassDef) and n.name == "_ProjectionReportDict"
    )
    keys = {n.target.id for n in stub.body if isinstance(n, ast.AnnAssign)}
    assert keys == set(_core.PROJECTION_REPORT_FIELDS)
    sim = fepr.Simulation(fepr.meshes.ell(), material=fepr.NeoHookean(1e3, 0.3), node_mass=1.0, dt=0.01)
    sim.positions = 1.1 * sim.rest_positions
    sim.step(1)
    assert list(sim._sim.last_projection()) == list(_core.PROJECTION_REPORT_FIELDS)


def test_history_columns_are_the_cores():
    assert _core.Simulation.history_columns() == list(_core.HISTORY_COLUMNS)
    assert fepr.History.INTEGER_COLUMNS == frozenset(_core.HISTORY_INTEGER_COLUMNS)
    assert set(_core.HISTORY_INTEGER_COLUMNS) <= set(_core.HISTORY_COLUMNS)


def test_projection_settings_cover_the_projection_fields():
    """Every ``fepr.Projection`` field crosses to the core under its own name (the core rejects unknown keys)."""
    p = fepr.Projection()
    _core.check_projection(p._settings())
    with pytest.raises(ValueError, match=r"projection: unknown key 'toleranse'"):
        _core.check_projection({"toleranse": 1e-8})


def test_warm_start_policy_is_the_cores():
    assert fsim.PD_WARM_START == _core.PD_WARM_START == _core.warm_start_threshold("projective_dynamics")
    assert fsim.XPBD_WARM_START == _core.XPBD_WARM_START == _core.warm_start_threshold("xpbd")
    assert math.isinf(_core.warm_start_threshold("implicit_euler"))
    assert math.isinf(_core.warm_start_threshold("symplectic_euler"))


@pytest.mark.parametrize(
    ("integrator", "expected"),
    [
        ("projective_dynamics", fepr.Arap),
        ("xpbd", fepr.ConstraintNeoHookean),
        ("implicit_euler", fepr.StableNeoHookean),
    ],
)
def test_conserved_material_is_the_cores(integrator, expected):
    sim = fepr.Simulation(
        fepr.meshes.ell(),
        material=fepr.StableNeoHookean(2e3, 0.25),
        node_mass=1.0,
        dt=0.01,
        integrator=integrator,
    )
    assert type(sim.material) is expected
    assert (sim.material.youngs_modulus, sim.material.poisson_ratio) == (2e3, 0.25)
    conserved = _core.conserved_material(integrator)
    assert conserved == (None if expected is fepr.StableNeoHookean else expected.model)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: fepr.Projection(tolerance=-1), r"^projection\.tolerance must satisfy 0 < tolerance < 1, got -1$"),
        (lambda: fepr.Projection(max_iterations=0), r"^projection\.max_iterations "),
        (lambda: fepr.Projection(max_iterations=2.0), r"^projection\.max_iterations must be a non-negative integer"),
        (lambda: fepr.Projection(c_eps=True), r"^projection\.c_eps must be a number, got True$"),
        (lambda: fepr.Projection(max_halvings=61), r"^projection\.max_halvings must be in 0\.\.=60, got 61$"),
        (lambda: fepr.Projection(rows="some"), r"^projection\.rows must be one of auto, energy, energy_momentum"),
        (lambda: fepr.Projection(metric="l2"), r"^projection\.metric must be one of auto, mass, stiffness"),
        (lambda: fepr.Projection(slack="yes"), r"^projection\.slack must be one of auto, on, off"),
        (lambda: fepr.Projection(warm_start="sometimes"), r"^projection\.warm_start must be one of auto, off"),
        (lambda: fepr.Projection(warm_start=-1.0), r"^projection\.warm_start_threshold must be >= 0"),
        (lambda: fepr.Projection(quality_guard=1), r"^projection\.quality_guard must be true or false"),
        (lambda: fepr.Projection(quality_margin=2.0), r"^projection\.quality_margin must satisfy"),
        (lambda: fepr.Projection(impact_bound=0.0), r"^projection\.impact_bound must be positive"),
        (lambda: fepr.ImplicitEuler(tolerance=2.0), r"^integrator\.tolerance must satisfy 0 < tolerance < 1"),
        (lambda: fepr.ImplicitEuler(max_iterations=0), r"^integrator\.max_iterations must be in 1\.\.=1000"),
        (lambda: fepr.ProjectiveDynamics(iterations=0), r"^integrator\.iterations must be in 1\.\.=10000"),
        (lambda: fepr.Xpbd(substeps=0), r"^integrator\.substeps must be in 1\.\.=10000, got 0$"),
        (lambda: fepr.Xpbd(iterations=-1), r"^integrator\.iterations must be a non-negative integer"),
        (lambda: fepr.NeoHookean(-1.0, 0.3), r"^material\.youngs_modulus must be a positive finite number"),
        (lambda: fepr.NeoHookean(1e3, 0.5), r"^material\.poisson_ratio must satisfy -1 < nu < 0\.5"),
        (lambda: fepr.NeoHookean(1e3, 0.3, j0=0.0), r"^material\.j0 must satisfy 0 < j0 <= 1, got 0$"),
        (lambda: fepr.Arap("1e3", 0.3), r"^material\.youngs_modulus must be a number, got '1e3'$"),
    ],
)
def test_validation_is_the_cores_and_names_the_key(make, message):
    with pytest.raises(fepr.ConfigError, match=message):
        make()


def test_settings_objects_keep_their_values():
    """The public dataclasses are unchanged: the values a user gives are the values they hold."""
    p = fepr.Projection(tolerance=1e-8, rows="energy", warm_start=None, quality_guard=False)
    assert (p.tolerance, p.rows, p.warm_start, p.quality_guard) == (1e-8, "energy", None, False)
    m = fepr.NeoHookean(np.float64(1e3), 0.3, j0=np.float64(0.2))
    assert type(m.youngs_modulus) is float and m.j0 == 0.2
    assert fepr.Xpbd(substeps=np.int64(5)).substeps == 5


def test_projection_keys_are_the_projection_fields_and_the_scene_keys():
    from fepr.scene import SCENE_KEYS

    fields = [f.name for f in dataclasses.fields(fepr.Projection)]
    assert sorted(fields) == sorted(_core.PROJECTION_KEYS)
    assert SCENE_KEYS["projection"] == ("enabled", *_core.PROJECTION_KEYS)
