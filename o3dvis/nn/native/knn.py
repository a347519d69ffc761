"""The nearest neighbours of the normals' plane fits in C (``o3dvis/nn/csrc/knn.c``; see
:class:`o3dvis.neighbours.NeighbourSearch`): in the cells of a grid, or among all points."""

from __future__ import annotations

import torch
from torch import Tensor

from . import _library
from ._library import check


def brute_knn(points: Tensor, rows: Tensor, k: int) -> Tensor:
    """(M, k) int64: the ``k`` nearest of ``points`` (N, 3) float64 to each of the points ``rows``
    (M,) int64, nearest first (ties: the lower index), by their distances to all points.

    Raises:
        ValueError: tensors of the wrong shapes or types, or ``k`` outside [1, min(N, 64)].
        IndexError: rows out of range.
    """
    n, m = points.shape[0], rows.shape[0]
    check("points", points, (n, 3), torch.float64)
    check("rows", rows, (m,), torch.long)
    if not 1 <= k <= min(n, 64):
        raise ValueError(f"k must lie in [1, {min(n, 64)}], got {k}")
    if m and (int(rows.min()) < 0 or int(rows.max()) >= n):
        raise IndexError(f"rows must lie in [0, {n})")
    out = torch.empty(m, k, dtype=torch.long)
    if m:
        _library.LIBRARY.o3dvis_brute_knn(n, points.data_ptr(), m, rows.data_ptr(), k, out.data_ptr())
    return out


def key_table(keys: Tensor) -> Tensor:
    """An open-addressing hash table of distinct int64 ``keys`` (M,): (S,) int64, S a power of two of
    at least 2 M, each slot -1 or the index of the key hashed there (what :func:`grid_knn` reads)."""
    check("keys", keys, (keys.shape[0],), torch.long)
    table = torch.full((1 << max(1, 2 * keys.shape[0] - 1).bit_length(),), -1, dtype=torch.long)
    _library.LIBRARY.o3dvis_key_table(keys.shape[0], keys.data_ptr(), table.shape[0], table.data_ptr())
    return table


def grid_knn(points: Tensor, cells: Tensor, keys: Tensor, starts: Tensor, table: Tensor, level: int, lo: Tensor,
             side: float, slack: float, k: int, cell_range: tuple[int, int], neighbours: Tensor,
             exact: Tensor, cell_list: Tensor | None = None, wanted: Tensor | None = None) -> None:
    """The ``k`` nearest of ``points`` to each point of the cells ``cell_range`` (or of the cells
    ``cell_list[cell_range[0]:cell_range[1]]``; of their points only those where ``wanted`` (N,)
    bool is set) among the 27 cells around it, written to rows of ``neighbours`` (N, k) int64 and
    ``exact`` (N,) uint8 (see ``o3dvis_grid_knn`` in ``knn.c``;
    :class:`o3dvis.neighbours.NeighbourSearch` prepares them).

    Args:
        points: (N, 3) float64, sorted by cell.
        cells: (M, 3) int64 integer coordinates of the occupied cells of a ``2^level`` grid.
        keys: (M,) int64 their Morton keys, distinct.
        starts: (M + 1,) int64 where each cell's points begin, then N.
        table: the :func:`key_table` of ``keys``.
        lo: (3,) float64 the grid's corner; side: its cells' side.
        slack: how far from its cell a point may lie (keys computed in a lower precision).

    Raises:
        ValueError: tensors of the wrong shapes or types, or ``k`` outside [1, 64].
    """
    n, m = points.shape[0], cells.shape[0]
    if not 1 <= k <= 64:
        raise ValueError(f"k must lie in [1, 64], got {k}")
    size = table.shape[0]
    if size < 2 * m or size & (size - 1):
        raise ValueError(f"table must have a power of two of at least {2 * m} slots, got {size}")
    for name, t, shape, dtype in (("points", points, (n, 3), torch.float64), ("cells", cells, (m, 3), torch.long),
                                  ("keys", keys, (m,), torch.long), ("starts", starts, (m + 1,), torch.long),
                                  ("table", table, (size,), torch.long), ("lo", lo, (3,), torch.float64),
                                  ("neighbours", neighbours, (n, k), torch.long), ("exact", exact, (n,), torch.uint8)):
        check(name, t, shape, dtype)
    first, last = cell_range
    if cell_list is not None:
        check("cell_list", cell_list, (cell_list.shape[0],), torch.long)
        if len(cell_list) and (int(cell_list.min()) < 0 or int(cell_list.max()) >= m):
            raise ValueError(f"cell_list must lie in [0, {m})")
    if wanted is not None:
        check("wanted", wanted, (n,), torch.bool)
    if not 0 <= first <= last <= (m if cell_list is None else len(cell_list)):
        raise ValueError(f"cell range {cell_range} outside [0, {m if cell_list is None else len(cell_list)}]")
    _library.LIBRARY.o3dvis_grid_knn(points.data_ptr(), cells.data_ptr(), keys.data_ptr(), starts.data_ptr(), size,
                                     table.data_ptr(), level, lo.data_ptr(), side, slack, k, first, last,
                                     None if cell_list is None else cell_list.data_ptr(),
                                     None if wanted is None else wanted.data_ptr(), neighbours.data_ptr(),
                                     exact.data_ptr())
