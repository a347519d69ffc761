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

from . import native

__all__ = ["ViewProjection", "view_cues", "num_cues", "DEFAULT_SCALES"]

DEFAULT_SCALES = (1, 2, 4, 8)


_EMPTY = -5.0  # cue of a neighbour pixel that no point falls into (below any asinh(+-50))
# what the in-place path gives an empty neighbour's residual before asinh: beyond the clamp, and
# asinh maps it to _EMPTY exactly, so no NaN reaches sqrt and log1p, which take a slow path on NaN
_EMPTY_RESIDUAL = math.sinh(_EMPTY)


def _asinh(x: Tensor) -> Tensor:
    """``asinh(x) = sign(x) log1p(|x| - 1 + sqrt(x^2 + 1))`` from vectorised ``log1p``/``sqrt``.

    Torch's CPU ``asinh`` is several times slower, and its ``log1p`` about twice as fast as ``log``.
    """
    a = x.abs()
    return torch.copysign(torch.log1p(a - 1 + torch.sqrt(a * a + 1)), x)


def _asinh_(x: Tensor) -> Tensor:
    """:func:`_asinh` with in-place steps: no autograd, fewer allocations."""
    a = x.abs()
    return torch.mul(a, a).add_(1).sqrt_().add_(a.sub_(1)).log1p_().copysign_(x)


def num_cues(scales: Sequence[int] = DEFAULT_SCALES) -> int:
    """The number of depth-buffer cues of a point: 3x3 residuals at each scale."""
    return 9 * len(scales)


def _sides(num_points: int, scales: Sequence[int]) -> list[int]:
    """The depth buffers' resolutions: ``ceil(sqrt(N))`` pixels a side (at least 4) over each scale."""
    finest = max(4, math.ceil(math.sqrt(num_points)))
    return [max(2, math.ceil(finest / scale)) for scale in scales]


