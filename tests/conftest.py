"""Shared fixtures: where the project's real test meshes live (``../shared/meshes``, which CI has)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def shared_meshes_dir() -> Path | None:
    env = os.environ.get("FEPR_SHARED_MESHES")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "shared" / "meshes")
    for c in candidates:
        if c.is_dir():
            return c
    return None


@pytest.fixture
def shared_meshes() -> Path:
    d = shared_meshes_dir()
    if d is None:
        pytest.skip("the shared test meshes (../shared/meshes or $FEPR_SHARED_MESHES) are not present")
    return d
