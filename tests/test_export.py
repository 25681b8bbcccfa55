"""Exports: boundary surface, per-frame fields, VTU + PVD, OBJ/PLY sequences, GLB, USD, Recorder, scene and CLI."""

from __future__ import annotations

import struct
import sys
from collections import Counter
from pathlib import Path

import meshio
import numpy as np
import pytest

import fepr
from fepr.cli import EXIT_INVALID, EXIT_OK, EXIT_RUNAWAY, main
from fepr.errors import ConfigError, MeshError
from fepr.export import (
    FORMATS,
    Z_UP_TO_Y_UP,
    GlbWriter,
    Recorder,
    TetKinematics,
    boundary_surface,
    deformation_gradients,
    enclosed_volume,
    glb_accessor,
    parse_formats,
    read_glb,
    read_ply,
    read_pvd,
    run_with_export,
    usd_available,
    vertex_normals,
    write_glb,
)
from fepr.scene import load_scene, run_scene, scene_from_dict

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def stretched_ell(**kw) -> fepr.Simulation:
    sim = fepr.Simulation(
        fepr.meshes.ell(),
        material=fepr.NeoHookean(youngs_modulus=1e3, poisson_ratio=0.3),
        node_mass=5.0,
        dt=1 / 30,
        **kw,
    )
    sim.positions = 1.5 * sim.rest_positions
    return sim


def obj_vertices(path: Path) -> np.ndarray:
    return np.array(
        [[float(x) for x in line.split()[1:4]] for line in path.read_text().splitlines() if line[:2] == "v "]
    )


def obj_faces(path: Path) -> np.ndarray:
    out = []
    for line in path.read_text().splitlines():
        if line.startswith("f "):
            out.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    return np.array(out)


# ---- boundary surface ----------------------------------------------------------------------------------


SHAPES = {
    "box": lambda: fepr.meshes.box(),
    "box_4x3x2": lambda: fepr.meshes.box(size=(2.0, 1.0, 0.5), resolution=(4, 3, 2)),
    "ell": lambda: fepr.meshes.ell(),
    "ell_r3": lambda: fepr.meshes.ell(size=0.3, resolution=3),
    "one_tet": lambda: fepr.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]]),
}


@pytest.mark.parametrize("shape", sorted(SHAPES))
def test_boundary_surface_is_closed_and_outward(shape):
    mesh = SHAPES[shape]()
    faces, verts, local = boundary_surface(mesh.tets)
    assert faces.dtype == np.int64 and faces.shape[1] == 3 and len(faces) > 0
    # Closed and consistently oriented: every directed edge appears once and its reverse once.
    directed = Counter()
    for a, b, c in faces.tolist():
        directed.update([(a, b), (b, c), (c, a)])
    assert all(n == 1 for n in directed.values())
    assert all((b, a) in directed for (a, b) in directed)
    # Outward: the enclosed signed volume is positive and equals the mesh volume.
    vol = enclosed_volume(mesh.vertices, faces)
    assert vol > 0
    assert vol == pytest.approx(mesh.volumes().sum(), rel=1e-12)
    # Compact re-indexing.
    assert np.array_equal(verts, np.unique(faces))
    assert np.array_equal(verts[local], faces)
    assert enclosed_volume(mesh.vertices[verts], local) == pytest.approx(vol, rel=1e-12)


def test_boundary_surface_counts_of_the_unit_box():
    # A 2x2x2 Kuhn box: each of the 6 sides has 4 squares of 2 triangles; 26 of the 27 lattice points.
    s = boundary_surface(fepr.meshes.box(resolution=2).tets)
    assert (s.num_faces, s.num_vertices) == (48, 26)


def test_boundary_surface_stays_outward_when_deformed():
    mesh = fepr.meshes.ell()
    faces = boundary_surface(mesh.tets).faces
    a = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 1.1]])
    x = mesh.vertices @ a.T + 3.0
    assert enclosed_volume(x, faces) == pytest.approx(np.linalg.det(a) * 5.0, rel=1e-12)


