"""Triangle-mesh obstacles (fepr.MeshObstacle, scene type "mesh"): a body lands on a bumpy terrain, a mesh box
acts as the analytic box does, a fast body does not tunnel through a thin mesh plate, and bad meshes are named
errors. Penetration is measured here by exact point-triangle distances and ray parity, not by the contact code."""

import subprocess
import sys
import warnings

import numpy as np
import pytest

import fepr
from fepr.errors import ConfigError, MeshError, SimulationError

G = 9.81


def _point_triangle_distance(p, a, b, c):
    """Exact distances (n, k) from points ``p`` (n, 3) to triangles ``a, b, c`` (k, 3) each (Ericson's regions)."""
    p = p[:, None, :]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        q = a + ab * v[..., None] + ac * w[..., None]  # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [
        ((d1 <= 0) & (d2 <= 0), a + 0 * p),
        ((d3 >= 0) & (d4 <= d3), b + 0 * p),
        ((d6 >= 0) & (d5 <= d6), c + 0 * p),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[..., None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[..., None]),
        ((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + (c - b) * t_bc[..., None]),
    ]
    for mask, point in reversed(regions):
        q = np.where(mask[..., None], point, q)
    return np.linalg.norm(p - q, axis=-1)


def _inside(p, a, b, c):
    """Whether each point of ``p`` (n, 3) is inside the closed surface (parity of a ray's crossings)."""
    d = np.array([0.0123, 0.0071, 1.0])
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = (e1 * h).sum(-1)
    s = p[:, None, :] - a
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (s * h).sum(-1) / det
        qv = np.cross(s, e1)
        v = (qv @ d) / det
        t = (qv * e2).sum(-1) / det
    hit = (np.abs(det) > 1e-300) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hit.sum(1) % 2 == 1


def _penetration(x, obstacle):
    """The deepest any point of ``x`` lies inside the closed mesh ``obstacle``, m (0 when none does)."""
    v, t = obstacle.vertices, obstacle.triangles
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    inside = _inside(x, a, b, c)
    if not inside.any():
        return 0.0
    return float(_point_triangle_distance(x[inside], a, b, c).min(1).max())


def _mean_edge(mesh):
    t, v = np.asarray(mesh.tets), np.asarray(mesh.vertices)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    return float(np.mean([np.linalg.norm(v[t[:, i]] - v[t[:, j]], axis=1).mean() for i, j in pairs]))


def _books(h):
    return float(np.max(np.abs(h["total"] - (h["total"][0] + h["budget_total"]))) / abs(h["total"][0]))


def _sim(mesh, obstacles, integrator, dt, projection=True, gravity=(0.0, 0.0, -G)):
    return fepr.Simulation(
        mesh,
        material=fepr.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.4),
        density=1000.0,
        integrator=integrator,
        dt=dt,
        projection=projection,
        gravity=gravity,
        obstacles=obstacles,
    )


