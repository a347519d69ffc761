"""Octree tables (``o3dvis.nn.octree``): Morton keys and order, parents and children, neighbours
looked up among the cells and through the parents."""

import pytest
import torch

from o3dvis.nn import Octree, morton_decode, morton_encode, morton_order, native, octree as octree_module


@pytest.mark.parametrize("depth", [3, 11, 12, 21])  # one table lookup up to depth 11, two above
def test_morton_roundtrip_and_order(depth):
    xyz = torch.randint(0, 1 << depth, (500, 3))
    key = morton_encode(xyz, depth)
    assert torch.equal(morton_decode(key, depth), xyz)
    # the child slot (lowest 3 bits) is x<<2 | y<<1 | z
    assert torch.equal(key & 7, ((xyz[:, 0] & 1) << 2) | ((xyz[:, 1] & 1) << 1) | (xyz[:, 2] & 1))


def test_morton_order_sorts_points_along_the_curve():
    pts = torch.rand(2000, 3) * 2 - 1
    order = morton_order(pts, depth=6)
    assert torch.equal(order.sort().values, torch.arange(2000))
    keys = morton_encode(((pts[order] + 1) * 32).floor().long(), 6)
    assert (keys[1:] >= keys[:-1]).all() and not (keys[1:] == keys[:-1]).all()


def test_octree_parents_children_consistent():
    torch.manual_seed(0)
    pts = torch.rand(3000, 3) * 2 - 1
    batch = torch.randint(0, 3, (3000,))
    o = Octree(pts, batch, depth=6, full_depth=2)
    assert o.num_nodes(2) == 3 * 64
    for level in range(1, 7):
        parent = o.parent[level]
        assert torch.equal(o.keys[level - 1][parent], o.keys[level] >> 3)
        ch = o.children[level - 1][parent, o.keys[level] & 7]
        assert torch.equal(ch, torch.arange(o.num_nodes(level)))
    # every point sits in the leaf whose coordinates contain it
    leaf_xyz = o.coords(6)[o.point_leaf]
    assert torch.equal(leaf_xyz, ((pts + 1) * 32).floor().long())
    assert torch.equal(o.batch_of(6)[o.point_leaf], batch)


def test_octree_of_morton_ordered_points_equals_the_sorted_build():
    # a Morton-ordered cloud skips the sort (unique_consecutive): same nodes, same leaf per point
    torch.manual_seed(2)
    pts = torch.rand(3000, 3) * 2 - 1
    order = morton_order(pts, depth=6)
    shuffled, ordered = Octree(pts, depth=6, full_depth=2), Octree(pts[order], depth=6, full_depth=2)
    for level in range(7):
        assert torch.equal(shuffled.keys[level], ordered.keys[level])
    assert torch.equal(shuffled.point_leaf[order], ordered.point_leaf)


def test_the_morton_sort_keys_build_the_same_octree():
    # the keys of the finest grid, shifted, are every coarser grid's: the octree built from them
    # (as an encode builds it) equals the one that computes its own, points on the box's faces included
    from o3dvis.nn.octree import MORTON_DEPTH, cell_keys, coarser_keys, morton_sort

    torch.manual_seed(3)
    pts = torch.cat([torch.rand(3000, 3) * 2 - 1, torch.tensor([[1.0, -1.0, 1.0], [-1.0, 1.0, 0.0]])])
    keys, order, rank = morton_sort(pts)
    assert torch.equal(order, morton_order(pts)) and torch.equal(keys, cell_keys(pts, MORTON_DEPTH)[order])
    assert torch.equal(rank[order], torch.arange(len(pts)))
    ordered = pts[order]
    for depth in (3, 6, 7):
        coarse = coarser_keys(keys, MORTON_DEPTH, depth)
        assert torch.equal(coarse, cell_keys(ordered, depth))
        given, own = Octree(ordered, depth=depth, full_depth=2, keys=coarse), Octree(ordered, depth=depth, full_depth=2)
        assert all(torch.equal(a, b) for a, b in zip(given.keys, own.keys))
        assert torch.equal(given.point_leaf, own.point_leaf)
    with pytest.raises(ValueError, match="coarser <= depth"):
        coarser_keys(keys, 6, 7)
    with pytest.raises(ValueError, match="keys must have shape"):
        Octree(ordered, depth=6, keys=keys[:10])


