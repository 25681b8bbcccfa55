"""Tests of the load options (scale, translate, fit, rotate, up_axis, center) in load_mesh, transform_mesh and
the scene file's [mesh] section."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import fepr
from fepr.errors import ConfigError
from fepr.io import load_mesh, transform_mesh, write_mesh
from fepr.io.transform import rotation_matrix
from fepr.scene import scene_from_dict

BOX = fepr.meshes.box(size=(4.0, 2.0, 1.0), resolution=(2, 1, 1), center=(10.0, 20.0, 30.0))


@pytest.fixture
def box_file(tmp_path):
    path = tmp_path / "box.npz"
    write_mesh(BOX, path)
    return path


def quiet_load(path, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # rotations and positive scales never invert a tet
        return load_mesh(path, **kwargs)


def test_up_axis_y_turns_y_up_into_z_up(box_file):
    mesh = quiet_load(box_file, up_axis="y")
    np.testing.assert_allclose(mesh.vertices, BOX.vertices @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).T)
    lo, hi = mesh.bounding_box()
    np.testing.assert_allclose(hi - lo, [4.0, 1.0, 2.0])  # the file's y extent (2) is now the height
    np.testing.assert_array_equal(quiet_load(box_file, up_axis="z").vertices, BOX.vertices)
    np.testing.assert_array_equal(quiet_load(box_file, up_axis="Y").vertices, mesh.vertices)


def test_rotate_angles_apply_about_x_then_y_then_z(box_file):
    angles = (30.0, -45.0, 120.0)
    mesh = quiet_load(box_file, rotate=angles)
    rx, ry, rz = rotation_matrix((30, 0, 0)), rotation_matrix((0, -45, 0)), rotation_matrix((0, 0, 120))
    expected = ((BOX.vertices @ rx.T) @ ry.T) @ rz.T
    np.testing.assert_allclose(mesh.vertices, expected, atol=1e-12)
    np.testing.assert_allclose(mesh.volumes(), BOX.volumes(), rtol=1e-12)
    np.testing.assert_allclose(rotation_matrix((0, 0, 90)) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    matrix = quiet_load(box_file, rotate=rotation_matrix(angles).tolist())
    np.testing.assert_allclose(matrix.vertices, mesh.vertices, atol=1e-12)


def test_fit_scales_the_largest_extent(box_file):
    mesh = quiet_load(box_file, fit=0.5)
    lo, hi = mesh.bounding_box()
    assert (hi - lo).max() == pytest.approx(0.5)
    np.testing.assert_allclose(hi - lo, [0.5, 0.25, 0.125])
    # fit is measured after the rotation: up_axis y makes z the 2 m side
    lo, hi = quiet_load(box_file, up_axis="y", rotate=(0, 0, 90), fit=1.0).bounding_box()
    np.testing.assert_allclose(hi - lo, [0.25, 1.0, 0.5], atol=1e-12)


@pytest.mark.parametrize("center", [True, "bbox"])
def test_center_bbox(box_file, center):
    lo, hi = quiet_load(box_file, center=center).bounding_box()
    np.testing.assert_allclose(lo + hi, 0.0, atol=1e-12)


def test_center_centroid_uses_the_volume():
    # an L: the centroid is not the bounding-box centre
    mesh = transform_mesh(fepr.meshes.ell(), center="centroid")
    vols = mesh.volumes()
    centroid = (vols[:, None] * mesh.vertices[mesh.tets].mean(axis=1)).sum(axis=0) / vols.sum()
    np.testing.assert_allclose(centroid, 0.0, atol=1e-12)
    lo, hi = mesh.bounding_box()
    assert np.abs(lo + hi).max() > 0.1


def test_order_of_operations(box_file):
    mesh = quiet_load(box_file, up_axis="y", rotate=(0, 0, 90), scale=0.5, center="bbox", translate=(1, 2, 3))
    v = BOX.vertices @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).T
    v = v @ rotation_matrix((0, 0, 90)).T
    v = v * 0.5
    v = v - 0.5 * (v.min(axis=0) + v.max(axis=0))
    v = v + [1, 2, 3]
    np.testing.assert_allclose(mesh.vertices, v, atol=1e-12)


def test_scale_and_translate_only_are_exact(box_file):
    mesh = quiet_load(box_file, scale=0.01, translate=(0.5, 0, 0))
    np.testing.assert_array_equal(mesh.vertices, BOX.vertices * 0.01 + np.array([0.5, 0, 0]))


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(fit=0), "fit"),
        (dict(fit=-1.0), "fit"),
        (dict(fit="1"), "fit"),
        (dict(fit=float("inf")), "fit"),
        (dict(fit=1.0, scale=2.0), "at most one of scale and fit"),
        (dict(rotate=(1, 2)), "rotate"),
        (dict(rotate="x"), "rotate"),
        (dict(rotate=45), "rotate"),
        (dict(rotate=(0, float("nan"), 0)), "rotate"),
        (dict(rotate=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "rotate: .*determinant -1"),
        (dict(rotate=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]), "rotate: .*not orthonormal"),
        (dict(up_axis="x"), "up_axis"),
        (dict(up_axis=1), "up_axis"),
        (dict(center="middle"), "center"),
        (dict(center=(0, 0, 0)), "center"),
        (dict(translate=(0, 0)), "translate"),
        (dict(scale=0), "scale"),
    ],
)
def test_invalid_options_name_the_key(box_file, kwargs, pattern):
    with pytest.raises(ConfigError, match=pattern):
        load_mesh(box_file, **kwargs)
    with pytest.raises(ConfigError, match=pattern):
        transform_mesh(BOX, **kwargs)


# ---- scene files --------------------------------------------------------------------------------------


def scene(mesh: dict):
    return {
        "mesh": mesh,
        "material": {"youngs_modulus": 1e3, "poisson_ratio": 0.3},
        "mass": {"node_mass": 1.0},
    }


def test_scene_load_options_for_a_file(box_file):
    sc = scene_from_dict(
        scene({"path": str(box_file), "up_axis": "y", "rotate": [0, 0, 90], "fit": 2.0, "center": "bbox"}), "."
    )
    mesh = sc.load_mesh()
    expected = load_mesh(box_file, up_axis="y", rotate=(0, 0, 90), fit=2.0, center="bbox")
    np.testing.assert_array_equal(mesh.vertices, expected.vertices)
    matrix = scene_from_dict(scene({"path": str(box_file), "rotate": [[0, -1, 0], [1, 0, 0], [0, 0, 1]]}), ".")
    np.testing.assert_allclose(matrix.load_mesh().vertices, load_mesh(box_file, rotate=(0, 0, 90)).vertices, atol=1e-12)


def test_scene_load_options_for_builtins():
    sc = scene_from_dict(scene({"builtin": "sphere", "radius": 0.5, "resolution": 4, "center": [1, 2, 3]}), ".")
    lo, hi = sc.load_mesh().bounding_box()
    np.testing.assert_allclose((lo + hi) / 2, [1, 2, 3], atol=1e-12)
    sc = scene_from_dict(scene({"builtin": "ell", "center": "centroid", "fit": 1.5}), ".")
    lo, hi = sc.load_mesh().bounding_box()
    assert (hi - lo).max() == pytest.approx(1.5)
    sc = scene_from_dict(scene({"builtin": "cylinder", "radius": 0.1, "height": 0.6, "up_axis": "y"}), ".")
    lo, hi = sc.load_mesh().bounding_box()
    np.testing.assert_allclose(hi - lo, [0.2, 0.6, 0.2], atol=1e-12)  # the cylinder's z axis now points along -y
    sc = scene_from_dict(scene({"builtin": "box", "center": True}), ".")
    assert sc.mesh.center == "bbox" and "center" not in sc.mesh.builtin_options


@pytest.mark.parametrize(
    "mesh, pattern",
    [
        ({"builtin": "box", "fit": 0}, r"\[mesh\] fit must be > 0"),
        ({"builtin": "box", "fit": 1, "scale": 2}, r"\[mesh\] give at most one of scale and fit"),
        ({"builtin": "box", "rotate": [1, 2]}, r"\[mesh\] rotate must be \[ax, ay, az\]"),
        ({"builtin": "box", "rotate": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}, r"\[mesh\] rotate: .*determinant"),
        ({"builtin": "box", "rotate": ["a", 0, 0]}, r"\[mesh\] rotate must be"),
        ({"builtin": "box", "up_axis": "x"}, r"\[mesh\] up_axis must be one of 'y', 'z'"),
        ({"builtin": "box", "center": "middle"}, r"\[mesh\] center must be \"bbox\", \"centroid\""),
        ({"builtin": "ell", "center": [0, 0, 0]}, r"\[mesh\] center does not apply to builtin 'ell'"),
        ({"builtin": "sphere", "size": 1.0}, r"\[mesh\] size does not apply to builtin 'sphere'"),
        ({"builtin": "box", "radius": 1.0}, r"\[mesh\] radius does not apply to builtin 'box'"),
        ({"builtin": "cylinder", "height": -1.0}, r"\[mesh\] height must be > 0"),
        ({"path": "x.msh", "radius": 1.0}, r"\[mesh\] radius applies to builtin meshes only"),
    ],
)
def test_scene_invalid_mesh_keys(tmp_path, mesh, pattern):
    (tmp_path / "x.msh").write_text("")
    with pytest.raises(ConfigError, match=pattern):
        scene_from_dict(scene(mesh), tmp_path)


def test_scene_center_point_for_a_file_is_rejected(box_file):
    with pytest.raises(ConfigError, match=r"center = \[x, y, z\] applies to builtin meshes only"):
        scene_from_dict(scene({"path": str(box_file), "center": [0, 0, 0]}), ".")


def test_scene_with_a_builtin_sphere_runs():
    sc = scene_from_dict(
        {
            "mesh": {"builtin": "sphere", "radius": 0.2, "resolution": 3, "center": [0, 0, 0.5]},
            "material": {"youngs_modulus": 1e4, "poisson_ratio": 0.3},
            "mass": {"density": 100.0},
            "initial": {"angular_velocity": [0.0, 0.0, 1.0]},
            "integrator": {"dt": 0.005},
        },
        ".",
    )
    sim = sc.build()
    sim.step(3)
    assert np.all(np.isfinite(np.asarray(sim.positions)))