def _cube_surface(center, half):
    """The 12 outward triangles of an axis-aligned box."""
    c, h = np.asarray(center, float), np.asarray(half, float)
    v = np.array([[(i & 1) * 2 - 1, ((i >> 1) & 1) * 2 - 1, ((i >> 2) & 1) * 2 - 1] for i in range(8)], float)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    tris = [[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads]
    return c + h * v, np.array(tris)


TERRAIN = dict(size=3.0, cells=40, height=0.08, wavelength=0.8, restitution=0.5, friction=0.3)


@pytest.mark.parametrize("integrator", ["implicit_euler", "projective_dynamics", "xpbd"])
def test_a_box_landing_on_a_bumpy_terrain_stays_out_of_it_keeps_its_shape_and_closes_the_books(integrator):
    terrain = fepr.MeshObstacle.terrain(**TERRAIN)
    assert terrain.closed
    mesh = fepr.meshes.box(size=0.4, resolution=4, center=(0.1, 0.05, 0.5))
    sim = _sim(mesh, [terrain], integrator, 1 / 60)
    edge = _mean_edge(mesh)
    deepest = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(90):
            sim.step(1)
            deepest = max(deepest, _penetration(sim.positions, terrain))
    h = sim.history
    assert h["contacts"].max() > 0, "the box reached the terrain"
    assert deepest <= 0.01 * edge
    assert _books(h) <= 1e-8
    assert h["inverted"].max() == 0 and h["min_j"].min() > 0.2
    assert h["base_substeps"].max() == 0
    assert h["work_contact"].sum() < 0  # restitution 0.5 and friction take energy
    # Unconverged contact steps carry their residual as deferred work, which a converged step reverses.
    assert np.all(np.isfinite(h["work_deferred"]))
    if h["proj_converged"][-1]:
        assert abs(h["work_deferred"].sum()) <= 1e-9 * abs(h["total"][0])


def test_a_mesh_box_acts_as_the_analytic_box():
    # On a flat face the mesh's exact point-triangle distance is the analytic box's distance: the same landing.
    vertices, triangles = _cube_surface((0.0, 0.0, -0.5), (2.0, 2.0, 0.5))
    as_mesh = fepr.MeshObstacle((vertices, triangles), restitution=0.5, friction=0.3)
    as_box = fepr.Box(center=(0.0, 0.0, -0.5), half_extents=(2.0, 2.0, 0.5), restitution=0.5, friction=0.3)
    runs = []
    for ob in (as_mesh, as_box):
        sim = _sim(fepr.meshes.box(size=0.3, resolution=3, center=(0, 0, 0.4)), [ob], "implicit_euler", 1 / 60)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            sim.step(60)
        runs.append(sim)
    assert runs[0].history["contacts"].max() > 0
    assert np.max(np.abs(runs[0].positions - runs[1].positions)) <= 1e-6


@pytest.mark.parametrize("integrator", ["symplectic_euler", "implicit_euler", "projective_dynamics", "xpbd"])
def test_a_fast_body_does_not_pass_through_a_thin_mesh_plate(integrator):
    # 10 m/s against a 1 cm plate given as 12 triangles: a vertex moves 16.7 cm per step at dt = 1/60.
    vertices, triangles = _cube_surface((0.0, 0.0, 0.0), (1.0, 1.0, 0.005))
    plate = fepr.MeshObstacle((vertices, triangles), restitution=0.5)
    mesh = fepr.meshes.box(size=0.1, resolution=2, center=(0.0, 0.0, 0.3))
    dt = 1e-3 if integrator == "symplectic_euler" else 1 / 60
    sim = _sim(mesh, [plate], integrator, dt, gravity=(0.0, 0.0, 0.0))
    sim.velocities = np.tile([0.0, 0.0, -10.0], (mesh.num_vertices, 1))
    edge = _mean_edge(mesh)
    lowest = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(int(round(0.2 / dt))):
            sim.step(1)
            lowest = min(lowest, float(sim.positions[:, 2].min()))
            assert _penetration(sim.positions, plate) <= 0.01 * edge
    assert lowest >= 0.005 - 0.01 * edge, "no vertex below the plate's top face"


def test_an_open_sheet_is_one_sided():
    # Two triangles, normals up: the solid is below; a body dropped on it rests on top.
    v = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    sheet = fepr.MeshObstacle((v, np.array([[0, 1, 2], [0, 2, 3]])), restitution=0.0, friction=0.5)
    assert not sheet.closed
    sim = _sim(fepr.meshes.box(size=0.3, resolution=2, center=(0, 0, 0.3)), [sheet], "implicit_euler", 1 / 60)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sim.step(90)
    assert sim.positions[:, 2].min() >= -1e-3
    # Wound the other way it is solid above: the body starts inside it, a named error.
    flipped = fepr.MeshObstacle((v, np.array([[0, 1, 2], [0, 2, 3]])), flip_normals=True)
    sim = _sim(fepr.meshes.box(size=0.3, resolution=2, center=(0, 0, 0.3)), [flipped], "implicit_euler", 1 / 60)
    with pytest.raises(SimulationError, match=r"inside obstacle 0 \(mesh\)"):
        sim.step(1)


def test_a_mesh_obstacle_reads_a_surface_file_and_names_a_bad_one(tmp_path):
    vertices, triangles = _cube_surface((0.0, 0.0, -0.5), (1.0, 1.0, 0.5))
    obj = tmp_path / "ground.obj"
    obj.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in vertices)
        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in triangles)
    )
    ground = fepr.MeshObstacle(obj, friction=0.2)
    assert ground.closed and len(ground.triangles) == 12 and ground.path == str(obj)
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(MeshError, match="bad.obj"):
        fepr.MeshObstacle(bad)
    with pytest.raises(MeshError, match="not found"):
        fepr.MeshObstacle(tmp_path / "missing.stl")


