"""Cameras inside the cloud: rooms with analytic visibility, cameras on points, range crops, the scene model."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis.apps import render, shadows
from o3dvis.nn import NetworkConfig, VisibilityNetwork, native

from conftest import box_surface

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


@pytest.mark.skipif(not native.available(), reason="no C kernels here")
def test_the_torch_zbuffer_answers_the_cameras_inside_as_the_kernels():
    """The surfel z-buffer in torch ops rounds as the kernels do (their arctangent, sums and tables of
    rays): each disc in their pixels and the same front disc of every pixel, so the same answers.
    Rounded as torch rounds, dozens of points of a view inside this box had another front disc."""
    from o3dvis.nn import zbuffer
    from o3dvis.nn.cues import point_surfels

    rng = np.random.default_rng(1)
    points = torch.tensor(box_surface((-0.9, -0.8, -0.7), (0.9, 0.8, 0.7), 30_000, rng), dtype=torch.float32)
    surfels = point_surfels(points, areas=True)
    for camera in torch.tensor(rng.uniform(-0.85, 0.85, (14, 3)), dtype=torch.float32):
        rows = zbuffer.buffer_rows(points, surfels[:, 4], camera)
        kernels = zbuffer.surfel_zbuffer(points, surfels, camera, rows)
        torch_ops = zbuffer._surfel_zbuffer_torch(points, surfels, camera, rows)
        assert torch.equal(kernels[:, 0], torch_ops[:, 0]), f"another front disc from {camera.tolist()}"
        torch.testing.assert_close(torch_ops, kernels, rtol=1e-5, atol=1e-5)


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
