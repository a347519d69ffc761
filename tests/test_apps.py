"""Applications on procedural shapes with known answers, run on ray-cast ground-truth visibility."""

from __future__ import annotations


import numpy as np
import open3d as o3d
import pytest
import torch

from o3dvis.apps import (best_view, depth_image, estimate_normals_neural, fibonacci_sphere,
                         ground_truth_method, make_view, orient_normals_neural, points_in_shadow,
                         reconstruct_poisson, reconstruct_view_dependent, render_points,
                         render_with_shadows, shadow_map)
from o3dvis.apps.normals import covisible_normals, multiview_normals, neighbourhoods
from o3dvis.cli import build_parser
from o3dvis.cli._common import split_vectors, visibility_method
from o3dvis.orientation import fit_planes, smallest_eigenvectors, vote
from o3dvis.training.data.sample import sample_surface


def _sample(mesh: o3d.geometry.TriangleMesh, count: int, seed: int = 0):
    """Points uniform on a mesh, their face normals, and the ground-truth method of the mesh."""
    points, normals = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.triangles), count,
                                     np.random.default_rng(seed))
    return points, normals, ground_truth_method(mesh)


def _cloud(points, colors=None) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(colors)
    return pcd


@pytest.fixture(scope="module")
def sphere():
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60)
    return _sample(mesh, 4000)


def _box(size, center) -> o3d.geometry.TriangleMesh:
    box = o3d.geometry.TriangleMesh.create_box(*size)
    return box.translate(np.asarray(center, float) - np.asarray(size, float) / 2)


