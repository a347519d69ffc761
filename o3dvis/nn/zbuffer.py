"""The surfel z-buffer of a camera: each point tested against the surface in front of it, along its own ray.

Every point becomes a disc of radius its spacing in the plane of its normal (its
:func:`~o3dvis.nn.cues.point_surfels`, the spacing from the spread of the points of
its cell), and the discs are rendered into a depth buffer over the full sphere
around the camera (latitude-longitude, ``rows`` x ``2 rows`` pixels), each over
the pixels whose centre ray meets it and always over its own pixel, the nearest
disc in front. A point is then compared with the plane of the disc in front at
its own pixel, evaluated along the point's own ray rather than at the pixel's
centre: on a surface seen at a grazing angle the point lies on that plane, behind
a wall it lies beyond it by many spacings. The buffer's resolution follows the
points' median angular spacing, so the test costs a few pixels a point.

This is the test of the ``zbuffer`` baseline (:func:`o3dvis.baselines.zbuffer_mask`)
with the network's surfels; :mod:`.fusion` combines its answers with the network's.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from . import native

__all__ = ["NUM_ZBUFFER_FEATURES", "buffer_rows", "surfel_zbuffer"]

NUM_ZBUFFER_FEATURES = 4
PIXELS_PER_SPACING = 1.0  # buffer pixels across the points' median angular spacing
MAX_ROWS = 4096  # a buffer of at most 4096 x 8192 pixels (256 MiB of depths and owners)
_MAX_HALF, _MAX_WIDE = 12, 48  # a disc's largest half height and half width, in pixels (near points, poles)
_CLIP = 1000.0  # the largest distance beyond the front plane reported, in spacings
_MEDIAN_POINTS = 1 << 16  # the most points whose median angular spacing sets the buffer's rows


def buffer_rows(points: Tensor, spacing: Tensor, camera: Tensor) -> int:
    """The rows of the buffer of ``camera``: :data:`PIXELS_PER_SPACING` pixels across the median
    angular spacing (``spacing`` over the distance) of the ``points`` (of every k-th of them in a
    cloud of more than 2^16, k the fewest that leaves at most 2^16), in [16, :data:`MAX_ROWS`]."""
    step = max(1, -(-len(points) // _MEDIAN_POINTS))
    angular = spacing[::step] / (points[::step] - camera).norm(dim=1).clamp_min(1e-12)
    median = float(angular.median()) if len(angular) else 1.0
    return int(min(max(PIXELS_PER_SPACING * math.pi / max(median, 1e-12), 16), MAX_ROWS))


def _pixel_rays(row: Tensor, col: Tensor, rows: int) -> Tensor:
    """Unit directions through the centres of the pixels ``(row, col)``."""
    pixel = math.pi / rows
    elevation = (row.to(torch.float32) + 0.5) * pixel - math.pi / 2
    azimuth = (col.to(torch.float32) + 0.5) * pixel - math.pi
    flat = elevation.cos()
    return torch.stack([flat * azimuth.cos(), flat * azimuth.sin(), elevation.sin()], dim=1)


def _surfel_zbuffer_torch(points: Tensor, surfels: Tensor, camera: Tensor, rows: int) -> Tensor:
    cols, pixel, n = 2 * rows, math.pi / rows, len(points)
    offset = points - camera
    dist = offset.norm(dim=1)
    sine = torch.where(dist > 0, offset[:, 2] / dist, torch.zeros_like(dist)).clamp(-1, 1)
    row_f = (sine.asin() + math.pi / 2) * rows / math.pi
    col_f = (torch.atan2(offset[:, 1], offset[:, 0]) + math.pi) * rows / math.pi
    own_row, own_col = row_f.long().clamp_max(rows - 1), col_f.long()
    own = own_row * cols + own_col % cols
    # the pixels whose centres the disc may cover (see kernels.c): its reach along the meridian, in
    # rows, and along the parallel, in columns
    radius, normals = surfels[:, 4], surfels[:, 1:4]
    reach = torch.where(radius < dist, radius / (dist - radius) / pixel, torch.full_like(dist, _MAX_HALF))
    h = offset[:, :2].norm(dim=1)
    flat_side = h > 0
    ez = torch.where(flat_side, offset[:, 2] / (h * dist), torch.zeros_like(h))
    along_v = torch.where(flat_side, -ez * (offset[:, 0] * normals[:, 0] + offset[:, 1] * normals[:, 1])
                          + h / dist * normals[:, 2], normals[:, 0])
    along_h = torch.where(flat_side, (offset[:, 0] * normals[:, 1] - offset[:, 1] * normals[:, 0]) / h,
                          normals[:, 1])
    half_h = (reach * ((1 - along_v.square()).clamp_min(0).sqrt() + 0.15).clamp_max(1)).clamp_max(_MAX_HALF)
    half_a = (reach * ((1 - along_h.square()).clamp_min(0).sqrt() + 0.15).clamp_max(1)).clamp_max(_MAX_HALF)
    flat = torch.where(dist > 0, h / dist, torch.ones_like(dist))  # cos(elevation)
    half_w = (half_a / flat.clamp_min(1e-3)).clamp_max(min((cols - 1) / 2, _MAX_WIDE))  # each pixel once
    r0 = torch.minimum((row_f - half_h - 0.5).ceil().long(), own_row).clamp_min(0)
    r1 = torch.maximum((row_f + half_h - 0.5).floor().long(), own_row).clamp_max(rows - 1)
    k0 = torch.minimum((col_f - half_w - 0.5).ceil().long(), own_col)
    k1 = torch.maximum((col_f + half_w - 0.5).floor().long(), own_col)
    height, width = r1 - r0 + 1, k1 - k0 + 1
    size = height * width
    owner = torch.repeat_interleave(torch.arange(n, device=points.device), size)
    local = torch.arange(len(owner), device=points.device) - torch.repeat_interleave(size.cumsum(0) - size, size)
    r, k = r0[owner] + local // width[owner], k0[owner] + local % width[owner]
    c = k % cols
    ray, normal, off = _pixel_rays(r, c, rows), normals[owner], offset[owner]
    depth = (off * normal).sum(dim=1) / (ray * normal).sum(dim=1)
    valid = (depth > 0) & (depth < math.inf)
    hit = valid & ((ray * depth[:, None] - off).square().sum(dim=1) <= radius[owner].square())
    hit |= (r == own_row[owner]) & (k == own_col[owner])  # a disc always covers its own pixel
    pixels = r * cols + c
    depth = torch.where(valid, depth, dist[owner])
    owner, pixels, depth = owner[hit], pixels[hit], depth[hit]
    nearest = depth.new_full((rows * cols,), math.inf).scatter_reduce(0, pixels, depth, "amin")
    first = depth == nearest[pixels]
    front = torch.full((rows * cols,), n, dtype=torch.long, device=points.device).scatter_reduce(
        0, pixels[first], owner[first], "amin")[own]
    normal = normals[front]
    facing = (offset * normal).sum(dim=1) / dist
    along = (offset[front] * normal).sum(dim=1) / facing
    along = torch.where(torch.isnan(along), math.inf, along)
    along = torch.minimum(torch.maximum(along, dist[front] - 3 * radius[front]), dist[front] + 3 * radius[front])
    beyond = ((dist - along) / radius).nan_to_num(0.0).clamp(-_CLIP, _CLIP)
    is_own = (front == torch.arange(n, device=points.device)).to(points.dtype)
    cosine = ((offset * normals).sum(dim=1) / dist).nan_to_num(0.0).abs()
    return torch.stack([is_own, beyond, radius / dist / pixel, cosine], dim=1)


def surfel_zbuffer(points: Tensor, surfels: Tensor, camera: Tensor, rows: int | None = None) -> Tensor:
    """Each point against the front disc of the surfel z-buffer of ``camera`` (see the module).

    Args:
        points: (N, 3) points (normalised coordinates).
        surfels: (N, 5) their spacing, unit normal and area spacing (:func:`~o3dvis.nn.cues.point_surfels`
            with ``areas``): the area spacing is each disc's radius and the unit of its distances.
        camera: (3,) the camera, anywhere but on a point.
        rows: the buffer's rows (default: :func:`buffer_rows`).

    Returns:
        (N, 4) float32, not differentiable: 1 where the point's own disc is the front one at its
        pixel (else 0); its distance beyond the front disc's plane along its own ray, in its
        spacings (negative: in front of it; within +-1000); its spacing in buffer pixels; the
        absolute cosine of the angle between its normal and its ray (0: seen edge-on).
    """
    points, surfels, camera = points.detach().float(), surfels.detach().float(), camera.detach().float()
    rows = buffer_rows(points, surfels[:, 4], camera) if rows is None else rows
    if native.available() and points.device.type == "cpu":
        return native.surfel_zbuffer(points.contiguous(), surfels.contiguous(), camera.contiguous(), rows,
                                     _MAX_HALF, _MAX_WIDE, _CLIP)
    return _surfel_zbuffer_torch(points, surfels, camera, rows)
