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
import platform
from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from . import native
from .octree import cell_keys

__all__ = ["ViewProjection", "view_cues", "num_cues", "point_surfels", "DEFAULT_SCALES", "atan2_pos", "dot3",
           "rounded_sqrt"]

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


def num_cues(scales: Sequence[int] = DEFAULT_SCALES, footprints: bool = False) -> int:
    """The number of depth-buffer cues of a point: 3x3 residuals at each scale (and, with
    ``footprints``, in the splatted buffer of each scale but the coarsest)."""
    return 9 * (2 * len(scales) - 1 if footprints else len(scales))


def _sides(num_points: int, scales: Sequence[int]) -> list[int]:
    """The depth buffers' resolutions: ``ceil(sqrt(N))`` pixels a side (at least 4) over each scale."""
    finest = max(4, math.ceil(math.sqrt(num_points)))
    return [max(2, math.ceil(finest / scale)) for scale in scales]


def point_surfels(points: Tensor, levels: Sequence[int] = (4, 5, 6, 7), count: int = 8,
                  areas: bool = False) -> Tensor:
    """(N, 4) each point's spacing to its neighbours and the unit normal of the surface around it.

    A surface that crosses a cell of side ``c`` holding ``n`` points has them about
    ``c / sqrt(n)`` apart; each point takes the finest of the ``levels`` (cells of
    ``2 / 2^level`` in the normalised cube) whose cell holds at least ``count``
    points, else the coarsest, and the normal (unoriented) of the plane fitted
    to the points of that same cell. The finest cells' Morton keys, sorted, give
    every level's cells, and the finest cells' sums of the points' moments
    theirs (in double, as the C kernel sums them). A cell that the surface crosses
    only in part holds its points closer than that: ``areas`` adds the spacing
    the points' spread gives, ``sqrt(12 sqrt(l1 l2) / n)`` with ``l1, l2`` the two
    larger eigenvalues of their covariance (a uniformly covered rectangle's area
    is ``12 sqrt(l1 l2)``), at least a tenth of the first spacing.

    Args:
        points: (N, 3) normalised points (in [-1, 1]^3).
        areas: also give the area spacing.

    Returns:
        (N, 4): the spacing, then the normal; with ``areas`` (N, 5), the area spacing last.
    """
    finest = max(levels)
    keys, order = cell_keys(points, finest), None
    if not bool((keys[1:] >= keys[:-1]).all()):  # points stored along the Morton curve need no sort
        keys, order = keys.sort()
        points = points[order]
    if native.usable(points):  # the same in one pass of C
        surfels = native.surfels(points.contiguous(), keys, finest, min(levels), count, areas)
        return surfels if order is None else surfels.new_empty(surfels.shape).index_copy_(0, order, surfels)
    keys, leaf, counts = torch.unique_consecutive(keys, return_inverse=True, return_counts=True)
    # each finest cell's sums of its points and of their products (x, y, z, xx, yy, zz, xy, xz, yz), in double
    x = points.double()
    products = torch.cat([x, x * x, x[:, [0, 0, 1]] * x[:, [1, 2, 2]]], dim=1)
    moments = products.new_zeros(len(keys), 9).index_add_(0, leaf, products)
    chosen = None
    for level in sorted(levels, reverse=True):  # fine to coarse: the finest cell with enough points
        _, cell = torch.unique_consecutive(keys >> 3 * (finest - level), return_inverse=True)
        total = torch.zeros(int(cell[-1]) + 1, dtype=counts.dtype, device=counts.device).index_add_(0, cell, counts)
        mean = moments.new_zeros(len(total), 9).index_add_(0, cell, moments) / total[:, None]
        here = torch.cat([((2.0 / (1 << level)) / total.double().sqrt())[:, None], mean, total.double()[:, None]],
                         dim=1)[cell]
        take = (total[cell] >= count) if level != min(levels) else torch.ones_like(cell, dtype=torch.bool)
        chosen = here if chosen is None else torch.where((take & ~done)[:, None], here, chosen)
        done = take if level == finest else done | take
    mean, second = chosen[:, 1:4], chosen[:, 4:10]
    cross = second[:, 3:] - mean[:, [0, 0, 1]] * mean[:, [1, 2, 2]]
    covariance = torch.diag_embed(second[:, :3] - mean * mean)
    covariance[:, [0, 0, 1], [1, 2, 2]] = cross
    covariance[:, [1, 2, 2], [0, 0, 1]] = cross
    axis, least = _least_axis(covariance)
    columns = [chosen[:, :1], axis]
    if areas:  # the product of the two larger eigenvalues, from the sum of the principal 2 x 2 minors
        d, c = covariance.diagonal(dim1=1, dim2=2), cross
        minors = d[:, 0] * d[:, 1] + d[:, 0] * d[:, 2] + d[:, 1] * d[:, 2] - c.square().sum(dim=1)
        product = (minors - least * (d.sum(dim=1) - least)).clamp_min(0)
        spread = (12 * product.sqrt() / chosen[:, 10]).sqrt()
        columns.append(torch.maximum(spread, 0.1 * chosen[:, 0])[:, None])
    surfels = torch.cat(columns, dim=1).to(points.dtype)[leaf]
    return surfels if order is None else surfels.new_empty(surfels.shape).index_copy_(0, order, surfels)


