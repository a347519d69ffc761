"""The query engine (``o3dvis.field``): batched, indexed, frustum-culled, orthographic and
differentiable queries of a small random network, answers in either array type, the features read per
leaf; and cameras inside the cloud: rooms with analytic visibility, cameras on points, range crops,
the scene model."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis.apps import render, shadows
from o3dvis.nn import NetworkConfig, VisibilityNetwork, native

from conftest import _camera, _median_threshold, _pinhole, box_surface


@pytest.fixture(scope="module")
def vis(small_vis):
    """The small random network's model here, not the shipped one."""
    return small_vis


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


# ---------------------------------------------------------------- cameras inside the cloud

ROOM = (6.0, 4.0, 3.0)  # length, width, height
WALL = (2.45, 2.55)  # the partition's faces, across the length: two closed rooms side by side


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, np.ndarray]:
    """A closed room split by a full partition, as its two convex halves' inner surfaces.

    From a camera in one half exactly the points of that half's boundary are
    visible (a convex room sees all of its walls), and none of the other half's.
    """
    rng = np.random.default_rng(0)
    length, width, height = ROOM
    left = box_surface((0, 0, 0), (WALL[0], width, height), 10_000, rng)
    right = box_surface((WALL[1], 0, 0), (length, width, height), 10_000, rng)
    return np.vstack([left, right]), np.r_[np.ones(len(left), bool), np.zeros(len(right), bool)]


CAMERAS = np.array([[1.0, 1.0, 1.5], [2.0, 3.0, 0.8], [4.5, 2.0, 1.5], [5.5, 0.5, 2.5]])


def _truth(in_left: np.ndarray) -> np.ndarray:
    return np.array([in_left if camera[0] < WALL[0] else ~in_left for camera in CAMERAS])


def _balanced_accuracy(predicted: np.ndarray, truth: np.ndarray) -> float:
    return 0.5 * ((predicted & truth).sum() / truth.sum() + (~predicted & ~truth).sum() / (~truth).sum())


def test_room_with_a_partition_from_inside(room):
    points, in_left = room
    visible = o3dvis.NeuralVisibility.pretrained().encode(points).query(CAMERAS)
    for predicted, truth in zip(visible, _truth(in_left)):
        assert _balanced_accuracy(predicted, truth) > 0.9


def test_camera_on_a_point_raises(room):
    points, _ = room
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    field = o3dvis.NeuralVisibility.pretrained().encode(points)
    for camera in (points[7], points[7] + 1e-9):
        with pytest.raises(ValueError, match="on a point"):
            field.query(camera)
        with pytest.raises(ValueError, match="on a point"):
            o3dvis.hidden_point_removal_neural(pcd, camera)
        with pytest.raises(ValueError, match="on a point"):
            o3dvis.select_visible(pcd, camera)
    # Only the offending camera of a batch is named, and a camera a millimetre off the wall is answered.
    with pytest.raises(ValueError, match="camera 1 "):
        field.query([CAMERAS[0], points[7]])
    assert field.query(points[7] + [0, 0, 1e-3]).shape == (1, len(points))