def test_boundary_surface_rejects_bad_input():
    with pytest.raises(MeshError, match="shape"):
        boundary_surface(np.zeros((3, 3), dtype=int))
    with pytest.raises(MeshError, match="integer"):
        boundary_surface(np.zeros((1, 4)))
    empty = boundary_surface(np.zeros((0, 4), dtype=np.int64))
    assert empty.faces.shape == (0, 3) and empty.vertices.shape == (0,)


def test_vertex_normals_point_out_of_a_box():
    mesh = fepr.meshes.box(center=(0.0, 0.0, 0.0))
    s = boundary_surface(mesh.tets)
    pts = mesh.vertices[s.vertices]
    n = vertex_normals(pts, s.local_faces)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", n, pts) > 0)  # the box is centred at the origin


# ---- per-frame fields ----------------------------------------------------------------------------------


def test_deformation_gradient_of_an_affine_map():
    mesh = fepr.meshes.ell()
    a = np.array([[1.1, 0.2, 0.0], [0.0, 0.8, 0.1], [0.3, 0.0, 1.2]])
    x = mesh.vertices @ a.T + np.array([1.0, -2.0, 0.5])
    F = deformation_gradients(mesh.vertices, x, mesh.tets)
    assert F.shape == (mesh.num_tets, 3, 3)
    assert np.allclose(F, a, atol=1e-13)
    assert np.allclose(TetKinematics(mesh.vertices, mesh.tets).deformation_gradients(mesh.vertices), np.eye(3))


# ---- Recorder: every format ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A stretched L run for 12 steps, every 3rd step in vtu, obj (with normals), ply and glb."""
    out = tmp_path_factory.mktemp("export")
    sim = stretched_ell()
    states = {}
    with Recorder(sim, out, formats="vtu,obj,ply,glb", every=3, name="ell", normals=True) as rec:
        rec.record()
        states[0] = (sim.positions, sim.velocities, sim.time)
        for _ in range(12):
            sim.step(1)
            if rec.record():
                states[sim.num_steps] = (sim.positions, sim.velocities, sim.time)
    return out, sim, rec, states


def test_recorder_writes_every_kth_step(recorded):
    out, sim, rec, states = recorded
    assert [f[1] for f in rec.frames] == [0, 3, 6, 9, 12] == sorted(states)
    assert rec.closed and rec.num_frames == 5
    rows = (out / "frames.csv").read_text().splitlines()
    assert rows[0] == "frame,step,time" and len(rows) == 6
    assert rows[2].split(",")[:2] == ["1", "3"]


def test_vtu_series_loads_back_with_meshio(recorded):
    out, sim, rec, states = recorded
    entries = read_pvd(out / "ell.pvd")
    assert len(entries) == 5
    steps = sorted(states)
    mat = sim.material
    for (t, path), step in zip(entries, steps):
        x, v, time = states[step]
        assert t == time
        assert path.parent.name == "vtu" and path.exists()
        m = meshio.read(path)
        assert m.points.shape == (sim.mesh.num_vertices, 3)
        assert np.array_equal(m.points, x)
        assert np.array_equal(m.cells_dict["tetra"], sim.tets)
        assert np.array_equal(m.point_data["velocity"], v)
        assert np.allclose(m.point_data["displacement"], x - sim.rest_positions, atol=0)
        F = deformation_gradients(sim.rest_positions, x, sim.tets)
        assert np.allclose(m.cell_data["J"][0], np.linalg.det(F), rtol=1e-13)
        assert np.allclose(m.cell_data["energy_density"][0], mat.energy_density(F), rtol=1e-13)
    # The stretched L has J = 1.5^3 everywhere at frame 0.
    assert np.allclose(meshio.read(entries[0][1]).cell_data["J"][0], 1.5**3)


