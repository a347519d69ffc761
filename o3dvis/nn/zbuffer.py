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
from .cues import atan2_pos, dot3, rounded_sqrt

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


def _pixel_rays(rows: int, pi: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The cosines and sines of the elevations of the pixels' centres (``rows``) and of their azimuths
    (``2 rows``), as the kernels' tables hold them: angles in float, their cosines and sines rounded
    from double."""
    pixel = pi / rows
    elevation = (torch.arange(rows, dtype=pi.dtype, device=pi.device) + 0.5) * pixel - pi / 2
    azimuth = (torch.arange(2 * rows, dtype=pi.dtype, device=pi.device) + 0.5) * pixel - pi
    return tuple(f(angle.double()).to(pi.dtype) for angle in (elevation, azimuth) for f in (torch.cos, torch.sin))


def _surfel_zbuffer_torch(points: Tensor, surfels: Tensor, camera: Tensor, rows: int) -> Tensor:
    """:func:`surfel_zbuffer` in torch ops, rounded as ``o3dvis_surfel_zbuffer`` of ``csrc/zbuffer.c`` rounds
    (its sums in its order, its arctangent, its tables of the pixels' rays): each point and disc in
    the kernels' pixels, the same front disc of every pixel."""
    cols, n, device = 2 * rows, len(points), points.device
    pi = torch.tensor(math.pi, dtype=points.dtype, device=device)
    pixel = pi / rows
    offset = points - camera
    x, y, z = offset.unbind(1)
    h, dist = rounded_sqrt(x * x + y * y), rounded_sqrt(dot3(offset, offset))
    row_f = atan2_pos(h, -z) * rows / pi  # elevation + pi / 2 and azimuth + pi, in pixels
    col_f = torch.where(y >= 0, pi + atan2_pos(y, x), pi - atan2_pos(-y, x)) * rows / pi
    own_row, own_col = row_f.long().clamp_max(rows - 1), col_f.long()
    own = own_row * cols + own_col % cols
    # the pixels whose centres the disc may cover (see csrc/zbuffer.c): its reach along the meridian, in
    # rows, and along the parallel, in columns
    radius, normals = surfels[:, 4], surfels[:, 1:4]
    reach = torch.where(radius < dist, radius / (dist - radius) / pixel, torch.full_like(dist, _MAX_HALF))
    flat_side = h > 0
    ez = torch.where(flat_side, z / (h * dist), torch.zeros_like(h))
    along_v = torch.where(flat_side, -ez * (x * normals[:, 0] + y * normals[:, 1]) + h / dist * normals[:, 2],
                          normals[:, 0])
    along_h = torch.where(flat_side, (x * normals[:, 1] - y * normals[:, 0]) / h, normals[:, 1])
    half_h = (reach * (rounded_sqrt((1 - along_v * along_v).clamp_min(0)) + 0.15).clamp_max(1)).clamp_max(_MAX_HALF)
    half_a = (reach * (rounded_sqrt((1 - along_h * along_h).clamp_min(0)) + 0.15).clamp_max(1)).clamp_max(_MAX_HALF)
    flat = torch.where(dist > 0, h / dist, torch.ones_like(dist))  # cos(elevation)
    half_w = (half_a / flat.clamp_min(1e-3)).clamp_max(min((cols - 1) / 2, _MAX_WIDE))  # each pixel once
    r0 = torch.minimum((row_f - half_h - 0.5).ceil().long(), own_row).clamp_min(0)
    r1 = torch.maximum((row_f + half_h - 0.5).floor().long(), own_row).clamp_max(rows - 1)
    k0 = torch.minimum((col_f - half_w - 0.5).ceil().long(), own_col)
    k1 = torch.maximum((col_f + half_w - 0.5).floor().long(), own_col)
    height, width = r1 - r0 + 1, k1 - k0 + 1
    size = height * width
    owner = torch.repeat_interleave(torch.arange(n, device=device), size)
    local = torch.arange(len(owner), device=device) - torch.repeat_interleave(size.cumsum(0) - size, size)
    r, k = r0[owner] + local // width[owner], k0[owner] + local % width[owner]
    c = k % cols
    row_cos, row_sin, col_cos, col_sin = _pixel_rays(rows, pi)
    ray = torch.stack([row_cos[r] * col_cos[c], row_cos[r] * col_sin[c], row_sin[r]], dim=1)
    depth = dot3(offset, normals)[owner] / dot3(ray, normals[owner])
    valid = (depth > 0) & (depth < math.inf)
    miss = ray * depth[:, None] - offset[owner]
    hit = valid & (dot3(miss, miss) <= (radius * radius)[owner])
    hit |= (r == own_row[owner]) & (k == own_col[owner])  # a disc always covers its own pixel
    pixels = r * cols + c
    depth = torch.where(valid, depth, dist[owner])
    owner, pixels, depth = owner[hit], pixels[hit], depth[hit]
    nearest = depth.new_full((rows * cols,), math.inf).scatter_reduce(0, pixels, depth, "amin")
    first = depth == nearest[pixels]
    front = torch.full((rows * cols,), n, dtype=torch.long, device=device).scatter_reduce(
        0, pixels[first], owner[first], "amin")[own]
    normal = normals[front]
    facing = dot3(offset, normal) / dist
    along = dot3(offset[front], normal) / facing
    along = torch.where(torch.isnan(along), math.inf, along)
    along = torch.minimum(torch.maximum(along, dist[front] - 3 * radius[front]), dist[front] + 3 * radius[front])
    beyond = ((dist - along) / radius).nan_to_num(0.0).clamp(-_CLIP, _CLIP)
    is_own = (front == torch.arange(n, device=device)).to(points.dtype)
    cosine = (dot3(offset, normals) / dist).nan_to_num(0.0).abs()
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