def test_every_public_form_answers_inside(room):
    points, in_left = room
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    camera, truth = CAMERAS[0], _truth(in_left)[0]
    field = o3dvis.NeuralVisibility.pretrained().encode(pcd)
    expected = field.query(camera)[0]
    assert _balanced_accuracy(expected, truth) > 0.9
    np.testing.assert_array_equal(field.probabilities(camera)[0].numpy() > 0.5, expected)
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera)
    np.testing.assert_array_equal(pt_map, np.flatnonzero(expected))
    assert len(o3dvis.select_visible(pcd, camera).points) == expected.sum()
    tensor = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    _, pt_map = o3dvis.hidden_point_removal_neural(tensor, camera)
    np.testing.assert_array_equal(pt_map.numpy(), np.flatnonzero(expected))
    # A pinhole camera inside, looking down the room: only what lies in its image.
    pinhole = o3d.camera.PinholeCameraParameters()
    pinhole.intrinsic = o3d.camera.PinholeCameraIntrinsic(64, 48, 40.0, 40.0, 31.5, 23.5)
    look = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], float)  # +x forward, z up
    look[:3, 3] = -look[:3, :3] @ camera
    pinhole.extrinsic = look
    framed = field.query(pinhole)[0]
    assert framed.any() and not (framed & ~expected).any() and not framed[points[:, 0] < camera[0]].any()
    # An orthographic view and a gradient through an inside camera.
    assert field.query(direction=[0, 0, -1]).any()
    position = torch.tensor(camera, requires_grad=True)
    field.probabilities(position).sum().backward()
    assert torch.isfinite(position.grad).all()
    # Applications: a light inside the room lights its own half; a render from inside draws something.
    dark = shadows.points_in_shadow(pcd, camera)
    assert _balanced_accuracy(~dark, truth) > 0.9
    image = np.asarray(render.render_points(pcd, camera, width=64, height=48))
    assert (image < 250).any()


def test_max_range_crops(room):
    points, _ = room
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    plain = o3dvis.NeuralVisibility(o3dvis.NeuralVisibility.pretrained().network)  # no scene model: one field answers all
    field = plain.encode(points)
    reach = 2.0
    far = np.linalg.norm(points[None] - CAMERAS[:, None], axis=2) > reach
    cropped = field.query(CAMERAS, max_range=reach)
    assert not cropped[far].any() and cropped.any()
    # The far points hide nothing either: a view of the cropped field is that of the near points alone.
    near = np.flatnonzero(~far[0])
    alone = plain.encode(points).probabilities(CAMERAS[0], max_range=reach)[0].numpy()
    assert (alone[far[0]] == 0).all()
    subset = field._restricted(torch.from_numpy(field.rank.numpy()[near]))
    np.testing.assert_allclose(alone[near], subset.probabilities(CAMERAS[0])[0].numpy(), atol=1e-6)
    # The one-view functions encode the crop alone: the same as a cloud of the near points.
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, CAMERAS[0], max_range=reach)
    _, own = o3dvis.hidden_point_removal_neural(pcd.select_by_index(near.tolist()), CAMERAS[0])
    np.testing.assert_array_equal(pt_map, near[own])
    assert len(o3dvis.select_visible(pcd, CAMERAS[0], max_range=reach).points) == len(own)
    assert o3dvis.select_visible(pcd, CAMERAS[0], max_range=1e-3).is_empty()
    for bad, error in ((0.0, ValueError), (-1.0, ValueError), (float("nan"), ValueError), ("far", TypeError)):
        with pytest.raises(error, match="max_range"):
            field.query(CAMERAS[0], max_range=bad)
    with pytest.raises(ValueError, match="max_range"):
        field.query(direction=[0, 0, 1], max_range=1.0)


def test_scene_model_answers_the_cameras_inside(room):
    points, _ = room
    torch.manual_seed(0)
    scene = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8, 8, 8), feature_channels=8,
                                            num_frequencies=2, hidden=(16,)))
    default = o3dvis.NeuralVisibility.pretrained().network
    both = o3dvis.NeuralVisibility(default, scene_network=scene).encode(points)
    outside = [[20.0, 2.0, 1.5], [-9.0, -9.0, 9.0]]
    cameras = np.vstack([outside[:1], CAMERAS[:2], outside[1:]])
    probs = both.probabilities(cameras).numpy()
    alone = o3dvis.NeuralVisibility(scene).encode(points).probabilities(CAMERAS[:2]).numpy()
    np.testing.assert_array_equal(probs[1:3], alone)
    np.testing.assert_array_equal(probs[[0, 3]], o3dvis.NeuralVisibility.pretrained().encode(points).probabilities(outside).numpy())
    np.testing.assert_array_equal(both.query(cameras), probs > 0.5)
    # The one-view functions answer an inside camera by the scene model too (encoding only it).
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    model = o3dvis.NeuralVisibility(default, scene_network=scene)
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, CAMERAS[0], model=model)
    np.testing.assert_array_equal(pt_map, np.flatnonzero(alone[0] > 0.5))
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, outside[0], model=model)
    np.testing.assert_array_equal(pt_map, np.flatnonzero(probs[0] > 0.5))
    with pytest.raises(ValueError, match="takes no normals"):
        o3dvis.NeuralVisibility(default, scene_network=VisibilityNetwork(NetworkConfig(use_normals=True)))


