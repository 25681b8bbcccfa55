"""XPBD (``integrator="xpbd"``) and the projection's metric, through the Python API and scene files."""

from __future__ import annotations

import numpy as np
import pytest

import fepr
from conftest import max_drifts, spinning_ell


def test_xpbd_uses_the_constraint_energy_its_compliance_encodes():
    sim = spinning_ell("xpbd", True)
    assert isinstance(sim.material, fepr.ConstraintNeoHookean)
    mu = 1e3 / (2 * 1.3)
    lam = 1e3 * 0.3 / (1.3 * 0.4) + mu
    alpha = 1 + mu / lam
    rest = sim.rest_positions[sim.tets]
    p = sim.positions[sim.tets]
    dm = np.stack([rest[:, k] - rest[:, 0] for k in (1, 2, 3)], axis=2)
    f = np.stack([p[:, k] - p[:, 0] for k in (1, 2, 3)], axis=2) @ np.linalg.inv(dm)
    vol = np.abs(np.linalg.det(dm)) / 6
    # The energies C^2 / (2 compliance) of the two constraints, less their rest value.
    c_d2 = np.sum(f * f, axis=(1, 2))
    c_h = np.linalg.det(f) - alpha
    expected = np.sum(vol * (0.5 * mu * (c_d2 - 3) + 0.5 * lam * (c_h**2 - (alpha - 1) ** 2)))
    assert sim.energy().elastic == pytest.approx(float(expected), rel=1e-10)


def test_xpbd_alone_dissipates_and_fepr_conserves():
    plain = spinning_ell("xpbd", False)
    plain.step(150)
    kept = plain.history["total"][-1] / plain.history["total"][0]
    assert kept < 0.5, f"XPBD alone kept {kept:.1%} of H after 5 s"
    sim = spinning_ell("xpbd", True)
    sim.step(150)
    dh, dp, dl = max_drifts(sim.history)
    assert np.all(sim.history["proj_converged"][1:] == 1)
    assert dh <= 1e-8 and dp <= 1e-10 and dl <= 1e-10
    assert sim.last_projection.stiffness_metric


def test_xpbd_settings_are_validated_and_used():
    with pytest.raises(fepr.ConfigError, match="substeps"):
        fepr.Xpbd(substeps=0)
    with pytest.raises(fepr.ConfigError, match="iterations"):
        fepr.Xpbd(iterations=0)
    sim = spinning_ell(fepr.Xpbd(substeps=4, iterations=2), False)
    sim.step(2)
    assert np.all(sim.history["base_iterations"][1:] == 8)


def test_projection_metric_option():
    with pytest.raises(fepr.ConfigError, match="metric"):
        fepr.Projection(metric="euclid")
    se = spinning_ell("symplectic_euler", True)
    se.step(1)
    assert not se.last_projection.stiffness_metric
    forced = spinning_ell("symplectic_euler", fepr.Projection(metric="stiffness"))
    forced.step(5)
    assert forced.last_projection.stiffness_metric and forced.last_projection.converged
    mass = spinning_ell("implicit_euler", fepr.Projection(metric="mass"))
    mass.step(1)
    assert not mass.last_projection.stiffness_metric


def test_scene_selects_xpbd_with_its_options(tmp_path):
    scene = tmp_path / "x.toml"
    scene.write_text(
        """
[mesh]
builtin = "ell"
[material]
model = "neo_hookean"
youngs_modulus = 1e3
poisson_ratio = 0.3
[mass]
node_mass = 5.0
[initial]
scale = 1.2
[integrator]
name = "xpbd"
dt = 0.0333
substeps = 10
iterations = 1
[projection]
metric = "stiffness"
[run]
steps = 5
"""
    )
    from fepr.scene import load_scene, run_scene

    result = run_scene(load_scene(scene))
    assert result.steps_completed == 5 and result.max_energy_error < 1e-8
    bad = tmp_path / "bad.toml"
    bad.write_text(scene.read_text().replace('name = "xpbd"', 'name = "projective_dynamics"'))
    with pytest.raises(fepr.ConfigError, match="substeps"):
        run_scene(load_scene(bad))


@pytest.fixture(scope="module")
def bunny(request):
    from conftest import shared_meshes_dir

    d = shared_meshes_dir()
    if d is None:
        pytest.skip("the shared test meshes (../shared/meshes or $FEPR_SHARED_MESHES) are not present")
    mesh = fepr.load_mesh(d / "bunny.msh")
    v = mesh.vertices
    return fepr.TetMesh(v * 0.5 / (v.max(0) - v.min(0)).max(), mesh.tets)


def bunny_run(mesh, integrator, projection, steps):
    """The integrators issue's bunny: largest extent 0.5 m, E = 1e5 Pa, nu = 0.3, 1000 kg/m^3, released from a
    uniform 1.1 stretch about the centre of mass, dt = 1/30 s, no gravity."""
    sim = fepr.Simulation(
        mesh,
        material=fepr.NeoHookean(youngs_modulus=1e5, poisson_ratio=0.3),
        density=1000.0,
        dt=1 / 30,
        integrator=integrator,
        projection=projection,
    )
    c = sim.center_of_mass()
    sim.positions = c + 1.1 * (sim.rest_positions - c)
    sim.step(steps)
    return sim


