"""The plane fits, their neighbours' weights and the cameras' votes of the normals' orientation
in passes of C (``o3dvis/nn/csrc/orientation.c``; see :mod:`o3dvis.orientation`)."""

from __future__ import annotations

import torch
from torch import Tensor

from . import _library
from ._library import check


def fit_planes(points: Tensor, neighbours: Tensor, weight: Tensor | None) -> tuple[Tensor, Tensor]:
    """(M, 3) unit normals and (M,) bool: :func:`o3dvis.orientation.fit_planes` of ``points``
    (N, 3) float64, rows of ``neighbours`` (M, K) int64 and ``weight`` (M, K) float64 (None: all
    1), in one pass (an index N stands for no point, as the numpy ops' padding: give it weight 0).

    Raises:
        ValueError: tensors of the wrong shapes or types.
        IndexError: neighbours out of range.
    """
    m, k = neighbours.shape
    check("points", points, (points.shape[0], 3), torch.float64)
    check("neighbours", neighbours, (m, k), torch.long)
    if weight is not None:
        check("weight", weight, (m, k), torch.float64)
    if neighbours.numel() and (int(neighbours.min()) < 0 or int(neighbours.max()) > points.shape[0]):
        raise IndexError(f"neighbours must lie in [0, {points.shape[0]}]")
    normals, planar = points.new_empty(m, 3), torch.empty(m, dtype=torch.uint8)
    if m:
        _library.LIBRARY.o3dvis_fit_planes(points.shape[0], m, k, points.data_ptr(), neighbours.data_ptr(),
                                           None if weight is None else weight.data_ptr(), normals.data_ptr(),
                                           planar.data_ptr())
    return normals, planar.bool()


def visibility_affinity(table: Tensor, cameras: int, neighbours: Tensor, first: int, scale: float, floor: float
                        ) -> Tensor:
    """(M, K) float64: :func:`o3dvis.orientation.visibility_affinity` of the points
    ``first .. first + M`` and their rows of ``neighbours`` (M, K) int64, from ``table`` (N, S)
    float32: a row a point, its answers from the ``cameras`` cameras then zeros up to S, a
    multiple of 16 (what :func:`affinity_table` makes); in one pass.

    Raises:
        ValueError: tensors of the wrong shapes or types, or rows past the table.
        IndexError: neighbours out of range.
    """
    (n, stride), (m, k) = table.shape, neighbours.shape
    check("table", table, (n, stride))
    check("neighbours", neighbours, (m, k), torch.long)
    if stride % 16 or not 0 < cameras <= stride:
        raise ValueError(f"the table's rows must hold the {cameras} cameras' answers padded to a multiple "
                         f"of 16, got {stride}")
    if not 0 <= first <= n - m:
        raise ValueError(f"rows {first}..{first + m} lie past the table's {n}")
    if neighbours.numel() and (int(neighbours.min()) < 0 or int(neighbours.max()) >= n):
        raise IndexError(f"neighbours must lie in [0, {n})")
    weight = torch.empty(m, k, dtype=torch.float64)
    if m:
        _library.LIBRARY.o3dvis_visibility_affinity(m, k, cameras, stride, first, table.data_ptr(),
                                                    neighbours.data_ptr(), 1.0 / scale ** 2, floor, weight.data_ptr())
    return weight


def affinity_table(visibility: Tensor) -> Tensor:
    """The (N, S) table :func:`visibility_affinity` reads of answers ``visibility`` (V, N): each
    point's row, padded with zeros to S, the multiple of 16 from V up."""
    v, n = visibility.shape
    table = visibility.new_zeros(n, -(-v // 16) * 16, dtype=torch.float32)
    table[:, :v] = visibility.T
    return table


def votes(points: Tensor, normals: Tensor, cameras: Tensor, visibility: Tensor, rows: slice
          ) -> tuple[Tensor, Tensor]:
    """``(vote, agreement)``, each (M,) float64: :func:`o3dvis.orientation.vote` and its agreement
    for the points ``rows`` (a slice with step 1) of ``points`` and ``normals`` (N, 3) float64, from
    ``cameras`` (V, 3) float64 and their probabilities ``visibility`` (V, N) float32; in one pass.

    Raises:
        ValueError: tensors of the wrong shapes or types, or rows past the points.
    """
    n, v = points.shape[0], cameras.shape[0]
    check("points", points, (n, 3), torch.float64)
    check("normals", normals, (n, 3), torch.float64)
    check("cameras", cameras, (v, 3), torch.float64)
    check("visibility", visibility, (v, n))
    first, last, step = rows.indices(n)
    if step != 1:
        raise ValueError(f"rows must be a slice with step 1, got {rows}")
    m = max(0, last - first)
    vote, agreement = points.new_empty(m), points.new_empty(m)
    if m:
        _library.LIBRARY.o3dvis_votes(first, m, n, v, points.data_ptr(), normals.data_ptr(), cameras.data_ptr(),
                                      visibility.data_ptr(), vote.data_ptr(), agreement.data_ptr())
    return vote, agreement
