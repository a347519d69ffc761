"""The drop-ins reuse the encoding of the same, unchanged cloud asked again, and only then."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis import encodings
from o3dvis.neural import NeuralVisibility
from o3dvis.evaluation.speed import bench_cloud


@pytest.fixture
def counted(monkeypatch):
    """The number of clouds encoded so far (every NeuralVisibility), starting from a cleared memory."""
    encodings.clear()
    calls = []
    encode = NeuralVisibility.encode

    def spy(self, *args, **kwargs):
        calls.append(self)
        return encode(self, *args, **kwargs)

    monkeypatch.setattr(NeuralVisibility, "encode", spy)
    yield calls
    encodings.clear()


@pytest.fixture(scope="module")
def scene():
    cloud = bench_cloud(3000, 4)
    return cloud.points, cloud.cameras


def _fresh(points: np.ndarray, camera: np.ndarray, model=None) -> list[int]:
    """The drop-in's answer with nothing kept."""
    encodings.clear()
    _, pt_map = o3dvis.hidden_point_removal_neural(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)),
                                                   camera, model=model)
    encodings.clear()
    return pt_map


def test_a_loop_over_cameras_encodes_once_and_answers_as_fresh_calls(scene, counted):
    points, cameras = scene
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    answers = [o3dvis.hidden_point_removal_neural(pcd, c)[1] for c in cameras]
    visible = o3dvis.select_visible(pcd, cameras[0])
    assert len(counted) == 1
    assert [np.asarray(visible.points).tolist()] == [points[answers[0]].tolist()]
    fresh = [_fresh(points, c) for c in cameras]
    assert answers == fresh and len({len(a) for a in answers}) > 1


def test_a_cloud_changed_in_place_is_encoded_anew(scene, counted):
    points, cameras = scene
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    before = o3dvis.hidden_point_removal_neural(pcd, cameras[0])[1]
    moved = points.copy()
    moved[: len(points) // 2] *= 0.5  # half the cloud shrinks towards the origin
    np.asarray(pcd.points)[:] = moved  # in place: the same object, the same buffer
    after = o3dvis.hidden_point_removal_neural(pcd, cameras[0])[1]
    assert len(counted) == 2
    assert after == _fresh(moved, cameras[0]) and after != before
    np.asarray(pcd.points)[7, 0] += 1e-9  # one coordinate, by a hair
    o3dvis.hidden_point_removal_neural(pcd, cameras[0])
    assert len(counted) == 4  # the _fresh call above encoded too


def test_tensor_clouds_normals_and_points_added_are_encoded_anew(scene, counted):
    points, cameras = scene
    pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    o3dvis.hidden_point_removal_neural(pcd, cameras[0])
    o3dvis.hidden_point_removal_neural(pcd, cameras[1])
    assert len(counted) == 1
    pcd.point.positions = o3d.core.Tensor(points[:-10])
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, cameras[1])
    assert len(counted) == 2 and int(pt_map.max().item()) < len(points) - 10
    legacy = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3dvis.select_visible(legacy, cameras[0])
    legacy.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (len(points), 1)))
    o3dvis.select_visible(legacy, cameras[0])
    o3dvis.select_visible(legacy, cameras[0], normals=False)
    o3dvis.select_visible(legacy, cameras[0], normals=np.asarray(legacy.normals))
    o3dvis.select_visible(legacy, cameras[0], normals=np.asarray(legacy.normals))
    assert len(counted) == 7  # explicit normals are never kept


def test_another_model_or_changed_weights_are_encoded_anew(scene, counted):
    points, cameras = scene
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    mine = NeuralVisibility.pretrained(precision="float32")
    o3dvis.hidden_point_removal_neural(pcd, cameras[0], model=mine)
    o3dvis.hidden_point_removal_neural(pcd, cameras[0])  # the shared default model
    o3dvis.hidden_point_removal_neural(pcd, cameras[0], model=mine)
    o3dvis.hidden_point_removal_neural(pcd, cameras[1], model=mine)
    assert [m is mine for m in counted] == [True, False, True]
    with torch.no_grad():
        mine.network.unet.head.bias.add_(5.0)  # a network these 3 000 points are not encoded with
    o3dvis.hidden_point_removal_neural(pcd, cameras[1], model=mine)
    assert len(counted) == 3
    with torch.no_grad():
        mine.small_network.unet.head.bias.add_(5.0)  # the one that encodes them, as an optimiser's step would
    _, changed = o3dvis.hidden_point_removal_neural(pcd, cameras[1], model=mine)
    assert len(counted) == 4
    mine.chunk_size = 1000
    o3dvis.hidden_point_removal_neural(pcd, cameras[1], model=mine)
    assert len(counted) == 5
    network = mine.small_network  # the one that encodes these 3 000 points
    network.unet.head = torch.nn.Linear(32, 32)  # a module put in: new tensors
    o3dvis.hidden_point_removal_neural(pcd, cameras[1], model=mine)
    network.unet.head.bias = torch.nn.Parameter(torch.zeros(32))  # a parameter put in
    o3dvis.hidden_point_removal_neural(pcd, cameras[1], model=mine)
    o3dvis.hidden_point_removal_neural(pcd, cameras[2], model=mine)
    assert len(counted) == 7
    with torch.no_grad():
        network.predictor.project_feature.weight.mul_(1.5)  # beside the U-Net: the features' projection
    o3dvis.hidden_point_removal_neural(pcd, cameras[2], model=mine)
    network.predictor = type(network.predictor)(32 + 3, 4, network.predictor.mlp[0].in_features - 27, (32, 32))
    o3dvis.hidden_point_removal_neural(pcd, cameras[2], model=mine)
    assert len(counted) == 9


