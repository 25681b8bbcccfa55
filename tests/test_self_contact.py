"""Self contact (``Simulation(self_contact=...)``, a scene's ``self_contact``): a bar folded over a rod
(``examples/fold.toml``) does not pass through itself and no vertex ends inside it (measured here by exact
point-in-tet queries against the tets away from the vertex, not by the contact code), the books close; in space
the impulses are internal, so momentum and angular momentum are kept from the raw arrays and, with restitution 1,
the energy; bad settings are named."""

from pathlib import Path

import numpy as np
import pytest

import fepr
import fepr.scene
from fepr.errors import ConfigError
from fepr.mesh_report import boundary_faces

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _mean_edge(tets, x):
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    return float(np.mean([np.linalg.norm(x[tets[:, i]] - x[tets[:, j]], axis=1).mean() for i, j in pairs]))


def _self_penetration(x, tets):
    """The deepest any surface vertex lies inside a tet of its own body that does not touch its two-ring (the
    vertices within two edges of it), m: the distance from the vertex to that tet's nearest face."""
    tets = np.asarray(tets)
    n = len(x)
    neighbours = [set() for _ in range(n)]
    for t in tets:
        for v in t:
            neighbours[v].update(t)
    p = x[tets]
    d = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    volume6 = np.linalg.det(d)
    ok = np.abs(volume6) > 1e-18
    inv = np.zeros_like(d)
    inv[ok] = np.linalg.inv(d[ok])
    faces = [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)]
    # Height of each tet over each face (the barycentric coordinate of a point times it is its distance).
    heights = np.stack(
        [
            np.abs(volume6) / np.linalg.norm(np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a]), axis=1).clip(1e-300)
            for a, b, c in faces
        ],
        axis=1,
    )
    lo, hi = p.min(1), p.max(1)
    deepest = 0.0
    for i in np.unique(boundary_faces(tets)[0]):
        ring = set().union(*(neighbours[j] for j in neighbours[i]))
        cand = np.flatnonzero(ok & np.all((x[i] >= lo) & (x[i] <= hi), axis=1))
        cand = [t for t in cand if not ring.intersection(tets[t])]
        if not cand:
            continue
        cand = np.asarray(cand)
        l3 = np.einsum("tij,tj->ti", inv[cand], x[i] - p[cand, 0])
        lam = np.column_stack([1.0 - l3.sum(1), l3])
        inside = np.all(lam > 0, axis=1)
        if inside.any():
            deepest = max(deepest, float((lam[inside] * heights[cand[inside]]).min(1).max()))
    return deepest


def _fold(self_contact=True):
    scene = fepr.scene.load_scene(EXAMPLES / "fold.toml")
    if not self_contact:
        scene.world.self_contact = None
    return scene.build()


def _ends(sim, rest):
    """Mean x of the bar's right end less its left end's (m): negative once the halves passed through each
    other."""
    x = sim.positions[:, 0]
    return float(x[rest[:, 0] > 0.79].mean() - x[rest[:, 0] < -0.79].mean())


def test_a_bar_folded_over_a_rod_does_not_pass_through_itself():
    sim = _fold()
    rest = sim.positions.copy()
    edge = _mean_edge(np.asarray(sim.tets), rest)
    apart = []
    for _ in range(45):
        sim.step(1)
        apart.append(_ends(sim, rest))
    h = sim.history
    assert h["contacts"].max() > 0
    # The halves swung into each other below the rod (their ends within a few cm) and came apart on their sides.
    assert 0.0 < min(apart) < 0.3, min(apart)
    assert _self_penetration(sim.positions, sim.tets) <= 0.01 * edge
    assert int(h["inverted"][-1]) == 0
    books = np.abs(h["total"] - h["total"][0] - h["budget_total"]).max() / abs(h["total"][0])
    assert books <= 1e-8, books


def test_without_self_contact_the_folded_bar_passes_through_itself():
    # The check above can fail: the same scene without self contact folds the halves through each other.
    sim = _fold(self_contact=False)
    rest = sim.positions.copy()
    apart = []
    for _ in range(45):
        sim.step(1)
        apart.append(_ends(sim, rest))
    assert min(apart) < 0.0


def _spinning_halves(integrator, restitution):
    mesh = fepr.meshes.box(size=(1.0, 0.1, 0.1), resolution=(20, 2, 2))
    sim = fepr.Simulation(
        mesh,
        material=fepr.StableNeoHookean(youngs_modulus=2e4, poisson_ratio=0.4),
        density=1000.0,
        dt=1 / 60,
        integrator=integrator,
        self_contact=(restitution, 0.0),
    )
    x = sim.positions
    v = np.zeros_like(x)
    # Each half turns at 6 rad/s about the centre, its end towards the other's.
    v[:, 2] = 6.0 * np.abs(x[:, 0])
    v[:, 0] = -6.0 * np.sign(x[:, 0]) * x[:, 2]
    sim.velocities = v
    return sim


def _totals(sim):
    m, x, v = sim.masses, sim.positions, sim.velocities
    return sim.energy().total, (m[:, None] * v).sum(0), np.cross(x, m[:, None] * v).sum(0)


