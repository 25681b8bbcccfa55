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


def spinning_ell(integrator, projection):
    """The built-in L stretched 1.3x about its centre of mass, spinning at 1 rad/s about z and drifting at
    (0.5, 0.2, 0.1) m/s; Neo-Hookean E = 1e3 Pa, nu = 0.3, 5 kg per vertex, dt = 1/30 s."""
    import numpy as np

    import fepr

    sim = fepr.Simulation(
        fepr.meshes.ell(),
        material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
        node_mass=5.0,
        dt=1 / 30,
        integrator=integrator,
        projection=projection,
    )
    c = sim.center_of_mass()
    x = c + 1.3 * (sim.rest_positions - c)
    sim.positions = x
    sim.velocities = np.array([0.5, 0.2, 0.1]) + np.cross([0.0, 0.0, 1.0], x - c)
    return sim


def max_drifts(history):
    """Largest relative drifts of H, P and L (about the centre of mass) over a history, against row 0."""
    import numpy as np

    h = history
    dh = np.abs(h["total"] / h["total"][0] - 1).max()
    p = np.stack([h["px"], h["py"], h["pz"]], axis=1)
    ang = np.stack([h["lx"], h["ly"], h["lz"]], axis=1)
    dp = (np.linalg.norm(p - p[0], axis=1) / np.linalg.norm(p[0])).max()
    dl = (np.linalg.norm(ang - ang[0], axis=1) / np.linalg.norm(ang[0])).max()
    return dh, dp, dl
