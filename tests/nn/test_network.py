"""The visibility network (``o3dvis.nn.network``): per-leaf encodings, a shared octree, invariance to
order, translation and scale, gradients, its config and checkpoints."""

import pytest
import torch

from o3dvis.nn import NetworkConfig, Octree, VisibilityNetwork, normalize_points

from conftest import _sphere_with_bump


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