@pytest.mark.skipif(not native.available(), reason="no C kernels here")
@pytest.mark.parametrize("scene", [False, True], ids=["default model", "scene model"])
def test_the_torch_ops_answer_the_cameras_inside_as_the_kernels(room, scene, monkeypatch):
    """The C kernels are the reference: the torch ops (a GPU, autograd, no kernels built) find each
    point's pixel as they do, from a mean view direction summed in double. From inside a room that
    direction is short, and rounded as torch rounds it, points on the far side of the azimuthal
    image changed pixels: answers 0.2 apart."""
    points, _ = room
    model = o3dvis.NeuralVisibility.pretrained() if scene else o3dvis.NeuralVisibility(o3dvis.NeuralVisibility.pretrained().network)
    cameras = np.vstack([CAMERAS, [[0.3, 3.7, 2.8], [3.0, 0.2, 0.1]]])
    kernels = model.encode(points).probabilities(cameras)
    monkeypatch.setattr(native, "usable", lambda *tensors: False)
    torch_ops = model.encode(points).probabilities(cameras)
    assert float((kernels - torch_ops).abs().max()) < 1e-4
    assert torch.equal(kernels > 0.5, torch_ops > 0.5)


def test_stored_probabilities_are_the_probabilities_in_the_stored_order(room):
    """Cameras outside and inside, answered by their fields, the points along the Morton curve."""
    points, _ = room
    torch.manual_seed(0)
    scene = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8, 8, 8), feature_channels=8,
                                            num_frequencies=2, hidden=(16,)))
    field = o3dvis.NeuralVisibility(o3dvis.NeuralVisibility.pretrained().network, scene_network=scene).encode(points)
    cameras = np.vstack([[[20.0, 2.0, 1.5]], CAMERAS[:2], [[-9.0, -9.0, 9.0]]])
    order = torch.argsort(field.rank)
    assert not torch.equal(order, torch.arange(len(points)))  # the cloud is not in Morton order
    stored = field.stored_probabilities(cameras)
    torch.testing.assert_close(stored, field.probabilities(cameras)[:, order], rtol=0, atol=1e-6)
    rows = np.arange(0, len(points), 7)
    torch.testing.assert_close(field.stored_probabilities(cameras, rows), stored[:, rows], rtol=0, atol=1e-6)


def test_rotations_average_the_scene_model_too(room):
    """num_rotations turns the cloud for the scene model as for the default: the cameras inside
    get the scene model's mean over the rotations, from a field and from the drop-in alike."""
    points, _ = room
    torch.manual_seed(0)
    scene = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8, 8, 8), feature_channels=8,
                                            num_frequencies=2, hidden=(16,)))
    default = o3dvis.NeuralVisibility.pretrained().network
    model = o3dvis.NeuralVisibility(default, scene_network=scene, num_rotations=3, precision="float32")
    got = model.encode(points).probabilities(CAMERAS[:2]).numpy()
    turned = o3dvis.NeuralVisibility(scene, num_rotations=3, precision="float32")
    np.testing.assert_array_equal(got, turned.encode(points).probabilities(CAMERAS[:2]).numpy())
    once = o3dvis.NeuralVisibility(scene, precision="float32").encode(points).probabilities(CAMERAS[:2]).numpy()
    assert np.abs(got - once).max() > 1e-3
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, CAMERAS[0], model=model)
    np.testing.assert_array_equal(pt_map, np.flatnonzero(got[0] > 0.5))