def test_vtu_is_binary(recorded):
    out = recorded[0]
    head = (out / "vtu" / "ell_00000.vtu").read_bytes()[:2000]
    assert b'format="binary"' in head or b"appended" in head


def test_obj_sequence(recorded):
    out, sim, rec, states = recorded
    files = sorted((out / "obj").glob("ell_*.obj"))
    assert [f.name for f in files] == [f"ell_{i:05d}.obj" for i in range(5)]
    s = rec.surface
    for f, step in zip(files, sorted(states)):
        pts = obj_vertices(f)
        assert pts.shape == (s.num_vertices, 3)
        assert np.allclose(pts, states[step][0][s.vertices], rtol=1e-8, atol=1e-12)
        assert np.array_equal(obj_faces(f), s.local_faces)
        text = f.read_text()
        assert text.count("\nvn ") == s.num_vertices and "//" in text


def test_ply_sequence(recorded):
    out, sim, rec, states = recorded
    files = sorted((out / "ply").glob("ell_*.ply"))
    assert len(files) == 5
    pts, faces = read_ply(files[-1])
    assert np.allclose(pts, states[12][0][rec.surface.vertices], rtol=1e-6)
    assert np.array_equal(faces, rec.surface.local_faces)


def test_glb_loads_with_pygltflib(recorded):
    pygltflib = pytest.importorskip("pygltflib")
    out, sim, rec, states = recorded
    g = pygltflib.GLTF2().load(str(out / "ell.glb"))
    nv = rec.surface.num_vertices
    prim = g.meshes[0].primitives[0]
    assert len(prim.targets) == 4  # frames 1..4 relative to frame 0
    assert g.meshes[0].extras["targetNames"] == [f"frame_{i:05d}" for i in range(1, 5)]
    assert g.accessors[prim.attributes.POSITION].count == nv
    assert g.accessors[prim.indices].count == 3 * rec.surface.num_faces
    for t in prim.targets:
        assert g.accessors[t["POSITION"]].count == nv
    anim = g.animations[0]
    assert anim.channels[0].target.path == "weights" and anim.channels[0].target.node == 0
    sampler = anim.samplers[0]
    assert sampler.interpolation == "LINEAR"
    assert g.accessors[sampler.input].count == 5
    assert g.accessors[sampler.output].count == 5 * 4
    # pygltflib sees the same binary chunk as our own parser.
    gltf, binary = read_glb(out / "ell.glb")
    assert g.binary_blob()[: len(binary)] == binary


def test_glb_container_layout_and_accessors(recorded):
    out, sim, rec, states = recorded
    data = (out / "ell.glb").read_bytes()
    magic, version, length = struct.unpack_from("<III", data)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0
    bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0 and 28 + json_len + bin_len == len(data)

    gltf, binary = read_glb(out / "ell.glb")
    assert gltf["asset"]["version"] == "2.0"
    assert gltf["buffers"][0]["byteLength"] <= len(binary)
    for view in gltf["bufferViews"]:
        assert view["byteOffset"] % 4 == 0
        assert view["byteOffset"] + view["byteLength"] <= gltf["buffers"][0]["byteLength"]
    # min/max of every POSITION accessor and of the time input equal the stored data.
    prim = gltf["meshes"][0]["primitives"][0]
    sampler = gltf["animations"][0]["samplers"][0]
    bounded = [prim["attributes"]["POSITION"], sampler["input"]] + [t["POSITION"] for t in prim["targets"]]
    for i in bounded:
        a = glb_accessor(gltf, binary, i).reshape(len(glb_accessor(gltf, binary, i)), -1)
        assert gltf["accessors"][i]["min"] == a.min(axis=0).tolist()
        assert gltf["accessors"][i]["max"] == a.max(axis=0).tolist()
    # Indices are in range; times are the frame times from 0; weights are one-hot.
    idx = glb_accessor(gltf, binary, prim["indices"])
    assert idx.max() == rec.surface.num_vertices - 1
    times = glb_accessor(gltf, binary, sampler["input"])
    assert np.allclose(times, [states[s][2] - states[0][2] for s in sorted(states)], rtol=1e-6)
    w = glb_accessor(gltf, binary, sampler["output"]).reshape(5, 4)
    assert np.array_equal(w, np.vstack([np.zeros(4), np.eye(4)]))
    # Base + target k, rotated back from +Y up, is the surface at frame k.
    base = glb_accessor(gltf, binary, prim["attributes"]["POSITION"]).astype(np.float64)
    for k, step in enumerate(sorted(states)):
        y_up = base + (glb_accessor(gltf, binary, prim["targets"][k - 1]["POSITION"]) if k else 0.0)
        z_up = y_up @ Z_UP_TO_Y_UP  # the inverse of a rotation is its transpose
        assert np.allclose(z_up, states[step][0][rec.surface.vertices], rtol=1e-6, atol=1e-6)
        # The rotation keeps the triangles outward.
        assert enclosed_volume(y_up, idx.reshape(-1, 3)) > 0


