"""The two-pass encoding: oriented normals from what the points-only network sees, for the normals model.

``normals="estimate"`` (:meth:`o3dvis.NeuralVisibility.encode`) encodes a cloud without normals,
asks that first pass about cameras around the cloud, fits a plane to each point's neighbours
and orients it by the cameras' vote (:func:`estimated_normals`); the normals model then encodes
the cloud with those normals. A cloud's own normals are checked against the same first pass
(:func:`facing_away_share`) before the normals model reads them: normals that point either way
(``estimate_normals()``) or face a sensor are replaced by estimated ones
(:func:`second_pass_normals`), with a warning (:func:`warn_ignored`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from .cameras import viewpoints_around
from .neighbours import NeighbourSearch
from .orientation import facing_away, oriented_planes, surface_variation
from .threads import workers_only

if TYPE_CHECKING:
    from .field import VisibilityField

__all__ = ["first_pass_normals", "estimated_normals", "facing_away_share", "second_pass_normals", "warn_ignored",
           "ESTIMATE_MIN_POINTS", "MAX_FACING_AWAY"]

# the two-pass encoding: cameras whose first-pass answers orient the normals, points per plane fit
_ORIENTING_VIEWS = 14
_PLANE_NEIGHBOURS = 8
# where normals="estimate" takes two passes: clouds of at least ESTIMATE_MIN_POINTS points whose
# noise cue (the cell thickness in spacings of o3dvis.nn.noise) is under _ESTIMATE_MAX_NOISE and,
# below _CUE_ALONE_POINTS points, where the cue cannot see noise finer than the spacing, whose
# plane fits' neighbourhoods have a lower quartile of surface variation
# (o3dvis.orientation.surface_variation, over an even sample of _VARIATION_SAMPLE of them) under
# _ESTIMATE_MAX_VARIATION: two passes pay on clean clouds and cost on noisy ones, whose estimated
# planes tilt (docs/results.md has the figures on the validation meshes)
ESTIMATE_MIN_POINTS = 1_000
_ESTIMATE_MAX_NOISE = 0.2
_CUE_ALONE_POINTS = 65_536
_ESTIMATE_MAX_VARIATION = 0.01
_VARIATION_SAMPLE = 4096
# a cloud's own normals are held against what the points-only network sees of _CHECK_POINTS of its
# points, spread along the Morton curve, from _CHECK_VIEWS cameras around it: where more than
# MAX_FACING_AWAY of the cameras' vote is against them, they are taken as unoriented. On the
# validation meshes at 2-32 k points that vote was 0.35-0.72 for normals from estimate_normals(),
# 0.48-0.53 for randomly flipped ones and 0.41-0.65 for ones facing a sensor, and at most 0.44 for
# oriented ones (0-0.05 on closed surfaces; bowls, cups, chairs and vases, whose thin walls the
# points-only network answers worst, reach 0.35-0.44). Those the check doubts are kept after all
# where, in the two passes that follow, at least _MIN_SAME_SIDE of them lie on the side of the
# estimated normals: 0.64-1 for oriented normals there, at most 0.53 for the others (2 k and 8 k points)
_CHECK_POINTS = 4096
_CHECK_VIEWS = 14
MAX_FACING_AWAY = 0.35
_MIN_SAME_SIDE = 0.6


def first_pass_normals(field: VisibilityField, points: np.ndarray, stored: bool = False) -> np.ndarray | None:
    """The normals ``normals="estimate"`` gives the normals model: a plane through each point's
    nearest neighbours, those the first pass sees alike from a few cameras around the cloud
    weighing most, oriented by the vote of those cameras, or where they split, by the side of its
    neighbours the point lies on (:func:`o3dvis.orientation.oriented_planes` of what ``field``
    answers); None where the cloud looks too noisy for that to pay (see :data:`_ESTIMATE_MAX_NOISE`)
    or no plane fits any of its neighbourhoods.

    Args:
        field: a points-only model's encoding of the cloud.
        points: (N, 3) the cloud's points, in its order.
        stored: ``points``, and the normals returned, in the order the field stores them (along
            the Morton curve; see :meth:`VisibilityField.stored_probabilities`).

    Returns:
        (N, 3) unit normals, or None.
    """
    return estimated_normals(field, points, stored)[0]


def estimated_normals(field: VisibilityField, points: np.ndarray, stored: bool = False,
                      clean_only: bool = True) -> tuple[np.ndarray | None, bool]:
    """:func:`first_pass_normals`, and whether the cloud looks clean enough for them to pay.

    Args:
        field, points, stored: as in :func:`first_pass_normals`.
        clean_only: False estimates the normals of a cloud that looks noisy too (to compare
            other normals with them, not to give them to the normals model).

    Returns:
        (N, 3) unit normals, or None (no plane fits, or a noisy cloud with ``clean_only``), and
        whether the cloud looks clean.
    """
    clean = float(field.noise[0]) < _ESTIMATE_MAX_NOISE
    if clean_only and not clean:
        return None, False
    # in the field's order along the Morton curve: neighbours close in memory make the KNN search
    # and the plane fits cache-friendly
    rank = None if stored or field.rank is None else field.rank.cpu().numpy()
    if rank is not None:
        order = np.empty_like(rank)
        order[rank] = np.arange(len(rank))
        points = points[order]
    search = NeighbourSearch(points)
    near = search.query(min(_PLANE_NEIGHBOURS, len(points)))  # the weak votes' wider planes: asked later
    if clean and len(points) < _CUE_ALONE_POINTS:
        sample = near[::max(1, len(near) // _VARIATION_SAMPLE), :_PLANE_NEIGHBOURS]
        clean = bool(np.quantile(surface_variation(points, sample), 0.25) < _ESTIMATE_MAX_VARIATION)
        if clean_only and not clean:
            return None, False
    cameras = viewpoints_around(points, _ORIENTING_VIEWS)
    visibility = field.stored_probabilities(cameras).cpu().numpy()
    try:
        normals = oriented_planes(points, near, cameras, visibility, fit=_PLANE_NEIGHBOURS, search=search)
    except ValueError:  # no plane fits anywhere: every neighbourhood is one point repeated, or a line
        return None, clean
    return (normals if rank is None else normals[rank]), clean


def facing_away_share(encode: Callable[[Tensor], "VisibilityField"], points: Tensor, order: Tensor,
                      normals: Tensor) -> float:
    """How much of the vote of cameras around a cloud (:func:`~o3dvis.orientation.facing_away`) on
    the normals (in Morton ``order``) of :data:`_CHECK_POINTS` of its points, evenly spread along
    that order, is against them, with the cameras' answers from the points-only encoding of
    those points alone.

    Args:
        encode: the points-only encoding of some (M, 3) points.
        points: (N, 3) the cloud's points, in its order.
        order: (N,) the Morton order of the points (rows of ``points``).
        normals: (N, 3) unit normals, in that order.

    Returns:
        The share of the vote against the normals, in [0, 1].
    """
    rows = torch.arange(0, len(order), max(1, len(order) // _CHECK_POINTS), device=order.device)
    sample = points.index_select(0, order.index_select(0, rows).to(points.device))
    field = encode(sample)
    sample = sample.detach().cpu().double().numpy()
    cameras = viewpoints_around(sample, _CHECK_VIEWS)
    sampled = normals.index_select(0, rows.to(normals.device)).detach().cpu().double().numpy()
    return facing_away(sample, sampled, cameras, field.probabilities(cameras).cpu().numpy())


def second_pass_normals(first: "VisibilityField", points: Tensor, order: Tensor, doubted: Tensor | None
                        ) -> tuple[Tensor | None, Tensor | None]:
    """The normals a second pass encodes with, from the first pass ``first``.

    Args:
        first: the points-only encoding of the cloud.
        points: (N, 3) the cloud's points, in its order.
        order: (N,) their Morton order, the field's row order.
        doubted: the cloud's own unit normals (in that order) that :func:`facing_away_share`
            doubted, or None.

    Returns:
        ``(normals, doubted)``: the unit normals for the normals model in the field's order (the
        doubted ones where most lie on the estimates' side: oriented after all), or None where a
        second pass does not pay (a noisy cloud, no plane fits); and the doubted normals still
        ignored (None where there were none or they were kept).
    """
    with workers_only():
        stored = points.detach().cpu().double().index_select(0, order.cpu()).numpy()
        normals, clean = estimated_normals(first, stored, stored=True, clean_only=doubted is None)
    if normals is None:
        return None, doubted
    unit = torch.from_numpy(normals).to(first.device).float()
    if doubted is not None and float(((doubted * unit).sum(dim=1) > 0).float().mean()) >= _MIN_SAME_SIDE:
        return doubted, None
    return (unit if clean else None), doubted


def warn_ignored(share: float) -> None:
    """The one-line warning for a cloud's normals that were ignored as unoriented."""
    warnings.warn(f"o3dvis: the cloud's normals look unoriented ({100 * share:.0f} % of the vote of cameras "
                  "around it is against them) and are ignored, as with normals='estimate'; orient them "
                  "first (o3dvis.orient_normals_neural) or pass normals=True to use them as they are",
                  stacklevel=4)