@pytest.fixture(scope="module")
def box_on_floor():
    """A unit cube standing on a thin 4 x 4 floor plate, both centred on the z axis."""
    mesh = _box((1, 1, 1), (0, 0, 0.5)) + _box((4, 4, 0.02), (0, 0, -0.01))
    return _sample(mesh, 12000, seed=1)


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.einsum("ij,ij->i", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


# ---------------------------------------------------------------- normals

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


def _scatters(points: np.ndarray) -> np.ndarray:
    centred = points - points.mean(axis=1, keepdims=True)
    return np.matmul(centred.transpose(0, 2, 1), centred)


@pytest.mark.parametrize("scale", [1e-150, 1.0, 1e150])
def test_closed_form_eigenvectors_match_eigh(scale):
    rng = np.random.default_rng(3)
    rotation = np.linalg.qr(rng.normal(size=(3000, 3, 3)))[0]
    # neighbourhoods of every shape: blobs, noisy planes, strips, near-lines
    extents = np.concatenate([np.ones((1000, 3)), [[1, 1, 1e-3]] * 500, [[1, 0.3, 1e-6]] * 500,
                              [[1, 1e-3, 1e-9]] * 500, [[1, 0.999, 0.998]] * 500])
    matrices = _scatters(rng.normal(size=(3000, 16, 3)) * extents[:, None] @ rotation) * scale
    vectors, planar = smallest_eigenvectors(matrices)
    values, reference = np.linalg.eigh(matrices)
    assert np.allclose(np.linalg.norm(vectors, axis=1), 1)
    separated = (values[:, 1] - values[:, 0]) > 1e-8 * values[:, 2]
    assert separated.mean() > 0.99
    cos = np.abs(np.einsum("ij,ij->i", vectors, reference[:, :, 0]))
    assert cos[separated].min() > 1 - 1e-12
    assert planar.all()


def test_closed_form_eigenvectors_of_degenerate_matrices():
    rng = np.random.default_rng(4)
    line = rng.normal(size=(1, 16, 1)) * np.array([0.6, 0.0, 0.8]) + 5.0
    matrices = np.concatenate([np.zeros((1, 3, 3)), _scatters(line), np.eye(3)[None],
                               np.diag([2.0, 2.0, 1.0])[None], np.diag([2.0, 1.0, 1.0])[None]])
    vectors, planar = smallest_eigenvectors(matrices)
    assert np.isfinite(vectors).all() and np.allclose(np.linalg.norm(vectors, axis=1), 1)
    assert planar.tolist() == [False, False, True, True, True]  # a line or a point has no plane
    assert abs(vectors[1] @ [0.6, 0.0, 0.8]) < 1e-9  # any normal of a line is across it
    assert abs(vectors[3][2]) == pytest.approx(1)  # the disk's axis
    assert abs(vectors[4][0]) < 1e-12  # any vector of the cigar's round section


def test_native_plane_fits_match_the_numpy_ones(monkeypatch):
    """The plane fits in C against the numpy ops they follow, degenerate neighbourhoods included:
    duplicates, collinear points, rows without three positive weights."""
    import o3dvis.orientation as orientation

    if not orientation.native.available():
        pytest.skip("the C kernels are not built")
    rng = np.random.default_rng(8)
    points = np.concatenate([rng.normal(size=(5000, 3)) * [1.0, 1.0, 0.05],
                             np.zeros((4, 3)), np.outer(np.arange(4.0), [0.6, 0.0, 0.8]) + 1e6])
    neighbours = rng.integers(0, 5000, size=(6000, 8))
    neighbours[:4] = 5000 + np.arange(4)[:, None] % 4  # a point's duplicates
    neighbours[4:8] = 5004 + np.arange(8) % 4  # a line, far from the origin
    neighbours[12:20, 5:] = len(points)  # no point, of no weight (the padding of covisible fits)
    weight = rng.random(neighbours.shape)
    weight[8:12, 2:] = 0  # two neighbours that count
    weight[12:20, 5:] = 0
    fast, fast_fitted = fit_planes(points, neighbours, weight)
    monkeypatch.setattr(orientation.native, "available", lambda: False)
    slow, slow_fitted = fit_planes(points, neighbours, weight)
    assert np.array_equal(fast_fitted, slow_fitted) and not fast_fitted[:12].any() and fast_fitted[12:].all()
    assert np.isfinite(fast).all() and np.allclose(np.linalg.norm(fast, axis=1), 1)
    assert np.abs(np.einsum("ij,ij->i", fast, slow))[12:].min() > 1 - 1e-9
    monkeypatch.undo()
    for unweighted, ones in zip(fit_planes(points, neighbours[20:]),  # None: every neighbour weighs 1
                                fit_planes(points, neighbours[20:], np.ones((5980, 8)))):
        assert np.array_equal(unweighted, ones)
    with pytest.raises(IndexError, match="neighbours"):
        orientation.native.fit_planes(torch.zeros(3, 3, dtype=torch.float64), torch.tensor([[0, 1, 4]]),
                                      torch.ones(1, 3, dtype=torch.float64))


def test_chunked_fit_and_vote_match_plain_formulas_across_chunks():
    rng = np.random.default_rng(6)
    points = rng.normal(size=(9000, 3)) * [1.0, 1.0, 0.05]  # more rows than one chunk
    neighbours = neighbourhoods(points, o3d.geometry.KDTreeSearchParamKNN(10))
    weight = rng.random(neighbours.shape)
    normals, fitted = fit_planes(points, neighbours, weight)
    near = points[neighbours]
    centre = np.einsum("nk,nki->ni", weight, near) / weight.sum(axis=1, keepdims=True)
    offset = near - centre[:, None]
    values, vectors = np.linalg.eigh(np.einsum("nk,nki,nkj->nij", weight, offset, offset))
    separated = values[:, 1] - values[:, 0] > 1e-6 * values[:, 2]
    assert fitted.all() and separated.mean() > 0.99
    assert np.abs(np.einsum("ij,ij->i", normals, vectors[:, :, 0]))[separated].min() > 1 - 1e-9

    cameras = rng.normal(size=(5, 3)) * 10
    visibility = rng.random((5, len(points))) < 0.5
    towards = cameras[:, None] - points[None]
    cos = np.einsum("vni,ni->vn", towards, normals) / np.linalg.norm(towards, axis=2)
    assert np.allclose(vote(points, normals, cameras, visibility), (cos * visibility).sum(axis=0))


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


def test_model_keyword_takes_names_and_visibility_methods(box_on_floor):
    """``model=`` of the applications takes what the drop-ins take (a shipped model's name) and
    any visibility method; ``method=`` is no keyword of theirs."""
    points, _, method = box_on_floor
    pcd = _cloud(points)
    by_name = points_in_shadow(pcd, LIGHT, model="default")
    np.testing.assert_array_equal(by_name, points_in_shadow(pcd, LIGHT))
    assert not np.array_equal(points_in_shadow(pcd, LIGHT, model=method), np.zeros(len(points), bool))
    with pytest.raises(TypeError, match="method"):
        points_in_shadow(pcd, LIGHT, method=method)


# ---------------------------------------------------------------- reconstruction

def test_view_dependent_mesh_is_the_visible_cap(sphere):
    points, _, method = sphere
    camera = np.array([0.0, 0.0, 5.0])
    mesh = reconstruct_view_dependent(_cloud(points), camera, method)
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert (vertices[:, 2] > 0.2 - 0.02).all()  # the cap z > r^2 / d seen from distance d = 5
    centroids = vertices[triangles].mean(axis=1)
    mesh.compute_triangle_normals()
    facing = np.einsum("ij,ij->i", np.asarray(mesh.triangle_normals), camera - centroids)
    assert (facing > 0).all()
    cap_area = 2 * np.pi * (1 - 1 / 5)  # 2 pi r h with h = r - r^2 / d
    assert 0.9 * cap_area < mesh.get_surface_area() < 1.02 * cap_area


def test_view_dependent_mesh_does_not_bridge_depth_jumps():
    near = _box((1.0, 1.0, 0.01), (0, 0, 1.0))
    far = _box((3.0, 3.0, 0.01), (0, 0, 0.0))
    points, _, method = _sample(near + far, 6000)
    mesh = reconstruct_view_dependent(_cloud(points), [0.2, 0.1, 6.0], method)
    z = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)][:, :, 2]
    assert len(z) > 1000
    assert ((z > 0.5).all(axis=1) | (z < 0.5).all(axis=1)).all()