@pytest.mark.parametrize(
    "source, message",
    [
        ((np.zeros((3, 3)), np.zeros((0, 3), int)), "no triangles"),
        ((np.eye(3), np.array([[0, 1, 2, 0]])), r"shape \(k, 3\)"),
        ((np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]])), "vertex 2 is not finite"),
        ((np.eye(3), np.array([[0, 1, 5]])), "triangle 0 refers to vertex"),
        ((np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float), np.array([[0, 1, 2]])), "triangle 0 .* no area"),
        ((np.eye(3), np.array([[0, 1, 1]])), "repeats a vertex"),
        ((np.eye(3), np.array([[0.0, 1.0, 2.0]])), "integer"),
        (b"not a tuple", "file path or"),
    ],
)
def test_a_bad_mesh_obstacle_is_a_named_error(source, message):
    with pytest.raises(ConfigError, match=message):
        fepr.MeshObstacle(source)


def test_bad_contact_coefficients_and_terrain_parameters_are_named():
    with pytest.raises(ConfigError, match="restitution"):
        fepr.MeshObstacle.terrain(restitution=1.5)
    with pytest.raises(ConfigError, match="friction"):
        fepr.MeshObstacle.terrain(friction=-1)
    with pytest.raises(ConfigError, match="terrain cells"):
        fepr.MeshObstacle.terrain(cells=0)
    with pytest.raises(ConfigError, match="terrain height"):
        fepr.MeshObstacle.terrain(height=float("nan"))


def test_a_scene_with_a_mesh_ground_runs_and_bad_mesh_entries_are_named(tmp_path):
    scene = tmp_path / "ground.toml"
    scene.write_text(
        """
[mesh]
builtin = "box"
size = 0.3
resolution = 2
center = [0.0, 0.0, 0.4]
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.4
[mass]
density = 1000.0
[integrator]
name = "implicit_euler"
dt = 0.016666666666666666
[world]
gravity = [0.0, 0.0, -9.81]
[[world.obstacles]]
type = "mesh"
terrain = { size = 2.0, cells = 16, height = 0.05 }
restitution = 0.5
friction = 0.3
[run]
steps = 40
"""
    )
    out = subprocess.run(
        [sys.executable, "-m", "fepr", "run", str(scene), "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    import csv

    rows = list(csv.DictReader(open(tmp_path / "out" / "diagnostics.csv")))
    assert max(int(r["contacts"]) for r in rows) > 0
    from fepr.scene import load_scene

    text = scene.read_text()
    for entry, message in [
        ('terrain = { size = 2.0, cells = 16, height = 0.05 }\npath = "x.obj"', "exactly one of 'path'"),
        ("terrain = { size = 2.0, bumps = 3 }", "unknown key 'bumps'"),
        ('path = "missing.obj"', "missing.obj"),
    ]:
        bad = tmp_path / "bad.toml"
        bad.write_text(text.replace("terrain = { size = 2.0, cells = 16, height = 0.05 }", entry))
        with pytest.raises((ConfigError, MeshError), match=message):
            load_scene(bad).build()