def _cell_lookup_neighbours(pts: torch.Tensor, level: int, batch: torch.Tensor | None = None,
                            depth: int = 5) -> tuple[torch.Tensor, int]:
    """The neighbours of ``level`` looked up among its cells, as levels up to the full depth are
    (a full depth of ``level`` set after the build), and the level's number of nodes."""
    tree = Octree(pts, batch, depth=depth, full_depth=2)
    tree.full_depth = level
    return tree.neighbours(level), tree.num_nodes(level)


def test_neighbours_dense_and_sparse_lookup_agree(monkeypatch):
    torch.manual_seed(1)
    pts = torch.rand(2000, 3) * 2 - 1
    dense, _ = _cell_lookup_neighbours(pts, 5)
    monkeypatch.setattr(octree_module, "_DENSE_CELLS", 0)
    sparse, _ = _cell_lookup_neighbours(pts, 5)
    assert torch.equal(dense, sparse)
    assert torch.equal(Octree(pts, depth=5, full_depth=2).neighbours(5), dense)  # through the parents


@pytest.mark.parametrize("kernels", [True, False])
def test_neighbours_from_parents_equal_the_cell_table(kernels, monkeypatch):
    # below the full levels each neighbour is found through the parent's (in C, or with torch ops);
    # the lookup among the level's cells is the reference
    if kernels and not native.available():
        pytest.skip("C kernels not built")
    monkeypatch.setattr(octree_module.native, "available", lambda: kernels)
    torch.manual_seed(3)
    pts = torch.rand(4000, 3) * 2 - 1
    pts[:1500] *= 0.05  # a dense cluster beside sparse points: nodes with and without neighbours
    batch = torch.randint(0, 3, (4000,))
    built = Octree(pts, batch, depth=7, full_depth=2)
    for level in range(3, 8):
        expected, nodes = _cell_lookup_neighbours(pts, level, batch, depth=7)
        assert (expected < nodes).float().mean() > 0.05  # not all missing
        assert torch.equal(built.neighbours(level), expected)


def test_full_levels_share_their_neighbours(monkeypatch):
    monkeypatch.setattr(octree_module, "_FULL_NEIGHBOURS", {})
    torch.manual_seed(4)
    pts, batch = torch.rand(3000, 3) * 2 - 1, torch.randint(0, 2, (3000,))
    a, b = Octree(pts, batch, depth=5, full_depth=2), Octree(pts.flip(1) * 0.5, batch, depth=5, full_depth=2)
    for level in range(3):
        assert b.neighbours(level) is a.neighbours(level)
        assert torch.equal(a.neighbours(level), _cell_lookup_neighbours(pts, level, batch)[0])
    one = Octree(pts, depth=5, full_depth=2)  # one cloud: its own table
    assert torch.equal(one.neighbours(2), _cell_lookup_neighbours(pts, 2)[0])
    assert one.neighbours(2).shape[0] == 64 and a.neighbours(2).shape[0] == 128
    partial = Octree(pts[:10], depth=5, full_depth=2)
    partial.full_depth = 3  # a level looked up among its cells that does not hold every cell
    assert torch.equal(partial.neighbours(3), _cell_lookup_neighbours(pts[:10], 3)[0])
    assert (3, 1, "cpu") not in octree_module._FULL_NEIGHBOURS


def test_neighbours_do_not_cross_clouds():
    pts = torch.zeros(2, 3)
    o = Octree(pts, torch.tensor([0, 1]), depth=3, full_depth=1)
    nbr = o.neighbours(3)
    n = o.num_nodes(3)
    assert n == 2 and (nbr[:, 13] == torch.arange(2)).all()
    assert ((nbr == n) | (nbr == torch.arange(2)[:, None])).all()
