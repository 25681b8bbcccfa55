"""docs/materials.md documents every material the Python API and the Rust core offer.

Guards: the page once covered only the two Neo-Hookean materials (not ``Arap`` and ``ConstraintNeoHookean``).
"""

from __future__ import annotations

import re
from pathlib import Path

import fepr
from fepr import materials
from fepr.scene import MATERIAL_MODELS

ROOT = Path(__file__).resolve().parents[1]
PAGE = (ROOT / "docs" / "materials.md").read_text(encoding="utf-8")


def python_materials() -> list:
    return [
        c for c in vars(materials).values() if isinstance(c, type) and issubclass(c, materials._Material) and c.model
    ]


def rust_materials() -> list:
    src = (ROOT / "crates" / "fepr-core" / "src" / "material" / "mod.rs").read_text(encoding="utf-8")
    body = src.split("pub enum Material {", 1)[1].split("}", 1)[0]
    return re.findall(r"^\s*([A-Z][A-Za-z]*)\(", body, flags=re.M)


def test_every_python_material_is_documented_with_its_constructor():
    classes = python_materials()
    assert len(classes) >= 4
    for cls in classes:
        assert getattr(fepr, cls.__name__) is cls, f"fepr.{cls.__name__} is not exported"
        assert f"fepr.{cls.__name__}(youngs_modulus" in PAGE, f"no constructor of fepr.{cls.__name__} in materials.md"
        assert f'"{cls.model}"' in PAGE, f"scene model name {cls.model!r} not in materials.md"


def test_every_rust_material_and_scene_model_is_documented():
    variants = rust_materials()
    assert set(variants) == {c.__name__ for c in python_materials()}
    for v in variants:
        assert f"`{v}`" in PAGE, f"Rust material {v} not in materials.md"
    for name in MATERIAL_MODELS:
        assert f'"{name}"' in PAGE
