"""The Open3D-facing API: HPR drop-in semantics, camera forms, batching, gradients, bad input."""

from __future__ import annotations

import json
import pydoc

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis import models
from o3dvis.cameras import all_finite, as_views, viewpoints_around
from o3dvis.cli import build_parser
from o3dvis.cli._common import split_vectors
from o3dvis.models import file_sha256
from o3dvis.geometry import bounds, fixed_rotations
from o3dvis.two_pass import first_pass_normals
from o3dvis.nn import NetworkConfig, VisibilityNetwork, native
from o3dvis.orientation import voted_normals
from o3dvis.pretrained import resolve_model
from o3dvis.training.data import random_shape

SMALL = dict(depth=5, full_depth=2, channels=(8, 16), feature_channels=8, num_frequencies=2, hidden=(16,))
CAMERA = [0.0, 0.0, 5.0]


@pytest.fixture(scope="module")
def network() -> VisibilityNetwork:
    torch.manual_seed(0)
    return VisibilityNetwork(NetworkConfig(**SMALL)).eval()


@pytest.fixture(scope="module")
def vis(network) -> o3dvis.NeuralVisibility:
    return o3dvis.NeuralVisibility(network)


@pytest.fixture(scope="module")
def pcd() -> o3d.geometry.PointCloud:
    """Open3D's HPR example on a procedural shape: 3 000 Poisson-disk samples."""
    mesh = random_shape(np.random.default_rng(3), parts=3)
    o3d.utility.random.seed(1)
    cloud = mesh.sample_points_poisson_disk(3000)
    cloud.colors = o3d.utility.Vector3dVector(np.random.default_rng(0).random((3000, 3)))
    return cloud


@pytest.fixture(scope="module")
def points(pcd) -> np.ndarray:
    return np.asarray(pcd.points).copy()


