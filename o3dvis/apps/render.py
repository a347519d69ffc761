"""Headless images of point clouds: z-buffered point splatting in numpy.

Hidden points are removed with the visibility method before splatting, so
far surfaces never show through the gaps between the splats of near ones.
No window, GPU or Open3D renderer needed.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .pinhole import PinholeView, make_view
from ..clouds import cloud_points, legacy_cloud
from ..methods import resolve_method
from .triangulation import local_spacing

__all__ = ["render_points", "depth_image", "splat", "rasterize", "point_colors", "lambert"]

MAX_SPLAT_RADIUS = 32


def splat(view: PinholeView, points: np.ndarray, radius: np.ndarray | float,
          keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffers round point splats into the view's image.

    Args:
        view: the camera.
        points: (N, 3) points.
        radius: splat radius in world units, per point (N,) or one for all; it is
            projected to pixels at each point's depth (at least one pixel wide,
            at most ``MAX_SPLAT_RADIUS`` pixels).
        keep: (N,) bool, the points to draw (default: all).

    Returns:
        ``index`` (H, W) int64: the nearest drawn point covering each pixel (an
        index into ``points``), -1 where none does; ``depth`` (H, W) float64: its
        depth along the optical axis, 0 where none.
    """
    uv, z = view.project(points)
    drawn = np.flatnonzero((z > 0) if keep is None else (z > 0) & keep)
    r_world = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(points),))[drawn]
    r_px = np.clip(view.intrinsic[0, 0] * r_world / z[drawn], 0.5, MAX_SPLAT_RADIUS)
    by_size = np.argsort(-r_px)
    drawn, r_px = drawn[by_size], r_px[by_size]
    centre, z = np.rint(uv[drawn]).astype(np.int64), z[drawn]
    pixels, owners = [], []
    reach = int(np.ceil(r_px[0])) if len(drawn) else 0
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            count = np.searchsorted(-r_px, -np.sqrt(dx * dx + dy * dy), side="right")
            col, row = centre[:count, 0] + dx, centre[:count, 1] + dy
            hit = np.flatnonzero((col >= 0) & (col < view.width) & (row >= 0) & (row < view.height))
            pixels.append(row[hit] * view.width + col[hit])
            owners.append(hit)
    pixels, owners = _nearest_per_pixel(np.concatenate(pixels), z, np.concatenate(owners))
    index = np.full(view.height * view.width, -1, dtype=np.int64)
    depth = np.zeros(view.height * view.width)
    index[pixels], depth[pixels] = drawn[owners], z[owners]
    return index.reshape(view.height, view.width), depth.reshape(view.height, view.width)