def test_read_glb_rejects_damaged_files(recorded, tmp_path):
    data = (recorded[0] / "ell.glb").read_bytes()
    bad = tmp_path / "bad.glb"
    bad.write_bytes(data[:-4])
    with pytest.raises(ConfigError, match="header length"):
        read_glb(bad)
    bad.write_bytes(b"glTX" + data[4:])
    with pytest.raises(ConfigError, match="magic"):
        read_glb(bad)


def test_glb_with_one_frame_has_no_animation(tmp_path):
    mesh = fepr.meshes.box()
    s = boundary_surface(mesh.tets)
    path = write_glb(tmp_path / "one.glb", mesh.vertices[s.vertices][None], s.local_faces, [0.0])
    gltf, binary = read_glb(path)
    assert "animations" not in gltf and "targets" not in gltf["meshes"][0]["primitives"][0]
    with pytest.raises(ConfigError, match="increasing"):
        write_glb(tmp_path / "two.glb", np.stack([mesh.vertices] * 2), s.faces, [1.0, 1.0])


def test_glb_writer_step_interpolation_and_no_rotation(tmp_path):
    sim = stretched_ell()
    w = GlbWriter(sim, tmp_path / "s.glb", interpolation="STEP", z_up=False)
    w.add_frame(sim)
    sim.step(2)
    w.add_frame(sim)
    with pytest.raises(ConfigError, match="increasing times"):
        w.add_frame(sim)
    assert w.close() == [tmp_path / "s.glb"]
    gltf, binary = read_glb(tmp_path / "s.glb")
    assert gltf["animations"][0]["samplers"][0]["interpolation"] == "STEP"
    base = glb_accessor(gltf, binary, gltf["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
    assert np.allclose(base, 1.5 * sim.rest_positions[w.surface.vertices], rtol=1e-7)
    with pytest.raises(ConfigError, match="closed"):
        w.add_frame(sim)


@pytest.mark.skipif(not usd_available(), reason="usd-core is not installed (pip install fepr[export-usd])")
def test_usd_has_time_sampled_points(tmp_path):
    from pxr import Usd, UsdGeom

    sim = stretched_ell()
    with Recorder(sim, tmp_path, formats=["usd"], every=2, name="ell") as rec:
        run_with_export(sim, 6, rec)
    stage = Usd.Stage.Open(str(tmp_path / "ell.usdc"))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == pytest.approx(15.0)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 3.0)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/fepr/ell"))
    assert stage.GetDefaultPrim().GetPath() == "/fepr"
    points = mesh.GetPointsAttr()
    assert points.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3] * rec.surface.num_faces
    assert np.array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()), rec.surface.local_faces.ravel())
    last = np.array(points.Get(3.0))
    assert np.allclose(last, sim.positions[rec.surface.vertices], rtol=1e-6)
    assert len(mesh.GetVelocitiesAttr().GetTimeSamples()) == 4


