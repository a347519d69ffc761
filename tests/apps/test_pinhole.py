"""Pinhole views for renders and shadow maps (o3dvis.apps.pinhole)."""

import numpy as np
import open3d as o3d
import pytest

from o3dvis.apps.pinhole import MAX_PIXELS, PinholeView, camera_location_of, look_at, make_view

POINTS = np.random.default_rng(1).uniform(-1, 1, size=(200, 3))


def test_look_at_is_a_rigid_transform_that_puts_the_target_on_the_axis():
    eye, target = np.array([3.0, -2.0, 1.5]), np.array([0.2, 0.1, -0.3])
    extrinsic = look_at(eye, target)
    rotation = extrinsic[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    ahead = rotation @ target + extrinsic[:3, 3]
    np.testing.assert_allclose(ahead[:2], 0, atol=1e-12)
    assert ahead[2] == pytest.approx(np.linalg.norm(target - eye))
    with pytest.raises(ValueError, match="looks at"):
        look_at(eye, eye)


def test_a_view_from_a_location_frames_every_point_and_projects_the_centre_to_the_middle():
    camera = np.array([0.0, 0.0, 6.0])
    view = make_view(POINTS, camera, 64, 48)
    assert isinstance(view, PinholeView) and (view.width, view.height) == (64, 48)
    np.testing.assert_allclose(view.location, camera, atol=1e-12)
    pixels, depths = view.project(POINTS)
    assert (depths > 0).all()
    assert (pixels[:, 0] >= -0.5).all() and (pixels[:, 0] < 63.5).all()
    assert (pixels[:, 1] >= -0.5).all() and (pixels[:, 1] < 47.5).all()
    centre, _ = view.project(((POINTS.min(axis=0) + POINTS.max(axis=0)) / 2)[None])
    np.testing.assert_allclose(centre[0], [31.5, 23.5], atol=1e-9)


def test_open3d_cameras_keep_their_intrinsic_and_size():
    params = o3d.camera.PinholeCameraParameters()
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(80, 60, 50.0, 50.0, 39.5, 29.5)
    params.extrinsic = look_at(np.array([0.0, 0.0, 5.0]), np.zeros(3))
    view = make_view(POINTS, params)
    assert (view.width, view.height) == (80, 60)
    np.testing.assert_allclose(view.intrinsic, params.intrinsic.intrinsic_matrix)
    np.testing.assert_allclose(camera_location_of(params), [0.0, 0.0, 5.0], atol=1e-12)


def test_images_too_large_or_empty_are_refused():
    with pytest.raises(ValueError, match="pixels"):
        make_view(POINTS, [0.0, 0.0, 6.0], 1 << 15, 1 << 14)
    assert (1 << 15) * (1 << 14) > MAX_PIXELS
    with pytest.raises(ValueError, match="positive width"):
        make_view(POINTS, [0.0, 0.0, 6.0], 0, 10)
