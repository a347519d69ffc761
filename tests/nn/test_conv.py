"""Sparse octree convolutions (``o3dvis.nn.conv``) against dense 3-D convolutions on a full grid,
gradients, bfloat16 products, the batch norm folded in inference."""

import pytest
import torch
import torch.nn.functional as F

from o3dvis.nn import Octree, OctreeConv, OctreeDownsample, OctreeUpsample


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