@pytest.mark.parametrize("search_param", [None, o3d.geometry.KDTreeSearchParamKNN(12)])
def test_poisson_on_neural_normals_recovers_the_sphere(sphere, search_param):
    points, _, method = sphere
    pcd = _cloud(points)
    mesh, densities = reconstruct_poisson(pcd, depth=6, model=method, search_param=search_param)
    radii = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert len(densities) == len(radii)
    assert np.abs(radii - 1).mean() < 0.02
    assert abs(mesh.get_surface_area() - 4 * np.pi) < 0.05 * 4 * np.pi
    assert not pcd.has_normals()  # the input is left alone
    if search_param is not None:  # the search reaches the fit: one too narrow for any plane fails
        with pytest.raises(ValueError, match="three neighbours"):
            reconstruct_poisson(pcd, depth=6, model=method,
                                search_param=o3d.geometry.KDTreeSearchParamHybrid(radius=1e-9, max_nn=5))


def test_poisson_refuses_a_depth_beyond_what_open3d_the_cloud_and_memory_allow(sphere, monkeypatch):
    """Refused before the normals are estimated: Open3D crashes at depth 30, and deep octrees exhaust memory."""
    from o3dvis.apps import reconstruction

    points, _, method = sphere
    with pytest.raises(ValueError, match="depth=30 is beyond 16"):
        reconstruct_poisson(_cloud(points), depth=30, model=method)
    with pytest.raises(ValueError, match="depth=11 is beyond 10, the deepest octree 160 points fill"):
        reconstruct_poisson(_cloud(points[:160]), depth=11, model=method)
    monkeypatch.setattr(reconstruction, "_available_memory", lambda: 2**20)
    with pytest.raises(ValueError, match=r"depth=6 needs about .* GiB for 4000 points.* memory available"):
        reconstruct_poisson(_cloud(points), depth=6, model=method)
    monkeypatch.setattr(reconstruction, "_available_memory", lambda: None)  # unknown: only the other limits
    assert len(reconstruct_poisson(_cloud(points[:160]), depth=10, model=method)[0].vertices) > 0


def test_poisson_gives_the_same_mesh_on_every_run(sphere):
    points, _, method = sphere
    pcd = _cloud(points)
    runs = [reconstruct_poisson(pcd, depth=7, model=method)[0] for _ in range(3)]
    for mesh in runs[1:]:
        assert np.array_equal(np.asarray(mesh.vertices), np.asarray(runs[0].vertices))
        assert np.array_equal(np.asarray(mesh.triangles), np.asarray(runs[0].triangles))


# ---------------------------------------------------------------- shadows

LIGHT = np.array([0.0, 0.0, 5.0])