def _least_axis(a: Tensor) -> tuple[Tensor, Tensor]:
    """(M, 3) unit eigenvectors of the smallest eigenvalues of symmetric (M, 3, 3) matrices, and (M,)
    those eigenvalues, in closed form (the trigonometric solution of the characteristic cubic, then
    the largest cross product of two rows of ``a - lambda I``); any unit vector where that
    eigenvalue is not single."""
    q = a.diagonal(dim1=1, dim2=2).sum(dim=1) / 3
    off = a[:, 0, 1] ** 2 + a[:, 0, 2] ** 2 + a[:, 1, 2] ** 2
    p = ((a.diagonal(dim1=1, dim2=2) - q[:, None]).pow(2).sum(dim=1) + 2 * off).div(6).sqrt()
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    b = (a - q[:, None, None] * eye) / p.clamp_min(1e-300)[:, None, None]
    phi = torch.acos((torch.linalg.det(b) / 2).clamp(-1, 1)) / 3
    smallest = q + 2 * p * torch.cos(phi + 2 * math.pi / 3)
    rows = a - smallest[:, None, None] * eye
    crosses = torch.stack([torch.linalg.cross(rows[:, 0], rows[:, 1]), torch.linalg.cross(rows[:, 0], rows[:, 2]),
                           torch.linalg.cross(rows[:, 1], rows[:, 2])], dim=1)
    norms = crosses.norm(dim=2)
    best = norms.argmax(dim=1)
    axis = crosses[torch.arange(len(a), device=a.device), best]
    length = norms.gather(1, best[:, None])
    unit = torch.where(length > 0, axis / length.clamp_min(1e-300), torch.tensor([0.0, 0.0, 1.0], dtype=a.dtype,
                                                                                   device=a.device))
    return unit, smallest


_SPLAT = 1.5  # a point covers its pixel at the finest scale whose pixels are this many spacings wide
_SLOPE = 3.0  # a splatted plane's depth differs from its point's by at most this times their lateral distance


def _splat_scales(angular: Tensor, pixel_sizes: Sequence[Tensor]) -> Tensor:
    """(N,) int8 each point's splat scale: the number of scales but the coarsest whose pixels are
    narrower than ``_SPLAT`` times its image spacing ``angular`` (0: no splat)."""
    return sum((angular * _SPLAT > p).to(torch.int8) for p in pixel_sizes[:-1])


