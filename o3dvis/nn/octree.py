"""Octree over a batch of normalised point clouds, built with vectorised torch ops.

Nodes of every level are identified by a key ``batch << 3*level | morton`` and
kept sorted, so parents, children and neighbours are found with
``torch.searchsorted`` instead of Python loops. Everything runs unchanged on
CPU and CUDA; on the CPU the neighbours below the full levels come from one
pass of C where the package's kernels are built (:mod:`o3dvis.nn.native`).
"""

from __future__ import annotations

from collections.abc import Callable, Hashable

import torch
from torch import Tensor

from . import native

__all__ = ["Octree", "bounding_box", "cube_frame", "cell_keys", "coarser_keys", "grid_cells", "morton_encode",
           "morton_decode", "morton_order", "morton_sort", "normalize_points", "MORTON_DEPTH"]

# The most cells (all clouds of the batch, a border of one cell included) of a level whose node
# lookups go through a dense table; larger levels search their sorted keys.
_DENSE_CELLS = 1 << 25

# The 27 neighbour offsets of a 3x3x3 kernel, ordered like the (kx, ky, kz)
# axes of a ``conv3d`` weight: index = (dx + 1) * 9 + (dy + 1) * 3 + (dz + 1).
_OFFSETS = torch.stack(
    torch.meshgrid(*(torch.arange(-1, 2),) * 3, indexing="ij"), dim=-1
).reshape(27, 3)


def _parent_steps() -> tuple[Tensor, Tensor]:
    """Where the neighbour at each offset of a node lies, by the node's octant (its key's low 3
    bits): (8, 27) indices of the offset at the parent's level whose node holds it, and (8, 27)
    octants of it in that node. Per axis a coordinate ``2 p + b`` plus ``d`` is ``2 (p + e) + c``
    with ``e = (b + d) >> 1`` and ``c = (b + d) & 1``."""
    bits = torch.stack([(torch.arange(8) >> 2) & 1, (torch.arange(8) >> 1) & 1, torch.arange(8) & 1], dim=1)
    moved = bits[:, None, :] + _OFFSETS[None]  # (8, 27, 3) in [-1, 2]
    step, octant = moved >> 1, moved & 1  # floor division: -1 >> 1 == -1
    return ((step[..., 0] + 1) * 9 + (step[..., 1] + 1) * 3 + step[..., 2] + 1,
            (octant[..., 0] << 2) | (octant[..., 1] << 1) | octant[..., 2])


_PARENT_OFFSET, _PARENT_OCTANT = _parent_steps()

# The neighbours of full levels (every node, in key order), by (level, clouds, device): the same for
# every octree, they are computed once (they were a third of a small cloud's octree) and shared,
# read-only, for at most this many keys.
_FULL_NEIGHBOURS: dict[tuple[int, int, str], Tensor] = {}
_FULL_NEIGHBOURS_KEPT = 64


def bounding_box(points: Tensor) -> tuple[Tensor, Tensor]:
    """Per-axis minimum and maximum of (N, 3) points.

    ``min``/``max`` over dim 0, which run faster than ``amin``/``amax`` on the
    CPU for this shape.
    """
    if points.dtype == torch.float64 and points.device.type == "cpu" and native.available():
        return native.bounds(points.detach().contiguous())[:2]  # one pass of C instead of two
    return points.min(dim=0).values, points.max(dim=0).values