def _camera(points: np.ndarray, direction=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A camera outside the cloud at one bounding-box diagonal from its centre."""
    center = (points.min(0) + points.max(0)) / 2
    diag = np.linalg.norm(points.max(0) - points.min(0))
    return center + diag * np.asarray(direction) / np.linalg.norm(direction)


def _median_threshold(vis, cloud, camera) -> float:
    """A threshold that splits the points into visible and hidden halves."""
    return float(vis.encode(cloud).probabilities(camera).median())


def test_hpr_legacy_semantics(vis, pcd, points):
    camera = _camera(points)
    threshold = _median_threshold(vis, pcd, camera)
    mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, 500.0, threshold=threshold, model=vis,
                                                      triangulate=True)
    assert isinstance(mesh, o3d.geometry.TriangleMesh)
    assert isinstance(pt_map, list) and all(isinstance(i, int) for i in pt_map)
    assert 0 < len(pt_map) < len(points)
    assert min(pt_map) >= 0 and max(pt_map) < len(points) and len(set(pt_map)) == len(pt_map)
    # Open3D's own test: the mesh vertices are the selected points.
    np.testing.assert_array_equal(np.asarray(mesh.vertices), points[pt_map])
    expected = vis.encode(points).query(camera, threshold=threshold)[0]
    np.testing.assert_array_equal(np.flatnonzero(expected), pt_map)
    triangles = np.asarray(mesh.triangles)
    assert len(triangles) > 0 and triangles.min() >= 0 and triangles.max() < len(pt_map)
    v = np.asarray(mesh.vertices)
    normals = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])
    assert (np.einsum("ij,ij->i", normals, camera - v[triangles[:, 0]]) >= 0).all()


@pytest.mark.parametrize("dtype", [o3d.core.float64, o3d.core.float32])
def test_hpr_tensor_semantics(vis, pcd, points, dtype):
    camera = _camera(points)
    threshold = _median_threshold(vis, pcd, camera)
    tpcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(points, dtype=dtype))
    mesh, pt_map = o3dvis.hidden_point_removal_neural(tpcd, o3d.core.Tensor(camera), 500.0,
                                                      threshold=threshold, model=vis)
    assert isinstance(mesh, o3d.t.geometry.TriangleMesh)
    assert isinstance(pt_map, o3d.core.Tensor) and pt_map.dtype == o3d.core.int64
    index = pt_map.numpy()
    assert index.ndim == 1 and 0 < len(index) < len(points)
    assert index.min() >= 0 and index.max() < len(points)
    np.testing.assert_array_equal(mesh.vertex.positions.numpy(), tpcd.point.positions.numpy()[index])
    assert mesh.vertex.positions.dtype == dtype
    if dtype == o3d.core.float64:
        _, legacy_map = o3dvis.hidden_point_removal_neural(pcd, camera, threshold=threshold, model=vis)
        np.testing.assert_array_equal(index, legacy_map)


def test_radius_is_unused_and_triangles_optional(vis, pcd, points):
    camera = _camera(points)
    maps = [o3dvis.hidden_point_removal_neural(pcd, camera, r, model=vis)[1] for r in (None, 1e-9, 1e5)]
    assert maps[0] == maps[1] == maps[2]
    mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)
    assert pt_map == maps[0] and len(mesh.triangles) == 0
    np.testing.assert_array_equal(np.asarray(mesh.vertices), points[pt_map])


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error without CUDA")
def test_cuda_without_cuda_is_a_clear_error(network, pcd, points):
    with pytest.raises(ValueError, match="CUDA"):
        o3dvis.hidden_point_removal_neural(pcd, _camera(points), model=network, device="cuda")
    with pytest.raises(ValueError, match="unknown torch device"):
        o3dvis.NeuralVisibility(network, device="gpu0")


def test_batched_query_equals_one_call_per_camera(network, points, monkeypatch):
    rng = np.random.default_rng(1)
    cameras = np.stack([_camera(points, d) for d in rng.normal(size=(5, 3))])
    field = o3dvis.NeuralVisibility(network).encode(points)
    batched = field.probabilities(cameras)
    single = torch.cat([field.probabilities(c) for c in cameras])
    torch.testing.assert_close(batched, single)
    threshold = float(batched.median())
    mask = field.query(cameras, threshold=threshold)
    assert mask.shape == (5, len(points)) and mask.dtype == bool and 0 < mask.mean() < 1
    singles = [field.query(c, threshold=threshold) for c in cameras]
    np.testing.assert_array_equal(mask, np.concatenate(singles))
    np.testing.assert_array_equal(mask, batched.numpy() > threshold)
    # Small chunks: several views per MLP call where a chunk holds several views' points; the torch
    # ops (here under autograd) also cut each view's points into chunks, one pass of C per view does not
    rows, margin = [], network.view_margin

    def counted(*args):
        out = margin(*args)
        rows.append(out.numel())
        return out

    monkeypatch.setattr(network, "view_margin", counted)
    n = len(points)
    in_c = native.available() and native.has_view_margin(field.matmul_dtype)
    differentiable = field.probabilities(torch.tensor(cameras, requires_grad=True)).detach()
    for chunk in (1000, 7000):
        small = o3dvis.NeuralVisibility(network, chunk_size=chunk).encode(points)
        rows.clear()
        torch.testing.assert_close(small.probabilities(cameras), batched, atol=1e-6, rtol=1e-5)
        if in_c:  # batches of 1 or 2 views, all their points in one call
            assert sorted(rows) == ([n] * 5 if chunk == 1000 else [n, 2 * n, 2 * n])
        rows.clear()
        grad = small.probabilities(torch.tensor(cameras, requires_grad=True))
        torch.testing.assert_close(grad.detach(), differentiable, atol=1e-6, rtol=1e-5)
        assert max(rows) <= chunk and sum(rows) == 5 * n
        assert len(rows) == (15 if chunk == 1000 else 3)


def _look_at(eye, target) -> np.ndarray:
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0] if abs(forward[1]) < 0.9 else [1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    extrinsic = np.eye(4)
    extrinsic[:3, :3], extrinsic[:3, 3] = rotation, -rotation @ eye
    return extrinsic


def _pinhole(eye, target, width=-1, height=-1, focal=50.0) -> o3d.camera.PinholeCameraParameters:
    params = o3d.camera.PinholeCameraParameters()
    params.extrinsic = _look_at(np.asarray(eye, float), np.asarray(target, float))
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, focal, focal,
                                                         (width - 1) / 2, (height - 1) / 2)
    return params


def test_each_camera_form_gives_the_same_answer(vis, points):
    field = vis.encode(points)
    eye = np.array([0.0, 0.0, 4.0])
    reference = field.probabilities(eye)
    forms = [eye.tolist(), tuple(eye), eye.astype(np.float32), eye.astype(np.int64), eye[None],
             torch.tensor(eye), torch.tensor(eye, dtype=torch.float32), o3d.core.Tensor(eye),
             o3d.core.Tensor(eye[None].astype(np.float32)),
             _pinhole(eye, points.mean(0)), [_pinhole(eye, points.mean(0))]]
    for form in forms:
        torch.testing.assert_close(field.probabilities(form), reference, atol=1e-6, rtol=1e-6)
    trajectory = o3d.camera.PinholeCameraTrajectory()
    trajectory.parameters = [_pinhole(eye, points.mean(0)), _pinhole(-eye, points.mean(0))]
    torch.testing.assert_close(field.probabilities(trajectory), field.probabilities([eye, -eye]),
                               atol=1e-6, rtol=1e-6)


def test_the_drop_in_takes_every_camera_form_of_one_view(vis, pcd, points):
    field = vis.encode(points)
    eye = _camera(points)
    params = _pinhole(eye, points.mean(0), width=40, height=30, focal=60.0)
    threshold = _median_threshold(vis, points, eye)

    def pt_map(camera=None, **kwargs):
        return o3dvis.hidden_point_removal_neural(pcd, camera, threshold=threshold, model=vis, **kwargs)[1]

    culled = np.flatnonzero(field.query(params, threshold=threshold)[0])
    assert pt_map(params) == pt_map([params]) == culled.tolist()
    assert pt_map(params, frustum=False) == pt_map(eye) == pt_map(eye[None])
    assert 0 < len(culled) < len(pt_map(eye))
    selected = o3dvis.select_visible(pcd, params, threshold=threshold, model=vis)
    np.testing.assert_array_equal(np.asarray(selected.points), points[culled])
    direction = np.array([0.2, -0.3, -1.0])
    expected = np.flatnonzero(field.query(direction=direction, threshold=threshold)[0])
    mesh, ortho = o3dvis.hidden_point_removal_neural(pcd, direction=direction, threshold=threshold, model=vis,
                                                     triangulate=True)
    assert ortho == expected.tolist()
    v, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert len(triangles) > 0
    normals = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])
    assert (normals @ -direction >= 0).all()  # facing the orthographic camera
    for batch in ([eye, -eye], [params, params]):
        with pytest.raises(ValueError, match=r"got 2: .*query\(cameras\)"):
            pt_map(batch)
    with pytest.raises(ValueError, match="exactly one"):
        pt_map(eye, direction=direction)


@pytest.mark.parametrize("radius", [-1.0, 0, float("nan"), float("inf")])
def test_the_drop_in_refuses_the_radius_open3d_refuses(vis, pcd, points, radius):
    camera = _camera(points)
    with pytest.raises(RuntimeError):
        pcd.hidden_point_removal(camera, radius)
    with pytest.raises(o3dvis.dropins.RadiusError, match="radius must be larger than zero") as error:
        o3dvis.hidden_point_removal_neural(pcd, camera, radius, model=vis)
    assert isinstance(error.value, RuntimeError) and isinstance(error.value, ValueError)


def test_the_drop_in_refuses_a_radius_that_is_not_a_number(vis, pcd, points):
    for bad in ("1", True, [1.0]):
        with pytest.raises(TypeError, match="radius must be a number"):
            o3dvis.hidden_point_removal_neural(pcd, _camera(points), bad, model=vis)


def test_a_field_answers_in_either_array_type_on_request(vis, points):
    field = vis.encode(points)
    cameras = np.stack([_camera(points, d) for d in ((0, 0, 1), (1, 0, 0))])
    probs, masks = field.probabilities(cameras), field.query(cameras)
    assert isinstance(probs, torch.Tensor) and isinstance(masks, np.ndarray) and masks.dtype == bool
    as_numpy = field.probabilities(cameras, as_numpy=True)
    assert isinstance(as_numpy, np.ndarray) and as_numpy.shape == (2, len(points))
    np.testing.assert_array_equal(as_numpy, probs.numpy())
    as_tensor = field.query(cameras, as_numpy=False)
    assert isinstance(as_tensor, torch.Tensor) and as_tensor.dtype == torch.bool
    assert as_tensor.device == field.device
    np.testing.assert_array_equal(as_tensor.numpy(), masks)
    np.testing.assert_array_equal(field.query(cameras, as_numpy=False, indices=[3, 1]).numpy(), masks[:, [3, 1]])
    camera = torch.tensor(cameras[0], requires_grad=True)
    with pytest.raises(ValueError, match="as_numpy=True drops the gradient"):
        field.probabilities(camera, as_numpy=True)
    with torch.no_grad():  # no gradient asked for: numpy is fine
        np.testing.assert_array_equal(field.probabilities(camera, as_numpy=True),
                                      field.probabilities(cameras[0]).numpy())


def test_indices_answer_for_those_points_only(network, points):
    rng = np.random.default_rng(4)
    cameras = np.stack([_camera(points, d) for d in rng.normal(size=(3, 3))])
    indices = rng.choice(len(points), 700, replace=False)
    full = o3dvis.NeuralVisibility(network).encode(points)
    expected = full.probabilities(cameras)[:, indices]
    for chunk in (300, 1 << 15):  # several chunks of the subset, and one
        field = o3dvis.NeuralVisibility(network, chunk_size=chunk).encode(points)
        torch.testing.assert_close(field.probabilities(cameras, indices=indices), expected)
        torch.testing.assert_close(field.probabilities(cameras, indices=torch.as_tensor(indices)), expected)
    threshold = float(expected.median())
    np.testing.assert_array_equal(full.query(cameras, threshold=threshold, indices=list(indices)),
                                  expected.numpy() > threshold)
    params = _pinhole(cameras[0], points.mean(0), width=40, height=30, focal=60.0)
    np.testing.assert_array_equal(full.query(params, indices=indices), full.query(params)[:, indices])
    camera = torch.tensor(cameras[0], requires_grad=True)
    full.probabilities(camera, indices=indices).sum().backward()
    assert camera.grad is not None and camera.grad.abs().sum() > 0
    assert full.query(cameras, indices=[]).shape == (3, 0)
    with pytest.raises(IndexError, match=r"\[0, 3000\)"):
        full.query(cameras, indices=[0, len(points)])
    with pytest.raises(IndexError):
        full.query(cameras, indices=[-1])
    for bad in ([0.5], np.ones(len(points), bool), [[1, 2]]):
        with pytest.raises(TypeError, match="1-D sequence of integers"):
            full.query(cameras, indices=bad)


def test_pinhole_frustum_culls_points_outside_the_image(vis, points):
    field = vis.encode(points)
    eye = _camera(points)
    params = _pinhole(eye, points.mean(0), width=40, height=30, focal=60.0)
    # Independent projection of the points into the image.
    cam = points @ params.extrinsic[:3, :3].T + params.extrinsic[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * 60.0 + [19.5, 14.5]
    inside = (cam[:, 2] > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < 39.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < 29.5)
    assert 0 < inside.mean() < 1
    threshold = _median_threshold(vis, points, eye)
    culled = field.query(params, threshold=threshold)[0]
    free = field.query(params, threshold=threshold, frustum=False)[0]
    assert not culled[~inside].any()
    np.testing.assert_array_equal(culled[inside], free[inside])
    assert free[~inside].any()
    probs = field.probabilities(params)[0].numpy()
    assert (probs[~inside] == 0).all()


def test_orthographic_direction(vis, points):
    field = vis.encode(points)
    a = field.probabilities(direction=[0.0, 0.0, -1.0])
    torch.testing.assert_close(field.probabilities(direction=[0.0, 0.0, -7.0]), a)
    both = field.query(direction=[[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    assert both.shape == (2, len(points)) and both.dtype == bool
    assert not torch.allclose(a, field.probabilities(direction=[1.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="zero vector"):
        field.query(direction=[0, 0, 0])
    with pytest.raises(ValueError, match="exactly one"):
        field.query(_camera(points), direction=[0, 0, 1])
    with pytest.raises(ValueError, match="exactly one"):
        field.query()


def test_gradient_reaches_the_camera(network, points):
    """The differentiable path computes in float32, as a float32 query does."""
    field = o3dvis.NeuralVisibility(network, precision="float32").encode(points)
    camera = torch.tensor(_camera(points, (1.0, 2.0, 3.0)), requires_grad=True)
    probs = field.probabilities(camera)
    assert probs.requires_grad and probs.shape == (1, len(points))
    probs.sum().backward()
    assert camera.grad is not None and torch.isfinite(camera.grad).all() and camera.grad.abs().sum() > 0
    torch.testing.assert_close(probs.detach(), field.probabilities(camera.detach()))
    bf16 = o3dvis.NeuralVisibility(network, precision="bfloat16").encode(points)
    assert bf16.probabilities(camera).requires_grad  # a gradient asked for: float32 whatever the precision
    direction = torch.tensor([0.0, 0.0, 1.0], requires_grad=True)
    field.probabilities(direction=direction).sum().backward()
    assert torch.isfinite(direction.grad).all()


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


def test_bfloat16_products_answer_as_float32_ones(points):
    """With the shipped weights the reduced-precision path gives the same answers to bfloat16
    rounding: views all around the cloud, batched (several per MLP call) and one at a time."""
    views = [_camera(points, d) for d in np.random.default_rng(3).normal(size=(12, 3))]
    exact = o3dvis.NeuralVisibility.pretrained(precision="float32").encode(points)
    reduced = o3dvis.NeuralVisibility.pretrained(precision="bfloat16").encode(points)
    assert exact.matmul_dtype == torch.float32 and reduced.matmul_dtype == torch.bfloat16
    p32, p16 = exact.probabilities(views), reduced.probabilities(views)
    assert not torch.equal(p16, p32)  # the products did run in bfloat16
    torch.testing.assert_close(p16, p32, atol=0.03, rtol=0)
    assert ((p16 > 0.5) == (p32 > 0.5)).float().mean() > 0.999
    reduced.chunk_size = 1000  # one view and part of the cloud per call
    torch.testing.assert_close(reduced.probabilities(views), p16, atol=0.03, rtol=0)


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


def test_fixed_rotations_are_rotations_and_the_same_each_call():
    r = fixed_rotations(5)
    assert r.shape == (5, 3, 3) and r.dtype == torch.float64
    torch.testing.assert_close(r[0], torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(5, 3, 3))
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(5, dtype=torch.float64))
    torch.testing.assert_close(fixed_rotations(3), r[:3], rtol=0, atol=0)
    assert (r[1:] - torch.eye(3, dtype=torch.float64)).abs().amax(dim=(1, 2)).min() > 0.1


def test_bounds_are_numpy_s_min_and_max_along_the_rows():
    points = np.random.default_rng(0).normal(size=(1000, 3)) * [1.0, 1e6, 1e-6]
    for lo, hi in [bounds(points), bounds(points[:, :2]), bounds(points[:1])]:
        assert lo.shape == hi.shape and lo.dtype == np.float64
    np.testing.assert_array_equal(np.stack(bounds(points)), np.stack([points.min(axis=0), points.max(axis=0)]))
    points[7, 1] = np.nan
    lo, hi = bounds(points)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and np.isfinite(lo[[0, 2]]).all()
    with pytest.raises(ValueError, match="no points"):
        bounds(np.empty((0, 3)))


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


@pytest.mark.parametrize("func", [o3dvis.hidden_point_removal_neural, o3dvis.select_visible,
                                  o3dvis.NeuralVisibility, o3dvis.NeuralVisibility.pretrained,
                                  o3dvis.NeuralVisibility.encode, o3dvis.VisibilityField.query,
                                  o3dvis.VisibilityField.probabilities, o3dvis.load_model, as_views])
def test_docstrings_render_with_args_and_returns(func):
    text = pydoc.render_doc(func, renderer=pydoc.plaintext)
    assert "Args:" in text
    if func is not o3dvis.NeuralVisibility:
        assert "Returns:" in text


def test_hpr_docstring_documents_radius_as_unused():
    doc = o3dvis.hidden_point_removal_neural.__doc__
    assert "radius: unused" in doc and "points[pt_map]" in doc


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


BAD_CAMERAS = [
    ([np.nan, 0, 5], ValueError, "NaN or Inf"),
    ([np.inf, 0, 5], ValueError, "NaN or Inf"),
    ([0, 5], ValueError, r"shape \(3,\) or \(V, 3\)"),
    (np.zeros((2, 2)), ValueError, r"shape \(3,\) or \(V, 3\)"),
    (np.zeros((0, 3)), ValueError, "no vectors"),
    ([[0, 0, 5], [0, 5]], ValueError, "3-vector"),
    (np.array([True, False, True]), TypeError, "real numbers"),
    ("0,0,5", TypeError, "real numbers"),
    (torch.tensor([1j, 0, 5]), TypeError, "real numbers"),
]


def test_all_finite_is_exact_where_the_sum_overflows_or_cancels():
    """The sum decides only when it is finite: finite entries whose sum overflows still pass, and
    +inf beside -inf (a NaN sum) or a NaN fail."""
    huge = torch.full((4, 3), 1e308, dtype=torch.float64)
    assert not torch.isfinite(huge.sum()) and all_finite(huge)
    assert all_finite(torch.zeros(5, 3)) and all_finite(torch.tensor([[1.0, -2.0, 3.0]]))
    for bad in ([np.inf, -np.inf, 0.0], [np.nan, 1.0, 2.0], [1e308, 1e308, np.inf]):
        assert not all_finite(torch.tensor([bad], dtype=torch.float64))


@pytest.mark.parametrize("camera, error, message", BAD_CAMERAS)
def test_bad_cameras_raise_clear_errors(vis, points, camera, error, message):
    with pytest.raises(error, match=message):
        vis.encode(points).query(camera)


def test_camera_inside_the_cloud_or_on_a_point(vis, pcd, points):
    field = vis.encode(points)
    for camera in (points[np.argmax(points[:, 0])], points[0]):
        with pytest.raises(ValueError, match="on a point"):
            field.query(camera)
        with pytest.raises(ValueError, match="on a point"):
            o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)
    # Only the offending camera of a batch is named; a camera inside, off the points, is answered.
    with pytest.raises(ValueError, match="camera 1 "):
        field.query([_camera(points), points[0]])
    assert field.query(points.mean(0)).shape == (1, len(points))


def test_other_bad_arguments(vis, pcd, points):
    field = vis.encode(points)
    camera = _camera(points)
    with pytest.raises(ValueError, match="threshold"):
        field.query(camera, threshold=1.5)
    with pytest.raises(TypeError, match="threshold"):
        field.query(camera, threshold="high")
    with pytest.raises(ValueError, match="give one camera, got 2"):
        o3dvis.hidden_point_removal_neural(pcd, [camera, camera], model=vis)
    with pytest.raises(TypeError, match="PointCloud"):
        o3dvis.hidden_point_removal_neural(points, camera, model=vis)
    with pytest.raises(ValueError, match="one camera"):
        o3dvis.select_visible(pcd, [camera, -camera], model=vis)
    with pytest.raises(TypeError, match="model must be"):
        o3dvis.select_visible(pcd, camera, model=3)
    params = o3d.camera.PinholeCameraParameters()
    params.extrinsic = np.diag([2.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="rigid"):
        field.query(params)
    with pytest.raises(TypeError, match="VisibilityNetwork"):
        o3dvis.NeuralVisibility("default")


def test_unknown_model_name(pcd, points, monkeypatch, tmp_path, network):
    network.save(tmp_path / "default.safetensors")
    card = {"models": {"default": {"file": "default.safetensors",
                                   "sha256": file_sha256(tmp_path / "default.safetensors")}}}
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    monkeypatch.setattr(models, "WEIGHTS_DIR", tmp_path)
    with pytest.raises(ValueError, match="unknown model 'tiny'; available: default"):
        o3dvis.hidden_point_removal_neural(pcd, _camera(points), model="tiny")
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, _camera(points), threshold=0.4)
    _, expected = o3dvis.hidden_point_removal_neural(pcd, _camera(points), threshold=0.4, model=network)
    assert pt_map == expected


def test_the_shipped_model_is_loaded_once_and_shared(pcd, monkeypatch):
    cpu = torch.device("cpu")
    shipped = resolve_model(None, cpu)
    assert resolve_model("default", cpu) is shipped
    with pytest.raises(ValueError, match="unknown model 'tiny'; available: default, normals"):
        resolve_model("tiny", cpu)

    def load_again(*args, **kwargs):
        raise AssertionError("the shipped weights were loaded again")

    monkeypatch.setattr(models, "_load_checked", load_again)
    cloud = o3d.geometry.PointCloud(pcd)
    o3dvis.estimate_normals_neural(cloud, num_views=4, refine_views=0)  # model=None: the shared model
    assert cloud.has_normals()
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, _camera(np.asarray(pcd.points)))
    assert len(pt_map) > 0
    mine = o3dvis.NeuralVisibility.pretrained()  # a model of its own over the networks loaded
    assert mine is not shipped and mine.networks() == shipped.networks()


def test_moving_a_pretrained_model_moves_copies_of_the_shared_networks():
    shipped = resolve_model(None, torch.device("cpu"))
    mine = o3dvis.NeuralVisibility.pretrained().to("meta")  # a device every torch build has
    assert all(next(net.parameters()).device.type == "meta" for net in mine.networks())
    assert all(next(net.parameters()).device.type == "cpu" for net in shipped.networks())
    assert resolve_model(None, torch.device("cpu")) is shipped


def test_the_shared_model_follows_the_weights_folder(pcd, monkeypatch, tmp_path, network):
    cpu = torch.device("cpu")
    shipped = resolve_model(None, cpu)
    network.save(tmp_path / "default.safetensors")
    card = {"models": {"default": {"file": "default.safetensors",
                                   "sha256": file_sha256(tmp_path / "default.safetensors")}}}
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    monkeypatch.setattr(models, "WEIGHTS_DIR", tmp_path)
    other = resolve_model(None, cpu)
    assert other is not shipped and other.network.config == network.config
    assert resolve_model(None, cpu) is other


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


def test_select_visible_keeps_colours_and_normals(vis, pcd, points):
    cloud = o3d.geometry.PointCloud(pcd)
    cloud.estimate_normals()
    camera = _camera(points)
    threshold = _median_threshold(vis, points, camera)
    out = o3dvis.select_visible(cloud, camera, threshold=threshold, model=vis)
    index = np.flatnonzero(vis.encode(points).query(camera, threshold=threshold)[0])
    assert 0 < len(index) < len(points)
    np.testing.assert_array_equal(np.asarray(out.points), points[index])
    np.testing.assert_array_equal(np.asarray(out.colors), np.asarray(cloud.colors)[index])
    np.testing.assert_array_equal(np.asarray(out.normals), np.asarray(cloud.normals)[index])
    tcloud = o3d.t.geometry.PointCloud.from_legacy(cloud, o3d.core.float64)
    tout = o3dvis.select_visible(tcloud, camera, threshold=threshold, model=vis)
    assert isinstance(tout, o3d.t.geometry.PointCloud)
    np.testing.assert_array_equal(tout.point.positions.numpy(), points[index])
    np.testing.assert_array_equal(tout.point.colors.numpy(), np.asarray(cloud.colors)[index])
    np.testing.assert_array_equal(tout.point.normals.numpy(), np.asarray(cloud.normals)[index])
    arrays = o3dvis.select_visible(points, camera, threshold=threshold, model=vis)
    np.testing.assert_array_equal(np.asarray(arrays.points), points[index])


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


def test_normals_estimated_in_a_first_pass_for_dense_clean_clouds(network):
    torch.manual_seed(5)
    normals_net = VisibilityNetwork(NetworkConfig(**SMALL, use_normals=True))
    paired = o3dvis.NeuralVisibility(network, normals_net)
    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(20_000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    field = paired.encode(sphere, normals="estimate")
    assert field.network is normals_net
    cameras = viewpoints_around(sphere, 14)  # the first pass's probabilities orient the normals
    expected = voted_normals(sphere, cameras, paired.encode(sphere, normals=False).probabilities(cameras).numpy())
    np.testing.assert_allclose(field.normals[field.rank].numpy(), expected, atol=1e-6)
    first, rank = paired.encode(sphere, normals=False), field.rank.numpy()
    np.testing.assert_array_equal(first_pass_normals(first, sphere[np.argsort(rank)], stored=True)[rank],
                                  first_pass_normals(first, sphere))  # in the field's order or the cloud's
    given = paired.encode(sphere, normals=field.normals[field.rank].double().numpy())  # the passes share
    torch.testing.assert_close(field.probabilities(cameras), given.probabilities(cameras))  # octree, noise
    assert paired.encode(sphere).network is network  # by default: one pass for a cloud without normals
    noisy = sphere * (1 + 0.05 * rng.uniform(-1, 1, (len(sphere), 1)))
    assert paired.encode(noisy, normals="estimate").network is network  # rough neighbourhoods: one pass
    assert paired.encode(sphere[:900], normals="estimate").network is network  # too sparse
    plane = sphere * [1, 1, 0]
    assert paired.encode(plane, normals="estimate").network is network  # flat: one pass is exact
    corners = np.repeat(np.eye(4, 3), 500, axis=0)  # 3-D, but every neighbourhood one point repeated
    assert paired.encode(corners, normals="estimate").network is network
    with pytest.raises(ValueError, match="needs a normals model"):
        o3dvis.NeuralVisibility(network).encode(sphere, normals="estimate")
    with pytest.raises(ValueError, match="got 'estimated'"):
        paired.encode(sphere, normals="estimated")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sphere))
    camera = _camera(sphere)
    _, two = o3dvis.hidden_point_removal_neural(cloud, camera, model=paired, normals="estimate")
    assert two == np.flatnonzero(field.query(camera)[0]).tolist()
    assert len(o3dvis.select_visible(cloud, camera, model=paired, normals="estimate").points) == len(two)
    _, cropped = o3dvis.hidden_point_removal_neural(cloud, camera, model=paired, normals="estimate", max_range=10.0)
    assert cropped == two  # a range that keeps every point changes nothing

def test_register_attaches_the_method(vis, pcd, points):
    o3dvis.register()
    camera = _camera(points)
    mesh, pt_map = pcd.hidden_point_removal_neural(camera, 100.0, model=vis)
    assert pt_map == o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)[1]
    tpcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    _, tmap = tpcd.hidden_point_removal_neural(o3d.core.Tensor(camera), 100.0, model=vis)
    assert tmap.numpy().tolist() == pt_map


def test_cli_visible_writes_the_visible_points(tmp_path, network, pcd, points, capsys):
    ckpt = tmp_path / "m.safetensors"
    network.save(ckpt)
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    o3d.io.write_point_cloud(str(src), pcd)
    parser = build_parser()
    camera = _camera(points)
    args = parser.parse_args(["visible", str(src), "--camera", *map(str, camera), "-o", str(dst),
                              "--model", str(ckpt), "--threshold", "0.4"])
    assert args.func(args) == 0
    written = np.asarray(o3d.io.read_point_cloud(str(dst)).points)
    expected = np.flatnonzero(o3dvis.NeuralVisibility(network).encode(points).query(camera, threshold=0.4)[0])
    np.testing.assert_allclose(written, points[expected])
    assert f"{len(expected)} of {len(points)} points visible" in capsys.readouterr().out
    for precision in ("float32", "bfloat16"):
        args = parser.parse_args(split_vectors(["visible", str(src), f"--camera={','.join(map(str, camera))}",
                                                "-o", str(dst), "--model", str(ckpt), "--precision", precision]))
        assert args.func(args) == 0
        field = o3dvis.NeuralVisibility(network, precision=precision).encode(points)
        np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(dst)).points),
                                   points[np.flatnonzero(field.query(camera)[0])])
    with pytest.raises(SystemExit):
        parser.parse_args(["visible", str(src), "--camera", "0", "0", "5", "-o", str(dst), "--precision", "half"])
    with pytest.raises(SystemExit):
        parser.parse_args(split_vectors(["visible", str(src), "--camera", "1,2", "-o", str(dst)]))
    args = parser.parse_args(["visible", str(tmp_path / "none.ply"), "--camera", "0", "0", "5", "-o", str(dst)])
    with pytest.raises(FileNotFoundError, match="none.ply"):
        args.func(args)


def test_the_runtime_never_imports_training_code():
    """Every module outside o3dvis.training, o3dvis.evaluation and the command line imports without
    either of the two."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(o3dvis.__file__).parent
    modules = sorted(".".join(("o3dvis",) + p.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
                     for p in root.rglob("*.py")
                     if p.relative_to(root).parts[0] not in ("training", "evaluation", "cli", "__main__.py"))
    assert {"o3dvis", "o3dvis.neural", "o3dvis.field", "o3dvis.dropins", "o3dvis.apps.normals"} <= set(modules)
    code = ("import importlib, sys\n"
            f"for name in {modules!r}:\n"
            "    importlib.import_module(name)\n"
            "print(sorted(m for m in sys.modules if m.startswith(('o3dvis.training', 'o3dvis.evaluation'))))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         cwd=root.parent)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"


def test_dense_clouds_read_the_features_from_the_leaves(vis, points):
    """A first query of one view (the drop-in's) reads the features where they are stored, per
    octree leaf, at any density; a dense cloud's later queries that the C kernels answer read them
    there too, where the torch ops answer a later query carries them to every point once, and a
    cloud of few points a leaf has them carried by its second query. The answers do not change."""
    camera = _camera(points)
    sparse = vis.encode(points)
    assert sparse.num_points < 4 * sparse._leaves.leaves.shape[1]
    once = sparse.probabilities(camera)
    assert sparse._features is None
    torch.testing.assert_close(sparse.probabilities(camera), once, atol=1e-6, rtol=0)
    assert sparse._features is not None
    rng = np.random.default_rng(5)  # 16 points around each of the cloud's
    points = np.repeat(points, 16, axis=0) + 1e-3 * rng.standard_normal((16 * len(points), 3))
    field = vis.encode(points)
    first = field.probabilities(camera)
    assert field._features is None  # nothing carried to the points for one view
    in_c = native.has_view_margin(field.matmul_dtype)
    again = field.probabilities(camera)
    assert (field._features is None) == in_c
    torch.testing.assert_close(again, first, atol=1e-6, rtol=0)
    two = vis.encode(points)  # several views at once
    torch.testing.assert_close(two.probabilities(np.stack([camera, -camera]))[:1], first, atol=1e-6, rtol=0)
    assert (two._features is None) == in_c
    differentiable = torch.tensor(camera, requires_grad=True)  # the torch ops, after a first query
    field.probabilities(differentiable).sum().backward()
    assert field._features is not None and differentiable.grad is not None
    features = field.features
    assert features.shape == (len(points), vis.network.predictor.embedding.dim) and features.stride(0) == 1


def test_every_module_defines_what_its_all_names():
    import importlib
    import pkgutil

    missing = []
    for info in pkgutil.walk_packages(o3dvis.__path__, "o3dvis."):
        name = info.name.rsplit(".", 1)[-1]
        if name == "__main__" or name.startswith("_kernels") or name.startswith("_delaunay"):
            continue  # the command line runs on import; native libraries are not Python modules
        module = importlib.import_module(info.name)
        missing += [f"{info.name}.{n}" for n in getattr(module, "__all__", ()) if not hasattr(module, n)]
    assert not missing, f"__all__ names what the module does not define: {missing}"
