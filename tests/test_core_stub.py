"""The type stub ``python/fepr/_core.pyi`` declares exactly what the compiled ``fepr._core`` exports.

Guards the stub against drift: every module-level name, every class's public attributes, their kinds
(method, static method, property, writable property) and every argument list (names, positional or keyword-only,
with or without a default) are compared with the extension at run time.
"""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import numpy as np
import pytest

import fepr
from fepr import _core

STUB = Path(fepr.__file__).with_name("_core.pyi")


def _stub() -> ast.Module:
    return ast.parse(STUB.read_text(encoding="utf-8"))


def _decorators(fn: ast.FunctionDef) -> set:
    names = set()
    for d in fn.decorator_list:
        if isinstance(d, ast.Name):
            names.add(d.id)
        elif isinstance(d, ast.Attribute):
            names.add(d.attr)  # "setter" of @name.setter
    return names


def _stub_module_names(tree: ast.Module) -> set:
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
    # Private names are typing helpers of the stub (e.g. a TypedDict), except the module's version.
    return {n for n in names if not n.startswith("_") or n == "__version__"}


def _stub_classes(tree: ast.Module) -> dict:
    return {n.name: n for n in tree.body if isinstance(n, ast.ClassDef)}


def _stub_members(cls: ast.ClassDef) -> dict:
    """name -> kind ("method", "staticmethod", "property", "property+setter", "attribute") and its FunctionDef."""
    members: dict = {}
    for node in cls.body:
        if isinstance(node, ast.FunctionDef):
            deco = _decorators(node)
            assert "deleter" not in deco, f"{cls.name}.{node.name}: the extension has no deleters"
            if "setter" in deco:
                kind, fn = members[node.name]
                assert kind == "property", f"{cls.name}.{node.name}: setter without a property"
                members[node.name] = ("property+setter", fn)
            elif "property" in deco:
                members[node.name] = ("property", node)
            elif "staticmethod" in deco:
                members[node.name] = ("staticmethod", node)
            else:
                members[node.name] = ("method", node)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            members[node.target.id] = ("attribute", None)
    return members


def _stub_parameters(fn: ast.FunctionDef, skip_self: bool) -> list:
    """[(name, kind, has_default)] with kind "positional" or "keyword"."""
    a = fn.args
    positional = a.posonlyargs + a.args
    defaults = [False] * (len(positional) - len(a.defaults)) + [True] * len(a.defaults)
    out = [(p.arg, "positional", d) for p, d in zip(positional, defaults)]
    out += [(p.arg, "keyword", d is not None) for p, d in zip(a.kwonlyargs, a.kw_defaults)]
    assert a.vararg is None and a.kwarg is None, f"{fn.name}: *args/**kwargs are not used by the extension"
    if skip_self:
        assert out and out[0][0] == "self", f"{fn.name}: first argument must be self"
        out = out[1:]
    return out


def _runtime_parameters(obj, skip_self: bool) -> list:
    sig = inspect.signature(obj)
    out = []
    for p in sig.parameters.values():
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            raise AssertionError(f"{obj!r}: unexpected {p}")
        kind = "keyword" if p.kind == p.KEYWORD_ONLY else "positional"
        out.append((p.name, kind, p.default is not p.empty))
    if skip_self:
        assert out and out[0][0] == "self"
        out = out[1:]
    return out


def _runtime_classes() -> dict:
    return {n: getattr(_core, n) for n in _core.__all__ if inspect.isclass(getattr(_core, n))}


def _runtime_kind(cls, name: str) -> str:
    raw = inspect.getattr_static(cls, name)
    if isinstance(raw, staticmethod):
        return "staticmethod"
    if inspect.isgetsetdescriptor(raw) or isinstance(raw, property):
        return "property"
    if callable(raw):
        return "method"
    return "attribute"


def test_stub_declares_every_module_level_name():
    tree = _stub()
    runtime = set(_core.__all__)
    assert _stub_module_names(tree) == runtime, "module-level names of _core.pyi and fepr._core differ"


def test_stub_declares_every_public_attribute_of_every_class():
    stub_classes = _stub_classes(_stub())
    runtime = _runtime_classes()
    assert runtime, "fepr._core exports no class?"
    for name, cls in runtime.items():
        assert name in stub_classes, f"class {name} is missing from _core.pyi"
        stub = {n for n in _stub_members(stub_classes[name]) if not n.startswith("_")}
        public = {n for n in dir(cls) if not n.startswith("_")}
        assert stub == public, (
            f"{name}: missing from the stub {sorted(public - stub)}, not in the extension {sorted(stub - public)}"
        )


def test_stub_member_kinds_match():
    stub_classes = _stub_classes(_stub())
    for name, cls in _runtime_classes().items():
        for member, (kind, _) in _stub_members(stub_classes[name]).items():
            if member.startswith("_"):
                continue
            runtime = _runtime_kind(cls, member)
            assert kind.split("+")[0] == runtime, f"{name}.{member}: stub says {kind}, the extension has a {runtime}"


def test_stub_argument_lists_match():
    tree = _stub()
    checked = 0
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            fn = getattr(_core, node.name)
            assert _stub_parameters(node, False) == _runtime_parameters(fn, False), node.name
            checked += 1
    stub_classes = _stub_classes(tree)
    for name, cls in _runtime_classes().items():
        members = _stub_members(stub_classes[name])
        assert "__init__" in members, f"{name}: the stub declares no __init__"
        assert _stub_parameters(members["__init__"][1], True) == _runtime_parameters(cls, False), f"{name}.__init__"
        checked += 1
        for member, (kind, fn) in members.items():
            if kind == "method" and not member.startswith("_"):
                got = _runtime_parameters(getattr(cls, member), True)
                assert _stub_parameters(fn, True) == got, f"{name}.{member}"
                checked += 1
            elif kind == "staticmethod":
                assert _stub_parameters(fn, False) == _runtime_parameters(getattr(cls, member), False), member
                checked += 1
    assert checked >= 15


def _small_simulation():
    sim = fepr.Simulation(
        fepr.meshes.ell(),
        material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
        node_mass=1.0,
        dt=0.01,
    )
    return sim._sim


def test_stub_marks_exactly_the_writable_properties():
    core = _small_simulation()
    members = _stub_members(_stub_classes(_stub())["Simulation"])
    for member, (kind, _) in members.items():
        if not kind.startswith("property"):
            continue
        value = getattr(core, member)
        try:
            setattr(core, member, value)
            writable = True
        except AttributeError:
            writable = False
        assert writable == (kind == "property+setter"), f"Simulation.{member}: writable at run time: {writable}"


def test_projection_report_keys_match_the_stub():
    core = _small_simulation()
    core.positions = 1.1 * np.asarray(core.positions)
    core.step(1)
    report = core.last_projection()
    assert report is not None
    stub = _stub_classes(_stub())["_ProjectionReportDict"]
    keys = [n.target.id for n in stub.body if isinstance(n, ast.AnnAssign)]
    assert sorted(keys) == sorted(report)
    assert sorted(keys) == sorted(fepr.ProjectionReport.__dataclass_fields__)


@pytest.mark.parametrize("name", ["set_obstacles", "set_kinematic_pins", "first_runaway", "set_drag"])
def test_stub_has_the_members_it_once_lacked(name):
    # The stub used to omit the world setters and first_runaway (see CHANGELOG).
    assert name in _stub_members(_stub_classes(_stub())["Simulation"])
