"""How noisy a cloud is next to its point spacing: two numbers per cloud for the network.

Noise of a few point spacings puts visible points behind the nearest depth in
the finest depth buffers, where they look hidden; fine detail (thin parts,
small features) can look the same to a single point. Over the whole cloud the
two differ: noise thickens every patch of surface, detail only some. Both cues
are the lower quartile over many small patches, so detail in some of them does
not move it:

* cells of a 32^3 grid with at least 8 points: the patch's thickness (square
  root of the smallest eigenvalue of its covariance) in point spacings (cell
  size / sqrt(count));
* runs of 16 points along a fine Morton curve (at most 2048 runs, evenly
  spread along it): thickness / width (square root of the smallest over the
  middle eigenvalue).

Invariant to the order of the points (up to float32 rounding of the cell sums and
the order of coincident points), to translation and to scale (of normalised
points); linear in the number of points but for one sort. A cloud too small for
a full cell or a run gets 0 for that cue. On the CPU the sums (in float64) and the
patches' eigenvalues (closed form, within a few ulps of the largest eigenvalue of
what ``eigvalsh`` gives) are computed by C over the points in Morton order, else by
torch ops (sums in float32).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from . import native
from .octree import grid_cells, morton_order

__all__ = ["noise_cues", "NUM_NOISE_CUES"]

NUM_NOISE_CUES = 2
_LEVEL, _MIN_COUNT, _RUN, _MAX_RUNS, _QUANTILE = 5, 8, 16, 2048, 0.25
_BLOCK = 1 << 18  # rows of moments summed at a time
_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the second moments, in their columns' order


def _eigenvalues(cov: Tensor) -> Tensor:
    """(..., 3) ascending eigenvalues of symmetric (..., 3, 3) matrices (upper triangles read), >= 0."""
    return torch.linalg.eigvalsh(cov, UPLO="U").clamp_min(0)


def _cell_moments(points: Tensor) -> tuple[Tensor, Tensor]:
    """Each cell's count (res^3,) and moments (res^3, 9) about its centre: the second moments in
    ``_PAIRS``' order, then the first (sums in float32: small numbers about the cells' centres)."""
    res = 1 << _LEVEL
    points = points.detach()
    c = grid_cells(points, _LEVEL)
    cell = (c[:, 0] * res + c[:, 1]) * res + c[:, 2]
    q = points.float() - ((c + 0.5) * (2 / res) - 1)
    m = q.new_zeros(res ** 3, 9)
    for a in range(0, len(q), _BLOCK):  # one index_add_ of (rows, 9) blocks, at most _BLOCK rows a time
        block = q[a:a + _BLOCK]
        moments = torch.stack([block[:, i] * block[:, j] for i, j in _PAIRS] + list(block.unbind(1)), dim=1)
        m.index_add_(0, cell[a:a + _BLOCK], moments)
    return torch.bincount(cell, minlength=res ** 3), m


def _quartile(values: Tensor) -> Tensor:
    """``torch.quantile(values, _QUANTILE)`` of a non-empty 1-D tensor, to the bit: the two values
    around the rank by selection, interpolated linearly as torch does (its sort of all the values
    took a fifth of a small cloud's noise cues)."""
    if bool(values.isnan().any()):
        return values.new_full((), float("nan"))
    rank = _QUANTILE * (len(values) - 1)
    below, above = math.floor(rank), math.ceil(rank)
    low = torch.kthvalue(values, below + 1).values
    high = low if above == below else torch.kthvalue(values, above + 1).values
    return torch.lerp(low, high, values.new_tensor(rank - below))


def _native(points: Tensor) -> bool:
    """Whether the C kernels compute the cues' terms of these points."""
    return points.device.type == "cpu" and points.dtype == torch.float32 and native.available()


def _cell_thickness(points: Tensor, ordered: bool) -> Tensor:
    """Lower quartile of the cells' thickness in point spacings."""
    res = 1 << _LEVEL
    if ordered and _native(points):  # each cell's points contiguous: sums and eigenvalues in one pass of C
        thickness = native.cell_thickness(points.detach().contiguous(), _LEVEL, _MIN_COUNT)
        return (_quartile(thickness) if len(thickness) else
                torch.zeros((), dtype=torch.float64, device=points.device))
    count, m = _cell_moments(points)
    full = torch.nonzero(count >= _MIN_COUNT).squeeze(1)
    if full.numel() == 0:
        return torch.zeros((), dtype=torch.float64, device=points.device)
    m = m.index_select(0, full).double().T
    n = count.index_select(0, full).double()
    mean, second = m[6:] / n, m[:6] / n
    cov = m.new_zeros(len(full), 3, 3)
    for k, (i, j) in enumerate(_PAIRS):
        cov[:, i, j] = second[k] - mean[i] * mean[j]
    thickness = _eigenvalues(cov)[:, 0].sqrt()
    return _quartile(thickness * n.sqrt() * (res / 2))


def _run_flatness(points: Tensor, ordered: bool) -> Tensor:
    """Lower quartile of thickness / width of runs of points along the Morton curve."""
    num_runs = len(points) // _RUN
    if num_runs == 0:
        return torch.zeros((), dtype=torch.float64, device=points.device)
    runs = torch.linspace(0, num_runs - 1, min(num_runs, _MAX_RUNS), device=points.device).long()
    if ordered and _native(points):  # contiguous runs: their scatters and eigenvalues in one pass of C
        return _quartile(native.run_flatness(points.detach().contiguous(), runs * _RUN, _RUN))
    index = (runs[:, None] * _RUN + torch.arange(_RUN, device=points.device)).flatten()
    if not ordered:
        index = morton_order(points).index_select(0, index)
    x = points.detach().index_select(0, index).double().view(-1, _RUN, 3)
    x = x - x.mean(dim=1, keepdim=True)
    eig = _eigenvalues(torch.einsum("rki,rkj->rij", x, x))
    return _quartile((eig[:, 0] / eig[:, 1].clamp_min(torch.finfo(x.dtype).tiny)).sqrt())


def noise_cues(points: Tensor, ordered: bool = False) -> Tensor:
    """(2,) noise cues of one cloud of normalised points (see the module's docstring).

    Args:
        points: (N, 3) points in [-1, 1]^3.
        ordered: the points are in :func:`~o3dvis.nn.octree.morton_order` already (as a
            :class:`~o3dvis.VisibilityField` stores them), which saves sorting them.

    Returns:
        (cell thickness in spacings, run thickness over width), in the points' dtype and device.
    """
    if not ordered and _native(points):  # the C kernels read cells and runs as contiguous points
        points, ordered = points.detach().index_select(0, morton_order(points)), True
    return torch.stack([_cell_thickness(points, ordered), _run_flatness(points, ordered)]).to(points.dtype)
