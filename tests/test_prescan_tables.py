"""The mesh pre-scan's format tables are its own (no import of meshio's private modules, which a meshio upgrade may
move): they agree with the formats as meshio reads them, checked here against meshio's tables when they exist."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from fepr.io import _prescan

PACKAGE = Path(_prescan.__file__).resolve().parent.parent


def test_no_module_of_fepr_imports_a_private_meshio_module():
    for path in PACKAGE.rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for n in names:
                if n.startswith("meshio"):
                    assert not any(part.startswith("_") for part in n.split(".")), f"{path}: imports {n}"


def test_the_gmsh_node_counts_match_meshio():
    common = pytest.importorskip("meshio._common", reason="meshio's private tables moved (nothing to compare)")
    gmsh = pytest.importorskip("meshio.gmsh.common")
    for code, cell in gmsh._gmsh_to_meshio_type.items():
        if code in _prescan.GMSH_NODES_PER_ELEMENT:
            assert _prescan.GMSH_NODES_PER_ELEMENT[code] == common.num_nodes_per_cell[cell], code


def test_the_meshb_item_sizes_match_meshio():
    medit = pytest.importorskip("meshio.medit._medit", reason="meshio's private tables moved (nothing to compare)")
    internal = pytest.importorskip("meshio.medit._medit_internal")
    for code, (name, _, layout) in _prescan.MESHB_KEYWORDS.items():
        assert internal.medit_codes[code][0] == name
        if not layout:
            continue
        for dim in (2, 3):
            for itype, ftype in (("i4", "f4"), ("i4", "f8"), ("i8", "f8")):
                expected = np.dtype(medit._produce_dtype(layout, dim, itype, ftype)).itemsize
                got = _prescan._meshb_item_bytes(layout, dim, np.dtype(itype).itemsize, np.dtype(ftype).itemsize)
                assert got == expected, (name, dim, itype, ftype)
