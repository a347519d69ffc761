"""Views at the limits: cameras and lights so far that they are directions, clouds a hair off flat,
pinhole intrinsics that are not cameras."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis.training.data.sample import sample_surface


@pytest.fixture(scope="module")
def torus():
    mesh = o3d.geometry.TriangleMesh.create_torus()
    points, _ = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.triangles), 5000,
                               np.random.default_rng(0))
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    return mesh, points, centre, float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


AWAY = np.array([1.5, -2.0, 2.5]) / np.linalg.norm([1.5, -2.0, 2.5])


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


# ------------------------------------------------------------------ distant cameras and lights

@pytest.mark.parametrize("diagonals", [1e7, 1e9])
def test_a_distant_camera_is_the_orthographic_view_and_matches_ray_casting(vis, torus, diagonals):
    mesh, points, centre, diagonal = torus
    camera = centre + AWAY * diagonal * diagonals
    truth = o3dvis.visibility_from_mesh(mesh, points, camera)[0]
    field = vis.encode(points)
    orthographic = field.query(direction=-AWAY)[0]
    mask = field.query(camera)[0]
    np.testing.assert_array_equal(mask, orthographic)
    assert (mask == truth).mean() > 0.93, f"{mask.sum()} visible, ray casting {truth.sum()}"
    torch.testing.assert_close(field.probabilities(camera), field.probabilities(direction=-AWAY),
                               rtol=0, atol=0)
    pcd = _cloud(points)
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)
    np.testing.assert_array_equal(pt_map, np.flatnonzero(orthographic))
    assert len(o3dvis.select_visible(pcd, camera, model=vis).points) == orthographic.sum()


def test_cameras_at_the_edge_of_float64_are_directions(vis, torus):
    _, points, _, _ = torus
    field = vis.encode(points)
    for camera in ([0.0, 0.0, 1e300], [1e308, -1e308, 1e308]):
        direction = -np.asarray(camera) / 1e300
        np.testing.assert_array_equal(field.query(camera), field.query(direction=direction))


@pytest.mark.parametrize("scale", [1e-170, 1e160, 1e-300, 1e300])
def test_a_cloud_and_its_cameras_scaled_alike_get_the_same_answers(vis, torus, scale):
    """The far-camera switch compares distances in the cloud's normalised frame: a cloud of 1e-170
    units (whose squared diagonal underflows) or 1e160 (overflows) is answered as at scale 1, near
    cameras and distant ones alike."""
    _, points, centre, diagonal = torus
    cameras = centre + AWAY * diagonal * np.array([[0.6], [2.0], [5.0], [1e4]])
    expected = vis.encode(points).query(cameras)
    np.testing.assert_array_equal(vis.encode(points * scale).query(cameras * scale), expected)
    _, pt_map = o3dvis.hidden_point_removal_neural(_cloud(points * scale), cameras[1] * scale, model=vis)
    np.testing.assert_array_equal(pt_map, np.flatnonzero(expected[1]))
    assert expected[:-1].mean() < 0.75  # perspective views: a camera counted far would see more


@pytest.mark.parametrize("scale", [1e-170, 1e160])
def test_viewpoints_around_a_cloud_scale_with_it(torus, scale):
    from o3dvis.cameras import viewpoints_around
    from o3dvis.geometry import diagonal

    _, points, _, size = torus
    assert diagonal(points * scale) == pytest.approx(size * scale, rel=1e-12)
    np.testing.assert_allclose(viewpoints_around(points * scale, 14), viewpoints_around(points, 14) * scale,
                               rtol=1e-12, atol=0)


def test_a_distant_camera_stays_differentiable(vis, torus):
    _, points, centre, diagonal = torus
    camera = torch.tensor(centre + AWAY * diagonal * 1e8, requires_grad=True)
    vis.encode(points).probabilities(camera).sum().backward()
    assert camera.grad is not None and torch.isfinite(camera.grad).all()


@pytest.mark.parametrize("diagonals", [1e7, 1e9])
def test_a_distant_light_casts_the_shadows_of_the_sun(vis, torus, diagonals):
    mesh, points, centre, diagonal = torus
    light = centre + np.array([0.0, 0.3, 1.0]) * diagonal * diagonals
    truth = ~o3dvis.visibility_from_mesh(mesh, points, light)[0]
    shadow = o3dvis.points_in_shadow(_cloud(points), light, vis)
    assert (shadow == truth).mean() > 0.93, f"{shadow.sum()} in shadow, ray casting {truth.sum()}"
    np.testing.assert_array_equal(shadow, ~vis.encode(points).query(direction=-light / np.linalg.norm(light))[0])
    # the pictures of a distant light and camera are those of the nearest far one
    near = centre + np.array([0.0, 0.3, 1.0]) * diagonal * 1e4
    camera = centre + AWAY * diagonal * diagonals
    for picture in (lambda l, c: o3dvis.render_with_shadows(_cloud(points), l, c, 64, 48, vis),
                    lambda l, c: np.asarray(o3dvis.shadow_map(_cloud(points), l, 32, vis)) > 0):
        far_image, near_image = np.asarray(picture(light, camera)), np.asarray(picture(near, camera))
        assert (far_image == near_image).mean() > 0.99


def test_a_distant_pinhole_camera_keeps_its_frustum(vis, torus):
    _, points, centre, diagonal = torus
    eye = centre + AWAY * diagonal * 1e7
    params = o3d.camera.PinholeCameraParameters()
    forward = (centre - eye) / np.linalg.norm(centre - eye)  # Open3D: +z ahead, x right, y down
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    rotation = np.stack([right, np.cross(forward, right), forward])
    params.extrinsic = np.r_[np.c_[rotation, -rotation @ eye], [[0, 0, 0, 1]]]
    width, height, focal = 64, 48, 32 * diagonal * 1e7 / 0.75  # the image holds about half the torus
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, focal, focal, width / 2 - 0.5, height / 2 - 0.5)
    field = vis.encode(points)
    mask = field.query(params)[0]
    cam = points @ params.extrinsic[:3, :3].T + params.extrinsic[:3, 3]
    u = focal * cam[:, 0] / cam[:, 2] + width / 2 - 0.5
    v = focal * cam[:, 1] / cam[:, 2] + height / 2 - 0.5
    inside = (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5) & (cam[:, 2] > 0)
    assert 0.2 < inside.mean() < 0.8
    np.testing.assert_array_equal(mask, inside & field.query(direction=-AWAY)[0])


# ------------------------------------------------------------------ clouds a hair off flat

GRID = np.stack(np.meshgrid(np.linspace(0, 1, 60), np.linspace(0, 1, 60)), axis=-1).reshape(-1, 2)


@pytest.mark.parametrize("bump", ["noise", "wave"])
def test_a_height_field_a_hair_off_flat_is_answered_as_the_flat_one(vis, bump):
    z = (np.random.default_rng(0).normal(size=len(GRID)) if bump == "noise"
         else np.sin(7 * GRID[:, 0]) * np.cos(5 * GRID[:, 1]))
    cameras = np.array([[0.3, 0.6, 2.0], [2.0, 0.4, 0.3], [0.5, 0.5, -3.0]])
    flat = vis.encode(np.c_[GRID, np.zeros(len(GRID))])
    for amplitude in (1e-12, 1e-9, 1e-7):
        field = vis.encode(np.c_[GRID, amplitude * z])
        assert field.frame.hull is not None, f"a bump of {amplitude:g} makes the cloud 3-D"
        mask = field.query(cameras)
        assert mask.all(), f"bump {amplitude:g}: {(~mask).sum(axis=1)} points hidden"
        np.testing.assert_array_equal(mask, flat.query(cameras))
    assert vis.encode(np.c_[GRID, 1e-3 * z]).frame.hull is None  # a real relief is left to the network


def test_the_flat_rule_is_relative_to_the_size_of_the_cloud(vis):
    z = 1e-9 * np.random.default_rng(1).normal(size=len(GRID))
    for size in (1e-6, 1.0, 1e6):
        assert vis.encode(size * np.c_[GRID, z]).frame.hull is not None
        assert vis.encode(size * np.c_[GRID, 1e-3 * z / 1e-9]).frame.hull is None


# ------------------------------------------------------------------ pinhole intrinsics

def _pinhole(fx: float, fy: float) -> o3d.camera.PinholeCameraParameters:
    params = o3d.camera.PinholeCameraParameters()
    params.extrinsic = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 5], [0, 0, 0, 1]])
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(64, 48, fx, fy, 31.5, 23.5)
    return params


@pytest.mark.parametrize("fx, fy", [(-60.0, 60.0), (60.0, -60.0), (-60.0, -60.0), (0.0, 60.0)])
def test_a_focal_length_that_is_not_positive_is_refused_everywhere(vis, fx, fy):
    points = np.random.default_rng(2).normal(size=(300, 3))
    pcd = _cloud(points)
    camera = _pinhole(fx, fy)
    calls = {"query": lambda: vis.encode(points).query(camera),
             "probabilities": lambda: vis.encode(points).probabilities(camera),
             "select_visible": lambda: o3dvis.select_visible(pcd, camera, model=vis),
             "render_with_shadows": lambda: o3dvis.render_with_shadows(pcd, [0, 0, 5], camera, model=vis),
             "render_points": lambda: o3dvis.render_points(pcd, [0, 0, 5], intrinsic=camera.intrinsic, model=vis),
             "depth_image": lambda: o3dvis.depth_image(pcd, [0, 0, 5], camera.intrinsic, model=vis)}
    for name, call in calls.items():
        with pytest.raises(ValueError, match="focal lengths must be positive"):
            call()
    assert vis.encode(points).query(_pinhole(60.0, 60.0)).shape == (1, 300)


@pytest.mark.parametrize("scale", [1e-170, 1e160])
def test_best_view_of_a_cloud_scaled_is_the_view_scaled(scale):
    """best_view's distance is the box's diagonal computed without squares: below 1e-154 or above
    1e154 units the squares underflow or overflow."""
    o3d.utility.random.seed(0)
    points = np.asarray(o3d.geometry.TriangleMesh.create_sphere(1.0, 20).sample_points_uniformly(1500).points)
    unit, curve = o3dvis.best_view(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)), progress=False)
    scaled, scaled_curve = o3dvis.best_view(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points * scale)),
                                            progress=False)
    assert np.allclose(np.asarray(scaled) / scale, unit, rtol=1e-6)
    assert np.allclose(scaled_curve, curve)
