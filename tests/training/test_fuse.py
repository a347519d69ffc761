"""The surfel z-buffer (native and torch), its fusion with the network, the fused field and ``o3dvis fuse``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from o3dvis.neural import NeuralVisibility
from o3dvis.nn import native
from o3dvis.nn.cues import point_surfels
from o3dvis.nn.fusion import NUM_FUSION_INPUTS, ZBufferFusion, fusion_inputs, zbuffer_inputs
from o3dvis.nn.network import NetworkConfig, VisibilityNetwork
from o3dvis.nn.octree import normalize_points
from o3dvis.nn.zbuffer import _surfel_zbuffer_torch, buffer_rows, surfel_zbuffer

from conftest import box_surface

SMALL = dict(depth=6, channels=(8, 16, 16, 16, 16), footprints=True)
WALL = 2.5  # a partition 0.3 thick across the room's length at x = 2.5, closed from floor to ceiling


def _room(count: int = 12_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on the inner faces of a 6 x 4 x 3 room and on both faces of a full partition at
    ``x = WALL``, and whether each lies in the left half (x < WALL)."""
    rng = np.random.default_rng(seed)
    size = np.array([6.0, 4.0, 3.0])
    points = box_surface(np.zeros(3), size, count, rng)
    points = points[np.abs(points[:, 0] - WALL) > 0.15]  # none inside the partition
    wall = rng.random((count // 6, 3)) * size
    wall[:, 0] = WALL + np.where(rng.random(len(wall)) < 0.5, -0.15, 0.15)
    points = np.vstack([points, wall])
    return points, points[:, 0] < WALL


def _normalised(points: np.ndarray, camera: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    p, center, scale = normalize_points(torch.from_numpy(points))
    p = p.float()
    with torch.inference_mode():  # as a field computes them (with the C kernels, where built)
        surfels = point_surfels(p, areas=True)
    return p, surfels, ((torch.from_numpy(camera) - center) / scale).float()


def test_zbuffer_separates_the_halves_of_a_partitioned_room():
    points, left = _room()
    p, surfels, camera = _normalised(points, np.array([1.2, 1.5, 1.4]))
    answer = surfel_zbuffer(p, surfels, camera)
    seen = (answer[:, 0] > 0) | (answer[:, 1] <= 1)
    assert answer.shape == (len(points), 4) and answer.dtype == torch.float32
    assert seen[torch.from_numpy(left)].float().mean() > 0.97
    assert (~seen[~torch.from_numpy(left)]).float().mean() > 0.97  # behind the partition
    assert float(answer[~torch.from_numpy(left), 1].median()) > 5  # by many spacings
    assert 0.5 < float(answer[:, 2].median()) < 2  # about one pixel across a spacing


@pytest.mark.skipif(not native.available(), reason="the C kernels are not built")
def test_native_and_torch_zbuffers_agree():
    points, _ = _room(6000, seed=1)
    for camera in ([1.2, 1.5, 1.4], [4.0, 3.5, 0.3], [2.0, 2.0, 2.95]):  # the last right under the ceiling
        p, surfels, cam = _normalised(points, np.array(camera))
        rows = buffer_rows(p, surfels[:, 4], cam)
        a, b = surfel_zbuffer(p, surfels, cam), _surfel_zbuffer_torch(p, surfels, cam, rows)
        assert (a[:, 0] == b[:, 0]).float().mean() > 0.999
        assert torch.isclose(a[:, 1], b[:, 1], rtol=1e-3, atol=1e-3).float().mean() > 0.999
        torch.testing.assert_close(a[:, 2], b[:, 2], rtol=1e-4, atol=1e-6)


def _sphere(count: int = 3000) -> np.ndarray:
    g = np.random.default_rng(2)
    points = g.normal(size=(count, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def test_sphere_seen_from_its_centre_is_visible():
    """Every point of a sphere faces its centre: it lies on (or, for the plane fitted to its
    curved cell, just beyond) the front disc at its pixel."""
    p, surfels, cam = _normalised(_sphere(), np.zeros(3))
    answer = surfel_zbuffer(p, surfels, cam)
    assert ((answer[:, 0] > 0) | (answer[:, 1] <= 1)).float().mean() > 0.9


@pytest.mark.skipif(not native.available(), reason="the C kernels are not built")
def test_coarse_buffer_wraps_around_the_poles_alike():
    """In a 16 x 32 buffer the discs near the poles span whole circles of latitude: each pixel once,
    in C as in torch."""
    p, surfels, cam = _normalised(_sphere(), np.zeros(3))
    a, b = surfel_zbuffer(p, surfels, cam, 16), _surfel_zbuffer_torch(p, surfels, cam, 16)
    assert torch.isfinite(a).all() and (a[:, 0] == b[:, 0]).float().mean() > 0.999
    assert torch.isclose(a[:, 1], b[:, 1], rtol=1e-3, atol=1e-3).float().mean() > 0.999


@pytest.mark.skipif(not native.available(), reason="the C kernels are not built")
def test_native_zbuffer_checks_its_arguments():
    points, _ = _room(600)
    p, surfels, cam = _normalised(points, np.array([1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="rows"):
        native.surfel_zbuffer(p, surfels, cam, 0, 12, 48, 1000.0)
    with pytest.raises(ValueError, match="surfels"):
        native.surfel_zbuffer(p, surfels[:, :4].contiguous(), cam, 64, 12, 48, 1000.0)


def test_fusion_inputs_and_folded_standardisation():
    margin = torch.tensor([40.0, -2.0])
    zbuffer = torch.tensor([[1.0, 0.0, 1.0, 0.9], [0.0, 16.0, 0.5, 0.2]])
    noise = torch.tensor([0.1, 0.2])
    x = fusion_inputs(margin, zbuffer_inputs(zbuffer), noise)
    assert x.shape == (2, NUM_FUSION_INPUTS)
    torch.testing.assert_close(x[:, 0], torch.tensor([15.0, -2.0]))  # clamped margins
    torch.testing.assert_close(x[:, 1], torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(x[1, 2:4], torch.tanh(torch.tensor([8.0, 2.0])))
    torch.testing.assert_close(x[:, 4], torch.log(torch.tensor([1.0, 0.5])))
    torch.testing.assert_close(x[:, 5], torch.tensor([0.9, 0.2]))
    torch.testing.assert_close(x[:, 6:], torch.tensor([[0.1, 0.2], [0.1, 0.2]]))
    fusion = _random_fusion()
    by_hand = fusion.mlp((x - fusion.mean) / fusion.std)[:, 0]
    torch.testing.assert_close(fusion(margin, zbuffer_inputs(zbuffer), noise), by_hand)


def _random_fusion(seed: int = 0) -> ZBufferFusion:
    torch.manual_seed(seed)
    fusion = ZBufferFusion()
    fusion.mean.copy_(torch.randn(NUM_FUSION_INPUTS))
    fusion.std.copy_(torch.rand(NUM_FUSION_INPUTS) + 0.5)
    return fusion


def _pairs(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Margins and z-buffer answers over their whole ranges: margins past the clamp, distances
    beyond from -1000 to 1000, spacings down to 0 (below the log's floor)."""
    g = torch.Generator().manual_seed(seed)
    zbuffer = torch.stack([(torch.rand(n, generator=g) < 0.5).float(),
                           torch.randn(n, generator=g) * 10 ** torch.randint(-3, 4, (n,), generator=g),
                           torch.rand(n, generator=g) * 4, torch.rand(n, generator=g)], dim=1)
    zbuffer[:8, 1] = torch.tensor([0.0, 1e-3, -1e-3, 0.125, -0.5, 1000.0, -1000.0, 80.0])
    zbuffer[:4, 2] = torch.tensor([0.0, 1e-7, 1e-6, 1e-5])
    return torch.randn(n, generator=g) * 12, zbuffer


@pytest.mark.skipif(not native.available(), reason="the C kernels are not built")
def test_native_fusion_matches_the_torch_ops():
    fusion, noise = _random_fusion(), torch.tensor([0.3, 0.05])
    margin, zbuffer = _pairs(5000)
    expected = fusion(margin, zbuffer_inputs(zbuffer), noise)
    with torch.inference_mode():
        fuse = fusion.bind(noise)
        chunk = slice(1000, 4000)
        m = margin[chunk].clone()
        assert fuse(m, zbuffer, chunk) is m  # in place
        torch.testing.assert_close(m, expected[chunk], atol=2e-5, rtol=1e-5)
        rows = torch.randperm(5000)[:700]
        torch.testing.assert_close(fuse(margin[rows].clone(), zbuffer, rows), expected[rows], atol=2e-5, rtol=1e-5)
    # with autograd on, the torch ops: the margins keep their gradient
    m = margin[:10].clone().requires_grad_()
    fused = fusion.bind(noise)(m, zbuffer, slice(0, 10))
    assert fused.requires_grad and fused.data_ptr() != m.data_ptr()
    torch.testing.assert_close(fused.detach(), expected[:10])


@pytest.mark.skipif(not native.available(), reason="the C kernels are not built")
def test_native_fusion_checks_its_arguments():
    margin, zbuffer = _pairs(100)
    mlp = native.pack_mlp([(torch.randn(16, 6), torch.randn(16)), (torch.randn(1, 16), torch.randn(1))],
                          torch.float32)
    out = torch.empty(100)
    with pytest.raises(ValueError, match="zbuffer"):
        native.fuse_margin(slice(0, 100), zbuffer[:, :3].contiguous(), margin, mlp, out)
    with pytest.raises(ValueError, match="margin"):
        native.fuse_margin(slice(0, 100), zbuffer, margin[:50], mlp, out)
    with pytest.raises(IndexError, match="rows"):
        native.fuse_margin(torch.tensor([0, 100]), zbuffer, margin[:2].contiguous(), mlp, out[:2])
    wrong = native.pack_mlp([(torch.randn(16, 8), torch.randn(16)), (torch.randn(1, 16), torch.randn(1))],
                            torch.float32)
    with pytest.raises(ValueError, match="6 inputs"):
        native.fuse_margin(slice(0, 100), zbuffer, margin, wrong, out)
    with pytest.raises(ValueError, match="float32"):
        native.fuse_margin(slice(0, 100), zbuffer, margin, native.pack_mlp(
            [(torch.randn(16, 6), torch.randn(16)), (torch.randn(1, 16), torch.randn(1))], torch.bfloat16), out)


def _fused_pair(seed: int = 0) -> tuple[VisibilityNetwork, VisibilityNetwork]:
    torch.manual_seed(seed)
    plain = VisibilityNetwork(NetworkConfig(**SMALL)).eval()
    fused = VisibilityNetwork(NetworkConfig(**SMALL, fusion=True)).eval()
    fused.load_state_dict({**plain.state_dict(), **{f"fusion.{k}": v for k, v in fused.fusion.state_dict().items()}})
    return plain, fused


def test_field_fuses_camera_views_and_keeps_directions(tmp_path):
    plain, fused = _fused_pair()
    path = tmp_path / "fused.safetensors"
    fused.save(path)
    loaded = VisibilityNetwork.load(path)
    assert loaded.config.fusion
    points, _ = _room(4000)
    cameras = np.array([[1.2, 1.5, 1.4], [4.5, 2.0, 2.0]])
    before = NeuralVisibility(plain).encode(points)
    field = NeuralVisibility(loaded).encode(points)
    after = field.probabilities(cameras).double()
    # by hand: the plain margins and the z-buffer of each camera, in the cloud's order
    p = before.probabilities(cameras).double()
    margin = (torch.log(p) - torch.log1p(-p)).float()
    rank = torch.arange(len(points)) if field.rank is None else field.rank
    with torch.inference_mode():  # as the field computes them (with the C kernels, where built)
        surfels = point_surfels(field.points, areas=True)
    for j, camera in enumerate(cameras):
        cam = field.frame.to_unit(torch.from_numpy(camera)).float()
        answers = surfel_zbuffer(field.points, surfels, cam)[rank]
        expected = torch.sigmoid(loaded.fusion(margin[j], zbuffer_inputs(answers), field.noise)).double()
        keep = p[j].sub(0.5).abs() < 0.49  # away from float32 saturation of the plain margins
        torch.testing.assert_close(after[j][keep], expected[keep], atol=2e-4, rtol=0)
    assert (after != p).float().mean() > 0.9
    direction = np.array([[0.0, 1.0, 0.0]])  # no camera position: the network's answer
    torch.testing.assert_close(field.probabilities(direction=direction), before.probabilities(direction=direction))


def test_fused_field_is_differentiable_in_the_camera():
    _, fused = _fused_pair(1)
    points, _ = _room(3000)
    field = NeuralVisibility(fused).encode(points)
    camera = torch.tensor([[1.2, 1.5, 1.4]], dtype=torch.float64, requires_grad=True)
    field.probabilities(camera).sum().backward()
    assert camera.grad is not None and torch.isfinite(camera.grad).all() and camera.grad.abs().sum() > 0


def test_fit_fusion_learns_from_the_zbuffer():
    from o3dvis.training.fuse import fit_fusion

    g = torch.Generator().manual_seed(0)
    n = 40_000
    beyond = torch.randn(n, generator=g) * 6
    zbuffer = torch.stack([(beyond.abs() < 0.3).float(), beyond, torch.rand(n, generator=g) + 0.5,
                           torch.rand(n, generator=g)], dim=1)
    labels = (beyond < 1).float()
    margins = torch.randn(n, generator=g)  # a network that knows nothing
    noise = torch.rand(n, 2, generator=g)
    fusion, before, after = fit_fusion(margins, zbuffer, noise, labels, steps=300, batch_size=4096)
    assert after < 0.2 < before
    assert ((fusion(margins, zbuffer_inputs(zbuffer), noise) > 0).float() == labels).float().mean() > 0.97


def test_fuse_command_writes_a_fused_network(tmp_path, monkeypatch):
    from o3dvis.training.data.prepare import prepare_scenes
    from o3dvis.training.fuse import fuse

    data = tmp_path / "scenes"
    prepare_scenes(data, 2, None, num_points=3000, num_views=8, progress=False)
    _, fused = _fused_pair(2)
    ckpt = tmp_path / "net.safetensors"
    fused.save(ckpt)  # a fusion it has is refitted
    out = tmp_path / "fused.safetensors"
    monkeypatch.chdir(tmp_path)
    summary = fuse(ckpt, [data], out, clouds=3, keep=1000, min_points=1500, max_points=3000, steps=50,
                   hidden=8, progress=False)
    net = VisibilityNetwork.load(out)
    assert net.config.fusion and net.config.fusion_hidden == 8 and net.fusion.mlp[0].out_features == 8
    assert summary["samples"] == 3 * 1000
    assert summary["cross_entropy_after"] < summary["cross_entropy_before"]  # an untrained network's margins
    assert summary["data"] == ["scenes"] and summary["checkpoint"] == "net.safetensors"
    with pytest.raises(ValueError, match="positive"):
        fuse(ckpt, [data], out, clouds=0)
    with pytest.raises(ValueError, match="fusion_hidden"):  # wider than the C kernel takes
        fuse(ckpt, [data], out, hidden=129)


def test_config_fusion_must_be_a_flag():
    with pytest.raises(ValueError, match="fusion"):
        NetworkConfig(fusion=1)


def test_without_drops_a_fitted_part_only():
    plain, fused = _fused_pair(3)
    stripped = fused.without("fusion")
    assert stripped.fusion is None and not stripped.config.fusion
    for name, value in plain.state_dict().items():
        torch.testing.assert_close(stripped.state_dict()[name], value)
    assert plain.without("fusion") is plain and fused.without("calibrated") is fused
    with pytest.raises(ValueError, match="option"):
        fused.without("footprints")


def test_warm_start_drops_a_fusion():
    """Training from a fused scene model (the GPU command's --init) starts from its network; its
    fusion, fitted to the margins training changes, is left to o3dvis fuse."""
    from o3dvis.training.train import warm_start

    plain, fused = _fused_pair(4)
    target = VisibilityNetwork(NetworkConfig(**SMALL)).eval()
    warm_start(target, fused.state_dict())
    for name, value in plain.state_dict().items():
        torch.testing.assert_close(target.state_dict()[name], value)
