"""The torch core: octree tables, sparse convolutions, network invariances."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from o3dvis.nn import (NetworkConfig, Octree, OctreeConv, OctreeDownsample, OctreeUpsample,
                       VisibilityNetwork, ViewEmbedding, VisibilityPredictor, morton_decode, morton_encode,
                       morton_order, noise_cues, normalize_points, view_cues)
from o3dvis.nn.cues import ViewProjection, point_surfels
from o3dvis.nn import native
from o3dvis.nn import octree as octree_module


def _full_grid_octree(depth=3):
    """An octree whose finest level is fully occupied (one point per voxel centre)."""
    res = 1 << depth
    idx = torch.stack(torch.meshgrid(*(torch.arange(res),) * 3, indexing="ij"), -1).reshape(-1, 3)
    points = (idx.double() + 0.5) / res * 2 - 1
    return Octree(points, depth=depth, full_depth=1), idx


def _to_grid(x, xyz, res):
    grid = torch.zeros(1, x.shape[1], res, res, res, dtype=x.dtype)
    grid[0, :, xyz[:, 0], xyz[:, 1], xyz[:, 2]] = x.T
    return grid


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


def test_conv_equals_conv3d_on_full_grid():
    torch.manual_seed(0)
    o, xyz = _full_grid_octree(3)
    conv = OctreeConv(4, 5).double()
    x = torch.randn(o.num_nodes(3), 4, dtype=torch.float64)
    y = conv(x, o, 3)
    order = o.coords(3)
    w = conv.weight.view(27, 4, 5).permute(2, 1, 0).reshape(5, 4, 3, 3, 3)
    ref = F.conv3d(_to_grid(x, order, 8), w, padding=1)[0][:, order[:, 0], order[:, 1], order[:, 2]].T
    torch.testing.assert_close(y, ref)


def test_down_and_up_sampling_equal_strided_convs():
    torch.manual_seed(0)
    o, _ = _full_grid_octree(3)
    fine, coarse = o.coords(3), o.coords(2)
    x = torch.randn(o.num_nodes(3), 3, dtype=torch.float64)
    down = OctreeDownsample(3, 2).double()
    w = down.weight.view(8, 3, 2).permute(2, 1, 0).reshape(2, 3, 2, 2, 2)
    ref = F.conv3d(_to_grid(x, fine, 8), w, stride=2)[0][:, coarse[:, 0], coarse[:, 1], coarse[:, 2]].T
    torch.testing.assert_close(down(x, o, 3), ref)

    up = OctreeUpsample(2, 3).double()
    xc = torch.randn(o.num_nodes(2), 2, dtype=torch.float64)
    wt = up.weight.view(2, 8, 3).permute(0, 2, 1).reshape(2, 3, 2, 2, 2)
    ref = F.conv_transpose3d(_to_grid(xc, coarse, 4), wt, stride=2)[0][:, fine[:, 0], fine[:, 1], fine[:, 2]].T
    torch.testing.assert_close(up(xc, o, 2), ref)


def test_conv_gradcheck():
    torch.manual_seed(0)
    pts = torch.rand(40, 3, dtype=torch.float64) * 2 - 1
    o = Octree(pts, depth=3, full_depth=1)
    conv = OctreeConv(2, 2).double()
    x = torch.randn(o.num_nodes(3), 2, dtype=torch.float64, requires_grad=True)
    w = conv.weight.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda a, w: torch.func.functional_call(conv, {"weight": w}, (a, o, 3)), (x, w))


def test_conv_products_in_bfloat16_without_grad_only():
    """products_in(bfloat16) rounds the products' inputs (float32 out, close to the float32
    answer), not with autograd on, not outside the block, and follows in-place weight changes."""
    from o3dvis.nn.conv import products_in

    torch.manual_seed(0)
    o, _ = _full_grid_octree(3)
    conv = OctreeConv(8, 8)
    x = torch.randn(o.num_nodes(3), 8)
    exact = conv(x, o, 3)
    with torch.no_grad(), products_in(torch.bfloat16):
        reduced = conv(x, o, 3)
    assert reduced.dtype == torch.float32 and not torch.equal(reduced, exact)
    torch.testing.assert_close(reduced, exact, rtol=0.05, atol=0.05)
    with products_in(torch.bfloat16):
        assert torch.equal(conv(x, o, 3), exact)  # autograd on: float32
    with torch.no_grad():
        assert torch.equal(conv(x, o, 3), exact)  # outside the block: float32
        conv.weight.mul_(2)
        with products_in(torch.bfloat16):
            torch.testing.assert_close(conv(x, o, 3), 2 * exact, rtol=0.05, atol=0.1)


@pytest.mark.parametrize("conv", [OctreeConv, OctreeDownsample, OctreeUpsample])
def test_batch_norm_folds_into_the_convolution_in_inference(conv):
    """Eval mode without autograd folds the batch norm into the weight: the same answers as the
    batch norm itself, and a change of its statistics (a load) is followed."""
    from o3dvis.nn.conv import ConvBnRelu

    torch.manual_seed(0)
    o, _ = _full_grid_octree(3)
    level = 2 if conv is OctreeUpsample else 3
    layer = ConvBnRelu(8, 16, conv).eval()
    with torch.no_grad():
        for t in (layer.bn.weight, layer.bn.bias, layer.bn.running_mean):
            t.normal_()
        layer.bn.running_var.uniform_(0.5, 2)
    x = torch.randn(o.num_nodes(level), 8)
    for _ in range(2):  # the second time after a change of the statistics in place
        with torch.no_grad(), pytest.MonkeyPatch.context() as mp:
            mp.setattr(layer.bn, "forward", None)  # folded: the batch norm is not run
            folded = layer(x, o, level)
        plain = layer.bn(layer.conv(x, o, level)).relu().detach()  # autograd on: not folded
        torch.testing.assert_close(folded, plain, rtol=1e-5, atol=1e-5)
        layer.load_state_dict({**layer.state_dict(), "bn.running_mean": torch.randn(16)})


@pytest.mark.parametrize("products", [torch.float32, torch.bfloat16])
def test_the_unets_inference_follows_its_weights(products):
    """The U-Net in inference runs layers kept with their weights folded and packed: a weight changed
    in place, a tensor or a module put in anew, or another products' dtype is followed, as a fresh
    network with the same weights answers."""
    import pickle

    from o3dvis.nn.conv import ConvBnRelu, OctreeDownsample as Down, products_in

    torch.manual_seed(1)
    network = VisibilityNetwork(NetworkConfig(channels=(16, 32, 48))).eval()
    points = torch.rand(3000, 3) * 2 - 1

    def agrees() -> None:
        fresh = VisibilityNetwork(network.config).eval()
        fresh.load_state_dict(network.state_dict())
        with torch.no_grad(), products_in(products):
            assert torch.equal(network.encode(points), fresh.encode(points))

    agrees()
    with torch.no_grad():
        network.unet.enc[1][0].a.conv.weight.mul_(1.5)
    agrees()
    network.unet.dec[0].b.bn.running_var = torch.rand_like(network.unet.dec[0].b.bn.running_var) + 0.5
    agrees()
    network.unet.down[0] = ConvBnRelu(network.unet.down[0].conv.in_channels, 16, Down).eval()
    agrees()
    with torch.no_grad(), products_in(torch.float32 if products == torch.bfloat16 else torch.bfloat16):
        network.encode(points)  # the other dtype, kept
    agrees()
    assert torch.equal(pickle.loads(pickle.dumps(network)).unet.head.weight, network.unet.head.weight)


@pytest.mark.parametrize("frequencies", [0, 1, 6])
@pytest.mark.parametrize("grad", [False, True])
def test_embedding_matches_direct_sinusoids(frequencies, grad):
    """Both the autograd path and the in-place one; (V, 3, N) batches of views too."""
    d = torch.nn.functional.normalize(torch.randn(2, 100, 3, dtype=torch.float64), dim=-1).requires_grad_(grad)
    emb = ViewEmbedding(frequencies)(d.transpose(-1, -2))  # channels first
    ref = [d] + [f(2**k * torch.pi * d) for k in range(frequencies) for f in (torch.sin, torch.cos)]
    assert emb.shape == (2, 3 + 6 * frequencies, 100) and emb.requires_grad == grad
    torch.testing.assert_close(emb, torch.cat(ref, dim=-1).transpose(-1, -2))


@pytest.mark.parametrize("grad", [False, True])
def test_predictor_equals_the_plain_mlp_on_the_concatenation(grad):
    torch.manual_seed(0)
    pred = VisibilityPredictor(8, num_frequencies=3, num_cues=5, hidden=(16, 12)).double()
    projected = torch.randn(2, 50, pred.embedding.dim, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(2, 50, 3, dtype=torch.float64), dim=-1).requires_grad_(grad)
    cues = torch.randn(2, 50, 5, dtype=torch.float64)
    emb = pred.embedding(dirs.transpose(-1, -2)).transpose(-1, -2)
    expected = pred.mlp(torch.cat([projected * emb, cues], dim=-1))
    with torch.set_grad_enabled(grad):
        torch.testing.assert_close(pred(projected, dirs, cues), expected)
        torch.testing.assert_close(pred.margin(projected, dirs, cues), expected[..., 1] - expected[..., 0])
        # one view's directions against features of two: broadcast, not written in place
        torch.testing.assert_close(pred(projected, dirs[0], cues[0]),
                                   pred.mlp(torch.cat([projected * emb[0], cues[0].expand(2, -1, -1)], dim=-1)))


def test_encode_projects_per_leaf_as_the_linear_layer_does_per_point():
    torch.manual_seed(0)
    net = VisibilityNetwork(NetworkConfig(depth=6)).double().eval()
    pn, _, _ = normalize_points(_sphere_with_bump().double())
    with torch.no_grad():
        octree = net.octree(pn)
        batch = torch.zeros(len(pn), dtype=torch.long)
        leaf = net.unet(net._signal(pn, batch, octree, None), octree)
        expected = net.predictor.project_feature(torch.cat([leaf[octree.point_leaf], pn], dim=1))
        torch.testing.assert_close(net.encode(pn), expected)


def test_encode_reuses_a_given_octree_of_its_depths():
    torch.manual_seed(0)
    net = VisibilityNetwork(NetworkConfig(depth=6)).eval()
    other = VisibilityNetwork(NetworkConfig(depth=6, use_normals=True)).eval()
    pn, _, _ = normalize_points(_sphere_with_bump())
    with torch.no_grad():
        shared = other.octree(pn)
        other.encode_leaves(pn, normals=torch.nn.functional.normalize(pn, dim=1), octree=shared)  # fills its tables
        torch.testing.assert_close(net.encode_leaves(pn, octree=shared).rows(), net.encode(pn))
        with pytest.raises(ValueError, match="depths 5/2 given to a network of depths 6/2"):
            net.encode_leaves(pn, octree=Octree(pn, depth=5))


def test_view_cues_flag_the_far_side_of_a_sphere():
    torch.manual_seed(0)
    p = torch.nn.functional.normalize(torch.randn(20000, 3), dim=1)
    cam = torch.tensor([3.0, 0.0, 0.0])
    dirs, cues = view_cues(p, cam)
    assert cues.shape == (20000, 36)
    torch.testing.assert_close(dirs, torch.nn.functional.normalize(p - cam, dim=1))
    visible = (p * (cam - p)).sum(1) > 0
    # residual to the own pixel (patch centre, index 4) at scale 2 (columns 9..17):
    # small in front, large behind, where the front surface covers every pixel
    own = cues[:, 9 + 4]
    assert own[visible].median() < 0.5 and own[~visible].median() > 2.0
    # the finest buffer has holes: many hidden points are alone in their pixel there
    assert (cues[~visible, 4] == 0).float().mean() > 0.2
    # an empty neighbour pixel is marked as such: the corners of the image are empty
    assert (cues == -5.0).any()


def test_view_cues_same_in_chunks_and_with_or_without_autograd(torch_ops):
    torch.manual_seed(0)
    p = torch.nn.functional.normalize(torch.randn(5000, 3), dim=1) * torch.rand(5000, 1)
    cam = torch.tensor([2.0, 1.0, -0.5], requires_grad=True)
    view = ViewProjection(p, cam)
    full = view.cues()
    assert full.shape == (5000, 36)
    full.sum().backward()  # the autograd path is differentiable end to end
    assert torch.isfinite(cam.grad).all()
    with torch.inference_mode():  # the in-place path
        fast = ViewProjection(p, cam.detach())
        chunks = torch.cat([fast.cues(slice(a, a + 1234)) for a in range(0, 5000, 1234)])
    torch.testing.assert_close(chunks, full.detach(), atol=1e-5, rtol=0)
    # an empty neighbour pixel gives exactly the empty cue on both paths (the in-place path maps it
    # to a residual beyond the clamp, whose asinh is that cue, so that no NaN reaches the asinh)
    empty = full.detach() == -5.0
    assert empty.any() and torch.equal(chunks == -5.0, empty)


def test_patch_table_rows_are_the_3x3_depth_neighbourhoods_of_the_pixels():
    torch.manual_seed(3)
    p = torch.nn.functional.normalize(torch.randn(700, 3), dim=1)
    view = ViewProjection(p, torch.tensor([0.5, 3.0, 1.0]))
    res = 27  # finest side: ceil(sqrt(700))
    pixel = view.pixels[:, 0]
    zbuf = torch.full(((res + 2) ** 2,), float("inf"))
    iu, iv = pixel // res, pixel % res
    zbuf = zbuf.scatter_reduce(0, (iu + 1) * (res + 2) + iv + 1, view.depth, "amin").view(res + 2, res + 2)
    zbuf[torch.isinf(zbuf)] = float("nan")  # empty or off the image
    for k in range(9):
        du, dv = divmod(k, 3)
        torch.testing.assert_close(view.patches[pixel, k], zbuf[iu + du, iv + dv], equal_nan=True)


def _grid_plane(side: int, z: float, extent: float = 0.9) -> torch.Tensor:
    """A side x side grid of points on the plane at ``z``, ``2 extent / (side - 1)`` apart."""
    t = torch.linspace(-extent, extent, side)
    u, v = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([u.flatten(), v.flatten(), torch.full((side * side,), z)], dim=1)


@pytest.mark.parametrize("side", [40, 120])
def test_point_surfels_of_a_grid(side):
    """Cell counts give the distance between neighbours of a plane's grid within a factor of 1.5,
    and a plane twice as dense gets half the spacing (one plane alone: the cube holds it); the
    cells' planes give the plane's normal, up to its sign."""
    points = _grid_plane(side, 0.1)
    surfels = point_surfels(points)
    spacing, normals = surfels[:, 0], surfels[:, 1:]
    true = 1.8 / (side - 1)
    assert surfels.shape == (side * side, 4)
    assert true / 1.5 < spacing.median() < true * 1.5
    assert point_surfels(_grid_plane(2 * side, 0.1))[:, 0].median() < 0.7 * spacing.median()
    inner = points[:, :2].abs().amax(dim=1) < 0.75  # border cells may hold one row of points: no plane
    torch.testing.assert_close(normals[inner, 2].abs(), torch.ones(int(inner.sum())), atol=1e-4, rtol=0)
    order = torch.randperm(len(points), generator=torch.Generator().manual_seed(0))  # unsorted: sorted inside
    shuffled = point_surfels(points[order])
    torch.testing.assert_close(shuffled[:, 0], spacing[order])
    torch.testing.assert_close((shuffled[:, 1:] * normals[order]).sum(dim=1).abs(), torch.ones(len(points)))


def test_area_spacing_of_a_strip_that_crosses_its_cells_in_part():
    """Two rows of grid points 0.02 apart: too few in the cells of their own size, they take cells
    several rows wide, whose side over the square root of their count overstates the spacing about
    twice; the spread of the points gives it (within 10 %), in C as in torch."""
    u, v = torch.meshgrid(torch.arange(-0.5, 0.5, 0.02), torch.tensor([0.3, 0.32]), indexing="ij")
    points = torch.stack([u.flatten(), v.flatten(), torch.zeros(u.numel())], dim=1)
    points = torch.cat([points, torch.tensor([[-0.99, -0.99, -0.99], [0.99, 0.99, 0.99]])])  # the cube's corners
    expected = point_surfels(points, areas=True)
    with torch.inference_mode():  # the C kernel, where built
        kernel = point_surfels(points, areas=True)
    for surfels in (expected, kernel):
        assert surfels.shape == (len(points), 5)
        torch.testing.assert_close(surfels[:, :4], point_surfels(points))
        strip = surfels[:-2]
        assert strip[:, 0].min() > 1.5 * 0.02 and (strip[:, 4] - 0.02).abs().max() < 0.002
    torch.testing.assert_close(kernel[:, 4], expected[:, 4], rtol=1e-4, atol=1e-7)


def _slanted_plane(side: int, extent: float, slope: float) -> torch.Tensor:
    """A side x side grid of points on the plane z = 0.5 + slope * x."""
    points = _grid_plane(side, 0.5, extent)
    points[:, 2] += slope * points[:, 0]
    return points


@pytest.mark.parametrize("slope", [0.0, 1.5])
def test_footprints_close_the_holes_of_a_near_sparse_surface(slope, torch_ops):
    """A sparse plane close to the camera in front of a dense far plane: in the finest buffer the
    far plane shows through the gaps between the near points, so most far points see only their own
    depth around them; in the splatted finest buffer the near plane covers them. The splat is the
    near plane itself, so also when it is slanted its own points lie on it, not behind it. The
    buffers of the other scales stay as they were."""
    near, far = _slanted_plane(30, 0.3, slope), _grid_plane(150, -0.5, 0.3)
    points = torch.cat([near, far])
    camera = torch.tensor([0.0, 0.0, 0.9 + 0.3 * slope])
    plain = ViewProjection(points, camera).cues()
    view = ViewProjection(points, camera, surfels=point_surfels(points))
    cues = view.cues()
    assert plain.shape == (len(points), 36) and cues.shape == (len(points), 63)
    torch.testing.assert_close(cues[:, :36], plain)
    behind = far[:, 0].abs().lt(0.2) & far[:, 1].abs().lt(0.2)  # far points behind the near plane
    centre = 4  # the point's own pixel in the 3x3 patch
    own_plain, own_splat = plain[len(near):, centre][behind], cues[len(near):, 36 + centre][behind]
    assert (own_plain.abs() < 0.1).float().mean() > 0.5  # the far point is the nearest in its pixel
    assert (own_splat > 2.0).float().mean() > 0.95  # the near plane lies in front of it
    # a near point's own pixel holds its own plane, within 1.5 pixel footprints (a splat at the
    # point's own depth leaves 60 % of the slanted plane's points behind it by more)
    assert cues[:len(near), 36 + centre].abs().max() < math.asinh(1.5)


def test_view_cues_orthographic_direction():
    p = torch.nn.functional.normalize(torch.randn(5000, 3), dim=1)
    dirs, cues = view_cues(p, direction=torch.tensor([-1.0, 0.0, 0.0]))
    assert torch.equal(dirs, torch.tensor([-1.0, 0.0, 0.0]).expand(5000, 3))
    visible = p[:, 0] > 0
    own = cues[:, 9 + 4]
    assert own[visible].median() < 0.5 and own[~visible].median() > 2.0


def _sphere_with_bump(n=3000, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    return p * (1 + 0.3 * (p[:, :1] > 0.7))


@pytest.mark.parametrize("use_normals, with_noise_cues", [(False, False), (True, False), (False, True)])
def test_network_invariant_to_order_translation_and_scale(use_normals, with_noise_cues):
    torch.manual_seed(0)
    net = VisibilityNetwork(NetworkConfig(depth=6, use_normals=use_normals, noise_cues=with_noise_cues)).eval()
    pts = _sphere_with_bump().double()
    normals = torch.nn.functional.normalize(pts, dim=1).float() if use_normals else None
    cam = torch.tensor([2.5, 1.0, 0.5], dtype=torch.float64)

    def probs(points, camera, nrm):
        pn, c, s = normalize_points(points)
        with torch.no_grad():
            f = net.encode(pn.float(), normals=nrm)
            return net.predict(f, pn.float(), ((camera - c) / s).float(), normals=nrm).softmax(1)[:, 1]

    base = probs(pts, cam, normals)
    perm = torch.randperm(len(pts))
    shuffled = probs(pts[perm], cam, None if normals is None else normals[perm])
    torch.testing.assert_close(shuffled, base[perm], atol=1e-4, rtol=0)
    moved = probs(pts * 3.7 + torch.tensor([10.0, -4.0, 2.0], dtype=torch.float64),
                  cam * 3.7 + torch.tensor([10.0, -4.0, 2.0], dtype=torch.float64), normals)
    torch.testing.assert_close(moved, base, atol=1e-4, rtol=0)


def test_gradient_reaches_camera_and_all_parameters():
    net = VisibilityNetwork(NetworkConfig(depth=6))
    pts = _sphere_with_bump()
    pn, _, _ = normalize_points(pts)
    cam = torch.tensor([2.0, 0.5, 0.3], requires_grad=True)
    f = net.encode(pn)
    net.predict(f, pn, cam).log_softmax(1)[:, 1].sum().backward()
    assert cam.grad is not None and torch.isfinite(cam.grad).all() and cam.grad.abs().sum() > 0
    assert all(p.grad is not None for p in net.parameters())


def test_config_reads_retired_options_at_their_one_value():
    """Checkpoints of earlier versions name interpolation, plane_cues and extra: at the value every
    shipped model has they are read and dropped; any other value is refused, not ignored."""
    old = {"depth": 6, "interpolation": "nearest", "plane_cues": False, "extra": {}}
    assert NetworkConfig.from_dict(old) == NetworkConfig(depth=6)
    for key, value in (("interpolation", "trilinear"), ("plane_cues", True), ("extra", {"a": 1})):
        with pytest.raises(ValueError, match=key):
            NetworkConfig.from_dict({**old, key: value})


def test_checkpoint_roundtrip(tmp_path):
    net = VisibilityNetwork(NetworkConfig(depth=6, channels=(8, 16, 16, 16, 16), num_frequencies=3))
    net.save(tmp_path / "m.safetensors", {"step": 7})
    again = VisibilityNetwork.load(tmp_path / "m.safetensors")
    assert again.config == net.config
    for a, b in zip(net.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)


def test_training_smoke_loss_falls(tmp_path):
    """A few steps on tiny procedural data: the loss must fall."""
    from o3dvis.training.data.prepare import label_mesh
    from o3dvis.training.data.sample import save_sample
    from o3dvis.training.data.shapes import write_shapes
    from o3dvis.training.train import TrainConfig, train

    meshes = write_shapes(str(tmp_path / "meshes"), 3, seed=5)
    data = tmp_path / "data"
    data.mkdir()
    for m in meshes:
        s = label_mesh(m, num_points=3000, num_views=8)
        save_sample(s, data / f"{s.name}.npz")
    torch.manual_seed(0)
    cfg = TrainConfig(data=[str(data)], out=str(tmp_path / "run"), steps=40, batch_size=2, lr=3e-3,
                      warmup=5, val_every=1000, log_every=5, network={"depth": 6},
                      augmentation={"min_points": 1500, "max_points": 3000, "views": 4, "noise": 0})
    train(cfg, progress=False)
    log = [__import__("json").loads(line) for line in open(tmp_path / "run" / "log.jsonl")]
    losses = [r["loss"] for r in log if "loss" in r]
    assert len(losses) == 8 and np.mean(losses[-2:]) < 0.8 * np.mean(losses[:2])


def test_training_with_footprints_finds_each_clouds_surfels_once(tmp_path, monkeypatch):
    """Training and validation of a network with footprints run, and each cloud's surfels are
    found once for all its views."""
    from o3dvis.nn import network as network_module
    from o3dvis.training.data.prepare import label_mesh
    from o3dvis.training.data.sample import save_sample
    from o3dvis.training.data.shapes import write_shapes
    from o3dvis.training.train import TrainConfig, train

    data = tmp_path / "data"
    data.mkdir()
    for m in write_shapes(str(tmp_path / "meshes"), 2, seed=3):
        s = label_mesh(m, num_points=2000, num_views=4)
        save_sample(s, data / f"{s.name}.npz")
    found = []
    monkeypatch.setattr(network_module, "point_surfels",
                        lambda points, find=network_module.point_surfels: found.append(len(points)) or find(points))
    cfg = TrainConfig(data=[str(data)], out=str(tmp_path / "run"), val=str(data), steps=2, batch_size=2,
                      val_every=2, val_points=1000, val_views=3, network={"depth": 6, "footprints": True},
                      augmentation={"min_points": 1000, "max_points": 2000, "views": 3, "noise": 0})
    train(cfg, progress=False)
    assert len(found) == 2 * 2 + 2  # two steps of two clouds, then two validation files
    assert found[-2:] == [1000, 1000]


@pytest.mark.parametrize("added", [{"use_normals": True}, {"noise_cues": True}])
def test_warm_start_with_added_inputs_keeps_the_function(added, torch_ops):
    from o3dvis.training.train import warm_start

    torch.manual_seed(0)
    small = dict(depth=6, channels=(8, 16, 16, 16, 16))
    source = VisibilityNetwork(NetworkConfig(**small))
    for p in source.parameters():  # non-trivial BN statistics and weights
        p.data.normal_()
    for m in source.modules():
        if isinstance(m, torch.nn.BatchNorm1d):
            m.running_mean.normal_()
            m.running_var.uniform_(0.5, 2)
    target = VisibilityNetwork(NetworkConfig(**small, **added))
    warm_start(target, source.state_dict())
    source.eval(), target.eval()
    pn, _, _ = normalize_points(_sphere_with_bump())
    normals = torch.nn.functional.normalize(torch.randn_like(pn), dim=1) if target.config.use_normals else None
    cam = torch.tensor([2.0, 0.5, 0.3])
    with torch.no_grad():
        a = source.predict(source.encode(pn), pn, cam)
        b = target.predict(target.encode(pn, normals=normals), pn, cam, normals=normals)
    torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def _noisy_sphere(n, noise, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    return normalize_points(p + noise * torch.randn(n, 3, generator=g, dtype=torch.float64))[0]


def test_noise_cues_grow_with_noise_and_ignore_order():
    cues = torch.stack([noise_cues(_noisy_sphere(40_000, s)) for s in (0.0, 0.003, 0.01)])
    assert (cues[1:] > cues[:-1]).all(), cues
    assert cues[0].max() < 0.05  # a smooth surface is thin and flat at this density
    p = _noisy_sphere(40_000, 0.003)
    torch.testing.assert_close(noise_cues(p[torch.randperm(len(p))]), noise_cues(p), atol=1e-6, rtol=0)
    # points already in Morton order (as a VisibilityField stores them) need no sort: the same cues
    torch.testing.assert_close(noise_cues(p[morton_order(p)], ordered=True), noise_cues(p), atol=1e-6, rtol=0)
    shuffled = noise_cues(p[torch.randperm(len(p))], ordered=True)  # the flag is believed: runs of far points
    assert shuffled[1] > 2 * noise_cues(p)[1]


def test_noise_cues_do_not_depend_on_the_block_size(monkeypatch):
    """The torch ops sum the cell moments over blocks of rows: blocks of 1 000 give the one-block sums."""
    import o3dvis.nn.noise as noise

    monkeypatch.setattr(noise.native, "available", lambda: False)
    p = _noisy_sphere(40_000, 0.003)
    whole = noise_cues(p)
    monkeypatch.setattr(noise, "_BLOCK", 1_000)
    torch.testing.assert_close(noise_cues(p), whole, atol=1e-6, rtol=0)


def _cell_thickness_by_torch(p: torch.Tensor) -> torch.Tensor:
    """Each full cell's thickness term as the C kernel computes it (offsets and their products in
    float32, sums in float64), by torch ops, with eigvalsh: in the cells' order."""
    import o3dvis.nn.noise as noise

    res = 1 << noise._LEVEL
    c = octree_module.grid_cells(p, noise._LEVEL)
    cell = (c[:, 0] * res + c[:, 1]) * res + c[:, 2]
    q = p - ((c + 0.5) * (2 / res) - 1)
    products = torch.stack([q[:, i] * q[:, j] for i, j in noise._PAIRS] + list(q.unbind(1)), dim=1).double()
    m = torch.zeros(res ** 3, 9, dtype=torch.float64).index_add_(0, cell, products)
    count = torch.bincount(cell, minlength=res ** 3)
    full = torch.nonzero(count >= noise._MIN_COUNT).squeeze(1)
    m, n = m[full].T, count[full].double()
    cov = m.new_zeros(len(full), 3, 3)
    for k, (i, j) in enumerate(noise._PAIRS):
        cov[:, i, j] = m[k] / n - (m[6 + i] / n) * (m[6 + j] / n)
    return noise._eigenvalues(cov)[:, 0].sqrt() * n.sqrt() * (res / 2)


