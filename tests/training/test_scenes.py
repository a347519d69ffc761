"""Procedural scenes: analytic visibility inside a partitioned room, LiDAR-like sampling, free cameras,
determinism, and the prepared files the trainer reads."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis import visibility_from_mesh
from o3dvis.training.data import load_sample
from o3dvis.training.data.prepare import label_scene, prepare_scenes
from o3dvis.training.data.scenes import (HeightField, box_scene, free_positions, random_rooms, random_scene,
                                         random_street, sample_lidar, sample_uniform, scene_sample)

CLOSED = ("box", "sphere", "cylinder", "cone", "torus")  # primitives with no open surface

# a closed 8 x 4 x 3 m room (inside), walls 0.2 m thick, a partition 0.2 m thick at x = 0
L, W, H, T = 4.0, 2.0, 3.0, 0.2


def _room(door: tuple[float, float, float] | None = None):
    """The partitioned room; ``door`` = (y0, y1, top) cuts a door gap in the partition."""
    shell = [((-L - T, -W - T, -T), (L + T, W + T, 0)), ((-L - T, -W - T, H), (L + T, W + T, H + T)),
             ((-L - T, -W - T, -T), (-L, W + T, H + T)), ((L, -W - T, -T), (L + T, W + T, H + T)),
             ((-L - T, -W - T, -T), (L + T, -W, H + T)), ((-L - T, W, -T), (L + T, W + T, H + T))]
    # the partition reaches into the floor and the ceiling, so that no face lies on another
    if door is None:
        partition = [((-T / 2, -W, -T), (T / 2, W, H + T))]
    else:
        y0, y1, top = door
        partition = [((-T / 2, -W, -T), (T / 2, y0, H + T)), ((-T / 2, y1, -T), (T / 2, W, H + T)),
                     ((-T / 2, y0, top), (T / 2, y1, H + T))]
    return box_scene(shell + partition, [(-L, -W, 0.3), (L, W, H - 0.3)])


def _on_box_boundary(points, lo, hi, eps=1e-6):
    inside = ((points >= np.asarray(lo) - eps) & (points <= np.asarray(hi) + eps)).all(axis=1)
    on_face = ((np.abs(points - lo) < eps) | (np.abs(points - hi) < eps)).any(axis=1)
    return inside & on_face


def test_camera_in_one_half_sees_exactly_its_own_half():
    scene = _room()
    points, _ = sample_uniform(scene, 30_000, np.random.default_rng(0))
    cameras = np.array([[-2.0, 0.5, 1.5], [-0.5, -1.5, 0.4], [3.0, 1.0, 2.5]])
    vis = visibility_from_mesh(scene.mesh, points, cameras)
    halves = [((-L, -W, 0), (-T / 2, W, H)), ((T / 2, -W, 0), (L, W, H))]
    left, right = (_on_box_boundary(points, lo, hi) for lo, hi in halves)
    assert left.sum() > 5000 and right.sum() > 5000
    # points less than 1 mm outside a half (on the floor, just under a wall) are within the
    # ground truth's depth tolerance of its boundary: either answer is right
    gap = [np.linalg.norm(np.maximum(np.maximum(np.subtract(lo, points), np.subtract(points, hi)), 0), axis=1)
           for lo, hi in halves]
    clear = ~np.any([(g > 1e-9) & (g < 1e-3) for g in gap], axis=0)
    assert clear.mean() > 0.99
    # a convex empty half: its camera sees every point of its boundary and nothing else
    np.testing.assert_array_equal(vis[0][clear], left[clear])
    np.testing.assert_array_equal(vis[1][clear], left[clear])
    np.testing.assert_array_equal(vis[2][clear], right[clear])


def test_door_gap_shows_the_far_wall_through_it_only():
    y0, y1, top = -0.5, 0.5, 2.0
    scene = _room(door=(y0, y1, top))
    points, _ = sample_uniform(scene, 60_000, np.random.default_rng(1))
    camera = np.array([-2.5, 0.2, 1.2])
    vis = visibility_from_mesh(scene.mesh, points, camera)[0]
    far = np.abs(points[:, 0] - L) < 1e-6  # the right half's far wall (inner face)
    # the ray crosses both faces of the partition inside the door opening
    margin = 0.02
    through = np.ones(len(points), dtype=bool)
    grazing = np.zeros(len(points), dtype=bool)
    for x in (-T / 2, T / 2):
        s = (x - camera[0]) / (points[:, 0] - camera[0])
        y, z = camera[1] + s * (points[:, 1] - camera[1]), camera[2] + s * (points[:, 2] - camera[2])
        through &= (y > y0) & (y < y1) & (z < top)
        grazing |= (np.abs(y - y0) < margin) | (np.abs(y - y1) < margin) | (np.abs(z - top) < margin)
    clear = far & ~grazing
    assert (through & clear).sum() > 300 and (~through & clear).sum() > 300
    np.testing.assert_array_equal(vis[clear], through[clear])


def test_lidar_points_are_seen_by_their_sensor_and_only_where_a_sensor_looked():
    scene = _room()  # closed partition: the right half is out of sight of a sensor on the left
    sensors = np.array([[-2.0, 0.0, 1.5], [-3.0, 1.0, 0.8]])
    points, normals, owner = sample_lidar(scene, 20_000, sensors, np.random.default_rng(2), max_range=5.0)
    assert points.shape == (20_000, 3) and set(np.unique(owner)) == {0, 1}
    assert (points[:, 0] < 0).all()
    assert (np.linalg.norm(points - sensors[owner], axis=1) <= 5.0 + 1e-6).all()
    seen = visibility_from_mesh(scene.mesh, points, sensors)
    assert seen[owner, np.arange(len(points))].all()
    # normals face their sensor
    assert (np.einsum("ij,ij->i", normals, sensors[owner] - points) > 0).all()
    # density falls with range: a patch of the wall 0.5 m from one sensor holds far more points than the
    # same patch of the partition 3.4 m away
    points, _, _ = sample_lidar(scene, 20_000, [[-3.5, 0.0, 1.5]], np.random.default_rng(3))
    near = np.linalg.norm(points - [-L, 0.0, 1.5], axis=1) < 0.5
    far = np.linalg.norm(points - [-T / 2, 0.0, 1.5], axis=1) < 0.5
    assert near.sum() > 10 * far.sum() > 0


def test_lidar_range_limit_and_bad_sensors():
    scene = _room()
    with pytest.raises(ValueError, match="max_range"):
        sample_lidar(scene, 10, [[-2.0, 0.0, 1.5]], np.random.default_rng(0), max_range=0.0)
    with pytest.raises(ValueError, match="sensors"):
        sample_lidar(scene, 10, np.zeros((0, 3)), np.random.default_rng(0))
    with pytest.raises(RuntimeError, match="hit"):
        sample_lidar(scene, 10, [[-2.0, 0.0, 1.5]], np.random.default_rng(0), max_range=0.1)


def _ball_room(rng, primitives):
    """The partitioned room with a ball 2.4 m wide filling much of its left half."""
    ball = o3d.geometry.TriangleMesh.create_sphere(1.2, 40).translate((-2.0, 0.0, 1.4))
    room = _room()
    return box_scene(room.solids, room.region, [ball])


@pytest.mark.parametrize("make", [random_rooms, random_street, _ball_room])
def test_free_cameras_are_never_inside_an_object(make):
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(400, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for _ in range(3):
        scene = make(rng, primitives=CLOSED)
        cameras = free_positions(scene, 12, rng, margin=0.3)
        lo, hi = scene.region
        assert ((cameras[:, :2] >= lo[:2]) & (cameras[:, :2] <= hi[:2])).all()
        boxes = np.concatenate([scene.solids, scene.obstacles])
        assert not ((cameras[:, None] > boxes[:, 0]) & (cameras[:, None] < boxes[:, 1])).all(axis=2).any()
        # every ray from a camera outside all objects first meets a surface from its front
        for camera in cameras:
            rays = np.column_stack([np.broadcast_to(camera, directions.shape), directions]).astype(np.float32)
            hit = scene.raycaster().cast_rays(o3d.core.Tensor(rays))
            t, n = hit["t_hit"].numpy(), hit["primitive_normals"].numpy()
            met = np.isfinite(t)
            assert (t[met] >= 0.3 - 1e-4).all()
            assert (np.einsum("ij,ij->i", n[met], directions[met]) < 0).all()


def test_height_field_matches_its_mesh():
    rng = np.random.default_rng(4)
    field = HeightField(np.array([-3.0, -2.0]), 0.7, rng.normal(size=(9, 7)))
    vertices, triangles = field.mesh()
    caster = o3d.t.geometry.RaycastingScene()
    caster.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    xy = rng.uniform([-3.0, -2.0], [-3.0 + 8 * 0.7, -2.0 + 6 * 0.7], (500, 2))
    rays = np.column_stack([xy, np.full(len(xy), 50.0), np.tile([0.0, 0.0, -1.0], (len(xy), 1))])
    hit = caster.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    np.testing.assert_allclose(50.0 - hit["t_hit"].numpy(), field.height(xy), atol=1e-4)
    assert (hit["primitive_normals"].numpy()[:, 2] > 0).all()


def test_uniform_points_are_on_exposed_surfaces():
    scene = random_street(np.random.default_rng(5), primitives=CLOSED)
    points, _ = sample_uniform(scene, 20_000, np.random.default_rng(6))
    assert not scene.buried(points).any()
    distance = scene.raycaster().compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
    assert distance.max() < 1e-3
    assert (points[:, 2] >= scene.floor(points[:, :2]) - 1e-3).all()


@pytest.mark.parametrize("sampling", ["uniform", "lidar"])
def test_scene_sample_is_deterministic_and_labels_inside_cameras(sampling, tmp_path):
    mesh = o3d.geometry.TriangleMesh.create_torus()
    path = tmp_path / "thing.ply"
    o3d.io.write_triangle_mesh(str(path), mesh)

    def make(seed):
        rng = np.random.default_rng(seed)
        scene = random_scene("rooms", rng, [path])
        return scene_sample(scene, sampling, 5000, 6, 2, rng)

    a, b, c = make(7), make(7), make(8)
    for field in ("points", "normals", "cameras", "visibility"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(a.points, c.points)
    lo, hi = a.points.min(axis=0), a.points.max(axis=0)
    inside = ((a.cameras > lo) & (a.cameras < hi)).all(axis=1)
    assert inside[:6].all() and not inside[6:].any()
    assert a.visibility.shape == (8, 5000) and a.visibility[:6].any(axis=1).all()


def test_bad_arguments_are_named():
    scene = _room()
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="sampling"):
        scene_sample(scene, "grid", 100, 1, 0, rng)
    with pytest.raises(ValueError, match="camera"):
        scene_sample(scene, "uniform", 100, 0, 0, rng)
    with pytest.raises(ValueError, match="kind"):
        random_scene("forest", rng)
    with pytest.raises(ValueError, match="min < max"):
        box_scene([((0, 0, 0), (1, 0, 1))], [(0, 0, 0), (1, 1, 1)])
    with pytest.raises(RuntimeError, match="free positions"):
        free_positions(scene, 3, rng, margin=5.0, tries=3)


def test_prepared_scenes_load_resume_and_feed_the_dataset(tmp_path):
    torch = pytest.importorskip("torch")
    from o3dvis.training.data.dataset import Augmentation, VisibilityDataset, collate

    result = prepare_scenes(tmp_path, 2, None, num_points=3000, num_views=8, progress=False)
    assert result == {"done": 2, "skipped": 0, "failed": []}
    files = sorted(tmp_path.glob("*.npz"))
    assert [f.name for f in files] == ["rooms-lidar__00000.npz", "rooms-uniform__00000.npz",
                                       "street-lidar__00001.npz", "street-uniform__00001.npz"]
    sample = load_sample(files[1])
    fresh = label_scene(0, [], 3000, 8)[0]
    np.testing.assert_array_equal(sample.visibility, fresh.visibility)
    assert sample.cameras.shape == (8, 3) and sample.visibility.shape == (8, 3000)
    assert prepare_scenes(tmp_path, 2, None, num_points=3000, num_views=8, progress=False)["skipped"] == 2
    data = VisibilityDataset(files, Augmentation(min_points=1000, max_points=2000, views=4), length=4)
    batch = collate([data[i] for i in range(4)])
    assert batch.points.shape[1] == 3 and all(v.dtype == torch.bool for v in batch.labels)
