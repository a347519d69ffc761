"""The octree of the encoding in passes of C (``o3dvis/nn/csrc/octree.c``; see
:mod:`o3dvis.nn.octree`): a cloud's bounds and normalisation with its Morton keys, the keys' radix
sort, an octree's levels and a level's neighbours."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from . import _library
from ._library import check
from .threads import kernel_threads


def bounds(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(lo, hi, sum)``, each (3,) float64: the per-axis minimum, maximum (NaN where an axis has
    one, as ``min``/``max`` give) and sum of ``points`` (N, 3) float64, in one pass."""
    check("points", points, (points.shape[0], 3), torch.float64)
    out = points.new_empty(9)
    _library.LIBRARY.o3dvis_bounds(points.shape[0], points.data_ptr(), out.data_ptr())
    return out[:3], out[3:6], out[6:]


_SCATTER_ENTRIES = torch.tensor([0, 1, 2, 1, 3, 4, 2, 4, 5])
"""The (3, 3) scatter matrix's entries among the six sums of ``o3dvis_normalize``."""


def normalize(points: Tensor, center: Tensor, scale: float, mean: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(normalised, keys, scatter)`` of ``points`` (N, 3) float64 in one pass: ``((points - center)
    / scale).float()``, the (N,) Morton keys of those float32 points on the finest grid
    (:func:`morton_keys` at depth 21), and the (3, 3) sum of the outer products of the float64
    offsets ``(points - center) / scale - mean``."""
    n = points.shape[0]
    check("points", points, (n, 3), torch.float64)
    check("center", center, (3,), torch.float64)
    check("mean", mean, (3,), torch.float64)
    out, keys, sums = torch.empty(n, 3), torch.empty(n, dtype=torch.long), points.new_empty(6)
    _library.LIBRARY.o3dvis_normalize(n, points.data_ptr(), center.data_ptr(), float(scale), mean.data_ptr(),
                                      out.data_ptr(), keys.data_ptr(), sums.data_ptr())
    return out, keys, sums.index_select(0, _SCATTER_ENTRIES).view(3, 3)


def morton_keys(points: Tensor, depth: int) -> Tensor:
    """(N,) int64 Morton keys of the cells of a ``2^depth`` grid over [-1, 1]^3 holding ``points``
    (N, 3) float32, as :func:`~o3dvis.nn.octree.morton_encode` of
    :func:`~o3dvis.nn.octree.grid_cells` computes them, in one pass."""
    check("points", points, (points.shape[0], 3))
    if not 1 <= depth <= 21:
        raise ValueError(f"depth must lie in [1, 21], got {depth}")
    keys = torch.empty(points.shape[0], dtype=torch.long)
    _library.LIBRARY.o3dvis_morton_keys(points.shape[0], points.data_ptr(), depth, keys.data_ptr())
    return keys


SHARED_KEYS = 1 << 16
"""Keys from which :func:`sort_keys` shares its buckets with helper threads by default."""


def sort_keys(keys: Tensor, threads: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """``torch.sort(keys, stable=True)`` of (N,) non-negative int64 keys by a radix sort:
    ``(sorted, permutation, its inverse)``, the inverse the place of each key. ``threads``: the
    buckets of the highest byte in which the keys differ are shared out among up to this many
    threads (see :func:`kernel_threads`; by default from :data:`SHARED_KEYS` keys on).

    Raises:
        ValueError: keys of another shape or dtype, 2^32 or more of them, or a negative one; a
            thread count out of range.
    """
    check("keys", keys, (keys.shape[0],), torch.long)
    n = keys.shape[0]
    if n >= 1 << 32:
        raise ValueError(f"at most 2^32 - 1 keys, got {n}")
    out, order, rank, scratch = (torch.empty_like(keys), torch.empty_like(keys), torch.empty_like(keys),
                                 keys.new_empty(4 * n))
    threads = kernel_threads(threads) if threads is not None or n >= SHARED_KEYS else 1
    if _library.LIBRARY.o3dvis_sort_keys(n, keys.data_ptr(), out.data_ptr(), order.data_ptr(), rank.data_ptr(),
                                         scratch.data_ptr(), threads):
        raise ValueError("keys must be non-negative")
    return out, order, rank


@dataclass
class OctreeLevels:
    """What :func:`octree_levels` gives, per level ``0 .. depth`` (lists of tensors)."""

    point_leaf: Tensor  # (N,) each point's leaf
    keys: list[Tensor]  # (n_l,) sorted cell keys
    parent: list[Tensor]  # (n_l,) each node's parent, -1 at the root
    octant_rows: list[Tensor]  # (n_l,) 8 * parent + octant
    children: list[Tensor]  # (n_l, 8) but at depth, -1 where empty
    child_rows: list[Tensor]  # (n_l, 8) but at depth, n_{l+1} where empty


def octree_levels(keys: Tensor, depth: int, full_depth: int) -> OctreeLevels | None:
    """The levels of the octree of one cloud (what :class:`~o3dvis.nn.octree.Octree` builds with some
    forty torch ops) from its points' cell keys at ``depth``, in two passes: every node up to
    ``full_depth``, the cells that hold points below.

    Args:
        keys: (N,) int64 cell keys at ``depth`` (1 <= depth <= 16), sorted.

    Returns:
        The levels, or None where ``keys`` are out of order or out of [0, 8^depth).

    Raises:
        ValueError: keys of the wrong shape or type, or depths out of range.
    """
    n = keys.shape[0]
    check("keys", keys, (n,), torch.long)
    if not 1 <= full_depth < depth <= 16:
        raise ValueError(f"need 1 <= full_depth < depth <= 16, got {full_depth}, {depth}")
    counts = keys.new_empty(depth + 1)
    if _library.LIBRARY.o3dvis_octree_counts(n, keys.data_ptr(), depth, full_depth, counts.data_ptr()):
        return None
    nodes = counts.tolist()
    flat = keys.new_empty(sum(3 * c for c in nodes) + sum(16 * c for c in nodes[:-1]))
    point_leaf = keys.new_empty(n)
    _library.LIBRARY.o3dvis_octree_fill(n, keys.data_ptr(), depth, full_depth, counts.data_ptr(), point_leaf.data_ptr(),
                                        flat.data_ptr())
    levels, at = OctreeLevels(point_leaf, [], [], [], [], []), 0
    for level, count in enumerate(nodes):
        for table in (levels.keys, levels.parent, levels.octant_rows):
            table.append(flat[at:at + count])
            at += count
        if level < depth:
            for table in (levels.children, levels.child_rows):
                table.append(flat[at:at + 8 * count].view(count, 8))
                at += 8 * count
    return levels


def child_neighbours(keys: Tensor, parent: Tensor, above: Tensor, children: Tensor, parent_offset: Tensor,
                     offset_octant: Tensor) -> Tensor:
    """(n, 27) the 3x3x3 neighbours of the n nodes of an octree level from those of their parents,
    n where missing, in one pass (what :meth:`o3dvis.nn.octree.Octree.neighbours` computes with torch
    ops below the full levels).

    Args:
        keys: (n,) int64 the level's keys (their low three bits: each node's octant).
        parent: (n,) int64 each node's parent, in the level above.
        above: (m, 27) int64 the level above's neighbours, m where missing.
        children: (m, 8) int64 the level above's children, -1 where empty.
        parent_offset: (8, 27) int64 by octant, the offset at the level above whose node holds each
            neighbour.
        offset_octant: (8, 27) int64 by octant, the neighbour's octant in that node.

    Raises:
        ValueError: a tensor of another shape or dtype, not contiguous or not on the CPU, or a parent
            index out of range.
    """
    n, m = keys.shape[0], above.shape[0]
    check("keys", keys, (n,), torch.long)
    check("parent", parent, (n,), torch.long)
    check("above", above, (m, 27), torch.long)
    check("children", children, (m, 8), torch.long)
    check("parent_offset", parent_offset, (8, 27), torch.long)
    check("offset_octant", offset_octant, (8, 27), torch.long)
    out = torch.empty((n, 27), dtype=torch.long)
    if _library.LIBRARY.o3dvis_child_neighbours(n, keys.data_ptr(), parent.data_ptr(), above.data_ptr(), m,
                                                children.data_ptr(), parent_offset.data_ptr(), offset_octant.data_ptr(),
                                                out.data_ptr()):
        raise ValueError(f"parent indices must lie in [0, {m}), parent_offset in [0, 27) and offset_octant in [0, 8)")
    return out