def test_usd_without_usd_core_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pxr", None)  # makes "import pxr" raise ImportError
    with pytest.raises(fepr.MissingDependencyError, match=r"usd-core.*export-usd"):
        Recorder(stretched_ell(), tmp_path, formats="usd")


# ---- Recorder API --------------------------------------------------------------------------------------


def test_run_with_export_every_three(tmp_path):
    sim = stretched_ell()
    with Recorder(sim, tmp_path, formats="obj", every=3) as rec:
        run_with_export(sim, 10, rec)
        assert sim.num_steps == 10
        assert [f[1] for f in rec.frames] == [0, 3, 6, 9]
        assert not rec.record()  # step 10 is not due
        assert rec.record(force=True)  # but can be forced, once
        assert not rec.record(force=True)
    assert len(list((tmp_path / "obj").glob("frame_*.obj"))) == 5
    with pytest.raises(ConfigError, match="closed"):
        rec.record()


def test_recorder_counts_steps_from_its_creation(tmp_path):
    sim = stretched_ell()
    sim.step(1)
    rec = Recorder(sim, tmp_path, formats="obj", every=2)
    run_with_export(sim, 4, rec)
    rec.close()
    assert [f[1] for f in rec.frames] == [1, 3, 5]


def test_parse_formats():
    assert parse_formats("vtu, GLB,vtu") == ("vtu", "glb")
    assert parse_formats(["obj", ".ply"]) == ("obj", "ply")
    assert set(FORMATS) == {"vtu", "obj", "ply", "glb", "usd"}
    with pytest.raises(ConfigError, match=r"unknown export format 'stl' \(known: vtu, obj, ply, glb, usd\)"):
        parse_formats("vtu,stl")
    with pytest.raises(ConfigError, match="no export format"):
        parse_formats(" , ")


@pytest.mark.parametrize(
    "kw, fragment",
    [({"every": 0}, "every"), ({"every": 1.5}, "every"), ({"name": "a/b"}, "name"), ({"formats": "gif"}, "gif")],
)
def test_recorder_rejects_bad_options(tmp_path, kw, fragment):
    with pytest.raises(ConfigError, match=fragment):
        Recorder(stretched_ell(), tmp_path, **kw)


# ---- scene files and run_scene -------------------------------------------------------------------------