def _write_patches(padded: Tensor, rows: Tensor) -> None:
    """Writes the 3x3 neighbourhoods of the pixels of a (R + 2, R + 2) bordered image into (R, R, 9) rows."""
    res = rows.shape[0]
    for k in range(9):  # nine slice copies: several times faster than copying an unfold
        rows[:, :, k] = padded[k // 3:k // 3 + res, k % 3:k % 3 + res]


def _frame(forward: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors orthogonal to ``forward`` (differentiable)."""
    helper = torch.tensor([0.0, 0.0, 1.0], dtype=forward.dtype, device=forward.device)
    if forward.detach()[2].abs() > 0.9:
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=forward.dtype, device=forward.device)
    right = torch.linalg.cross(forward, helper)
    right = right / right.norm()
    return right, torch.linalg.cross(forward, right)


class ViewProjection:
    """One viewpoint's projection of a cloud: view directions and multi-scale depth buffers.

    Built once per view in linear time; :meth:`cues` then assembles the cues of
    any rows of points, so that a caller can stream a large cloud through the
    predictor in cache-sized chunks. Differentiable in the camera (the pixel
    assignment itself is piecewise constant). Without autograd on the CPU it is
    built by the C kernels of :mod:`o3dvis.nn.native` where they are available
    (``native`` is then True), which also run the predictor on it (:meth:`margin`).

    Args:
        points: (N, 3) points (normalised coordinates).
        camera: (3,) camera position, or None when ``direction`` is given.
        direction: (3,) viewing direction of an orthographic camera.
        scales: pixel sizes of the depth buffers, in multiples of the finest
            one, whose resolution is ``ceil(sqrt(N))`` pixels a side.

    Attributes:
        dirs: (N, 3) unit vectors from the camera to the points.
    """

    def __init__(self, points: Tensor, camera: Tensor | None = None, direction: Tensor | None = None,
                 scales: Sequence[int] = DEFAULT_SCALES):
        if (camera is None) == (direction is None):
            raise ValueError("give exactly one of camera and direction")
        sides = _sides(points.shape[0], scales)
        self.native = 0 < points.shape[0] <= native.MAX_POINTS and native.usable(points, camera, direction)
        if self.native:  # the bordered buffers and each point's 3x3 corner in them; the tables on demand
            if direction is not None:
                direction = direction / direction.norm()
            dirs, self.depth, self.buffers, self.corners, self.rpix = native.project(
                points.contiguous(), camera, direction, sides)
            self.dirs = dirs if direction is None else direction.expand_as(points)
            self.perspective = direction is None
            self.sides, self.patches, self.pixels, self.inv_footprint = sides, None, None, None
            return
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
            u, v = (a * k).detach(), (b * k).detach()
            footprint = depth
        else:
            forward = direction / direction.norm()
            right, up = _frame(forward)
            dirs = forward.expand_as(points)
            u, v, depth = (points @ right).detach(), (points @ up).detach(), points @ forward
            footprint = torch.ones_like(depth)
        half = torch.maximum(u.abs().amax(), v.abs().amax()) * (1 + 1e-6) + 1e-12
        self.dirs, self.depth = dirs, depth
        # the 3x3 neighbourhoods of the pixels of all scales in one table, NaN where a pixel is
        # empty or off the image; row pixels[i, s] of it is point i's at scale s. Each scale's
        # patches are written into their rows in place (no concatenation of copies).
        self.patches = depth.new_empty(sum(res * res for res in sides), 9)
        self.pixels = torch.empty(points.shape[0], len(sides), dtype=torch.long, device=points.device)
        u, v = u + half, v + half  # image positions from the corner, computed once for all scales
        pixel_sizes, start = [], 0
        for s, res in enumerate(sides):
            pixel = 2 * half / res
            pixel_sizes.append(pixel)
            fu, fv = u / pixel, v / pixel
            iu, iv = fu.long().clamp_(0, res - 1), fv.long().clamp_(0, res - 1)
            index = iu.mul_(res).add_(iv)
            zbuf = depth.new_full((res * res,), float("inf")).scatter_reduce(0, index, depth, "amin")
            zbuf = torch.where(torch.isinf(zbuf), float("nan"), zbuf).view(res, res)
            _write_patches(F.pad(zbuf, (1, 1, 1, 1), value=float("nan")),
                           self.patches[start:start + res * res].view(res, res, 9))
            torch.add(index, start, out=self.pixels[:, s])
            start += res * res
        # -1 / (pixel size x footprint): the scale of a depth residual, (N, S, 1)
        self.inv_footprint = (-1 / (footprint[:, None] * torch.stack(pixel_sizes)))[:, :, None]

    def margin(self, rows: slice | Tensor, projected: Tensor, num_frequencies: int, normals: Tensor | None,
               mlp: native.PackedMLP, out: Tensor) -> None:
        """Writes the predictor's margins of ``points[rows]`` into ``out`` (only when ``native``
        and :func:`o3dvis.nn.native.has_view_margin` of ``mlp.dtype``; see
        :func:`o3dvis.nn.native.view_margin`)."""
        native.view_margin(rows, self.dirs, projected, num_frequencies, self.buffers, self.corners, self.sides,
                           self.depth, self.rpix, self.perspective, _EMPTY_RESIDUAL, normals, mlp, out)

    def _tables(self) -> tuple[Tensor, Tensor]:
        """The 3x3 patches and each point's row of them (see ``__init__``) from a native
        view's bordered buffers, and the residuals' scales, for :meth:`cues`."""
        if self.patches is None:
            patches = self.depth.new_empty(sum(res * res for res in self.sides), 9)
            pixels = torch.empty(self.corners.shape, dtype=torch.long)
            start = first = 0  # the scale's first row of patches and first pixel in the buffers
            for s, res in enumerate(self.sides):
                width = res + 2
                _write_patches(self.buffers[first:first + width * width].view(width, width),
                               patches[start:start + res * res].view(res, res, 9))
                corner = self.corners[:, s] - first
                torch.add(corner // width * res + corner % width, start, out=pixels[:, s])
                start, first = start + res * res, first + width * width
            self.patches, self.pixels = patches, pixels
            # -1 / (footprint x pixel size) as the kernels compute it: (-1 / depth) x (1 / pixel size)
            footprint = -1 / self.depth if self.perspective else torch.full_like(self.depth, -1.0)
            self.inv_footprint = (footprint[:, None] * self.rpix)[:, :, None]
        return self.patches, self.pixels

    def cues(self, rows: slice = slice(None)) -> Tensor:
        """(n, 9 * len(scales)) cues of ``points[rows]``.

        For each scale, ``asinh`` of the point's depth residual to each of the
        3x3 pixels around its own, in pixel footprints (clamped to +-50), or
        ``_EMPTY`` where that pixel is empty.
        """
        patches, pixels = self._tables()
        pixels = pixels[rows]
        near = patches.index_select(0, pixels.reshape(-1)).view(*pixels.shape, 9)
        depth, inv = self.depth[rows, None, None], self.inv_footprint[rows]
        if torch.is_grad_enabled():  # out of place, and no NaN through which to back-propagate
            empty = torch.isnan(near)
            residual = ((torch.where(empty, depth, near) - depth) * inv).clamp(-50, 50)
            return torch.where(empty, _EMPTY, _asinh(residual)).flatten(1)
        return _asinh_(near.sub_(depth).mul_(inv).clamp_(-50, 50).nan_to_num_(_EMPTY_RESIDUAL)).flatten(1)

def view_cues(points: Tensor, camera: Tensor | None = None, direction: Tensor | None = None,
              scales: Sequence[int] = DEFAULT_SCALES) -> tuple[Tensor, Tensor]:
    """View directions (N, 3) and depth-buffer cues (N, num_cues(scales)) of one viewpoint.

    See :class:`ViewProjection`, which this builds and reads in one go.
    """
    view = ViewProjection(points, camera, direction, scales)
    return view.dirs, view.cues()
