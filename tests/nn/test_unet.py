"""The octree U-Net (``o3dvis.nn.unet``): its inference follows its weights."""

import pytest
import torch

from o3dvis.nn import NetworkConfig, VisibilityNetwork


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