def test_large_clouds_are_not_kept(scene, counted, monkeypatch):
    points, cameras = scene
    monkeypatch.setattr(encodings, "MAX_POINTS", len(points) - 1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3dvis.hidden_point_removal_neural(pcd, cameras[0])
    o3dvis.hidden_point_removal_neural(pcd, cameras[1])
    assert len(counted) == 2 and encodings._last is None


def test_cameras_inside_and_outside_are_kept_apart(counted):
    """With the shipped scene model, a loop of cameras inside a room encodes once, and a camera on the
    other side of the bounding box gets its own network's field, as a fresh call does."""
    rng = np.random.default_rng(3)
    room = rng.uniform(-1, 1, (4000, 3))
    room[np.arange(4000), rng.integers(0, 3, 4000)] = rng.choice([-1.0, 1.0], 4000)  # on the walls
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(room))
    model = o3dvis.NeuralVisibility.pretrained()
    if model.scene_network is None:
        pytest.skip("no scene model installed")
    inside, outside = np.array([[0.1, 0.2, -0.3], [-0.4, 0.1, 0.2]]), np.array([[3.0, 0.5, 0.2]])
    answers = [o3dvis.hidden_point_removal_neural(pcd, c, model=model)[1] for c in inside]
    assert len(counted) == 1
    far = o3dvis.hidden_point_removal_neural(pcd, outside[0], model=model)[1]
    again = o3dvis.hidden_point_removal_neural(pcd, inside[0], model=model)[1]
    assert len(counted) == 3
    assert answers + [far, again] == [_fresh(room, c, model) for c in [*inside, outside[0], inside[0]]]
    o3dvis.hidden_point_removal_neural(pcd, inside[0], model=model)
    model.scene_network = model.small_network  # another network answers the cameras inside
    put_in = o3dvis.hidden_point_removal_neural(pcd, inside[0], model=model)[1]
    assert put_in == _fresh(room, inside[0], model) != again


def test_networks_and_rotations_put_in_anew_are_encoded_anew(scene, counted):
    """What the model holds now decides: a network put in (or taken out) where the cloud is routed, and
    rotations of the same count but other turns, give the answer of a fresh call, not the kept one."""
    from o3dvis.geometry import fixed_rotations

    points, cameras = scene
    model = NeuralVisibility.pretrained(precision="float32")
    other = NeuralVisibility.pretrained(precision="float32").scene_network  # a network without normals
    if other is None or model.small_network is None or model.normals_network is None:
        pytest.skip("needs the shipped scene, small and normals models")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals()
    pcd.orient_normals_towards_camera_location(points.mean(axis=0))
    answers = [o3dvis.hidden_point_removal_neural(pcd, cameras[0], model=model)[1]]
    changes = [lambda: setattr(model, "normals_network", None),  # the normals now go unused
               lambda: setattr(model, "small_network", other),  # these 3 000 points' network, put in anew
               lambda: setattr(model, "small_network", None),  # the main network answers them
               lambda: setattr(model, "network", other),
               lambda: setattr(model, "rotations", fixed_rotations(2)),
               lambda: setattr(model, "rotations", fixed_rotations(3)[[0, 2]])]  # as many turns, other ones
    for change in changes:
        change()
        kept = o3dvis.hidden_point_removal_neural(pcd, cameras[0], model=model)[1]
        encodings.clear()
        fresh = o3dvis.hidden_point_removal_neural(pcd, cameras[0], model=model)[1]
        assert kept == fresh
        answers.append(fresh)
    assert all(a != b for a, b in zip(answers, answers[1:]))  # each change changed the answer