@pytest.mark.parametrize("integrator", ["projective_dynamics", "implicit_euler"])
def test_self_contact_in_space_keeps_the_momenta_and_with_restitution_one_the_energy(integrator):
    sim = _spinning_halves(integrator, 1.0)
    rest = sim.positions.copy()
    h0, p0, l0 = _totals(sim)
    apart = []
    for _ in range(60):
        sim.step(1)
        apart.append(float(sim.positions[rest[:, 0] > 0.49, 0].mean() - sim.positions[rest[:, 0] < -0.49, 0].mean()))
    h1, p1, l1 = _totals(sim)
    assert sim.history["contacts"].max() > 0
    assert min(apart) > 0.0
    scale_p = np.linalg.norm(p0)
    assert np.abs(p1 - p0).max() <= 1e-10 * scale_p
    assert np.abs(l1 - l0).max() <= 1e-10 * max(np.linalg.norm(l0), scale_p)
    assert abs(h1 - h0) <= 1e-8 * abs(h0)
    assert _self_penetration(sim.positions, sim.tets) <= 0.01 * _mean_edge(np.asarray(sim.tets), rest)


def test_inelastic_self_contact_books_its_loss():
    sim = _spinning_halves("projective_dynamics", 0.0)
    sim.step(60)
    h = sim.history
    assert h["work_contact"].min() < 0.0
    assert h["work_contact"].max() <= 0.0
    books = np.abs(h["total"] - h["total"][0] - h["budget_total"]).max() / abs(h["total"][0])
    assert books <= 1e-8


@pytest.mark.parametrize(
    "value, message",
    [
        ((2.0, 0.0), "restitution"),
        ((0.5, -1.0), "friction"),
        ((float("nan"), 0.0), "restitution"),
        ("yes", "self_contact"),
        ((0.5,), "self_contact"),
    ],
)
def test_bad_self_contact_settings_are_named(value, message):
    with pytest.raises(ConfigError, match=message):
        fepr.Simulation(
            fepr.meshes.box(size=0.3, resolution=2),
            material=fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4),
            density=1000.0,
            dt=0.01,
            self_contact=value,
        )


@pytest.mark.parametrize(
    "value, message",
    [
        ({"restitution": 1.5}, r"\[world\] self_contact: restitution must be in \[0, 1\]"),
        ({"friction": -0.1}, r"self_contact: friction must be >= 0"),
        ({"bounce": 1.0}, r"self_contact: unknown key 'bounce'"),
        ("on", r"self_contact must be true, false or a table"),
    ],
)
def test_bad_scene_self_contact_is_named(value, message):
    scene = {
        "mesh": {"builtin": "box"},
        "material": {"model": "stable_neo_hookean", "youngs_modulus": 1e5, "poisson_ratio": 0.4},
        "mass": {"density": 1000.0},
        "integrator": {"name": "implicit_euler", "dt": 0.01},
        "world": {"self_contact": value},
    }
    with pytest.raises(ConfigError, match=message):
        fepr.scene.scene_from_dict(scene)


def test_scene_bodies_take_self_contact_and_the_world_table_names_where_it_belongs():
    body = {
        "mesh": {"builtin": "box"},
        "material": {"model": "stable_neo_hookean", "youngs_modulus": 1e5, "poisson_ratio": 0.4},
        "mass": {"density": 1000.0},
    }
    scene = fepr.scene.scene_from_dict(
        {"bodies": [{**body, "self_contact": True}, body], "integrator": {"name": "implicit_euler", "dt": 0.01}}
    )
    assert [b.self_contact for b in scene.body_settings()] == [(1.0, 0.0), None]
    assert [s.self_contact for s in scene.build_bodies()] == [(1.0, 0.0), None]
    with pytest.raises(ConfigError, match="self_contact is per body"):
        fepr.scene.scene_from_dict(
            {"bodies": [body], "world": {"self_contact": True}, "integrator": {"name": "implicit_euler", "dt": 0.01}}
        )


def test_the_fold_example_is_the_bench_fold():
    from fepr.cli.bench_contact import fold_scene

    f = fepr.scene.load_scene(EXAMPLES / "fold.toml")
    s = fepr.scene.scene_from_dict(fold_scene(), ".")
    for part in ("mesh", "material", "mass", "world", "run"):
        assert getattr(f, part) == getattr(s, part), part
    assert f.integrator.name == s.integrator.name and f.integrator.dt == s.integrator.dt


def test_a_body_among_others_keeps_its_self_contact():
    """Self contact of a body in a scene of several bodies (Projective Dynamics: the bodies' solves taken
    together): the folding bar of the space test, with a ball beside it that it does not touch, does not pass
    through itself, and the scene keeps its momentum."""
    bar = _spinning_halves("projective_dynamics", 1.0)
    ball = fepr.Simulation(
        fepr.meshes.sphere(radius=0.1, resolution=3, center=(0.0, 1.0, 0.0)),
        material=fepr.StableNeoHookean(youngs_modulus=2e4, poisson_ratio=0.4),
        density=1000.0,
        dt=1 / 60,
        integrator="projective_dynamics",
    )
    from fepr.multibody import MultiBody

    scene = MultiBody([bar, ball], names=["bar", "ball"])
    rest = bar.positions.copy()
    p0 = (scene.masses[:, None] * scene.velocities).sum(0)
    apart = []
    for _ in range(60):
        scene.step(1)
        apart.append(float(bar.positions[rest[:, 0] > 0.49, 0].mean() - bar.positions[rest[:, 0] < -0.49, 0].mean()))
    p1 = (scene.masses[:, None] * scene.velocities).sum(0)
    assert bar.history["contacts"].max() > 0 and ball.history["contacts"].max() == 0
    assert min(apart) > 0.0
    assert np.abs(p1 - p0).max() <= 1e-10 * np.linalg.norm(p0)
