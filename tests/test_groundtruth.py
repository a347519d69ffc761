"""Ray-cast ground truth (``o3dvis.groundtruth``) against analytic answers."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis import visibility_from_mesh
from o3dvis.training.data.sample import sample_surface


def _surface(mesh: o3d.geometry.TriangleMesh, count: int, seed: int = 0) -> np.ndarray:
    return sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.triangles), count,
                          np.random.default_rng(seed))[0]


def _cameras(count: int, distance: float, center=(0.0, 0.0, 0.0), seed: int = 1) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(count, 3))
    return np.asarray(center) + distance * d / np.linalg.norm(d, axis=1, keepdims=True)


def _sphere(center, radius: float) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh.create_sphere(radius, resolution=80).translate(center)


def _first_sphere_hit(cameras: np.ndarray, targets: np.ndarray, center, radius: float) -> np.ndarray:
    """Distance along camera->target to the first crossing of an exact sphere (inf when missed)."""
    u = targets[None] - cameras[:, None]
    length = np.linalg.norm(u, axis=2)
    u = u / length[..., None]
    oc = cameras[:, None] - np.asarray(center)
    b = np.einsum("vnk,vnk->vn", u, oc)
    disc = b ** 2 - (np.einsum("vnk,vnk->vn", oc, oc) - radius ** 2)
    t = -b - np.sqrt(np.maximum(disc, 0))
    return np.where(disc > 0, t, np.inf)


def _grazing(cameras: np.ndarray, targets: np.ndarray, center, radius: float, margin: float) -> np.ndarray:
    """Rays passing within ``margin`` of the sphere's silhouette (the analytic answer is ambiguous there)."""
    u = targets[None] - cameras[:, None]
    u = u / np.linalg.norm(u, axis=2, keepdims=True)
    oc = np.asarray(center) - cameras[:, None]
    miss = np.linalg.norm(oc - np.einsum("vnk,vnk->vn", oc, u)[..., None] * u, axis=2)
    return np.abs(miss - radius) < margin * radius


def test_sphere_matches_analytic_away_from_silhouette():
    center, radius = np.array([0.3, -0.2, 0.1]), 1.0
    mesh = _sphere(center, radius)
    points = _surface(mesh, 20_000)
    cameras = _cameras(8, 2 * np.sqrt(3) * radius, center)
    vis = visibility_from_mesh(mesh, points, cameras)
    normal = points - center
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    to_cam = cameras[:, None] - points[None]
    cos = np.einsum("nk,vnk->vn", normal, to_cam) / np.linalg.norm(to_cam, axis=2)
    analytic = cos > 0
    away = np.abs(cos) > 0.05
    assert away.mean() > 0.9
    assert (vis[away] == analytic[away]).mean() >= 0.999
    assert 0.35 < vis.mean() < 0.5  # a bit less than half of a sphere from a finite distance


@pytest.mark.parametrize("offset, camera_distance", [(1e4, 3.0), (0.0, 3e3), (1e5, 3e3)])
def test_far_from_the_origin_keeps_precision(offset, camera_distance):
    """Embree casts in float32: a unit sphere at 1e5 or a camera 3 km away must still be labelled right."""
    center = np.array([offset, -offset / 2, 0.3 * offset])
    mesh = _sphere(center, 1.0)
    points = _surface(mesh, 4000)
    cameras = _cameras(4, camera_distance, center)
    vis = visibility_from_mesh(mesh, points, cameras)
    normal = (points - center) / np.linalg.norm(points - center, axis=1, keepdims=True)
    to_cam = cameras[:, None] - points[None]
    cos = np.einsum("nk,vnk->vn", normal, to_cam) / np.linalg.norm(to_cam, axis=2)
    away = np.abs(cos) > 0.05
    assert (vis[away] == (cos > 0)[away]).mean() >= 0.999


def test_box_matches_face_orientation():
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 0.5).translate((-0.5, -1.0, -0.25))
    points = _surface(mesh, 10_000, seed=2)
    cameras = _cameras(6, 4.0, seed=3)
    vis = visibility_from_mesh(mesh, points, cameras)
    half = np.array([0.5, 1.0, 0.25])
    face = np.argmax(np.abs(points) / half, axis=1)  # the axis whose face the point lies on
    normal = np.zeros_like(points)
    normal[np.arange(len(points)), face] = np.sign(points[np.arange(len(points)), face])
    to_cam = cameras[:, None] - points[None]
    cos = np.einsum("nk,vnk->vn", normal, to_cam) / np.linalg.norm(to_cam, axis=2)
    near_edge = np.sort(np.abs(np.abs(points) - half), axis=1)[:, 1] < 1e-3
    away = (np.abs(cos) > 0.02) & ~near_edge[None]
    assert (vis[away] == (cos > 0)[away]).mean() >= 0.999
    assert vis[away].any() and (~vis[away]).any()


