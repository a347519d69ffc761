"""Renders (``o3dvis.apps.render``) on ray-cast ground-truth visibility: a sphere's depth image, and
the far plane hidden behind the near one."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from o3dvis.apps import depth_image, make_view, render_points

from conftest import _box, _cloud, _sample


def test_depth_image_of_a_sphere(sphere):
    points, _, method = sphere
    intrinsic = o3d.camera.PinholeCameraIntrinsic(100, 100, 100.0, 100.0, 49.5, 49.5)
    depth = np.asarray(depth_image(_cloud(points), [0, 0, 5], intrinsic, model=method))
    assert depth.shape == (100, 100) and depth.dtype == np.float32
    assert 4.0 <= depth[49:51, 49:51].min() and depth[49:51, 49:51].max() < 4.02
    radius = 100 * np.tan(np.arcsin(1 / 5))  # of the silhouette, in pixels
    offset = np.hypot(*(np.mgrid[0:100, 0:100] - 49.5))
    assert (depth[offset < radius] > 0).all()
    assert offset[depth > 0].max() < radius + 4  # splats reach past the rim by their radius
    covered = depth[depth > 0]
    assert covered.max() < np.sqrt(5 ** 2 - 1) + 0.05  # no back-side point


def test_render_points_hides_the_far_plane():
    near = _box((1.0, 1.0, 0.01), (0, 0, 1.0))
    far = _box((3.0, 3.0, 0.01), (0, 0, 0.0))
    points, _, method = _sample(near + far, 8000)
    colors = np.where((points[:, 2] > 0.5)[:, None], [1.0, 0, 0], [0, 0, 1.0])
    pcd = _cloud(points, colors)
    camera = [0.0, 0.0, 6.0]
    view = make_view(points, camera, 160, 160)
    corners, _ = view.project(np.array([[-0.4, -0.4, 1.01], [0.4, 0.4, 1.01]]))
    (c0, r0), (c1, r1) = np.rint(corners).astype(int)
    rows, cols = slice(min(r0, r1), max(r0, r1)), slice(min(c0, c1), max(c0, c1))
    small = dict(point_size=0.005)  # small splats leave gaps to see through
    with_vis = np.asarray(render_points(pcd, camera, True, 160, 160, method, **small))[rows, cols]
    without = np.asarray(render_points(pcd, camera, False, 160, 160, **small))[rows, cols]
    blue = lambda img: ((img[..., 2] == 255) & (img[..., 0] == 0)).sum()  # noqa: E731
    assert blue(without) > 20 and blue(with_vis) == 0
    full = np.asarray(render_points(pcd, camera, True, 160, 160, method))[rows, cols]
    assert (full[..., 0] == 255).all()  # default splats close the front square
