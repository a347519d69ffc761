"""Nearest neighbours of a cloud's points: a grid of the octree's cells searched in C, a k-d tree
where that is faster (small clouds, many neighbours).

The plane fits of :mod:`o3dvis.orientation` and of :mod:`o3dvis.apps.normals` ask for them.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from .nn import native
from .nn.octree import cell_keys, morton_decode, normalize_points
from .threads import PARALLEL_ROWS, plan_threads, side_by_side

__all__ = ["nearest_neighbours", "NeighbourSearch"]

_GRID_DEPTH = 16  # the finest grid of the neighbour search
_CELL_POINTS = 6  # points per occupied cell the neighbour search's grid aims at, at least
_GRID_MIN_POINTS = 2_000  # smaller clouds are searched with a k-d tree (faster there)
_KEY_SLACK = 1e-6  # how far off its cell float32 keys may put a point, in normalised coordinates
# (row, point) distances the search again computes before taking a k-d tree: 2^24 take about as
# long as building one for 200 k points
_BRUTE_FORCE_PAIRS = 1 << 24


def nearest_neighbours(points: np.ndarray, k: int) -> np.ndarray:
    """(N, k) indices of the ``k`` nearest points to each point, itself included, nearest first (the
    order of equally near ones is left open), as ``cKDTree(points).query(points, k)`` finds them.

    Where the package's kernels are built, the points are bucketed in the cells of a grid with about
    :data:`_CELL_POINTS` points in each occupied one and each point's neighbours are sought among
    the 27 cells around it, in one pass of C (``native.grid_knn``); a point whose k-th neighbour is
    not nearer than the border of those cells, in a sparse corner of the cloud, is searched again
    among all points. The grid is the octree's (:func:`~o3dvis.nn.octree.cell_keys`), so points in
    the order of an encoding are sorted by cell already and are not moved. Small clouds and ``k``
    over 64 take a k-d tree. :class:`NeighbourSearch` asks again for some of the points.

    Args:
        points: (N, 3) finite points.
        k: neighbours per point (at most N).

    Returns:
        (N, k) int64 indices.
    """
    return NeighbourSearch(points).query(k)


class NeighbourSearch:
    """:func:`nearest_neighbours` of one cloud, asked for all its points or some, as often as
    needed: the grid (or the k-d tree) is made once.

    Args:
        points: (N, 3) finite points.
    """

    def __init__(self, points: np.ndarray):
        self.points = points
        self._tree: cKDTree | None = None
        self._grid: tuple | None = None

    def query(self, k: int, rows: np.ndarray | None = None) -> np.ndarray:
        """(M, k) int64: the ``k`` nearest points (at most N) to each of the points ``rows``
        ((M,) indices; None: all), nearest first, as :func:`nearest_neighbours` finds them."""
        count = len(self.points)
        asked = np.arange(count) if rows is None else np.asarray(rows, dtype=np.int64)
        if not (native.available() and count >= _GRID_MIN_POINTS and k <= 64):
            if self._tree is None:
                self._tree = cKDTree(self.points, balanced_tree=False)
            return self._tree.query(self.points[asked], k=k, workers=-1)[1].reshape(len(asked), k)
        grid = self._grid_of()
        if grid is None:  # one point, repeated
            return np.broadcast_to(np.arange(k), (len(asked), k)).copy()
        order, ordered, first, tensors, level, corner, side = grid
        near, exact = torch.empty((count, k), dtype=torch.long), torch.empty(count, dtype=torch.uint8)
        if ordered:  # the rows' places in the sorted points
            place = asked
        else:
            inverse = np.empty_like(order)
            inverse[order] = np.arange(count)
            place = inverse[asked]
        cells = wanted = None
        if rows is not None:  # the cells holding the rows, and in them the rows alone
            cells = torch.from_numpy(np.unique(np.searchsorted(first, place, side="right") - 1))
            wanted = torch.zeros(count, dtype=torch.bool)
            wanted[torch.from_numpy(place)] = True
        todo = len(first) if cells is None else len(cells)
        workers = plan_threads(len(asked), 2 * PARALLEL_ROWS)
        bounds = (np.searchsorted(first, np.linspace(0, count, workers + 1)[1:-1]).tolist() if cells is None else
                  np.linspace(0, todo, workers + 1)[1:-1].astype(int).tolist())
        ranges = list(zip([0, *bounds], [*bounds, todo]))
        for _ in side_by_side(lambda span: native.grid_knn(*tensors, level, corner, side, _KEY_SLACK, k, span, near,
                                                            exact, cells, wanted), ranges, workers):
            pass
        every = rows is None and ordered  # the rows as the kernel wrote them
        found = near.numpy() if every else near.numpy()[place]
        result = found if ordered else order[found]
        again = np.flatnonzero((exact.numpy() if every else exact.numpy()[place]) == 0)
        if len(again):
            result[again] = _nearest_by_search(self.points, asked[again], k)
        return result

    def _grid_of(self) -> tuple | None:
        """The grid's arrays (made on first use), None for a cloud of one point repeated."""
        if self._grid is None:
            points = np.ascontiguousarray(self.points, dtype=np.float64)
            count = len(points)
            normalised, _, scale = normalize_points(torch.from_numpy(points))
            if float(scale) <= torch.finfo(torch.float64).tiny:
                return None
            keys = cell_keys(normalised.float(), _GRID_DEPTH).numpy()  # as the octree's: an encoding's order sorts them
            order = np.argsort(keys, kind="stable")
            ordered = bool((order[1:] > order[:-1]).all())
            sorted_points = normalised.numpy() if ordered else normalised.numpy()[order]
            keys = keys if ordered else keys[order]
            level = 1  # the finest grid whose occupied cells hold _CELL_POINTS points on average
            while level < _GRID_DEPTH and count >= _CELL_POINTS * _occupied(keys, 3 * (_GRID_DEPTH - level - 1)):
                level += 1
            coarse = keys >> (3 * (_GRID_DEPTH - level))
            first = np.flatnonzero(np.diff(coarse, prepend=-1))
            unique = torch.from_numpy(coarse[first])
            tensors = [torch.from_numpy(sorted_points), morton_decode(unique, level), unique,
                       torch.from_numpy(np.append(first, count)), native.key_table(unique)]
            self._grid = (order, ordered, first, tensors, level, torch.full((3,), -1.0, dtype=torch.float64),
                          2.0 / (1 << level))
        return self._grid


def _occupied(sorted_keys: np.ndarray, shift: int) -> int:
    """How many cells the sorted fine ``sorted_keys`` occupy on the grid ``shift`` bits coarser."""
    coarse = sorted_keys >> shift
    return 1 + int(np.count_nonzero(coarse[1:] != coarse[:-1]))


def _nearest_by_search(points: np.ndarray, rows: np.ndarray, k: int) -> np.ndarray:
    """(len(rows), k) the ``k`` nearest points to ``points[rows]``, nearest first: by their distances
    to all points in C for a few rows (the grid's kernels are built wherever this is asked), by a
    k-d tree for many."""
    if len(rows) * len(points) > _BRUTE_FORCE_PAIRS:
        return cKDTree(points, balanced_tree=False).query(points[rows], k=k, workers=-1)[1].reshape(-1, k)
    return native.brute_knn(torch.from_numpy(np.ascontiguousarray(points, dtype=np.float64)),
                            torch.from_numpy(np.asarray(rows, dtype=np.int64)), k).numpy()
