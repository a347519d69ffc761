"""Per-view geometric cues: view directions and multi-scale depth-buffer residuals.

For one viewpoint the points are projected onto an image around the viewing
axis (azimuthal-equidistant for a camera position, parallel for a viewing
direction) and a min-depth buffer is built at several resolutions with a
scatter-min. A point's depth residuals to the 3x3 pixels around its own,
measured in pixel footprints, show whether it lies behind the nearest surface
or on it (a sloped surface has residuals that change across the patch); the
network learns which scale to trust. The cost is linear in the number of
points and has no parameter to tune.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["view_cues", "num_cues", "DEFAULT_SCALES"]

DEFAULT_SCALES = (1, 2, 4, 8)


_EMPTY = -5.0  # cue of a neighbour pixel that no point falls into (below any asinh(+-50))


def _asinh(x: Tensor) -> Tensor:
    """``asinh`` from vectorised ``log``/``sqrt`` (torch's CPU ``asinh`` is several times slower)."""
    a = x.abs()
    return torch.copysign(torch.log(a + torch.sqrt(a * a + 1)), x)


def num_cues(scales: Sequence[int] = DEFAULT_SCALES) -> int:
    return 9 * len(scales)


def _frame(forward: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors orthogonal to ``forward`` (differentiable)."""
    helper = torch.tensor([0.0, 0.0, 1.0], dtype=forward.dtype, device=forward.device)
    if forward.detach()[2].abs() > 0.9:
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=forward.dtype, device=forward.device)
    right = torch.linalg.cross(forward, helper)
    right = right / right.norm()
    return right, torch.linalg.cross(forward, right)


def view_cues(points: Tensor, camera: Tensor | None = None, direction: Tensor | None = None,
              scales: Sequence[int] = DEFAULT_SCALES) -> tuple[Tensor, Tensor]:
    """View directions and depth-buffer cues of ``points`` for one viewpoint.

    Args:
        points: (N, 3) points (normalised coordinates).
        camera: (3,) camera position, or None when ``direction`` is given.
        direction: (3,) viewing direction of an orthographic camera.
        scales: pixel sizes of the depth buffers, in multiples of the finest
            one, whose resolution is ``ceil(sqrt(N))`` pixels a side.

    Returns:
        ``(dirs, cues)``: (N, 3) unit vectors from the camera to the points and
        (N, 9 * len(scales)) cues: ``asinh`` of the depth residual to each of
        the 3x3 pixels around the point's own, in pixel footprints, or
        ``_EMPTY`` where that pixel is empty. Both are differentiable in
        ``camera`` (the pixel assignment itself is piecewise constant).
    """
    if (camera is None) == (direction is None):
        raise ValueError("give exactly one of camera and direction")
    if direction is None:
        offset = points - camera
        depth = offset.norm(dim=1).clamp_min(1e-12)
        dirs = offset / depth[:, None]
        mean_dir = dirs.detach().mean(dim=0)
        forward = (mean_dir / mean_dir.norm().clamp_min(1e-12)).to(points.dtype)
        right, up = _frame(forward)
        a, b, z = dirs @ right, dirs @ up, dirs @ forward
        s = torch.sqrt(a * a + b * b + 1e-24)
        k = torch.atan2(s, z) / s
        u, v = a * k, b * k
        footprint = depth
    else:
        forward = direction / direction.norm()
        right, up = _frame(forward)
        dirs = forward.expand_as(points)
        u, v, depth = points @ right, points @ up, points @ forward
        footprint = torch.ones_like(depth)
    half = torch.maximum(u.detach().abs().amax(), v.detach().abs().amax()) * (1 + 1e-6) + 1e-12
    finest = max(4, math.ceil(math.sqrt(points.shape[0])))
    cues = depth.new_empty(points.shape[0], 9 * len(scales))
    for i, scale in enumerate(scales):
        res = max(2, math.ceil(finest / scale))
        pixel = 2 * half / res
        iu = ((u.detach() + half) / pixel).long().clamp_(0, res - 1)
        iv = ((v.detach() + half) / pixel).long().clamp_(0, res - 1)
        zbuf = depth.new_full((res * res,), float("inf")).scatter_reduce(0, iu * res + iv, depth, "amin")
        padded = F.pad(zbuf.view(1, 1, res, res), (1, 1, 1, 1), value=float("inf")).view(-1)
        patch = torch.tensor([du * (res + 2) + dv for du in (-1, 0, 1) for dv in (-1, 0, 1)],
                             device=points.device)
        near = padded[((iu + 1) * (res + 2) + iv + 1)[:, None] + patch]
        found = torch.isfinite(near)
        residual = (depth[:, None] - torch.where(found, near, depth[:, None])) / (pixel * footprint)[:, None]
        cues[:, 9 * i:9 * i + 9] = torch.where(found, _asinh(residual.clamp(-50, 50)), _EMPTY)
    return dirs, cues
