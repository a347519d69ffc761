"""The noise cues' patch terms in one pass of C each (``o3dvis/nn/csrc/noise.c``; see
:mod:`o3dvis.nn.noise`)."""

from __future__ import annotations

import torch
from torch import Tensor

from . import _library
from ._library import check


def cell_thickness(points: Tensor, level: int, min_count: int) -> Tensor:
    """(M,) float64: for each cell of a ``2^level`` grid over [-1, 1]^3 (``1 <= level <= 10``) with at
    least ``min_count`` of ``points`` (N, 3) float32, in the points' order, its thickness in point
    spacings (the noise cue's cell term, see ``noise.c``: the smallest eigenvalue of its
    covariance in closed form). The points of each cell must be contiguous, as along a Morton curve.

    Raises:
        ValueError: points of the wrong shape or type, or a level out of [1, 10].
    """
    check("points", points, (points.shape[0], 3))
    if not 1 <= level <= 10:
        raise ValueError(f"level must lie in [1, 10], got {level}")
    out = points.new_empty(points.shape[0], dtype=torch.float64)
    full = _library.LIBRARY.o3dvis_cell_thickness(points.shape[0], points.data_ptr(), level, min_count, out.data_ptr())
    return out[:full]


def run_flatness(points: Tensor, starts: Tensor, run: int) -> Tensor:
    """(R,) float64: for each run of ``run`` points of ``points`` (N, 3) float32 from ``starts`` (R,)
    int64, the square root of the smallest over the middle eigenvalue of its scatter about its
    mean (closed form, see ``noise.c``).

    Raises:
        ValueError: tensors of the wrong shape or type, or a run that leaves the points.
    """
    check("points", points, (points.shape[0], 3))
    check("starts", starts, (starts.shape[0],), torch.long)
    if run < 1 or (len(starts) and (int(starts.min()) < 0 or int(starts.max()) + run > points.shape[0])):
        raise ValueError(f"runs of {run} points from starts must lie in the {points.shape[0]} points")
    out = points.new_empty(starts.shape[0], dtype=torch.float64)
    _library.LIBRARY.o3dvis_run_flatness(starts.shape[0], starts.data_ptr(), run, points.data_ptr(), out.data_ptr())
    return out
