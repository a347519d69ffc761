"""The visibility model (``o3dvis.neural``) on a small random network: invariance to point order,
translation and scale at each precision, averaged rotations, the network chosen for a cloud (small
model, normals model), tiny and planar clouds, and bad clouds and settings."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis.geometry import fixed_rotations
from o3dvis.nn import NetworkConfig, VisibilityNetwork

from conftest import SMALL, _camera, _pinhole


@pytest.fixture(scope="module")
def vis(small_vis):
    """The small random network's model here, not the shipped one."""
    return small_vis


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error without CUDA")
def test_cuda_without_cuda_is_a_clear_error(network, pcd, points):
    with pytest.raises(ValueError, match="CUDA"):
        o3dvis.hidden_point_removal_neural(pcd, _camera(points), model=network, device="cuda")
    with pytest.raises(ValueError, match="unknown torch device"):
        o3dvis.NeuralVisibility(network, device="gpu0")


# (precision, tolerance): bfloat16 products round the float32 differences of the inputs to their
# own 8-bit mantissas, so their answers move by up to a few thousandths
PRECISION_TOLERANCE = [("float32", 1e-4), ("bfloat16", 5e-3)]


@pytest.mark.parametrize("precision, tol", PRECISION_TOLERANCE)
def test_invariant_to_point_order(network, points, precision, tol):
    vis = o3dvis.NeuralVisibility(network, precision=precision)
    camera = _camera(points, (1.0, -1.0, 0.5))
    perm = np.random.default_rng(2).permutation(len(points))
    a = vis.encode(points).probabilities(camera)[0]
    b = vis.encode(points[perm]).probabilities(camera)[0]
    torch.testing.assert_close(b, a[perm], atol=tol / 10, rtol=tol / 10)


@pytest.mark.parametrize("precision, tol", PRECISION_TOLERANCE)
@pytest.mark.parametrize("scale, offset", [(3.7, (10.0, -2.0, 5.0)), (1e-3, (1e6, 1e6, -1e6)),
                                           (250.0, (0, 0, 0))])
def test_invariant_to_translation_and_uniform_scale(network, points, scale, offset, precision, tol):
    vis = o3dvis.NeuralVisibility(network, precision=precision)
    camera = _camera(points, (-1.0, 0.3, 0.8))
    a = vis.encode(points).probabilities(camera)
    moved = points * scale + np.asarray(offset)
    b = vis.encode(moved).probabilities(camera * scale + np.asarray(offset))
    torch.testing.assert_close(b, a, atol=tol, rtol=tol)


def test_precision_auto_and_bad_values(network):
    from o3dvis.nn.predictor import resolve_precision

    assert resolve_precision("float32", torch.device("cpu")) == torch.float32
    assert resolve_precision("bfloat16", torch.device("cpu")) == torch.bfloat16
    assert resolve_precision("auto", torch.device("meta")) == torch.float32  # never off a CPU
    native = torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported()
    assert resolve_precision("auto", torch.device("cpu")) == (torch.bfloat16 if native else torch.float32)
    for bad in ("half", "fp32", None):
        with pytest.raises(ValueError, match="precision must be one of auto, float32, bfloat16"):
            o3dvis.NeuralVisibility(network, precision=bad)


def test_rotations_average_the_network_over_rotated_copies(network, points):
    """num_rotations=K answers the mean of the plain answers for the cloud and cameras turned
    by each fixed rotation about the cloud's centre, whatever the camera form."""
    rng = np.random.default_rng(5)
    cameras = np.stack([_camera(points, d) for d in rng.normal(size=(3, 3))])
    center = (points.min(0) + points.max(0)) / 2
    plain = o3dvis.NeuralVisibility(network, precision="float32")  # exact products: the algebra alone
    expected = torch.stack([
        plain.encode((points - center) @ r.T).probabilities((cameras - center) @ r.T)
        for r in fixed_rotations(3).numpy()]).mean(0)
    vis = o3dvis.NeuralVisibility(network, num_rotations=3, precision="float32")
    field = vis.encode(points)
    assert "3 rotations" in repr(vis) and "3 frames" in repr(field)
    got = field.probabilities(cameras)
    # the turned copies are normalised in float32 here and in float64 there: the odd point may
    # fall on the other side of a cell or pixel border
    assert (got - expected).abs().le(1e-4).float().mean() > 0.999 and (got - expected).abs().max() < 0.05
    assert not torch.allclose(got, plain.encode(points).probabilities(cameras), atol=1e-3)
    direction = torch.tensor([0.3, -1.0, 0.2], dtype=torch.float64)
    expected = torch.stack([plain.encode(points @ r.numpy().T).probabilities(direction=direction @ r.T)
                            for r in fixed_rotations(3)]).mean(0)
    diff = (field.probabilities(direction=direction) - expected).abs()
    assert diff.le(1e-4).float().mean() > 0.999 and diff.max() < 0.05
    indices = rng.choice(len(points), 50, replace=False)
    torch.testing.assert_close(field.probabilities(cameras, indices=indices), got[:, indices])
    params = _pinhole(cameras[0], points.mean(0), width=40, height=30, focal=60.0)
    culled, free = field.query(params)[0], field.query(params, frustum=False)[0]
    assert free[~culled].any() and not (culled & ~free).any()
    camera = torch.tensor(cameras[1], requires_grad=True)
    field.probabilities(camera).sum().backward()
    assert torch.isfinite(camera.grad).all() and camera.grad.abs().sum() > 0


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "8"])
def test_bad_num_rotations(network, bad):
    with pytest.raises(ValueError, match="num_rotations must be a positive int"):
        o3dvis.NeuralVisibility(network, num_rotations=bad)


