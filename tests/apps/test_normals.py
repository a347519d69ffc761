"""Normals from visibility (``o3dvis.apps.normals``) on procedural shapes with known answers, run on
ray-cast ground-truth visibility: estimated and oriented normals, co-visible plane fits, Open3D's search
parameters, duplicates, bad input."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis.apps import estimate_normals_neural, orient_normals_neural
from o3dvis.apps.normals import covisible_normals, multiview_normals, neighbourhoods
from o3dvis.orientation import fit_planes

from conftest import _box, _cloud, _sample


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.einsum("ij,ij->i", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def test_sphere_normals_point_outward(sphere):
    points, _, method = sphere
    pcd = estimate_normals_neural(_cloud(points), model=method)
    outward = points / np.linalg.norm(points, axis=1, keepdims=True)
    angles = _angles(np.asarray(pcd.normals), outward)
    assert angles.max() < 90  # every normal oriented
    assert angles.mean() < 3
    assert np.allclose(np.linalg.norm(np.asarray(pcd.normals), axis=1), 1)


def test_box_normals_are_face_normals_and_outward():
    mesh = _box((2.0, 1.0, 0.5), (0.3, -0.2, 0.1))
    points, face_normals, method = _sample(mesh, 5000)
    mesh.compute_triangle_normals()
    assert mesh.is_watertight() and mesh.get_volume() > 0  # face normals point out
    normals = np.asarray(estimate_normals_neural(_cloud(points), num_views=26, model=method).normals)
    angles = _angles(normals, face_normals)
    assert (angles < 90).all()
    assert np.median(angles) < 0.5  # flat faces: triangles in a face are coplanar


def test_tensor_cloud_gets_normals(sphere):
    points, _, method = sphere
    tcloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(np.float32)))
    out = estimate_normals_neural(tcloud, num_views=12, model=method)
    assert out is tcloud
    normals = tcloud.point.normals.numpy()
    assert normals.dtype == np.float32 and normals.shape == points.shape
    assert (np.einsum("ij,ij->i", normals, points) > 0).mean() > 0.99


def test_points_no_view_sees_get_the_plane_of_the_surface():
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.random((500, 2)), np.zeros(500)])

    def top_left_from_above(p, cameras):  # only cameras above the plane see, and only x < 0.7
        return (cameras[:, 2:] > 0.5) & (p[:, 0] < 0.7)

    normals = multiview_normals(points, top_left_from_above, 12)
    assert np.allclose(normals, [0, 0, 1])


def _floor_under_a_lid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A floor (z = 0, normals +z) on a 0.01 grid, x in [0, 1), and a lid 0.04 above its right half
    (normals -z); the method sees the floor's left half from above and the lid from below: the
    nearest seen point of most of the right half of the floor is the lid point above it."""
    x, y = np.meshgrid(np.arange(100) / 100, np.arange(20) / 100, indexing="ij")
    floor = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    lid = floor[floor[:, 0] >= 0.5] + [0, 0, 0.04]
    points = np.concatenate([floor, lid])
    truth = np.repeat([[0, 0, 1.0], [0, 0, -1.0]], [len(floor), len(lid)], axis=0)

    def method(p, cameras):
        on_lid = p[:, 2] > 0.02
        return ((cameras[:, 2:] > 0.5) & ~on_lid & (p[:, 0] < 0.5)) | ((cameras[:, 2:] < -0.5) & on_lid)

    return points, truth, method


@pytest.mark.parametrize("search_param", [None, o3d.geometry.KDTreeSearchParamKNN(16)])
def test_unseen_points_take_the_side_of_the_surface_they_join(search_param):
    points, truth, method = _floor_under_a_lid()
    normals = multiview_normals(points, method, 26, refine_views=0, search_param=search_param)
    assert (np.einsum("ij,ij->i", normals, truth) > 0).all()


def test_orient_propagates_along_the_surface_not_to_the_nearest_point():
    points, truth, method = _floor_under_a_lid()
    far = np.column_stack([np.random.default_rng(2).random((30, 2)), np.full(30, 5.0)])  # joins nothing
    points, truth = np.concatenate([points, far]), np.concatenate([truth, np.tile([0, 0, -1.0], (30, 1))])
    signs = np.where(np.random.default_rng(3).random(len(points)) < 0.5, -1.0, 1.0)
    pcd = _cloud(points)
    pcd.normals = o3d.utility.Vector3dVector(truth * signs[:, None])
    orient_normals_neural(pcd, 26, method, refine_views=0)
    # the far patch, seen by no camera and joined to no seen point, faces as its nearest seen
    # point, on the lid
    assert np.allclose(np.asarray(pcd.normals), truth)


