"""HPR baselines: agreement with analytic visibility, parity with Open3D, degenerate inputs."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis.baselines import (SWEEPS, exponential_hpr_mask, exponential_method, hidden_point_removal_mask,
                              hpr_method, sweep, zbuffer_mask, zbuffer_method)

METHODS = [hpr_method(2.0), exponential_method(-0.01)]


def _sphere_points(n: int, seed: int = 0) -> np.ndarray:
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def _cameras(count: int, distance: float, seed: int = 1) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(count, 3))
    return distance * d / np.linalg.norm(d, axis=1, keepdims=True)


def _facing(points: np.ndarray, normals: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """cos of the angle between each normal and the direction to each camera, (V, N)."""
    to_cam = cameras[:, None] - points[None]
    return np.einsum("nk,vnk->vn", normals, to_cam) / np.linalg.norm(to_cam, axis=2)


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_sphere_is_near_perfect(method):
    points = _sphere_points(8000)
    cameras = _cameras(4, 2.0)
    mask = method(points, cameras)
    cos = _facing(points, points, cameras)
    assert mask.shape == (4, 8000) and mask.dtype == bool
    assert (mask == (cos > 0)).mean() > 0.985
    away = np.abs(cos) > 0.15
    assert (mask[away] == (cos > 0)[away]).mean() > 0.999


def test_matches_open3d_hidden_point_removal():
    rng = np.random.default_rng(2)
    points = rng.normal(size=(3000, 3)) * [1.0, 0.5, 0.2]
    cameras = _cameras(3, 4.0)
    mask = hidden_point_removal_mask(points, cameras, radius=50.0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    for v, camera in enumerate(cameras):
        expected = np.zeros(len(points), dtype=bool)
        expected[pcd.hidden_point_removal(camera, 50.0)[1]] = True
        np.testing.assert_array_equal(mask[v], expected)


def test_radius_and_gamma_trade_false_negatives_for_false_positives():
    """Larger radius / gamma nearer 0 mark more points visible, on a concave (noisy) cloud."""
    rng = np.random.default_rng(3)
    points = _sphere_points(4000) * rng.uniform(0.9, 1.1, (4000, 1))
    camera = np.array([0.0, 0.0, 3.0])
    counts = [hidden_point_removal_mask(points, camera, r).sum() for r in (3.0, 30.0, 3000.0)]
    assert counts[0] < counts[1] < counts[2]
    counts = [exponential_hpr_mask(points, camera, g).sum() for g in (-0.3, -0.03, -0.001)]
    assert counts[0] < counts[1] < counts[2]


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_scale_and_translation_invariant(method):
    rng = np.random.default_rng(4)
    points = rng.normal(size=(2000, 3)) * [1.0, 0.7, 0.3]
    cameras = _cameras(2, 3.0)
    shift = np.array([10.0, -5.0, 2.0])
    np.testing.assert_array_equal(method(points, cameras), method(points * 7.0 + shift, cameras * 7.0 + shift))


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_duplicates_share_one_answer(method):
    points = _sphere_points(1500, seed=5)
    cameras = _cameras(3, 2.5)
    doubled = np.concatenate([points, points[::3]])
    mask = method(doubled, cameras)
    np.testing.assert_array_equal(mask[:, :1500], method(points, cameras))
    np.testing.assert_array_equal(mask[:, 1500:], mask[:, :1500][:, ::3])


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_planar_cloud_seen_from_off_the_plane_is_all_visible(method):
    rng = np.random.default_rng(6)
    points = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    assert method(points, [[0.2, 0.1, 3.0], [1.0, -2.0, -2.0]]).all()


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_circle_seen_from_its_plane_matches_the_2d_answer(method):
    """Points and camera coplanar: solved as 2-D HPR, which is exact on a circle."""
    angle = np.linspace(0, 2 * np.pi, 721)[:-1]
    points = np.c_[np.cos(angle), np.sin(angle), np.zeros_like(angle)]
    camera = np.array([[3.0, 0.5, 0.0]])
    cos = _facing(points, points, camera)
    mask = method(points, camera)
    away = np.abs(cos) > 0.1
    np.testing.assert_array_equal(mask[away], (cos > 0)[away])


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_collinear_points(method):
    t = np.linspace(-1, 1, 50)
    line = np.c_[t, np.zeros(50), np.zeros(50)]
    assert method(line, [0.0, 0.0, 2.0]).all()  # off the line: nothing is in front of anything
    on_axis = method(line, [5.0, 0.0, 0.0])  # on the line: only the nearest point
    np.testing.assert_array_equal(np.flatnonzero(on_axis[0]), [49])


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
@pytest.mark.parametrize("n", [1, 2, 3])
def test_fewer_than_four_points_are_all_visible(method, n):
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])[:n]
    assert method(points, [0.3, 0.2, 4.0]).all()


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_all_points_identical(method):
    assert method(np.ones((20, 3)), [0.0, 0.0, 5.0]).all()


@pytest.mark.parametrize("method", METHODS, ids=lambda m: m.__name__)
def test_nearly_flat_cloud_does_not_crash(method):
    rng = np.random.default_rng(7)
    points = np.c_[rng.uniform(-1, 1, (400, 2)), 1e-13 * rng.normal(size=400)]
    mask = method(points, [[0.0, 0.0, 3.0], [3.0, 0.0, 0.0]])
    assert mask[0].mean() > 0.95  # from above the sheet every point shows


@pytest.mark.parametrize("call, error", [
    (lambda: hidden_point_removal_mask(np.zeros((5, 2)), [0, 0, 1], 1.0), ValueError),
    (lambda: hidden_point_removal_mask(np.zeros((0, 3)), [0, 0, 1], 1.0), ValueError),
    (lambda: hidden_point_removal_mask(np.full((5, 3), np.nan), [0, 0, 1], 1.0), ValueError),
    (lambda: hidden_point_removal_mask(np.eye(3), [[0, 0]], 1.0), ValueError),
    (lambda: hidden_point_removal_mask(np.eye(3), [0, 0, 5], 0.0), ValueError),
    (lambda: hidden_point_removal_mask(np.eye(3), [0, 0, 5], -1.0), ValueError),
    (lambda: hidden_point_removal_mask(np.eye(3), [1, 0, 0], 10.0), ValueError),  # a point at the camera
    (lambda: exponential_hpr_mask(np.eye(3), [0, 0, 5], 0.5), ValueError),
    (lambda: exponential_hpr_mask(np.eye(3), [0, 0, np.inf], -0.1), ValueError),
    (lambda: hpr_method(2.0)(np.eye(3), [1, 0, 0]), ValueError),
    (lambda: sweep("nope"), ValueError),
])
def test_bad_input_raises(call, error):
    with pytest.raises(error):
        call()


def test_sweeps_label_their_parameters():
    for name, (param, _, values) in SWEEPS.items():
        methods = sweep(name)
        assert list(methods) == [f"{param}={v:g}" for v in values]
    assert list(sweep("hpr", [1, 2])) == ["k=1", "k=2"]
    points = _sphere_points(500)
    camera = [0.0, 0.0, 3.0]
    np.testing.assert_array_equal(sweep("hpr", [2])["k=2"](points, camera),
                                  hidden_point_removal_mask(points, camera, 100.0 * np.linalg.norm(
                                      points.max(axis=0) - points.min(axis=0))))


def test_zbuffer_matches_the_sphere_seen_from_outside():
    points = _sphere_points(8000)
    cameras = _cameras(3, 2.5)
    mask = zbuffer_mask(points, cameras)
    cos = _facing(points, points, cameras)
    away = np.abs(cos) > 0.15
    assert (mask[away] == (cos > 0)[away]).mean() > 0.99


def test_zbuffer_answers_cameras_inside_a_partitioned_room():
    from o3dvis.groundtruth import visibility_from_mesh
    from o3dvis.training.data.scenes import box_scene, sample_uniform

    walls = [((-4.2, -2.2, -0.2), (4.2, 2.2, 0)), ((-4.2, -2.2, 3), (4.2, 2.2, 3.2)),
             ((-4.2, -2.2, -0.2), (-4, 2.2, 3.2)), ((4, -2.2, -0.2), (4.2, 2.2, 3.2)),
             ((-4.2, -2.2, -0.2), (4.2, -2, 3.2)), ((-4.2, 2, -0.2), (4.2, 2.2, 3.2)),
             ((-0.1, -2, -0.2), (0.1, 0.5, 3.2))]  # a partition with a gap at y > 0.5
    scene = box_scene(walls, [(-4, -2, 0.3), (4, 2, 2.7)])
    points, _ = sample_uniform(scene, 20_000, np.random.default_rng(8))
    cameras = np.array([[-2.0, -1.0, 1.5], [2.5, 1.2, 0.8]])
    truth = visibility_from_mesh(scene.mesh, points, cameras)
    mask = zbuffer_mask(points, cameras)
    assert 0.2 < truth.mean() < 0.8
    assert (mask == truth).mean() > 0.9  # the misses sit along edges, where the PCA normal bends
    # a larger disc hides more
    assert zbuffer_mask(points, cameras, splat=1.5).sum() < mask.sum() < zbuffer_mask(points, cameras, splat=0.5).sum()


@pytest.mark.parametrize("call", [
    lambda: zbuffer_mask(np.eye(3), [0, 0, 5], splat=0.0),
    lambda: zbuffer_mask(np.eye(3), [0, 0, 5], tolerance=-1.0),
    lambda: zbuffer_mask(np.eye(3), [1, 0, 0]),  # a point at the camera
    lambda: zbuffer_method(1.0)(np.zeros((4, 2)), [0, 0, 1]),
])
def test_zbuffer_bad_input_raises(call):
    with pytest.raises(ValueError):
        call()
