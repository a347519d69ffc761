"""A cloud's projected features, stored once per octree leaf.

The predictor's first layer is linear in ``[feature, point]``
(:meth:`~o3dvis.nn.predictor.VisibilityPredictor.project`): its feature part is
computed once per leaf of the octree, and a point's projected features are its
leaf's plus a linear term of its own coordinates. Kept that way, a cloud's
features take E values a leaf instead of E a point (a dense cloud has a few
points a leaf), and they are carried to the points where they are read: by the
C kernels a block of points at a time (:func:`o3dvis.nn.native.view_margin`),
or by :meth:`LeafFeatures.rows` for the torch ops.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["LeafFeatures"]


@dataclass(frozen=True)
class LeafFeatures:
    """Projected features of N points, point i's being ``leaves[:, leaf[i]] + point_weight @ points[i]``.

    Attributes:
        leaves: (E, L) each leaf's projected features (the bias included), contiguous.
        leaf: (N,) long, each point's leaf.
        point_weight: (E, 3) the projection's weights of the point's coordinates.
        points: (N, 3) the normalised points.
    """

    leaves: Tensor
    leaf: Tensor
    point_weight: Tensor
    points: Tensor

    def __post_init__(self) -> None:
        e, n = self.leaves.shape[0], self.leaf.shape[0]
        if (self.leaves.ndim != 2 or self.leaf.ndim != 1 or self.leaf.dtype != torch.long
                or self.point_weight.shape != (e, 3) or self.points.shape != (n, 3)):
            raise ValueError(f"leaves must be (E, L), leaf (N,) long, point_weight (E, 3) and points (N, 3), got "
                             f"{tuple(self.leaves.shape)}, {tuple(self.leaf.shape)} {self.leaf.dtype}, "
                             f"{tuple(self.point_weight.shape)}, {tuple(self.points.shape)}")
        if n and (int(self.leaf.min()) < 0 or int(self.leaf.max()) >= self.leaves.shape[1]):
            raise IndexError(f"leaf must lie in [0, {self.leaves.shape[1]})")

    @property
    def num_points(self) -> int:
        return self.leaf.shape[0]

    @property
    def channels(self) -> int:
        return self.leaves.shape[0]

    def rows(self, rows: slice | Tensor = slice(None)) -> Tensor:
        """(n, E) the projected features of the points ``rows`` (a slice or (n,) indices),
        stored channels first (strides (1, n)); differentiable in the leaves and the weights."""
        leaf, points = self.leaf[rows], self.points[rows]
        return self.leaves.index_select(1, leaf).addmm_(self.point_weight, points.transpose(0, 1)).transpose(0, 1)

    def restricted(self, kept: Tensor) -> "LeafFeatures":
        """These features of the points ``kept`` (indices) only, in that order."""
        return LeafFeatures(self.leaves, self.leaf.index_select(0, kept), self.point_weight,
                            self.points.index_select(0, kept))