def _splat_footprints(grids: list[Tensor], indices: list[Tensor], pixel_sizes: list[Tensor], depth: Tensor,
                      angular: Tensor, points: Tensor, normals: Tensor,
                      rays: Callable[[int], tuple[Tensor, Tensor]]) -> list[Tensor]:
    """The min-depth buffers of all scales but the coarsest with each point splatted over its footprint.

    A point near the camera is farther from its neighbours in the image than a
    pixel of the finest buffers, which then show holes through which hidden points
    look visible. Each point is assigned the finest scale whose pixels are
    ``_SPLAT`` times its image spacing ``angular``; the nearest point of each of
    that scale's pixels then fills every pixel of the finer buffers that the
    pixel covers with the depth of its plane along that pixel's centre ray, so
    that a slanted surface does not hide its own points. That depth stays within
    ``_SLOPE`` times the ray's lateral distance from the point (grazing planes).

    Args:
        grids: (R_s, R_s) min-depth buffer of each scale, empty pixels inf or NaN.
        indices: (N,) each point's pixel (row * R_s + column) at each scale.
        pixel_sizes: each scale's pixel size, in the units of ``angular``.
        depth: (N,) the points' depths.
        angular: (N,) each point's distance to its neighbours in the image.
        points: (N, 3) the points.
        normals: (N, 3) unit normals of their planes.
        rays: ``rays(res)`` gives the origins ((3,) or (res * res, 3)) and unit
            directions (res * res, 3) of the centre rays of a res-pixel image's
            pixels (row * res + column).

    Returns:
        The splatted (R_s, R_s) buffers of all scales but the coarsest (empty: as in ``grids``).
    """
    level = _splat_scales(angular, pixel_sizes)
    out = [g for g in grids[:-1]]
    image_rays: dict[int, tuple[Tensor, Tensor]] = {}
    for k in range(1, len(grids)):
        mine = level == k
        if not mine.any():
            continue
        res = grids[k].shape[0]
        nearest = depth.new_full((res * res,), float("inf")).scatter_reduce(0, indices[k][mine], depth[mine], "amin")
        nearest = mine & (depth == nearest[indices[k]])
        owner = torch.full((res * res,), -1, dtype=torch.long, device=depth.device).scatter_reduce(
            0, indices[k][nearest], torch.nonzero(nearest).flatten(), "amax").view(res, res)
        for j in range(k):  # the scale-k pixel holding each scale-j pixel's centre (same image, res_j pixels)
            fine = grids[j].shape[0]
            coarse = (2 * torch.arange(fine, device=depth.device) + 1) * res // (2 * fine)
            who = owner.index_select(0, coarse).index_select(1, coarse).flatten()
            pixels = torch.nonzero(who >= 0).flatten()
            if fine not in image_rays:
                image_rays[fine] = rays(fine)
            origins, directions = image_rays[fine]
            who = who[pixels]
            normal, near, ray = normals.index_select(0, who), depth.index_select(0, who), directions.index_select(0, pixels)
            offset = points.index_select(0, who).sub_(origins.index_select(0, pixels) if origins.dim() == 2 else origins)
            along = (offset * ray).sum(dim=1)
            lateral = (offset - along[:, None] * ray).norm(dim=1).mul_(_SLOPE)
            facing = (normal * ray).sum(dim=1)
            facing = torch.where(facing.abs() < 1e-9, torch.full_like(facing, 1e-9), facing)
            plane = torch.clamp((offset * normal).sum(dim=1) / facing, near - lateral, near + lateral)
            splat = depth.new_full((fine * fine,), float("nan")).index_put_((pixels,), plane)
            out[j] = torch.fmin(out[j], splat.view(fine, fine))
    return out