def _nearest_per_pixel(pixels: np.ndarray, depth: np.ndarray, owners: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The z-buffer test: for each covered pixel, the candidate of smallest ``depth[owner]``.

    Args:
        pixels: (K,) flat pixel index of each candidate.
        depth: depths, indexed by ``owners``.
        owners: (K,) what each candidate draws.

    Returns:
        The distinct covered pixels and the owner that wins each.
    """
    order = np.lexsort((depth[owners], pixels))
    pixels, first = np.unique(pixels[order], return_index=True)
    return pixels, owners[order][first]


def rasterize(view: PinholeView, points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Z-buffered depth image of triangles over ``points``, depth interpolated inside each.

    Args:
        view: the camera.
        points: (N, 3) vertices.
        triangles: (T, 3) vertex indices.

    Returns:
        (H, W) float64 depth along the optical axis at each pixel centre, 0
        where no triangle covers it. Triangles reaching behind the camera are skipped.
    """
    uv, z = view.project(points)
    triangles = triangles[(z[triangles] > 0).all(axis=1)]
    corners = uv[triangles]
    edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    det = edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0]
    lo = np.maximum(np.ceil(corners.min(axis=1)), 0).astype(np.int64)
    hi = np.minimum(np.floor(corners.max(axis=1)), [view.width - 1, view.height - 1]).astype(np.int64)
    size = np.maximum(hi - lo + 1, 0) * (np.abs(det) > 1e-12)[:, None]
    count = size[:, 0] * size[:, 1]
    owner = np.repeat(np.arange(len(triangles)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    col = lo[owner, 0] + local % size[owner, 0]
    row = lo[owner, 1] + local // np.maximum(size[owner, 0], 1)
    offset = np.stack([col, row], axis=1) - corners[owner, 0]
    inv = 1.0 / det[owner]
    l1 = (offset[:, 0] * edge2[owner, 1] - offset[:, 1] * edge2[owner, 0]) * inv
    l2 = (edge1[owner, 0] * offset[:, 1] - edge1[owner, 1] * offset[:, 0]) * inv
    bary = np.stack([1 - l1 - l2, l1, l2], axis=1)
    inside = (bary >= -1e-9).all(axis=1)
    fragment_depth = np.einsum("ij,ij->i", bary[inside], z[triangles[owner[inside]]])
    pixels, winner = _nearest_per_pixel(row[inside] * view.width + col[inside], fragment_depth,
                                        np.arange(inside.sum()))
    image = np.zeros(view.height * view.width)
    image[pixels] = fragment_depth[winner]
    return image.reshape(view.height, view.width)


def lambert(pcd, points: np.ndarray, light_location: np.ndarray) -> np.ndarray:
    """Two-sided Lambert term ``|n . l|`` per point, (N,); all ones for a cloud without normals."""
    if not pcd.has_normals():
        return np.ones(len(points))
    normals = np.asarray(pcd.normals, dtype=np.float64)
    to_light = light_location - points
    cosine = np.abs(np.einsum("ij,ij->i", normals, to_light))
    return cosine / np.maximum(np.linalg.norm(normals, axis=1) * np.linalg.norm(to_light, axis=1),
                               1e-300)


def point_colors(pcd, points: np.ndarray, light_location: np.ndarray) -> np.ndarray:
    """Per-point RGB in [0, 1]: the cloud's colours, else its normals shaded by a point light.

    Shading is two-sided (``0.2 + 0.8 |n . l|``), so unoriented normals look
    right too; a cloud with neither colours nor normals is a flat grey.
    """
    if pcd.has_colors():
        return np.clip(np.asarray(pcd.colors, dtype=np.float64), 0, 1)
    shade = 0.2 + 0.8 * lambert(pcd, points, light_location) if pcd.has_normals() else 0.6
    return np.broadcast_to(np.asarray(shade)[..., None] * np.array([0.85, 0.85, 0.9]),
                           (len(points), 3))


def splat_size(points: np.ndarray, point_size: float | None) -> np.ndarray | float:
    """Splat radius in world units: ``point_size``, or the local point spacing."""
    if point_size is not None:
        if not point_size > 0:
            raise ValueError(f"point_size must be positive, got {point_size}")
        return float(point_size)
    return local_spacing(points)


def image_from(index: np.ndarray, colors: np.ndarray, background) -> o3d.geometry.Image:
    """An 8-bit RGB image with each pixel coloured by the point ``index`` names."""
    background = np.asarray(background, dtype=np.float64)
    if background.shape != (3,):
        raise ValueError(f"background must be an RGB triple in [0, 1], got {background.tolist()}")
    rgb = np.where(index[..., None] >= 0, colors[np.maximum(index, 0)], background)
    return o3d.geometry.Image(np.ascontiguousarray(np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8)))


def render_points(pcd, camera, visible_only: bool = True, width: int = 640, height: int = 480,
                  model=None, *, intrinsic=None, point_size: float | None = None,
                  background=(1.0, 1.0, 1.0)) -> o3d.geometry.Image:
    """Renders a point cloud to an RGB image, headless.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor). Colours are used when
            present, else normals are shaded by a light at the camera.
        camera: a (3,) location looking at the cloud's centre, a 4x4 extrinsic or
            ``o3d.camera.PinholeCameraParameters``.
        visible_only: drop points the visibility method finds hidden before splatting.
        width, height: image size (ignored when an intrinsic is given).
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        intrinsic: ``o3d.camera.PinholeCameraIntrinsic`` (default: framed to the cloud).
        point_size: splat radius in world units (default: the local point spacing).
        background: RGB in [0, 1].

    Returns:
        ``o3d.geometry.Image``, (height, width, 3) uint8.
    """
    pcd = legacy_cloud(pcd)
    points = cloud_points(pcd)
    view = make_view(points, camera, width, height, intrinsic)
    keep = resolve_method(model)(points, view.location[None])[0] if visible_only else None
    index, _ = splat(view, points, splat_size(points, point_size), keep)
    return image_from(index, point_colors(pcd, points, view.location), background)


def depth_image(pcd, camera, intrinsic=None, *, width: int = 640, height: int = 480,
                visible_only: bool = True, model=None,
                point_size: float | None = None) -> o3d.geometry.Image:
    """A float depth image of a point cloud, like a depth camera would see it.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor).
        camera: a (3,) location looking at the cloud's centre, a 4x4 extrinsic or
            ``o3d.camera.PinholeCameraParameters``.
        intrinsic: ``o3d.camera.PinholeCameraIntrinsic`` (default: framed to the
            cloud at ``width`` x ``height``).
        width, height: image size when no intrinsic is given.
        visible_only: drop points the visibility method finds hidden first.
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        point_size: splat radius in world units (default: the local point spacing).

    Returns:
        ``o3d.geometry.Image`` of float32 depth along the optical axis, in the
        cloud's units, 0 where no point projects (use ``depth_scale=1`` with
        ``o3d.geometry.PointCloud.create_from_depth_image``).
    """
    points = cloud_points(pcd)
    view = make_view(points, camera, width, height, intrinsic)
    keep = resolve_method(model)(points, view.location[None])[0] if visible_only else None
    _, depth = splat(view, points, splat_size(points, point_size), keep)
    return o3d.geometry.Image(depth.astype(np.float32))