def scene_dict(**export) -> dict:
    d = {
        "mesh": {"builtin": "ell"},
        "material": {"youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 5.0},
        "initial": {"scale": 1.5},
        "run": {"steps": 6},
    }
    if export:
        d["export"] = export
    return d


def test_scene_export_section(tmp_path):
    s = scene_from_dict(scene_dict(formats=["vtu", "glb"], every=2), ".")
    assert s.export.formats == ("vtu", "glb") and s.export.every == 2
    assert scene_from_dict(scene_dict(), ".").export.formats == ()
    res = run_scene(s, out_dir=tmp_path)
    assert res.export_dir == tmp_path / "export" and res.export_frames == 4
    assert len(read_pvd(tmp_path / "export" / "scene.pvd")) == 4
    assert (tmp_path / "export" / "scene.glb").exists()
    # No out_dir: nothing is written, as for the diagnostics.
    assert run_scene(s).export_dir is None
    with pytest.raises(ConfigError, match="out_dir"):
        run_scene(s, export="obj")


@pytest.mark.parametrize(
    "export, fragment",
    [
        ({"formats": ["vtu", "gif"]}, "[export] formats: unknown export format 'gif'"),
        ({"formats": "vtu"}, "[export] formats must be a list"),
        ({"every": 0}, "[export] every must be >= 1"),
        ({"every": 2.0}, "[export] every must be an integer"),
        ({"fromats": ["vtu"]}, "[export] unknown key 'fromats' (known: formats, every)"),
    ],
)
def test_scene_export_errors_name_the_key(export, fragment):
    with pytest.raises(ConfigError) as info:
        scene_from_dict(scene_dict(**export), ".", source="s.toml")
    assert str(info.value).startswith("s.toml: ") and fragment in str(info.value)


def test_run_scene_export_overrides_and_progress(tmp_path):
    s = scene_from_dict(scene_dict(formats=["vtu"], every=5), ".")
    calls = []

    def progress(done, total, sim):
        calls.append(done)

    res = run_scene(s, steps=20, out_dir=tmp_path, export="obj", export_every=4, progress=progress)
    assert res.export_formats == ("obj",) and res.export_frames == 6
    assert not (tmp_path / "export" / "vtu").exists()
    assert calls == list(range(0, 21, 2))  # every tenth of the run, as without export
    calls.clear()
    res = run_scene(s, steps=20, out_dir=tmp_path / "b", export_every=3, progress=progress)
    assert res.export_frames == 7  # steps 0, 3, ..., 18
    assert calls[0] == 0 and calls[-1] == 20 and len(calls) <= 11 and calls == sorted(set(calls))


# ---- command line --------------------------------------------------------------------------------------


def test_cli_export_writes_every_other_frame(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["run", str(EXAMPLES / "seed_demo3_stretch.toml"), "--out", str(out), "--steps", "10"]
    code = main(args + ["--export", "vtu,obj,glb", "--export-every", "2"])
    assert code == EXIT_OK
    assert "exported 6 frames (vtu, obj, glb)" in capsys.readouterr().out
    ex = out / "export"
    name = load_scene(EXAMPLES / "seed_demo3_stretch.toml").name
    entries = read_pvd(ex / f"{name}.pvd")
    assert len(entries) == 6
    assert len(list((ex / "vtu").glob("*.vtu"))) == 6
    assert len(list((ex / "obj").glob("*.obj"))) == 6
    steps = [int(r.split(",")[1]) for r in (ex / "frames.csv").read_text().splitlines()[1:]]
    assert steps == [0, 2, 4, 6, 8, 10]
    gltf, _ = read_glb(ex / f"{name}.glb")
    assert len(gltf["meshes"][0]["primitives"][0]["targets"]) == 5


def test_cli_export_errors(tmp_path, capsys):
    scene = str(EXAMPLES / "seed_demo3_stretch.toml")
    assert main(["run", scene, "--out", str(tmp_path), "--export", "vtu,stl"]) == EXIT_INVALID
    assert "unknown export format 'stl'" in capsys.readouterr().err
    assert main(["run", scene, "--out", str(tmp_path), "--export-every", "0"]) == EXIT_INVALID
    assert main(["run", scene, "--out", str(tmp_path), "--export-every", "2"]) == EXIT_INVALID
    assert "export" in capsys.readouterr().err


def test_cli_export_of_a_runaway_keeps_the_frames(tmp_path):
    scene = tmp_path / "runaway.toml"
    scene.write_text(
        "[mesh]\nbuiltin = 'ell'\n[material]\nyoungs_modulus = 1e7\npoisson_ratio = 0.3\n[mass]\nnode_mass = 1.0\n"
        "[initial]\nscale = 1.5\n[integrator]\ndt = 0.1\n[projection]\nenabled = false\n[run]\nsteps = 200\n"
        "[export]\nformats = ['vtu', 'glb']\nevery = 5\n"
    )
    out = tmp_path / "out"
    assert main(["run", str(scene), "--out", str(out), "-q"]) == EXIT_RUNAWAY
    rows = (out / "export" / "frames.csv").read_text().splitlines()[1:]
    entries = read_pvd(out / "export" / "runaway.pvd")
    assert len(entries) == len(rows) >= 1
    for _, path in entries:
        assert np.all(np.isfinite(meshio.read(path).points))
    read_glb(out / "export" / "runaway.glb")