def _empty_tensor_cloud():
    return o3d.t.geometry.PointCloud()


BAD_CLOUDS = [
    (lambda p: o3d.geometry.PointCloud(), ValueError, "empty"),
    (lambda p: _empty_tensor_cloud(), ValueError, "empty"),
    (lambda p: np.zeros((0, 3)), ValueError, "empty"),
    (lambda p: np.where(np.arange(len(p))[:, None] == 5, np.nan, p), ValueError, "NaN or Inf"),
    (lambda p: np.where(np.arange(len(p))[:, None] == 5, np.inf, p), ValueError, "NaN or Inf"),
    (lambda p: p[:, :2], ValueError, r"shape \(N, 3\)"),
    (lambda p: p[None], ValueError, r"shape \(N, 3\)"),
    (lambda p: p.astype(complex), TypeError, "real numbers"),
    (lambda p: p > 0, TypeError, "real numbers"),
    (lambda p: p.tolist(), TypeError, "PointCloud"),
]


@pytest.mark.parametrize("make, error, message", BAD_CLOUDS)
def test_bad_clouds_raise_clear_errors(vis, points, make, error, message):
    with pytest.raises(error, match=message):
        vis.encode(make(points)).query(_camera(points))


TINY = {
    "one point": np.array([[0.1, 0.2, 0.3]]),
    "two points": np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
    "three points": np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
    "duplicates": np.repeat([[0.5, 0.5, 0.5]], 10, axis=0),
    "planar": np.c_[np.random.default_rng(0).random((500, 2)), np.zeros(500)],
    "collinear": np.c_[np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)],
    "offset 1e6 float32": (np.random.default_rng(1).normal(size=(400, 3)) + 1e6).astype(np.float32),
}


@pytest.mark.parametrize("num_rotations", [1, 3])
@pytest.mark.parametrize("name", TINY)
def test_planar_and_tiny_clouds_get_an_answer(network, name, num_rotations):
    vis = o3dvis.NeuralVisibility(network, num_rotations=num_rotations)
    points = TINY[name]
    camera = points.astype(np.float64).mean(0) + [0.3, -0.2, 5.0]
    field = vis.encode(points)
    assert torch.isfinite(field.probabilities(camera)).all()
    mask = field.query(camera)
    assert mask.shape == (1, len(points)) and mask.dtype == bool
    mesh, pt_map = o3dvis.hidden_point_removal_neural(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64))), camera, model=vis)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), points.astype(np.float64)[pt_map])
    np.testing.assert_array_equal(np.flatnonzero(mask[0]), pt_map)


def test_small_clouds_without_normals_go_to_the_small_model(network, points):
    """Under 5 500 points, a cloud without normals is encoded by the small network (the shipped one
    on a depth-6 octree, loaded by pretrained()); larger ones, and clouds with normals, are not."""
    torch.manual_seed(6)
    small = VisibilityNetwork(NetworkConfig(**SMALL))
    normals_net = VisibilityNetwork(NetworkConfig(**SMALL, use_normals=True))
    vis = o3dvis.NeuralVisibility(network, normals_net, small_network=small)
    rng = np.random.default_rng(0)
    few, many = rng.normal(size=(5499, 3)), rng.normal(size=(5500, 3))
    assert vis.encode(few).network is small and vis.encode(many).network is network
    assert vis.encode(few, normals=few).network is normals_net
    assert "small model" in repr(vis) and small in vis.networks()
    with pytest.raises(ValueError, match="small_network must be a model that takes no normals"):
        o3dvis.NeuralVisibility(network, small_network=normals_net)
    shipped = o3dvis.NeuralVisibility.pretrained()
    assert shipped.small_network is not None and shipped.small_network.config.depth == 6
    assert o3dvis.NeuralVisibility.pretrained(use_small=False).small_network is None
    assert o3dvis.NeuralVisibility.pretrained("small").small_network is None  # a companion of the default only
    small.train()
    assert vis.to("cpu") is vis and not small.training  # to() puts a network left in train mode back in eval


def test_normals_are_used_automatically_when_a_normals_model_exists(network, points):
    torch.manual_seed(5)
    normals_net = VisibilityNetwork(NetworkConfig(**SMALL, use_normals=True))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    plain = o3d.geometry.PointCloud(cloud)
    cloud.estimate_normals()
    paired = o3dvis.NeuralVisibility(network, normals_net)
    assert paired.encode(cloud).network is normals_net
    assert paired.encode(cloud, normals=False).network is network
    assert paired.encode(plain).network is network
    with pytest.raises(ValueError, match="no normals"):
        paired.encode(plain, normals=True)
    alone = o3dvis.NeuralVisibility(network)
    assert alone.encode(cloud).network is network
    with pytest.raises(ValueError, match="no loaded model takes normals"):
        alone.encode(cloud, normals=True)
    with pytest.raises(ValueError, match="needs normals"):
        o3dvis.NeuralVisibility(normals_net).encode(plain)
    with pytest.raises(ValueError, match="zero length"):
        paired.encode(points, normals=np.zeros_like(points))
    camera = _camera(points)
    a = paired.encode(cloud).probabilities(camera)
    b = paired.encode(points, normals=-2 * np.asarray(cloud.normals)).probabilities(camera)
    assert not torch.allclose(a, b)  # the given normals reach the network