def _floor_in_shadow(points: np.ndarray) -> np.ndarray:
    """Floor points a light at (0, 0, 5) cannot see past the cube top (z = 1, |x|, |y| <= 0.5)."""
    return np.abs(points[:, :2]).max(axis=1) * 4 / 5 < 0.5


def test_points_in_shadow_under_a_light_above_a_box(box_on_floor):
    points, _, method = box_on_floor
    shadow = points_in_shadow(_cloud(points), LIGHT, method)
    floor_top = np.abs(points[:, 2]) < 1e-6
    cube_bottom = (np.abs(points[:, 2]) < 1e-6) & (np.abs(points[:, :2]).max(axis=1) < 0.5)
    cube_top = np.abs(points[:, 2] - 1) < 1e-6
    floor_bottom = np.abs(points[:, 2] + 0.02) < 1e-6
    assert shadow[cube_bottom].all() and shadow[floor_bottom].all()
    assert not shadow[cube_top].any()
    expected = _floor_in_shadow(points[floor_top])
    assert expected.sum() > 50 and (~expected).sum() > 1000
    assert (shadow[floor_top] == expected).mean() > 0.995  # points on the shadow's rim may differ


def test_shadow_map_holds_the_depths_of_the_cube_top_and_the_floor(box_on_floor):
    points, _, method = box_on_floor
    image = np.asarray(shadow_map(_cloud(points), LIGHT, 128, method))
    assert image.shape == (128, 128) and image.dtype == np.float32
    assert abs(image[64, 64] - 4.0) < 1e-3  # the light looks straight down at the cube top
    values = image[image > 0]
    near_expected = np.minimum(np.abs(values - 4.0), np.abs(values - 5.0)) < 1e-3
    assert near_expected.mean() > 0.99
    assert (np.abs(values - 5.0) < 1e-3).sum() > (np.abs(values - 4.0) < 1e-3).sum()


def test_render_with_shadows_darkens_the_shadow(box_on_floor):
    points, _, method = box_on_floor
    camera = np.array([3.0, 0.5, 2.5])
    image = np.asarray(render_with_shadows(_cloud(points), LIGHT, camera, 200, 150, method,
                                           ambient=0.25))
    view = make_view(points, camera, 200, 150)
    uv, _ = view.project(np.array([[0.56, 0.0, 0.0], [1.6, 0.0, 0.0]]))
    (c1, r1), (c2, r2) = np.rint(uv).astype(int)
    assert image[r1, c1].mean() == pytest.approx(0.25 * 0.8 * 255, abs=2)  # shadowed floor
    assert image[r2, c2].mean() == pytest.approx(0.8 * 255, abs=2)  # lit floor


# ---------------------------------------------------------------- renders

def test_depth_image_of_a_sphere(sphere):
    points, _, method = sphere
    intrinsic = o3d.camera.PinholeCameraIntrinsic(100, 100, 100.0, 100.0, 49.5, 49.5)
    depth = np.asarray(depth_image(_cloud(points), [0, 0, 5], intrinsic, model=method))
    assert depth.shape == (100, 100) and depth.dtype == np.float32
    assert 4.0 <= depth[49:51, 49:51].min() and depth[49:51, 49:51].max() < 4.02
    radius = 100 * np.tan(np.arcsin(1 / 5))  # of the silhouette, in pixels
    offset = np.hypot(*(np.mgrid[0:100, 0:100] - 49.5))
    assert (depth[offset < radius] > 0).all()
    assert offset[depth > 0].max() < radius + 4  # splats reach past the rim by their radius
    covered = depth[depth > 0]
    assert covered.max() < np.sqrt(5 ** 2 - 1) + 0.05  # no back-side point


def test_render_points_hides_the_far_plane():
    near = _box((1.0, 1.0, 0.01), (0, 0, 1.0))
    far = _box((3.0, 3.0, 0.01), (0, 0, 0.0))
    points, _, method = _sample(near + far, 8000)
    colors = np.where((points[:, 2] > 0.5)[:, None], [1.0, 0, 0], [0, 0, 1.0])
    pcd = _cloud(points, colors)
    camera = [0.0, 0.0, 6.0]
    view = make_view(points, camera, 160, 160)
    corners, _ = view.project(np.array([[-0.4, -0.4, 1.01], [0.4, 0.4, 1.01]]))
    (c0, r0), (c1, r1) = np.rint(corners).astype(int)
    rows, cols = slice(min(r0, r1), max(r0, r1)), slice(min(c0, c1), max(c0, c1))
    small = dict(point_size=0.005)  # small splats leave gaps to see through
    with_vis = np.asarray(render_points(pcd, camera, True, 160, 160, method, **small))[rows, cols]
    without = np.asarray(render_points(pcd, camera, False, 160, 160, **small))[rows, cols]
    blue = lambda img: ((img[..., 2] == 255) & (img[..., 0] == 0)).sum()  # noqa: E731
    assert blue(without) > 20 and blue(with_vis) == 0
    full = np.asarray(render_points(pcd, camera, True, 160, 160, method))[rows, cols]
    assert (full[..., 0] == 255).all()  # default splats close the front square