def check_guarded_bunny(sim, plain, label):
    """With the quality guard (the default), FEPR on the sliver-rich bunny at 1/30 s keeps its books: H equals H0
    plus the energy booked as unresolved (most of it: a pressure wave crosses the 0.5 m body in about two steps),
    P and L stay on their targets, every projection converges and no tet inverts that the base integrator alone
    keeps upright."""
    h, hp = sim.history, plain.history
    assert np.all(np.isfinite(h["total"]))
    assert np.all(h["proj_converged"][1:] == 1)
    books = np.abs((h["total"] - h["budget_total"]) / h["total"][0] - 1).max()
    unresolved = -h["work_unresolved"].sum() / h["total"][0]
    p = np.abs(np.stack([h["px"], h["py"], h["pz"]])).max()
    ang = np.abs(np.stack([h["lx"], h["ly"], h["lz"]])).max()
    scale = sim.total_mass * 0.5 * 10  # kg * m * (1/s): momentum scale of a 0.5 m body moving at 10 m/s
    print(
        f"\nbunny {label} + FEPR 2 s: books {books:.2e}, unresolved {unresolved:.2f} H0, |P| {p:.1e}, |L| {ang:.1e}, "
        f"min J {h['min_j'].min():.3f} (alone {hp['min_j'].min():.3f}), inverted {h['inverted'].max():.0f} "
        f"(alone {hp['inverted'].max():.0f})"
    )
    assert books <= 1e-8 and p <= 1e-10 * scale and ang <= 1e-10 * scale * 0.5
    assert 0.0 < unresolved < 1.0
    if hp["inverted"].max() == 0:
        assert h["inverted"].max() == 0


def test_bunny_projective_dynamics_loses_half_alone_and_fepr_holds_it(bunny):
    plain = bunny_run(bunny, "projective_dynamics", False, 60)
    h = plain.history
    assert h["total"][-1] / h["total"][0] < 0.5
    # Without the quality guard, FEPR restores every joule (the model's own dynamics on this mesh).
    sim = bunny_run(bunny, "projective_dynamics", fepr.Projection(quality_guard=False), 60)
    h = sim.history
    assert np.all(np.isfinite(h["total"]))
    assert np.all(h["proj_converged"][1:] == 1)
    dh = np.abs(h["total"] / h["total"][0] - 1).max()
    p = np.abs(np.stack([h["px"], h["py"], h["pz"]])).max()
    ang = np.abs(np.stack([h["lx"], h["ly"], h["lz"]])).max()
    scale = sim.total_mass * 0.5 * 10  # kg * m * (1/s): momentum scale of a 0.5 m body moving at 10 m/s
    print(
        f"\nbunny PD + FEPR (no guard) 2 s: max |H/H0-1| {dh:.2e}, |P| {p:.1e}, |L| {ang:.1e}, "
        f"min J {h['min_j'].min():.3f}, iterations {h['proj_iterations'][1:].mean():.2f} mean / "
        f"{h['proj_iterations'].max():.0f} max"
    )
    assert dh <= 1e-8 and p <= 1e-10 * scale and ang <= 1e-10 * scale * 0.5
    check_guarded_bunny(bunny_run(bunny, "projective_dynamics", True, 60), plain, "PD")


# XPBD's default settings (20 substeps x 1 sweep); the projection warm-starts after XPBD by default.
BUNNY_XPBD = fepr.Xpbd(substeps=20, iterations=1)


def test_bunny_xpbd_loses_half_alone_and_fepr_holds_it(bunny):
    """Issue 3 on the sliver-rich bunny: XPBD alone loses more than half of H within 2 s, and with FEPR without the
    quality guard keeps |H/H0 - 1| <= 1e-8 with every projection converged and P, L conserved (with the guard, the
    default: its books, see `check_guarded_bunny`). XPBD loses about a quarter of H per
    step here, so the projection's default warm start after XPBD rescales the velocities first (without it a few
    projections per 300 steps fail on the slivers). Tets that invert (the mesh has slivers; the constraint energy
    has no barrier) are survived: finite states, no fallback."""
    plain = bunny_run(bunny, BUNNY_XPBD, False, 60)
    h = plain.history
    assert np.all(np.isfinite(h["total"]))
    assert h["total"][-1] / h["total"][0] < 0.5, f"XPBD alone kept {h['total'][-1] / h['total'][0]:.1%}"
    sim = bunny_run(bunny, BUNNY_XPBD, fepr.Projection(quality_guard=False), 60)
    h = sim.history
    assert isinstance(sim.material, fepr.ConstraintNeoHookean)
    assert np.all(np.isfinite(h["total"])) and np.all(np.isfinite(sim.positions))
    assert np.all(h["proj_converged"][1:] == 1) and np.all(h["proj_fallback"][1:] == 0)
    assert h["proj_warm_start"][1:].sum() > 0
    dh = np.abs(h["total"] / h["total"][0] - 1).max()
    p = np.abs(np.stack([h["px"], h["py"], h["pz"]])).max()
    ang = np.abs(np.stack([h["lx"], h["ly"], h["lz"]])).max()
    scale = sim.total_mass * 0.5 * 10  # kg * m * (1/s): momentum scale of a 0.5 m body moving at 10 m/s
    print(
        f"\nbunny XPBD + FEPR (no guard) 2 s: max |H/H0-1| {dh:.2e}, |P| {p:.1e}, |L| {ang:.1e}, "
        f"min J {h['min_j'].min():.3f}, iterations {h['proj_iterations'][1:].mean():.2f} mean / "
        f"{h['proj_iterations'].max():.0f} max"
    )
    assert dh <= 1e-8 and p <= 1e-10 * scale and ang <= 1e-10 * scale * 0.5
    check_guarded_bunny(bunny_run(bunny, BUNNY_XPBD, True, 60), plain, "XPBD")