@pytest.mark.skipif(not native.available(), reason="the C kernels are not built")
def test_native_patch_terms_match_the_torch_eigenvalues(monkeypatch):
    """The cells' thickness and the runs' flatness by C (sums along the Morton curve, eigenvalues in
    closed form) against eigvalsh on the same sums by torch ops: equal to a few ulps of the largest
    eigenvalue, on noisy patches and on degenerate ones (a plane, a line, one point, a cube's
    corners of equal eigenvalues, a sheet 1e-6 thick); the cues from unordered points are those
    of the ordered ones, and close to the torch path's (sums in float32)."""
    import o3dvis.nn.noise as noise

    p = _noisy_sphere(30_000, 0.003).float()
    p[:5] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 1.0, 0.0], [0.5, -0.5, 1.0]])
    ordered = p[morton_order(p)].contiguous()
    got = native.cell_thickness(ordered, noise._LEVEL, noise._MIN_COUNT)
    expected = _cell_thickness_by_torch(p)
    assert len(got) == len(expected) > 100
    torch.testing.assert_close(got.sort().values, expected.sort().values, rtol=1e-6, atol=1e-9)
    g = torch.Generator().manual_seed(1)
    flat = torch.rand(16, 3, generator=g)
    patches = [ordered[:16], flat * torch.tensor([1.0, 1.0, 0.0]), flat * torch.tensor([1.0, 0.0, 0.0]),
               torch.zeros(16, 3), torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0)
                                                 for z in (-1.0, 1.0)] * 2),
               flat * torch.tensor([1.0, 1.0, 1e-6])]
    runs = torch.cat(patches).contiguous()
    got = native.run_flatness(runs, torch.arange(0, len(runs), 16), 16)
    x = runs.double().view(-1, 16, 3)
    x = x - x.mean(dim=1, keepdim=True)
    eig = noise._eigenvalues(torch.einsum("rki,rkj->rij", x, x))
    want = (eig[:, 0] / eig[:, 1].clamp_min(torch.finfo(torch.float64).tiny)).sqrt()
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-7)
    assert got[4] == 1.0 and got[3] == 0.0 and got[2] == 0.0
    assert torch.equal(noise_cues(p), noise_cues(ordered, ordered=True))
    monkeypatch.setattr(noise.native, "available", lambda: False)
    torch.testing.assert_close(noise_cues(ordered, ordered=True), noise_cues(p), atol=1e-5, rtol=1e-3)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="runs of 16 points"):
        native.run_flatness(runs, torch.tensor([len(runs) - 8]), 16)
    with pytest.raises(ValueError, match="level"):
        native.cell_thickness(ordered, 11, 8)
    with pytest.raises(ValueError, match="points"):
        native.cell_thickness(ordered.double(), 5, 8)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_noise_cues_lower_quartile_is_torch_quantile_to_the_bit(dtype):
    """The cues' lower quartile by two selections equals torch.quantile's sort and interpolation,
    value for value, with ties, at ranks between two values and on them, and NaN where one is."""
    from o3dvis.nn.noise import _quartile

    g = torch.Generator().manual_seed(3)
    for n in [*range(1, 40), 1001, 2048, 5000]:
        values = torch.rand(n, generator=g, dtype=dtype) ** 3
        values[::5] = values[0]
        assert torch.equal(_quartile(values), torch.quantile(values, 0.25)), n
    values[7] = float("nan")
    assert _quartile(values).isnan() and torch.quantile(values, 0.25).isnan()


def test_noise_cues_of_clouds_too_small_to_measure_are_zero():
    assert torch.equal(noise_cues(_noisy_sphere(10, 0.01)), torch.zeros(2, dtype=torch.float64))


def test_noise_cues_are_per_cloud_in_a_batch():
    torch.manual_seed(0)
    net = VisibilityNetwork(NetworkConfig(depth=6, noise_cues=True)).double().eval()
    clouds = [_noisy_sphere(3000, 0.0, seed=1), _noisy_sphere(5000, 0.01, seed=2)]
    batch = torch.cat([torch.full((len(c),), i) for i, c in enumerate(clouds)])
    with torch.no_grad():
        together = net.encode(torch.cat(clouds), batch, batch_size=2)
        alone = torch.cat([net.encode(c) for c in clouds])
    torch.testing.assert_close(together, alone)