# ---------------------------------------------------------------- best view

def _backface_field(points: np.ndarray, normals: np.ndarray, sharpness: float = 8.0):
    """Differentiable stand-in: sigmoid(k cos(normal, direction to the camera))."""
    p, n = torch.tensor(points), torch.tensor(normals)

    def probabilities(cameras: torch.Tensor) -> torch.Tensor:
        to_cam = cameras.double()[:, None, :] - p[None]
        cos = (to_cam * n).sum(-1) / to_cam.norm(dim=-1)
        return torch.sigmoid(sharpness * cos)

    return probabilities


@pytest.fixture(scope="module")
def box_field():
    mesh = _box((3.0, 2.0, 1.0), (0.0, 0.0, 0.0))
    points, normals, _ = _sample(mesh, 1500, seed=4)
    return points, _backface_field(points, normals)


def _brute_force(points: np.ndarray, field, count: int = 500) -> np.ndarray:
    lo, hi = points.min(0), points.max(0)
    cams = (lo + hi) / 2 + np.linalg.norm(hi - lo) * fibonacci_sphere(count)
    with torch.no_grad():
        return field(torch.tensor(cams)).mean(dim=1).numpy()


@pytest.mark.parametrize("search, steps, length", [("candidates", 10, 11), ("gradient", 120, 120)])
@pytest.mark.parametrize("maximize", [True, False])
def test_best_and_worst_view_beat_brute_force(box_field, maximize, search, steps, length):
    points, field = box_field
    camera, losses = best_view(points, maximize, steps=steps, model=field, starts=6, search=search)
    assert losses.shape == (length,) and losses[-1] < losses[0]
    diag = np.linalg.norm(points.max(0) - points.min(0))
    assert np.linalg.norm(camera - (points.max(0) + points.min(0)) / 2) == pytest.approx(diag, rel=1e-5)
    with torch.no_grad():
        found = float(field(torch.tensor(camera[None])).mean())
    scores = _brute_force(points, field)
    if maximize:
        assert found >= np.quantile(scores, 0.95)
    else:
        assert found <= np.quantile(scores, 0.05)


def _tiny_visibility():
    from o3dvis.neural import NeuralVisibility
    from o3dvis.nn import NetworkConfig, VisibilityNetwork

    torch.manual_seed(0)
    return NeuralVisibility(VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 16), feature_channels=8,
                                                            num_frequencies=2, hidden=(16,))).eval())


@pytest.mark.parametrize("maximize", [True, False])
def test_best_view_is_as_good_as_every_candidate_from_one_encoding(box_field, maximize, monkeypatch):
    """The default search scores its candidate views from one encoding, then only improves on the best."""
    from o3dvis.neural import NeuralVisibility

    points = box_field[0]
    vis, encodes = _tiny_visibility(), []
    encode = NeuralVisibility.encode
    monkeypatch.setattr(NeuralVisibility, "encode", lambda self, *a, **k: encodes.append(1) or encode(self, *a, **k))
    camera, losses = best_view(points, maximize, model=vis, candidates=60, steps=4, starts=2, progress=False)
    assert len(encodes) == 1 and losses.shape == (5,) and (np.diff(losses) <= 0).all()
    field = encode(vis, points)
    lo, hi = points.min(0), points.max(0)
    lattice = (lo + hi) / 2 + np.linalg.norm(hi - lo) * fibonacci_sphere(60)
    scores = field.probabilities(lattice).mean(dim=1).numpy()
    found = float(field.probabilities(camera).mean())
    assert np.linalg.norm(camera - (lo + hi) / 2) == pytest.approx(np.linalg.norm(hi - lo), rel=1e-9)
    assert (found >= scores.max() - 1e-6) if maximize else (found <= scores.min() + 1e-6)
    assert (-losses[-1] if maximize else losses[-1]) == pytest.approx(found, abs=1e-5)