def test_orient_flips_existing_normals_outward(sphere):
    points, _, method = sphere
    outward = points / np.linalg.norm(points, axis=1, keepdims=True)
    signs = np.where(np.random.default_rng(1).random(len(points)) < 0.5, -1.0, 1.0)
    pcd = _cloud(points)
    pcd.normals = o3d.utility.Vector3dVector(outward * signs[:, None])
    orient_normals_neural(pcd, 26, method)
    assert np.allclose(np.asarray(pcd.normals), outward)


def test_orient_open3d_normals_on_a_box():
    mesh = _box((1.5, 1.0, 0.6), (0, 0, 0))
    points, face_normals, method = _sample(mesh, 4000, seed=2)
    pcd = _cloud(points)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(10))
    orient_normals_neural(pcd, 26, method)
    cos = np.einsum("ij,ij->i", np.asarray(pcd.normals), face_normals)
    assert (cos[np.abs(cos) > 0.87] > 0).all()  # every normal within 30 degrees of its face's
    assert (cos > 0).mean() > 0.98  # PCA normals across an edge may lean to the other face


def _wedge(count: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Points on two planes meeting at the y axis at 17 degrees (z = 0 and z = 0.3 x, x in [0, 1]),
    and which plane each is on."""
    rng = np.random.default_rng(5)
    x, y = rng.random(count), rng.random(count)
    upper = np.arange(count) % 2 == 1
    return np.column_stack([x, y, np.where(upper, 0.3 * x, 0.0)]), upper


def test_covisible_fit_leaves_out_neighbours_never_seen_with_the_point():
    points, upper = _wedge()
    truth = np.where(upper[:, None], np.array([-0.3, 0, 1]) / np.hypot(0.3, 1), [0.0, 0, 1])
    neighbours = neighbourhoods(points, o3d.geometry.KDTreeSearchParamKNN(12))
    apex = points[:, 0] < 0.2  # where the other plane's points are among the 12 nearest
    assert (upper[neighbours[apex]] != upper[apex, None]).any(axis=1).mean() > 0.5

    together, fitted = covisible_normals(points, np.ones((2, len(points)), bool), neighbours)
    assert fitted.all()
    assert np.median(_angles(together, truth)[apex] % 180) > 3  # a plain fit mixes the planes

    apart, fitted = covisible_normals(points, np.stack([~upper, upper]), neighbours)
    angles = np.minimum(_angles(apart, truth), 180 - _angles(apart, truth))
    assert fitted.all() and angles.max() < 1e-6


def test_covisible_weights_count_every_shared_view_past_255():
    points, upper = _wedge(200)
    neighbours = neighbourhoods(points, o3d.geometry.KDTreeSearchParamKNN(12))
    # 256 views see every point, 44 more only the upper plane: 300 views, shares of 256 and 300
    visibility = np.concatenate([np.ones((256, len(points)), bool), np.repeat(upper[None], 44, axis=0)])
    padded = np.concatenate([visibility, np.zeros((300, 1), bool)], axis=1)
    shared = (visibility[:, :, None] & padded[:, neighbours]).sum(axis=0)
    expected = fit_planes(points, neighbours, shared / visibility.sum(axis=0)[:, None])
    normals, fitted = covisible_normals(points, visibility, neighbours)
    assert fitted.all() and np.allclose(np.abs(np.einsum("ij,ij->i", normals, expected[0])), 1)


def test_covisible_fit_of_a_point_whose_neighbours_no_view_shares_is_undefined():
    points = np.zeros((6, 3))  # duplicates: the search may return others, not the point itself
    visibility = np.array([[True, False, False, False, False, False]])
    neighbours = np.array([[1, 2, 3]] + [[0, 1, 2]] * 5)
    normals, fitted = covisible_normals(points, visibility, neighbours)
    assert np.isfinite(normals).all() and not fitted[0]


def test_plane_fit_far_from_the_origin_is_exact():
    rng = np.random.default_rng(5)
    points = np.column_stack([rng.random((200, 2)) * 1e-3, np.zeros(200)]) + 1e6
    neighbours = neighbourhoods(points, o3d.geometry.KDTreeSearchParamKNN(8))
    normals, fitted = covisible_normals(points, np.ones((1, 200), bool), neighbours)
    assert fitted.all() and np.abs(normals[:, 2]).min() > 1 - 1e-9


def test_knn_normals_on_a_box_are_face_normals_and_outward(capsys):
    mesh = _box((1.5, 1.0, 0.6), (0, 0, 0))
    points, face_normals, method = _sample(mesh, 4000, seed=2)
    pcd = estimate_normals_neural(_cloud(points), num_views=26, model=method, progress=True,
                                  search_param=o3d.geometry.KDTreeSearchParamKNN(10))
    assert "3/3" in capsys.readouterr().err  # the steps' progress bar
    cos = np.einsum("ij,ij->i", np.asarray(pcd.normals), face_normals)
    assert (cos[np.abs(cos) > 0.87] > 0).all()  # every normal within 30 degrees of its face's
    assert (cos > 0).mean() > 0.98  # a plane fitted next to an edge may be the other face's
    assert np.median(_angles(np.asarray(pcd.normals), face_normals)) < 1


def test_neighbourhoods_follow_open3d_search_parameters():
    points = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    knn = neighbourhoods(points, o3d.geometry.KDTreeSearchParamKNN(3))
    assert knn.shape == (10, 3) and (knn[:, 0] == np.arange(10)).all()  # each point is its own nearest
    hybrid = neighbourhoods(points, o3d.geometry.KDTreeSearchParamHybrid(radius=1.5, max_nn=5))
    assert hybrid.shape == (10, 5)
    assert ((hybrid < 10).sum(axis=1) == [2] + [3] * 8 + [2]).all()  # the rest is padding (= N)
    with pytest.raises(TypeError, match="KDTreeSearchParamKNN"):
        neighbourhoods(points, o3d.geometry.KDTreeSearchParamRadius(1.0))
    with pytest.raises(ValueError, match="at least 1"):
        neighbourhoods(points, o3d.geometry.KDTreeSearchParamKNN(0))
    with pytest.raises(ValueError, match="radius"):
        neighbourhoods(points, o3d.geometry.KDTreeSearchParamHybrid(radius=0.0, max_nn=5))


@pytest.mark.parametrize("search_param", [None, o3d.geometry.KDTreeSearchParamKNN(12)])
def test_exact_duplicates_share_one_normal(search_param):
    mesh = o3d.geometry.TriangleMesh.create_torus()
    points, _, method = _sample(mesh, 1500)
    order = np.random.default_rng(1).permutation(2 * len(points))
    doubled = np.vstack([points, points])[order]
    normals = np.asarray(estimate_normals_neural(_cloud(doubled), num_views=26, model=method, search_param=search_param).normals)
    first, second = np.empty_like(points), np.empty_like(points)
    first[order[order < len(points)]] = normals[order < len(points)]
    second[order[order >= len(points)] - len(points)] = normals[order >= len(points)]
    assert np.array_equal(first, second)
    # and the answer is the one of the cloud without its duplicates
    single = np.asarray(estimate_normals_neural(_cloud(points), num_views=26, model=method, search_param=search_param).normals)
    assert np.array_equal(first, single)


def test_normals_bad_input(sphere):
    points, _, method = sphere
    with pytest.raises(ValueError, match="no normals"):
        orient_normals_neural(_cloud(points), 4, method)
    with pytest.raises(ValueError, match="empty"):
        estimate_normals_neural(o3d.geometry.PointCloud(), num_views=4, model=method)
    with pytest.raises(ValueError, match="shape"):
        estimate_normals_neural(_cloud(points), num_views=4, model=lambda p, c: np.ones(len(p), bool))
    with pytest.raises(TypeError, match="model must be"):
        estimate_normals_neural(_cloud(points), num_views=4, model=3.5)
    with pytest.raises(TypeError, match="search_param, the first argument"):  # Open3D's order: num_views by name
        estimate_normals_neural(_cloud(points), 4, method)
    with pytest.raises(ValueError, match="one line"):
        line = np.column_stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)])
        estimate_normals_neural(_cloud(line), num_views=6, model=lambda p, c: np.ones((len(c), len(p)), bool))
    with pytest.raises(ValueError, match="three neighbours"):
        estimate_normals_neural(_cloud(points), num_views=4, model=method,
                                search_param=o3d.geometry.KDTreeSearchParamHybrid(1e-6, 30))
    with pytest.raises(ValueError, match="one line"):
        estimate_normals_neural(_cloud(line), num_views=6, model=lambda p, c: np.ones((len(c), len(p)), bool),
                                search_param=o3d.geometry.KDTreeSearchParamKNN(8))