def _write_patches(padded: Tensor, rows: Tensor) -> None:
    """Writes the 3x3 neighbourhoods of the pixels of a (R + 2, R + 2) bordered image into (R, R, 9) rows."""
    res = rows.shape[0]
    for k in range(9):  # nine slice copies: several times faster than copying an unfold
        rows[:, :, k] = padded[k // 3:k // 3 + res, k % 3:k % 3 + res]


def _frame(forward: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors orthogonal to ``forward`` (differentiable); with tensor ops only, so that
    on a GPU nothing waits for the device."""
    steep = (forward.detach()[2].abs() > 0.9).to(forward.dtype)
    helper = torch.zeros_like(forward)
    helper[0], helper[2] = steep, 1 - steep  # x for a forward near z, else z
    right = torch.linalg.cross(forward, helper)
    right = right / right.norm()
    return right, torch.linalg.cross(forward, right)


def _pixel_rays(forward: Tensor, right: Tensor, up: Tensor, half: Tensor, camera: Tensor | None,
                dtype: torch.dtype) -> Callable[[int], tuple[Tensor, Tensor]]:
    """The centre rays of the pixels of a view's images (see :func:`_splat_footprints`): from the
    camera, or, for a viewing direction, from the pixel's place on the image plane through 0."""

    forward, right, up, half = forward.to(dtype), right.to(dtype), up.to(dtype), half.to(dtype)

    def rays(res: int) -> tuple[Tensor, Tensor]:
        centre = ((torch.arange(res, dtype=dtype, device=forward.device) + 0.5) * (2 * half / res) - half)
        u, v = centre[:, None, None], centre[None, :, None]  # rows along right, columns along up
        if camera is None:
            return (u * right + v * up).view(-1, 3), forward.expand(res * res, 3)
        theta = (u * u + v * v).sqrt()
        sinc = torch.where(theta > 1e-12, theta.sin() / theta.clamp_min(1e-12), torch.ones_like(theta))
        return camera.to(dtype), (theta.cos() * forward + sinc * (u * right + v * up)).view(-1, 3)

    return rays


def dot3(x: Tensor, y: Tensor) -> Tensor:
    """The dot products of the rows of ``x`` (..., 3) with ``y`` (..., 3 or 3,), summed in the order of the
    C kernels, each product rounded (they fuse no multiply-add there): the same rounding as theirs."""
    return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]


def rounded_sqrt(x: Tensor) -> Tensor:
    """``sqrt(x)`` correctly rounded to ``x``'s dtype, as C's ``sqrtf`` gives it (torch's float32 ``sqrt`` on
    the CPU is an ulp off for about one value in seven; the double root rounded to float is exact)."""
    return x.double().sqrt().to(x.dtype)


def _madd(a: Tensor, b: Tensor, c: float, fused: bool) -> Tensor:
    """``a * b + c`` in ``a``'s dtype, rounded once where ``fused`` (a fused multiply-add: the product of
    two floats is exact in double, the sum is rounded there and again to float)."""
    if not fused:
        return a * b + c
    return (a.double() * b.double() + float(torch.tensor(c, dtype=a.dtype))).to(a.dtype)


def atan2_pos(s: Tensor, z: Tensor) -> Tensor:
    """``atan2(s, z)`` for ``s >= 0`` as the C kernels compute it (``atan2_pos`` of ``csrc/kernels.h``: the
    octant reduction, then Cephes' polynomial, its multiply-adds fused where the loaded kernels fuse
    them: every variant but x86-64's base), so that the points fall into the kernels' pixels."""
    fused = native.available() and (native.variant() != "base" or platform.machine().lower() in ("aarch64", "arm64"))
    az = z.abs()
    steep = s > az
    t = torch.where(steep, az / s, torch.where(az > 0, s / az, torch.zeros_like(s)))
    big = t > 0.414213562373095
    x = torch.where(big, (t - 1) / (t + 1), t)
    square = x * x
    p = torch.full_like(x, 8.05374449538e-2)
    for c in (-1.38776856032e-1, 1.99777106478e-1, -3.33329491539e-1):
        p = _madd(p, square, c, fused)
    r = x + x * square * p
    r = torch.where(big, r + 0.785398163397448, r)
    r = torch.where(steep, 1.57079632679490 - r, r)
    return torch.where(z < 0, 3.14159265358979 - r, r)


def _project(points: Tensor, camera: Tensor | None, direction: Tensor | None
             ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None, tuple[Tensor, Tensor, Tensor]]:
    """A view's image positions in torch ops, with the rounding of the C kernels' ``o3dvis_project``
    (its sums in its order, its frame in double, its arctangent), so that each point falls into
    the kernels' pixel: a camera inside a cloud sees points all around, whose mean direction is
    short, and a point on the far side of its azimuthal image moves with any rounding of it.

    Returns:
        ``dirs`` (N, 3) unit vectors from the camera (the viewing direction for a ``direction``) and
        ``depth`` (N,), differentiable; the image positions ``u``, ``v`` (N,) around the image's
        centre and, for a camera, the stretch ``theta / sin(theta)`` (N,) of its azimuthal image,
        detached; the unit ``forward``, ``right`` and ``up`` vectors of the image.
    """
    dtype = points.dtype
    if direction is None:
        offset = points - camera
        depth = rounded_sqrt(dot3(offset, offset)).clamp_min(1e-12)
        dirs = offset / depth[:, None]
        total = dirs.detach().double().sum(dim=0)
        forward = total / total.norm().clamp_min(1e-12 * len(points))
    else:
        forward = direction / direction.norm()
        dirs = forward.expand_as(points)
    right, up = _frame(forward.detach().double())
    right, up = right.to(dtype), up.to(dtype)
    if direction is not None:
        u, v = dot3(points, right).detach(), dot3(points, up).detach()
        return dirs, dot3(points, forward), u, v, None, (forward.detach(), right, up)
    forward = forward.to(dtype)
    with torch.no_grad():
        seen = dirs.detach()
        a, b, z = dot3(seen, right), dot3(seen, up), dot3(seen, forward)
        s = rounded_sqrt(a * a + b * b + 1e-24)
        k = atan2_pos(s, z) / s
    return dirs, depth, a * k, b * k, k, (forward, right, up)


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
        surfels: None, or the points' (N, 4) :func:`point_surfels`: the buffers
            of all scales but the coarsest then follow, splatted over the points'
            footprints (:func:`_splat_footprints`), as scales of their own.

    Attributes:
        dirs: (N, 3) unit vectors from the camera to the points.
    """

    def __init__(self, points: Tensor, camera: Tensor | None = None, direction: Tensor | None = None,
                 scales: Sequence[int] = DEFAULT_SCALES, surfels: Tensor | None = None):
        if (camera is None) == (direction is None):
            raise ValueError("give exactly one of camera and direction")
        sides = _sides(points.shape[0], scales)
        self.native = (0 < points.shape[0] <= native.MAX_POINTS and native.usable(points, camera, direction)
                       and (surfels is None or len(scales) <= 4))
        if self.native:  # the bordered buffers and each point's 3x3 corner in them; the tables on demand
            if direction is not None:
                direction = direction / direction.norm()
            dirs, self.depth, self.buffers, self.corners, self.rpix, uv = native.project(
                points.contiguous(), camera, direction, sides)
            self.dirs = dirs if direction is None else direction.expand_as(points)
            self.perspective = direction is None
            self.sides, self.patches, self.pixels, self.inv_footprint = sides, None, None, None
            if surfels is not None:
                self._splat_native(points, camera, surfels, uv)
            return
        dirs, depth, u, v, stretch, (forward, right, up) = _project(points, camera, direction)
        footprint = depth if direction is None else torch.ones_like(depth)
        half = torch.maximum(u.abs().amax(), v.abs().amax()) * (1 + 1e-6) + 1e-12
        self.dirs, self.depth = dirs, depth
        u, v = u + half, v + half  # image positions from the corner, computed once for all scales
        pixel_sizes, rpix, indices, zbufs = [], [], [], []
        for res in sides:
            scale = half.new_tensor(float(res)) / (2 * half)  # 1 / pixel size, as the kernels find the pixel
            iu, iv = (u * scale).long().clamp_(0, res - 1), (v * scale).long().clamp_(0, res - 1)
            index = iu.mul_(res).add_(iv)
            pixel_sizes.append(1 / scale)
            rpix.append(scale)
            indices.append(index)
            zbufs.append(depth.new_full((res * res,), float("inf")).scatter_reduce(0, index, depth, "amin"))
        if surfels is not None:  # the splatted buffers of the finer scales follow as scales of their own
            angular = surfels[:, 0] / footprint.detach()
            if stretch is not None:
                angular = angular * stretch
            grids = [z.view(res, res) for z, res in zip(zbufs, sides)]
            rays = _pixel_rays(forward.detach(), right.detach(), up.detach(), half.detach(),
                               None if camera is None else camera.detach(), points.dtype)
            zbufs += [z.flatten() for z in _splat_footprints(grids, indices, pixel_sizes, depth.detach(), angular,
                                                             points.detach(), surfels[:, 1:], rays)]
            sides, indices, rpix = sides + sides[:-1], indices + indices[:-1], rpix + rpix[:-1]
        # the 3x3 neighbourhoods of the pixels of all buffers in one table, NaN where a pixel is
        # empty or off the image; row pixels[i, s] of it is point i's in buffer s
        self.patches = depth.new_empty(sum(res * res for res in sides), 9)
        self.pixels = torch.empty(points.shape[0], len(sides), dtype=torch.long, device=points.device)
        start = 0
        for s, (res, zbuf, index) in enumerate(zip(sides, zbufs, indices)):
            zbuf = torch.where(torch.isinf(zbuf), float("nan"), zbuf).view(res, res)
            _write_patches(F.pad(zbuf, (1, 1, 1, 1), value=float("nan")),
                           self.patches[start:start + res * res].view(res, res, 9))
            torch.add(index, start, out=self.pixels[:, s])
            start += res * res
        # -1 / (pixel size x footprint), the scale of a depth residual, (N, S, 1), as the kernels compute it
        self.inv_footprint = ((-1 / footprint)[:, None] * torch.stack(rpix))[:, :, None]

    def _splat_native(self, points: Tensor, camera: Tensor | None, surfels: Tensor, uv: Tensor) -> None:
        """Appends the splatted buffers (see :func:`_splat_footprints`; here the C kernel
        :func:`o3dvis.nn.native.plane_splat`) to a native view's buffers as scales of their own, in
        the kernels' bordered layout (its image axes are the torch path's: the frame of the mean
        view direction, the image ``sides[0] / rpix[0]`` wide)."""
        sides = self.sides
        angular = surfels[:, 0] / self.depth if self.perspective else surfels[:, 0]
        if self.perspective:  # the azimuthal-equidistant image stretches by theta / sin(theta) across the radius
            theta = (uv - sides[0] / (2 * self.rpix[0])).norm(dim=1)
            angular = angular * torch.where(theta > 1e-6, theta / theta.sin().clamp_min(1e-12), 1.0)
        level = _splat_scales(angular, 1 / self.rpix)
        forward = self.dirs[0].double() if not self.perspective else self.dirs.sum(dim=0, dtype=torch.float64)
        forward = forward / forward.norm().clamp_min(1e-300)
        frame = torch.stack([forward, *_frame(forward)]).float()
        splatted = self.buffers[:-(sides[-1] + 2) ** 2].clone()  # all scales but the coarsest
        native.plane_splat(points, surfels.contiguous(), self.depth, level, sides, self.corners, frame,
                           float(sides[0] / (2 * self.rpix[0].double())), camera, _SLOPE, splatted)
        self.corners = torch.cat([self.corners, self.corners[:, :-1] + self.buffers.shape[0]], dim=1)
        self.buffers = torch.cat([self.buffers, splatted])
        self.sides, self.rpix = sides + sides[:-1], torch.cat([self.rpix, self.rpix[:-1]])

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