def test_best_view_shows_progress_by_default_where_it_lasts(box_field, monkeypatch, capsys):
    from o3dvis.apps import views

    points, field = box_field
    monkeypatch.setattr(views, "_PROGRESS_DELAY", 0.0)  # as if the call lasted
    best_view(points, model=field, candidates=20, steps=1, starts=1)
    assert "best view" in capsys.readouterr().err
    best_view(points, model=field, candidates=20, steps=1, starts=1, progress=False)
    assert "best view" not in capsys.readouterr().err


def test_best_view_refuses_an_unknown_search_and_no_candidates(box_field):
    points, field = box_field
    with pytest.raises(ValueError, match="search must be one of candidates, gradient"):
        best_view(points, model=field, search="random")
    with pytest.raises(ValueError, match="candidates must be at least 1"):
        best_view(points, model=field, candidates=0)


def test_the_cli_offers_the_searches_of_best_view():
    from o3dvis.apps.views import SEARCHES
    from o3dvis.cli.apps import _SEARCHES

    assert _SEARCHES == SEARCHES


def test_best_view_with_the_network_field(sphere):
    from o3dvis.nn import NetworkConfig, VisibilityNetwork
    from o3dvis.neural import NeuralVisibility

    torch.manual_seed(0)
    network = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 16), feature_channels=8,
                                              num_frequencies=2, hidden=(16,))).eval()
    vis = NeuralVisibility(network)
    points = sphere[0][:1500]
    camera = torch.tensor([[0.3, 0.2, 4.0]], requires_grad=True)
    vis.encode(points).probabilities(camera).mean().backward()
    assert camera.grad is not None and camera.grad.abs().sum() > 0
    found, losses = best_view(points, steps=5, model=vis, starts=2)
    assert np.isfinite(losses).all() and found.shape == (3,)


def test_methods_answer_for_indices_and_encode_a_cloud_once(sphere):
    from o3dvis.apps import resolve_method
    from o3dvis.nn import NetworkConfig, VisibilityNetwork
    from o3dvis.neural import NeuralVisibility

    points, _, truth = sphere
    cameras = np.array([[0.0, 0.0, 4.0], [4.0, 1.0, 0.0]])
    indices = np.arange(0, len(points), 7)
    exact = resolve_method(truth)
    np.testing.assert_array_equal(exact(points, cameras, indices), truth(points, cameras)[:, indices])
    with pytest.raises(ValueError, match="returned shape"):
        resolve_method(lambda p, c: np.ones((1, 3), bool))(points, cameras, indices)

    def answers_for_all(points, cameras, indices=None):  # claims to take indices, ignores them
        return truth(points, cameras)
    answers_for_all.takes_indices = True
    with pytest.raises(ValueError, match="returned shape"):
        resolve_method(answers_for_all)(points, cameras, indices)

    torch.manual_seed(0)
    network = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 16), feature_channels=8,
                                              num_frequencies=2, hidden=(16,))).eval()
    vis = NeuralVisibility(network)
    encoded = []
    vis.encode = lambda cloud, _encode=vis.encode: encoded.append(1) or _encode(cloud)
    method = resolve_method(vis)
    full = method(points, cameras)
    np.testing.assert_array_equal(method(points, cameras, indices), full[:, indices])
    assert len(encoded) == 1
    again = resolve_method(method)  # a resolved method keeps its indices and its encoding
    np.testing.assert_array_equal(again(points, cameras, indices), full[:, indices])
    assert len(encoded) == 1
    method(points.copy(), cameras)  # another array: encoded afresh
    assert len(encoded) == 2


# ---------------------------------------------------------------- command line

def _cli(*argv: str) -> int:
    """Runs a command as ``o3dvis`` parses it, but raising its errors."""
    args = build_parser().parse_args(split_vectors(list(argv)))
    return args.func(args)


