"""Shadows of a point cloud under a point light: a point is lit exactly when the light sees it.

No shadow-map bias to tune: :func:`points_in_shadow` asks the visibility method
directly. :func:`shadow_map` gives the depth image from the light (the
triangulated visible surface, depth interpolated) to shade other geometry, and
:func:`render_with_shadows` draws the cloud with its shadows.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..cameras import as_camera_location
from .pinhole import make_view
from ..clouds import cloud_points, legacy_cloud
from ..field import OnPointError
from ..methods import resolve_method
from .render import image_from, lambert, rasterize, splat, splat_size
from .triangulation import DEFAULT_EDGE_FACTOR, local_spacing, visible_triangles

__all__ = ["shadow_map", "points_in_shadow", "render_with_shadows"]


def _seen_from(model, points: np.ndarray, cameras: np.ndarray, light: int) -> np.ndarray:
    """(V, N) bool: which points each camera sees by ``model`` (see :func:`~o3dvis.methods.resolve_method`);
    a camera on a point is reported as the light where it is camera ``light``."""
    try:
        return resolve_method(model)(points, cameras)
    except OnPointError as error:
        if error.view != light:
            raise
        raise error.named("the light") from None


def shadow_map(pcd, light, resolution: int = 512, model=None, *,
               edge_factor: float = DEFAULT_EDGE_FACTOR) -> o3d.geometry.Image:
    """The depth image of the surface a point light sees.

    The light is a pinhole at ``light`` looking at the bounding-box centre,
    framed to the cloud (:func:`o3dvis.apps.pinhole.make_view` with
    ``width = height = resolution``). Points visible from the light are
    triangulated in its image plane (long triangles dropped) and their depth
    interpolated linearly inside each triangle.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor).
        light: (3,) light position.
        resolution: image width and height in pixels.
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        edge_factor: triangles with an edge longer than this many local point
            spacings are holes, not surface.

    Returns:
        ``o3d.geometry.Image`` of float32 depth along the light's axis, 0 where
        the light sees no surface.
    """
    points = cloud_points(pcd)
    light = as_camera_location(light, "light")
    if int(resolution) < 1:
        raise ValueError(f"resolution must be a positive number of pixels, got {resolution}")
    view = make_view(points, light, int(resolution), int(resolution))
    seen = np.flatnonzero(_seen_from(model, points, light[None], 0)[0])
    triangles = visible_triangles(points, light, seen, edge_factor * local_spacing(points))
    return o3d.geometry.Image(rasterize(view, points, triangles).astype(np.float32))


def points_in_shadow(pcd, light, model=None) -> np.ndarray:
    """Which points a point light does not reach.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor).
        light: (3,) light position.
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.

    Returns:
        (N,) bool, True for points in shadow (hidden from the light).
    """
    points = cloud_points(pcd)
    light = as_camera_location(light, "light")
    return ~_seen_from(model, points, light[None], 0)[0]


def render_with_shadows(pcd, light, camera, width: int = 640, height: int = 480, model=None, *,
                        ambient: float = 0.3, intrinsic=None, point_size: float | None = None,
                        background=(1.0, 1.0, 1.0)) -> o3d.geometry.Image:
    """Renders the points a camera sees, lit by a point light, with cast shadows.

    Lit points are shaded ``ambient + (1 - ambient) |n . l|`` (``n . l`` = 1 when the
    cloud has no normals); points hidden from the light get ``ambient`` only.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor); colours are used when present.
        light: (3,) light position.
        camera: a (3,) location looking at the cloud's centre, a 4x4 extrinsic or
            ``o3d.camera.PinholeCameraParameters``.
        width, height: image size (ignored when an intrinsic is given).
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        ambient: brightness of shadowed points, in [0, 1].
        intrinsic: ``o3d.camera.PinholeCameraIntrinsic`` (default: framed to the cloud).
        point_size: splat radius in world units (default: the local point spacing).
        background: RGB in [0, 1].

    Returns:
        ``o3d.geometry.Image``, (height, width, 3) uint8.
    """
    if not 0 <= ambient <= 1:
        raise ValueError(f"ambient must be in [0, 1], got {ambient}")
    pcd = legacy_cloud(pcd)
    points = cloud_points(pcd)
    light = as_camera_location(light, "light")
    view = make_view(points, camera, width, height, intrinsic)
    seen_by_camera, lit = _seen_from(model, points, np.stack([view.location, light]), 1)
    base = np.clip(np.asarray(pcd.colors), 0, 1) if pcd.has_colors() else np.full((len(points), 3), 0.8)
    brightness = np.where(lit, ambient + (1 - ambient) * lambert(pcd, points, light), ambient)
    index, _ = splat(view, points, splat_size(points, point_size), seen_by_camera)
    return image_from(index, base * brightness[:, None], background)