def cube_frame(lo: Tensor, hi: Tensor, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """``(center, scale)`` of :func:`normalize_points` for the bounding box ``lo``, ``hi``: the box's
    centre, and half its longest side, enlarged by the relative margin ``eps``."""
    center = (lo + hi) / 2
    return center, ((hi - lo).amax() / 2).clamp_min(torch.finfo(lo.dtype).tiny) * (1 + eps)


def normalize_points(points: Tensor, eps: float = 1e-6,
                     bounds: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Maps a cloud into the cube [-1, 1]^3 by its bounding box.

    Args:
        points: (N, 3) float tensor.
        eps: relative margin that keeps points strictly inside the cube.
        bounds: the cloud's :func:`bounding_box`, when the caller has it already.

    Returns:
        ``(normalised, center, scale)`` with ``normalised = (points - center) / scale``.
    """
    center, scale = cube_frame(*(bounding_box(points) if bounds is None else bounds), eps)
    return (points - center).div_(scale), center, scale  # one temporary: at 10 M points 240 MB each


_SPREAD = ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
           (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249))


def _spread_bits(v: Tensor) -> Tensor:
    """Puts bit ``i`` of ``v`` (< 2^21) at bit ``3 i``."""
    for shift, mask in _SPREAD:
        v = (v | (v << shift)) & mask
    return v


def _compact(v: Tensor) -> Tensor:
    """Inverse of :func:`_spread`."""
    v = v & _SPREAD[-1][1]
    masks = [m for _, m in _SPREAD[-2::-1]] + [(1 << 21) - 1]
    for (shift, _), mask in zip(_SPREAD[::-1], masks):
        v = (v | (v >> shift)) & mask
    return v


_TABLE_DEPTH = 11
_SPREAD_TABLE = _spread_bits(torch.arange(1 << _TABLE_DEPTH))


def morton_encode(xyz: Tensor, depth: int) -> Tensor:
    """Interleaves the bits of integer coordinates (x highest, z lowest), ``depth`` <= 21.

    Bits are spread by table lookups (one per coordinate up to depth 11, two above: the low 10
    bits and the rest) instead of five shift-and-mask passes.
    """
    xyz = xyz.long()
    table = _SPREAD_TABLE.to(xyz.device)
    if depth <= _TABLE_DEPTH:
        spread = torch.take(table, xyz)
    else:
        spread = (torch.take(table, xyz >> 10) << 30) | torch.take(table, xyz & 1023)
    return (spread[:, 0] << 2) | (spread[:, 1] << 1) | spread[:, 2]


def morton_decode(key: Tensor, depth: int) -> Tensor:
    """Inverse of :func:`morton_encode` for the lowest ``3 * depth`` bits."""
    key = key & ((1 << (3 * depth)) - 1)
    return torch.stack([_compact(key >> 2), _compact(key >> 1), _compact(key)], dim=1)


def grid_cells(points: Tensor, depth: int) -> Tensor:
    """(N, 3) integer coordinates of the cells of a ``2^depth`` grid over [-1, 1]^3 holding ``points``."""
    res = 1 << depth
    return (points.detach() + 1).mul_(res / 2).long().clamp_(0, res - 1)  # truncation = floor here


MORTON_DEPTH = 21
"""The grid of the Morton order (2^21 cells a side, 63-bit keys): the finest one the keys hold."""


def cell_keys(points: Tensor, depth: int) -> Tensor:
    """(N,) Morton keys of the cells of a ``2^depth`` grid over [-1, 1]^3 holding ``points``:
    ``morton_encode(grid_cells(points, depth), depth)``, in one pass of C
    (:func:`o3dvis.nn.native.morton_keys`) for float32 points on the CPU, where the twenty or so
    passes of these ops were half a 10 M-point encode."""
    if points.device.type == "cpu" and points.dtype == torch.float32 and depth <= 21 and native.available():
        return native.morton_keys(points.detach().contiguous(), depth)
    return morton_encode(grid_cells(points, depth), depth)


def morton_order(points: Tensor, depth: int = MORTON_DEPTH) -> Tensor:
    """The permutation that sorts normalised points along the Morton curve of a ``2^depth`` grid.

    Points close in space end up close in memory, which keeps the per-view
    gathers and scatters of a cloud cache-friendly. At the default depth, the
    finest, the order is also that of every coarser grid (an octree's levels)
    and of the noise cues' runs (:func:`o3dvis.nn.noise.noise_cues`).
    """
    return morton_sort(points, depth)[1]


def morton_sort(points: Tensor, depth: int = MORTON_DEPTH, keys: Tensor | None = None
                ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`morton_order` with the keys it sorts and its inverse: ``(sorted cell keys,
    permutation, rank)``, ``rank[i]`` the place of point ``i``; the keys are those of the
    ``2^depth`` grid (:func:`cell_keys`, or ``keys`` where the caller has them), from which
    :func:`coarser_keys` gives any coarser grid's without another pass over the points. Ties
    (points of one cell) keep their order: a radix sort of C on the CPU, a stable ``torch.sort``
    elsewhere."""
    keys = cell_keys(points, depth) if keys is None else keys
    if keys.device.type == "cpu" and native.available():
        return native.sort_keys(keys)
    keys, order = torch.sort(keys, stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(order), device=order.device)
    return keys, order, rank


def coarser_keys(keys: Tensor, depth: int, coarser: int) -> Tensor:
    """The cell keys of a ``2^coarser`` grid from those of the ``2^depth`` grid (``coarser <= depth``):
    a Morton key's leading bits are its ancestors' keys, so the same as :func:`cell_keys` there."""
    if not 0 <= coarser <= depth:
        raise ValueError(f"need 0 <= coarser <= depth, got {coarser} and {depth}")
    return keys >> (3 * (depth - coarser))


def _bordered_cell(width: int, batch: Tensor | int, xyz: Tensor) -> Tensor:
    """Index of the cell at integer coords ``xyz`` (..., 3) in [-1, width - 2] of cloud ``batch`` in
    a dense table of ``width``^3 cells a cloud (a level's cells inside a border one cell wide)."""
    return ((batch * width + xyz[..., 0] + 1) * width + xyz[..., 1] + 1) * width + xyz[..., 2] + 1


class Octree:
    """A sparse octree of ``depth`` levels over a batch of clouds in [-1, 1]^3.

    Levels ``0..full_depth`` hold every node; deeper levels hold the nodes that
    contain points. Attributes per level ``l``: ``keys[l]`` (sorted),
    ``parent[l]`` (index into level ``l - 1``), ``children[l]`` ((n, 8) index
    into level ``l + 1``, -1 where empty). ``point_leaf`` maps each input point
    to its node at the finest level.
    """

    def __init__(self, points: Tensor, batch: Tensor | None = None, depth: int = 7,
                 full_depth: int = 2, batch_size: int | None = None, keys: Tensor | None = None):
        """``keys``: the points' :func:`cell_keys` at ``depth`` where known already (e.g. by
        :func:`coarser_keys` of :func:`morton_sort`'s), else None to compute them."""
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {tuple(points.shape)}")
        if keys is not None and keys.shape != points.shape[:1]:
            raise ValueError(f"keys must have shape ({points.shape[0]},), got {tuple(keys.shape)}")
        if not 1 <= full_depth < depth <= 16:
            raise ValueError(f"need 1 <= full_depth < depth <= 16, got {full_depth}, {depth}")
        device = points.device
        if batch is None:
            batch = torch.zeros(points.shape[0], dtype=torch.long, device=device)
        self.depth, self.full_depth = depth, full_depth
        self.batch_size = int(batch.max().item()) + 1 if batch_size is None else batch_size
        self.device = device
        self._neighbours: dict[int, Tensor] = {}
        self._tables: dict[int, Tensor] = {}
        self._child_rows: dict[int, Tensor] = {}
        self._octant_rows: dict[int, Tensor] = {}
        self._derived: dict[Hashable, Tensor] = {}
        if keys is None:
            keys = cell_keys(points, depth)
        # one cloud on the CPU, its points along the Morton curve (as an encoding orders them): two passes of C
        levels = (native.octree_levels(keys.contiguous(), depth, full_depth)
                  if self.batch_size == 1 and device.type == "cpu" and keys.dtype == torch.long and native.available()
                  else None)
        if levels is not None:
            self.keys, self.parent, self.children = levels.keys, levels.parent, levels.children
            self.point_leaf = levels.point_leaf
            self._child_rows = dict(enumerate(levels.child_rows))
            self._octant_rows = dict(enumerate(levels.octant_rows))
            return

        leaf_keys = (batch.long() << (3 * depth)) | keys
        keys: list[Tensor] = [torch.empty(0)] * (depth + 1)
        if bool((leaf_keys[1:] >= leaf_keys[:-1]).all()):  # points in Morton order: no sort needed
            keys[depth], self.point_leaf = torch.unique_consecutive(leaf_keys, return_inverse=True)
        else:
            keys[depth], self.point_leaf = torch.unique(leaf_keys, sorted=True, return_inverse=True)
        for level in range(depth - 1, full_depth, -1):  # sorted keys stay sorted when shifted
            keys[level] = torch.unique_consecutive(keys[level + 1] >> 3)
        for level in range(full_depth + 1):
            nodes = torch.arange(8**level, device=device)
            b = torch.arange(self.batch_size, device=device)
            keys[level] = ((b[:, None] << (3 * level)) | nodes[None, :]).reshape(-1)
        self.keys = keys

        self.parent: list[Tensor] = [torch.full((self.batch_size,), -1, dtype=torch.long, device=device)]
        self.children: list[Tensor] = []
        for level in range(depth):
            child_keys = keys[level + 1]
            parent = torch.searchsorted(keys[level], child_keys >> 3)
            self.parent.append(parent)
            children = torch.full((keys[level].shape[0], 8), -1, dtype=torch.long, device=device)
            children[parent, child_keys & 7] = torch.arange(child_keys.shape[0], device=device)
            self.children.append(children)

    def derived(self, key: Hashable, make: Callable[[], Tensor]) -> Tensor:
        """A table that ``make`` derives from this octree's (e.g. the lists by which a convolution
        kernel takes a level's neighbours), made on first use and kept with the octree under ``key``."""
        if key not in self._derived:
            self._derived[key] = make()
        return self._derived[key]

    def num_nodes(self, level: int) -> int:
        return self.keys[level].shape[0]

    def child_rows(self, level: int) -> Tensor:
        """(n, 8) the children of the nodes of ``level``, ``num_nodes(level + 1)`` where empty: rows of
        the finer level's features padded with one row of zeros (what a down-sampling gathers)."""
        if level not in self._child_rows:
            children = self.children[level]
            self._child_rows[level] = torch.where(children < 0, self.num_nodes(level + 1), children)
        return self._child_rows[level]

    def octant_rows(self, level: int) -> Tensor:
        """(n,) ``8 * parent + octant`` of each node of ``level``: its row among the eight octants of
        each node of ``level - 1`` (what an up-sampling gathers)."""
        if level not in self._octant_rows:
            self._octant_rows[level] = self.parent[level] * 8 + (self.keys[level] & 7)
        return self._octant_rows[level]

    def coords(self, level: int) -> Tensor:
        """Integer (x, y, z) of the nodes of ``level``."""
        return morton_decode(self.keys[level], level)

    def batch_of(self, level: int) -> Tensor:
        return self.keys[level] >> (3 * level)

    def _table(self, level: int) -> Tensor:
        """Dense int32 table of the node index of every cell of ``level`` and of a border one cell
        wide around it (-1 where empty), indexed by :func:`_bordered_cell`."""
        if level not in self._tables:
            w = (1 << level) + 2
            cell = _bordered_cell(w, self.batch_of(level), self.coords(level))
            table = torch.full((self.batch_size * w**3,), -1, dtype=torch.int32, device=self.device)
            table[cell] = torch.arange(cell.shape[0], dtype=torch.int32, device=self.device)
            self._tables[level] = table
        return self._tables[level]

    def _dense(self, level: int) -> bool:
        return self.batch_size * ((1 << level) + 2) ** 3 <= _DENSE_CELLS

    def lookup(self, level: int, xyz: Tensor, batch: Tensor) -> Tensor:
        """Index of the node at integer coords ``xyz`` (..., 3) of ``level``, or -1 if absent.

        Uses a dense table of the level when it has at most ``2**25`` cells and
        a binary search over the sorted keys otherwise.
        """
        res = 1 << level
        inside = ((xyz >= 0) & (xyz < res)).all(dim=-1)
        if self._dense(level):
            idx = self._table(level)[_bordered_cell(res + 2, batch, xyz.clamp(-1, res))].long()
            return torch.where(inside, idx, torch.full_like(idx, -1))
        xyz = xyz.clamp(0, res - 1)
        query = (batch << (3 * level)) | morton_encode(xyz.reshape(-1, 3), level).view(xyz.shape[:-1])
        keys = self.keys[level]
        idx = torch.searchsorted(keys, query).clamp_(max=keys.shape[0] - 1)
        found = inside & (keys[idx] == query)
        return torch.where(found, idx, torch.full_like(idx, -1))

    def neighbours(self, level: int) -> Tensor:
        """(n, 27) indices of the 3x3x3 neighbours at ``level``; missing ones are ``n``.

        Pointing missing neighbours at row ``n`` lets a convolution gather from
        features padded with one row of zeros.
        """
        kept = self._neighbours.get(level)
        if kept is not None:  # asked by every convolution of the level
            return kept
        if level > self.full_depth:
            self._neighbours[level] = self._neighbours_from_parents(level)
        # a level that holds every cell of each cloud has the neighbours of any other such level
        full = self.num_nodes(level) == self.batch_size << (3 * level)
        shared = (level, self.batch_size, str(self.device))
        if level not in self._neighbours and full and shared in _FULL_NEIGHBOURS:
            self._neighbours[level] = _FULL_NEIGHBOURS[shared]
        if level not in self._neighbours:
            xyz = self.coords(level)
            offsets = _OFFSETS.to(self.device)
            if self._dense(level):  # each offset is one step in the bordered table: no bounds to check
                w = (1 << level) + 2
                steps = _bordered_cell(w, 0, offsets) - _bordered_cell(w, 0, torch.zeros_like(offsets[0]))
                idx = self._table(level)[_bordered_cell(w, self.batch_of(level), xyz)[:, None] + steps]
            else:
                batch = self.batch_of(level)[:, None].expand(-1, 27)
                idx = self.lookup(level, xyz[:, None, :] + offsets[None], batch)
            self._neighbours[level] = torch.where(idx < 0, xyz.shape[0], idx.long())
            if full and len(_FULL_NEIGHBOURS) < _FULL_NEIGHBOURS_KEPT:
                _FULL_NEIGHBOURS[shared] = self._neighbours[level]
        return self._neighbours[level]

    def _neighbours_from_parents(self, level: int) -> Tensor:
        """:meth:`neighbours` of a level below the full ones, from those of its parents: each
        neighbour is a child of a neighbour of the node's parent (:func:`_parent_steps`), so no
        table of the level's cells is built (filling it was most of the time at the fine levels
        of small clouds)."""
        above = self.neighbours(level - 1)  # (m, 27), m where missing
        if self.device.type == "cpu" and native.available():  # one pass of C instead of some ten ops
            return native.child_neighbours(self.keys[level], self.parent[level], above, self.children[level - 1],
                                           _PARENT_OFFSET, _PARENT_OCTANT)
        octant = self.keys[level] & 7
        offset, child = _PARENT_OFFSET.to(self.device)[octant], _PARENT_OCTANT.to(self.device)[octant]
        holder = above.index_select(0, self.parent[level]).gather(1, offset)  # (n, 27) node at level - 1, or m
        children = torch.cat([self.children[level - 1].view(-1),
                              self.children[level - 1].new_full((8,), -1)])  # row m: no children
        idx = children.take(holder.mul_(8).add_(child))
        return torch.where(idx < 0, octant.new_tensor(idx.shape[0]), idx)