def test_cli_normals_render_shadow_reconstruct(tmp_path, sphere):
    points, _, _ = sphere
    mesh_path, cloud_path = str(tmp_path / "sphere_mesh.ply"), str(tmp_path / "sphere.ply")
    o3d.io.write_triangle_mesh(mesh_path, o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60))
    o3d.io.write_point_cloud(cloud_path, _cloud(points))
    gt = ["--method", "gt", "--mesh", mesh_path]
    out = str(tmp_path / "normals.ply")
    assert _cli("normals", cloud_path, "-o", out, "--views", "12", *gt) == 0
    normals = np.asarray(o3d.io.read_point_cloud(out).normals)
    assert (np.einsum("ij,ij->i", normals, points) > 0).all()
    knn_out = str(tmp_path / "normals_knn.ply")
    assert _cli("normals", cloud_path, "-o", knn_out, "--views", "12", "--knn", "12", *gt) == 0
    knn_normals = np.asarray(o3d.io.read_point_cloud(knn_out).normals)
    assert (np.einsum("ij,ij->i", knn_normals, points) > 0).all()
    assert not np.allclose(knn_normals, normals)  # another fit: the flag reached the function
    with pytest.raises(ValueError, match="--orient-only"):
        _cli("normals", out, "-o", knn_out, "--orient-only", "--knn", "12", *gt)
    assert _cli("render", out, "--camera", "0,0,4", "-o", str(tmp_path / "r.png"), "--width", "80",
                "--height", "60", "--depth-output", str(tmp_path / "d.npy"), *gt) == 0
    assert np.asarray(o3d.io.read_image(str(tmp_path / "r.png"))).shape == (60, 80, 3)
    assert np.load(tmp_path / "d.npy").max() < 4.0
    assert _cli("shadow", cloud_path, "--light", "0,0,4", "--camera=4,0,0", "-o",
                str(tmp_path / "s.png"), "--width", "80", "--height", "60", *gt) == 0
    assert _cli("reconstruct", cloud_path, "-o", str(tmp_path / "m.ply"), "--camera", "0,0,4",
                *gt) == 0
    assert len(o3d.io.read_triangle_mesh(str(tmp_path / "m.ply")).triangles) > 1000
    assert _cli("reconstruct", cloud_path, "-o", str(tmp_path / "p.ply"), "--depth", "5", "--views", "12",
                "--knn", "12", *gt) == 0
    radii = np.linalg.norm(np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "p.ply")).vertices), axis=1)
    assert np.abs(radii - 1).mean() < 0.05  # inside out, or on unoriented normals, it would not be
    with pytest.raises(ValueError, match="three neighbours"):  # the flag reaches the fit
        _cli("reconstruct", cloud_path, "-o", str(tmp_path / "p.ply"), "--views", "12", "--knn", "2", *gt)
    with pytest.raises(ValueError, match="--knn"):
        _cli("reconstruct", cloud_path, "-o", str(tmp_path / "m.ply"), "--camera", "0,0,4", "--knn", "12", *gt)
    with pytest.raises(ValueError, match="--mesh"):
        _cli("normals", cloud_path, "-o", out, "--method", "gt")


def test_cli_network_precision(tmp_path):
    parser = build_parser()
    for flags, precision in (([], "auto"), (["--precision", "float32"], "float32"),
                             (["--precision", "bfloat16"], "bfloat16")):
        args = parser.parse_args(["normals", "in.ply", "-o", "out.ply", *flags])
        assert visibility_method(args).precision == precision
    with pytest.raises(SystemExit):
        parser.parse_args(["normals", "in.ply", "-o", "out.ply", "--precision", "float16"])


def test_cli_best_view_with_a_checkpoint(tmp_path, sphere):
    from o3dvis.nn import NetworkConfig, VisibilityNetwork

    torch.manual_seed(0)
    checkpoint = tmp_path / "tiny.safetensors"
    VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 16), feature_channels=8, num_frequencies=2,
                                    hidden=(16,))).save(checkpoint)
    cloud_path = str(tmp_path / "sphere.ply")
    o3d.io.write_point_cloud(cloud_path, _cloud(sphere[0][:1000]))
    assert _cli("best-view", cloud_path, "--model", str(checkpoint), "--steps", "3", "--starts", "2",
                "-o", str(tmp_path / "best.png"), "--plot", str(tmp_path / "loss.png")) == 0
    assert np.asarray(o3d.io.read_image(str(tmp_path / "best.png"))).shape == (480, 640, 3)
    assert (tmp_path / "loss.png").stat().st_size > 0
