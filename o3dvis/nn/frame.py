"""The frame of one cloud: where its points sit in the network's cube [-1, 1]^3.

:meth:`CloudFrame.of` normalises a cloud once (its bounding box, centre and scale, and for a
flat cloud the plane or line it lies on); everything that later meets the cloud's coordinates
(cameras, crops, inside tests) goes through the same :class:`CloudFrame`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from . import native
from .octree import bounding_box, cube_frame, normalize_points

__all__ = ["CloudFrame", "normalized"]

FLAT_TOL = 1e-6
"""A cloud is flat along a direction when no point lies farther from its mean along it than this
many bounding-box diagonals: below what the network's float32 coordinates (about 2^-23 of the box)
resolve, so such a cloud is answered as the exactly flat one."""
INSIDE_TOL = 1e-6
"""A position within this many half longest sides of the bounding box counts as inside it (and as
on a point, or on a flat cloud's plane)."""


@dataclass(frozen=True)
class CloudFrame:
    """A cloud's normalisation: ``unit = (world - center) / scale`` maps it into [-1, 1]^3.

    Attributes:
        center: (3,) float64 centre of the bounding box.
        scale: () float64 half its longest side, with a small margin.
        lo, hi: (3,) float64 corners of the bounding box, in world coordinates.
        hull: for a flat cloud, the centre and orthonormal basis (rows) of the plane or line it
            lies on, in the normalised frame; None for a 3-D cloud.
    """

    center: Tensor
    scale: Tensor
    lo: Tensor
    hi: Tensor
    hull: tuple[Tensor, Tensor] | None = None

    @classmethod
    def of(cls, points: Tensor) -> tuple[Tensor, Tensor | None, "CloudFrame"]:
        """``(normalised float32 points, their Morton keys at depth 21 or None, frame)`` of (N, 3)
        float64 points. On the CPU two passes of C: bounds, then the normalised points, their keys
        and their scatter matrix (the float64 normalised points are made only for a cloud that
        may be flat, to find its plane to the last bits).

        Raises:
            ValueError: a cloud whose bounding box overflows float64.
        """
        in_c = points.device.type == "cpu" and points.dtype == torch.float64 and native.available()
        if in_c:
            points = points.contiguous()
            lo, hi, total = native.bounds(points)
        else:
            lo, hi = bounding_box(points)
        if not bool(torch.isfinite(hi - lo).all()):
            raise ValueError(f"the cloud spans more than float64 holds: its bounding box runs from {lo.tolist()} "
                             f"to {hi.tolist()}, whose sides overflow; scale it down")
        if not (in_c and (hi - lo).amax() > 0):  # torch ops, or all points coincide
            unit, center, scale = normalized(points, (lo, hi))
            hull = _flat_hull(unit, ((hi - lo) / scale).norm())  # float64: flat to the last bits
            return unit.float(), None, cls(center, scale, lo, hi, hull)
        center, scale = cube_frame(lo, hi)
        unit, keys, scatter = native.normalize(points, center, float(scale), (total / len(points) - center) / scale)
        diagonal = ((hi - lo) / scale).norm()
        hull = None if _solid(scatter, len(points), diagonal) else _flat_hull(normalized(points, (lo, hi))[0],
                                                                              diagonal)
        return unit, keys, cls(center, scale, lo, hi, hull)

    @property
    def bounds(self) -> tuple[Tensor, Tensor]:
        """``(lo, hi)``: the bounding box in world coordinates."""
        return self.lo, self.hi

    @property
    def unit_diagonal(self) -> Tensor:
        """The bounding box's diagonal in the normalised frame."""
        return ((self.hi - self.lo) / self.scale).norm()

    def tolerance(self) -> Tensor:
        """What counts as zero distance in world coordinates: :data:`INSIDE_TOL` half longest sides."""
        return INSIDE_TOL * (self.hi - self.lo).amax() / 2

    def to_unit(self, positions: Tensor) -> Tensor:
        """(V, 3) world positions in the normalised frame, in the frame's float64."""
        return (positions.to(self.center) - self.center) / self.scale

    def contains(self, positions: Tensor) -> Tensor:
        """(V,) bool: which of the (V, 3) world positions lie in the bounding box, up to :meth:`tolerance`."""
        tol = self.tolerance()
        positions = positions.detach().to(self.lo)
        return ((positions >= self.lo - tol) & (positions <= self.hi + tol)).all(dim=1)

    def off_the_hull(self, positions: Tensor | None, directions: Tensor | None = None) -> Tensor | None:
        """(V,) bool: which views leave the plane or line of a flat cloud (None for a 3-D cloud):
        cameras at the (V, 3) world ``positions``, or else orthographic views along ``directions``."""
        if self.hull is None:
            return None
        centre, basis = self.hull
        if directions is not None:
            offset, tol = directions.detach().to(centre.device), INSIDE_TOL
        else:
            offset = (positions.detach().to(centre.device) - self.center) / self.scale - centre
            tol = self.tolerance() / self.scale
        return (offset - (offset @ basis.T) @ basis).norm(dim=1) > tol

def normalized(points: Tensor, bounds: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`~o3dvis.nn.octree.normalize_points`, with scale 1 when all points coincide (any scale
    maps them to 0)."""
    lo, hi = bounding_box(points) if bounds is None else bounds
    if (hi - lo).amax() > 0:
        return normalize_points(points, bounds=(lo, hi))
    return points - lo, lo, torch.ones((), dtype=points.dtype, device=points.device)


def _flat_hull(points: Tensor, diagonal: Tensor) -> tuple[Tensor, Tensor] | None:
    """Centre and orthonormal basis (rows) of the affine hull of a flat cloud; None for a 3-D one.

    A cloud extends along a direction when some point lies farther than ``FLAT_TOL`` x
    ``diagonal`` (its bounding box's) from the mean along it. Most clouds are told 3-D by the
    3x3 scatter matrix alone: when the root-mean-square spread along its least direction,
    less the matrix's rounding, exceeds that, so does every direction's largest one. The others'
    principal directions come from the SVD of the 3x3 R of a QR of the centred points (O(N) and
    accurate), and the largest distances along them decide, so that a cloud a hair off its
    plane is answered as the exactly flat one.
    """
    centre = points.mean(dim=0)
    offsets = points - centre
    if _solid(offsets.T @ offsets, len(points), diagonal):
        return None
    bound = FLAT_TOL * diagonal
    _, _, vt = torch.linalg.svd(torch.linalg.qr(offsets, mode="r").R)
    spans = (offsets @ vt.T).abs().max(dim=0).values > bound
    return None if bool(spans.all()) else (centre, vt[spans])


def _solid(scatter: Tensor, count: int, diagonal: Tensor) -> bool:
    """Whether the (3, 3) float64 scatter matrix of ``count`` points about their mean (or a point
    a few ulps from it) tells that they extend along every direction (see :func:`_flat_hull`)."""
    least, _, largest = torch.linalg.eigvalsh(scatter).tolist()
    bound = FLAT_TOL * float(diagonal)
    return least - 1e3 * torch.finfo(scatter.dtype).eps * largest > bound * bound * count
