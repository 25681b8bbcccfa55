"""Backward Euler (``integrator="implicit_euler"``), alone and with FEPR, through the Python API."""

from __future__ import annotations

import numpy as np
import pytest

import fepr
from conftest import max_drifts, spinning_ell


def test_integrator_by_name_and_by_object():
    a = spinning_ell("implicit_euler", False)
    b = spinning_ell(fepr.ImplicitEuler(tolerance=1e-6, max_iterations=20), False)
    a.step(3)
    b.step(3)
    np.testing.assert_array_equal(a.positions, b.positions)
    assert a.integrator == "implicit_euler"


@pytest.mark.parametrize("kwargs", [{"tolerance": 0.0}, {"tolerance": 1.5}, {"max_iterations": 0}, {"tolerance": "x"}])
def test_invalid_newton_settings_are_config_errors(kwargs):
    with pytest.raises(fepr.ConfigError, match=r"^integrator\.(tolerance|max_iterations) "):
        fepr.ImplicitEuler(**kwargs)


def test_backward_euler_alone_loses_more_than_half_its_energy_within_2_s():
    sim = spinning_ell("implicit_euler", False)
    sim.step(60)
    h = sim.history
    kept = h["total"][-1] / h["total"][0]
    assert kept < 0.5, kept
    assert np.all(h["base_iterations"][1:] >= 1)
    # Converged: the relative decrement below the tolerance (1e-6), or just above it where Newton stops because the
    # decrease it predicts is below Phi's round-off (the later iterations' directions come from conjugate
    # gradients, whose decrement differs from a direct solve's in the last digits).
    assert np.all(h["base_residual"][1:] <= 2e-6)


def test_backward_euler_with_fepr_holds_h_p_l_for_10_s():
    sim = spinning_ell("implicit_euler", True)
    sim.step(300)
    h = sim.history
    dh, dp, dl = max_drifts(h)
    print(
        f"\nbackward Euler + FEPR, 10 s: max |H/H0-1| {dh:.1e}, |dP|/P0 {dp:.1e}, |dL|/L0 {dl:.1e}, "
        f"projection iterations mean {h['proj_iterations'][1:].mean():.2f} max {h['proj_iterations'].max():.0f}"
    )
    assert np.all(h["proj_converged"][1:] == 1)
    assert dh <= 1e-8 and dp <= 1e-10 and dl <= 1e-10
    assert np.all(np.isfinite(sim.positions))


def test_pinned_cantilever_keeps_oscillating_with_fepr_and_dies_out_without():
    """A bar pinned at one end sags under gravity. Backward Euler damps the oscillation to nothing within 5 s;
    with FEPR (energy row only, the default with pins) the energy stays and the bar keeps swinging."""
    mesh = fepr.meshes.box(size=(1.0, 0.1, 0.1), resolution=(20, 2, 2), center=(0.5, 0.0, 1.0))
    pinned = np.flatnonzero(mesh.vertices[:, 0] <= 1e-9)
    tip = np.flatnonzero(mesh.vertices[:, 0] >= 1 - 1e-9)
    ratio = {}
    for projection in (True, False):
        sim = fepr.Simulation(
            mesh,
            material=fepr.NeoHookean(youngs_modulus=1e7, poisson_ratio=0.3),
            density=1000.0,
            dt=1 / 30,
            integrator="implicit_euler",
            projection=projection,
            gravity=(0, 0, -9.81),
            pinned=pinned,
        )
        z = []
        for _ in range(150):
            sim.step()
            z.append(sim.positions[tip, 2].mean())
        z = np.array(z)
        first = np.ptp(z[:15])
        last = np.ptp(z[-30:])
        ratio[projection] = last / first
        assert np.all(sim.positions[pinned] == mesh.vertices[pinned])
        if projection:
            h = sim.history
            assert np.all(h["proj_converged"][1:] == 1)
            assert np.abs(h["total"] / h["total"][0] - 1).max() <= 1e-8
    print(f"\ncantilever amplitude after 5 s / first swing: with FEPR {ratio[True]:.3f}, without {ratio[False]:.4f}")
    assert ratio[True] > 0.3
    assert ratio[False] < 0.01