def test_sphere_hiding_another_sphere():
    big_c, big_r = np.array([0.0, 0.0, 0.0]), 1.0
    small_c, small_r = np.array([0.0, 0.0, -2.0]), 0.6
    mesh = _sphere(big_c, big_r) + _sphere(small_c, small_r)
    points = np.concatenate([_surface(_sphere(big_c, big_r), 6000, 4), _surface(_sphere(small_c, small_r), 6000, 5)])
    on_small = np.arange(len(points)) >= 6000
    cameras = np.array([[0.0, 0.0, 4.0], [0.3, 0.2, 5.0], [4.0, 0.0, -1.0], [0.0, 0.0, -6.0]])
    vis = visibility_from_mesh(mesh, points, cameras)
    # exact spheres: push each point onto its own analytic sphere, then intersect the segment with both
    center = np.where(on_small[:, None], small_c, big_c)
    radius = np.where(on_small, small_r, big_r)
    exact = center + radius[:, None] * (points - center) / np.linalg.norm(points - center, axis=1, keepdims=True)
    dist = np.linalg.norm(exact[None] - cameras[:, None], axis=2)
    first = np.minimum(_first_sphere_hit(cameras, exact, big_c, big_r),
                       _first_sphere_hit(cameras, exact, small_c, small_r))
    analytic = first >= dist - 1e-6
    ambiguous = _grazing(cameras, exact, big_c, big_r, 0.03) | _grazing(cameras, exact, small_c, small_r, 0.03)
    away = ~ambiguous
    assert (vis[away] == analytic[away]).mean() >= 0.999
    # from straight above the big sphere hides the small one completely; from below the small one
    # hides the big one's bottom cap, not its rim
    assert not vis[0, on_small].any() and vis[0, ~on_small].any()
    cap = ~on_small & (np.hypot(points[:, 0], points[:, 1]) < 0.3)
    assert cap.sum() > 50 and not vis[3, cap].any()
    assert vis[3, ~on_small].any() and vis[3, on_small].any()


def test_point_exactly_on_silhouette_is_visible():
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    camera = np.array([0.5, -3.0, 0.5])  # sees the face y = 0; its edges are the silhouette
    edge_points = np.array([[0.5, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.5]])
    hidden = np.array([[0.5, 1.0, 1.0], [0.5, 0.5, 1.0], [0.5, 1.0, 0.5]])
    vis = visibility_from_mesh(box, np.concatenate([edge_points, hidden]), camera)
    assert vis.shape == (1, 7)
    assert vis[0, :4].all() and not vis[0, 4:].any()


def test_batched_equals_one_call_per_camera():
    mesh = o3d.geometry.TriangleMesh.create_torus(1.0, 0.3)
    points = _surface(mesh, 3000)
    cameras = _cameras(5, 3.0)
    batched = visibility_from_mesh(mesh, points, cameras)
    single = np.concatenate([visibility_from_mesh(mesh, points, c) for c in cameras])
    assert batched.dtype == bool and batched.shape == (5, 3000)
    np.testing.assert_array_equal(batched, single)
    assert 0.05 < batched.mean() < 0.95


def test_tensor_mesh_and_arrays_give_the_same_answer():
    mesh = o3d.geometry.TriangleMesh.create_torus(1.0, 0.3)
    points = _surface(mesh, 2000)
    cameras = _cameras(3, 3.0)
    legacy = visibility_from_mesh(mesh, points, cameras)
    tensor = visibility_from_mesh(o3d.t.geometry.TriangleMesh.from_legacy(mesh), points, cameras)
    arrays = visibility_from_mesh((np.asarray(mesh.vertices), np.asarray(mesh.triangles)), points, cameras)
    np.testing.assert_array_equal(legacy, tensor)
    np.testing.assert_array_equal(legacy, arrays)


@pytest.mark.parametrize("mesh, points, cameras, error", [
    ("box", np.zeros((4, 2)), np.ones(3) * 5, ValueError),
    ("box", np.zeros((4, 3)), np.ones(2), ValueError),
    ("box", np.full((4, 3), np.nan), np.ones(3) * 5, ValueError),
    ("box", np.zeros((4, 3)), np.array([np.inf, 0, 0]), ValueError),
    ("empty", np.zeros((4, 3)), np.ones(3) * 5, ValueError),
    ("bad-index", np.zeros((4, 3)), np.ones(3) * 5, ValueError),
    ("bad-shape", np.zeros((4, 3)), np.ones(3) * 5, ValueError),
    ("pcd", np.zeros((4, 3)), np.ones(3) * 5, TypeError),
    ("text", np.zeros((4, 3)), np.ones(3) * 5, TypeError),
])
def test_bad_input_raises(mesh, points, cameras, error):
    box = o3d.geometry.TriangleMesh.create_box()
    meshes = {"box": box, "empty": o3d.geometry.TriangleMesh(),
              "bad-index": (np.asarray(box.vertices), np.asarray(box.triangles) + 10),
              "bad-shape": (np.asarray(box.vertices)[:, :2], np.asarray(box.triangles)),
              "pcd": o3d.geometry.PointCloud(box.vertices), "text": "box.ply"}
    with pytest.raises(error):
        visibility_from_mesh(meshes[mesh], points, cameras)
