"""Oriented normals from visibility: planes through neighbours, voted by the cameras that see them."""

from __future__ import annotations

import numpy as np
import pytest

import torch
from scipy.spatial import cKDTree

from o3dvis.cameras import viewpoints_around
from o3dvis.nn import native
from o3dvis.nn.octree import morton_order, normalize_points
from o3dvis.neighbours import nearest_neighbours
from o3dvis.orientation import (layer_sides, surface_variation, visibility_affinity, vote,
                                voted_normals)


def _sphere(count: int, seed: int = 0) -> np.ndarray:
    points = np.random.default_rng(seed).normal(size=(count, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def _seen(points: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """Exact visibility on the unit sphere: a point is seen from where it faces."""
    return np.einsum("ij,vij->vi", points, cameras[:, None] - points[None]) > 0


def test_voted_normals_point_out_of_a_sphere_and_lie_along_its_radius():
    points = _sphere(4000)
    cameras = viewpoints_around(points, 6)
    normals = voted_normals(points, cameras, _seen(points, cameras))
    assert np.allclose(np.linalg.norm(normals, axis=1), 1)
    cosine = np.einsum("ij,ij->i", normals, points)
    assert (cosine > 0.95).all()


def test_points_no_camera_sees_take_their_side_along_the_surface():
    points = _sphere(4000, seed=1)
    cameras = viewpoints_around(points, 6)
    visibility = _seen(points, cameras)
    cap = points[:, 2] < -0.5  # a cap that no camera gets to vote on
    visibility[:, cap] = False
    normals = voted_normals(points, cameras, visibility)
    assert (np.einsum("ij,ij->i", normals[cap], points[cap]) > 0.95).all()


def test_the_vote_decides_the_side():
    points = _sphere(2000, seed=2)
    cameras = viewpoints_around(points, 6)
    inside = -cameras * 0.01  # cameras near the centre "see" every point from inside
    normals = voted_normals(points, inside, np.ones((len(inside), len(points)), dtype=bool))
    assert (np.einsum("ij,ij->i", normals, points) < -0.95).all()


def test_a_camera_more_likely_not_to_see_a_point_does_not_vote():
    points = _sphere(500, seed=7)
    cameras = viewpoints_around(points, 6)
    outward = points.copy()
    seen = _seen(points, cameras)
    probable = np.where(seen, 0.9, 0.0)
    unlikely = np.where(seen, 0.9, 0.4)  # every camera half sure it sees the points it faces away from
    assert np.allclose(vote(points, outward, cameras, probable), vote(points, outward, cameras, unlikely))
    assert np.allclose(vote(points, outward, cameras, seen), vote(points, outward, cameras, probable) / 0.8)


def _thin_plate(count: int, seed: int = 0) -> np.ndarray:
    """The two faces of a plate 0.01 thick, their points mingled (spacing about 0.03)."""
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(-1, 1, (count, 2)), np.full(count, 0.005)])
    points[count // 2:, 2] *= -1
    return points


def test_layer_sides_tell_the_faces_of_a_thin_wall_apart():
    points = _thin_plate(4000)
    near = nearest_neighbours(points, 16)
    sides = layer_sides(points, near, np.tile([0.0, 0.0, 1.0], (len(points), 1)))
    assert (sides == np.sign(points[:, 2])).mean() > 0.99
    # rows of a subset: each row's point is its first neighbour
    rows = np.arange(0, 4000, 7)
    assert np.array_equal(layer_sides(points, near[rows], np.tile([0.0, 0.0, 1.0], (len(rows), 1))), sides[rows])


@pytest.mark.skipif(not native.available(), reason="C kernels turned off (O3DVIS_NATIVE=0)")
@pytest.mark.parametrize("answers", ["probabilities", "bool"])
def test_votes_in_c_equal_the_numpy_ones(answers, monkeypatch):
    """The cameras' votes and their agreement by one pass of C (on the planned threads) against the
    numpy ops: equal to rounding, the same signs."""
    import o3dvis.orientation as orientation

    g = np.random.default_rng(4)
    points, normals = g.normal(size=(5000, 3)), _sphere(5000, 1)
    cameras = g.normal(size=(10, 3)) * 4
    visibility = g.random((10, 5000)).astype(np.float32)
    visibility = visibility if answers == "probabilities" else visibility > 0.5
    fast = orientation._votes(points, normals, cameras, visibility)
    monkeypatch.setattr(orientation.native, "available", lambda: False)
    slow = orientation._votes(points, normals, cameras, visibility)
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    assert np.array_equal(np.sign(fast[0]), np.sign(slow[0]))
    monkeypatch.undo()
    tensors = [torch.from_numpy(a) for a in (points, normals, cameras, visibility.astype(np.float32))]
    with pytest.raises(ValueError, match="step 1"):
        native.votes(*tensors, slice(0, 10, 2))
    with pytest.raises(ValueError, match="visibility must be"):
        native.votes(*tensors[:3], tensors[3][:, 1:], slice(0, 10))


def test_a_split_vote_leaves_the_side_to_the_faces_of_a_thin_wall():
    points = _thin_plate(4000, seed=1)
    cameras = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0], [2.0, 0.0, 2.0], [-2.0, 0.0, -2.0]])
    # the first pass's answer on a wall thinner than the spacing: both faces look seen from both sides
    normals = voted_normals(points, cameras, np.full((4, len(points)), 0.9))
    assert (np.sign(normals[:, 2]) == np.sign(points[:, 2])).mean() > 0.97
    assert (np.abs(normals[:, 2]) > 0.95).all()


def _roof(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on the two faces of a roof (a ridge along x) and their faces' unit normals."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (count, 2))
    side = np.where(u[:, 1] < 0, -1.0, 1.0)
    points = np.stack([u[:, 0], u[:, 1], 1 - np.abs(u[:, 1])], axis=1)
    normals = np.stack([np.zeros(count), side, np.ones(count)], axis=1) / np.sqrt(2)
    return points, normals


def test_neighbours_seen_alike_weigh_most_at_a_sharp_edge():
    points, truth = _roof(3000)
    cameras = np.array([[0.0, -3.0, 3.0], [0.0, 3.0, 3.0], [2.0, -3.0, 2.0], [2.0, 3.0, 2.0]])
    seen = np.einsum("ij,vij->vi", truth, cameras[:, None] - points[None]) > 0  # each face by its side
    assert not seen.all(axis=0).any()
    edge = np.abs(points[:, 1]) < 0.05
    plain = voted_normals(points, cameras, seen, affinity=None)
    weighted = voted_normals(points, cameras, seen)
    # within 0.99 of their face's normal: along the edge, plain fits span both faces
    assert (np.einsum("ij,ij->i", plain[edge], truth[edge]) > 0.99).mean() < 0.5
    assert (np.einsum("ij,ij->i", weighted[edge], truth[edge]) > 0.99).mean() > 0.9
    assert (np.einsum("ij,ij->i", weighted, truth) > 0.99).mean() > 0.99
    weights = visibility_affinity(seen, nearest_neighbours(points, 8))
    assert weights.shape == (3000, 8) and np.allclose(weights[:, 0], 1)
    with pytest.raises(ValueError, match="scale"):
        visibility_affinity(seen, nearest_neighbours(points, 8), 0.0)


def test_surface_variation_is_zero_on_a_plane_and_rises_with_noise():
    rng = np.random.default_rng(3)
    plane = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    sphere = _sphere(2000, seed=3)
    noisy = sphere * (1 + 0.02 * rng.uniform(-1, 1, (2000, 1)))
    cube = rng.random((2000, 3))

    def median(points: np.ndarray) -> float:
        return float(np.median(surface_variation(points, nearest_neighbours(points, 8))))

    assert median(plane) < 1e-12
    assert 0 < median(sphere) < 0.005 < median(noisy) < median(cube) <= 1 / 3
    with pytest.raises(ValueError, match="at least 3"):
        surface_variation(plane, nearest_neighbours(plane, 2))


def test_no_plane_to_fit_is_a_clear_error():
    line = np.linspace(0, 1, 50)[:, None] * np.array([[1.0, 2.0, 3.0]])
    cameras = np.array([[5.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="one line"):
        voted_normals(line, cameras, np.ones((1, 50), dtype=bool))
    with pytest.raises(ValueError, match="at least 3 neighbours"):
        voted_normals(_sphere(100), cameras, np.ones((1, 100), dtype=bool), neighbours=2)


def _clouds() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    line = np.c_[np.linspace(0, 1, 6000), np.zeros((6000, 2))]
    sphere = _sphere(20000, seed=4)
    along_curve = sphere[morton_order(normalize_points(torch.from_numpy(sphere))[0].float()).numpy()]
    return {"sphere": sphere, "sphere in an encoding's order": along_curve, "cube": rng.random((8000, 3)),
            "repeated": np.repeat(rng.random((3000, 3)), 3, axis=0),  # ties everywhere
            "line and far points": np.concatenate([line, rng.random((5, 3)) * 100]),  # searched again
            "a dense blob": np.concatenate([rng.normal(size=(2000, 3)) * 1e-4 + 0.5, rng.random((1000, 3))]),
            "clusters": np.concatenate([rng.normal(size=(5000, 3)) * 1e-3 + c for c in np.eye(3) * 1e3])}


@pytest.fixture
def grid_search(monkeypatch):
    """The grid search for clouds of every size (it takes only large ones)."""
    monkeypatch.setattr("o3dvis.neighbours._GRID_MIN_POINTS", 1)


@pytest.mark.parametrize("name", list(_clouds()))
@pytest.mark.parametrize("k", [1, 8, 64])
def test_nearest_neighbours_are_those_of_a_kd_tree(grid_search, name, k):
    """As far as the distances go (equally near points may come in another order)."""
    points = _clouds()[name]
    near = nearest_neighbours(points, k)
    distance, _ = cKDTree(points).query(points, k=k)
    found = np.linalg.norm(points[near] - points[:, None], axis=2)
    assert near.shape == (len(points), k) and near.dtype == np.int64
    np.testing.assert_allclose(found, distance.reshape(len(points), k), rtol=0, atol=1e-12)


@pytest.mark.parametrize("by_tree", [False, True])
def test_nearest_neighbours_search_again_where_the_grid_is_too_coarse(grid_search, monkeypatch, by_tree):
    """A dense cluster and a sparse shell: the shell's points have no k neighbours in the 27 cells
    around them, and get their exact ones all the same (by distances to all points, or with many
    such points by a k-d tree)."""
    monkeypatch.setattr("o3dvis.neighbours._BRUTE_FORCE_PAIRS", 0 if by_tree else 1 << 40)
    rng = np.random.default_rng(5)
    points = np.concatenate([rng.normal(size=(20000, 3)) * 0.01, _sphere(300, seed=6) * 10])
    near = nearest_neighbours(points, 8)
    distance, _ = cKDTree(points).query(points, k=8)
    np.testing.assert_allclose(np.linalg.norm(points[near] - points[:, None], axis=2), distance, atol=1e-12)


@pytest.mark.parametrize("grid", [False, True])
@pytest.mark.parametrize("shuffled", [False, True])
def test_a_search_asked_for_some_points_answers_as_for_all(monkeypatch, grid, shuffled):
    """NeighbourSearch.query of some rows (the grid's cells of those rows only, the rows alone in
    them; or the k-d tree) gives the rows of the query of all points: in a dense cluster, and in a
    sparse shell whose points the grid cannot answer (searched again among all points)."""
    from o3dvis.neighbours import NeighbourSearch

    if grid:
        monkeypatch.setattr("o3dvis.neighbours._GRID_MIN_POINTS", 1)
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.normal(size=(20000, 3)) * 0.01, _sphere(300, seed=6) * 10])
    order = (rng.permutation(len(points)) if shuffled else
             morton_order(normalize_points(torch.from_numpy(points))[0].float()).numpy())  # as an encoding's
    points = points[order]
    search = NeighbourSearch(points)
    every = search.query(16)
    rows = np.sort(rng.choice(len(points), 700, replace=False))
    some = search.query(16, rows)
    distance = lambda near, at: np.linalg.norm(points[near] - points[at][:, None], axis=2)  # noqa: E731
    np.testing.assert_allclose(distance(some, rows), distance(every[rows], rows), atol=1e-12)
    np.testing.assert_allclose(distance(some, rows), cKDTree(points).query(points[rows], k=16)[0], atol=1e-12)
    assert search.query(8).shape == (len(points), 8) and search.query(4, np.array([], dtype=np.int64)).shape == (0, 4)


@pytest.mark.skipif(not native.available(), reason="C kernels turned off (O3DVIS_NATIVE=0)")
def test_brute_force_search_finds_the_nearest_and_checks_its_arguments():
    rng = np.random.default_rng(8)
    points = torch.from_numpy(rng.random((3000, 3)))
    rows = torch.tensor([0, 17, 2999])
    near = native.brute_knn(points, rows, 12).numpy()
    distance, _ = cKDTree(points.numpy()).query(points.numpy()[rows.numpy()], k=12)
    np.testing.assert_allclose(np.linalg.norm(points.numpy()[near] - points.numpy()[rows.numpy()][:, None], axis=2),
                               distance, atol=1e-12)
    assert (near[:, 0] == rows.numpy()).all()
    with pytest.raises(ValueError, match="k must lie"):
        native.brute_knn(points, rows, 65)
    with pytest.raises(IndexError, match="rows must lie"):
        native.brute_knn(points, rows + 1, 4)


@pytest.mark.skipif(not native.available(), reason="C kernels turned off (O3DVIS_NATIVE=0)")
def test_grid_search_checks_its_arguments():
    long = torch.zeros(2, dtype=torch.long)
    args = (torch.zeros(1, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.long), long[:1], long)
    table = native.key_table(long[:1])
    out = (torch.empty(1, 8, dtype=torch.long), torch.empty(1, dtype=torch.uint8))
    with pytest.raises(ValueError, match="k must lie"):
        native.grid_knn(*args, table, 1, torch.zeros(3, dtype=torch.float64), 1.0, 0.0, 65, (0, 1), *out)
    with pytest.raises(ValueError, match="power of two"):
        native.grid_knn(*args, table[:1], 1, torch.zeros(3, dtype=torch.float64), 1.0, 0.0, 8, (0, 1), *out)
    with pytest.raises(ValueError, match="cell range"):
        native.grid_knn(*args, table, 1, torch.zeros(3, dtype=torch.float64), 1.0, 0.0, 8, (0, 2), *out)
    with pytest.raises(ValueError, match="points must be"):
        native.grid_knn(args[0].float(), *args[1:], table, 1, torch.zeros(3, dtype=torch.float64), 1.0, 0.0, 8,
                        (0, 1), *out)
    with pytest.raises(ValueError, match="cell_list must lie"):
        native.grid_knn(*args, table, 1, torch.zeros(3, dtype=torch.float64), 1.0, 0.0, 8, (0, 1), *out,
                        torch.tensor([1]))
    with pytest.raises(ValueError, match="wanted must be"):
        native.grid_knn(*args, table, 1, torch.zeros(3, dtype=torch.float64), 1.0, 0.0, 8, (0, 1), *out,
                        torch.tensor([0]), torch.ones(2, dtype=torch.bool))


@pytest.mark.skipif(not native.available(), reason="C kernels turned off (O3DVIS_NATIVE=0)")
@pytest.mark.parametrize("cameras", [1, 14, 16, 33])
def test_affinity_kernel_matches_the_numpy_ops(monkeypatch, cameras):
    rng = np.random.default_rng(cameras)
    points = rng.random((9000, 3))  # more rows than a thread's share: the kernel runs on row offsets
    visibility = rng.random((cameras, 9000)).astype(np.float32)
    visibility[:, :100] = visibility[:, :100] > 0.5  # exact answers too: weights down to the floor
    near = nearest_neighbours(points, 8)
    fast = visibility_affinity(visibility, near)
    monkeypatch.setattr(native, "available", lambda: False)
    slow = visibility_affinity(visibility, near)
    np.testing.assert_allclose(fast, slow, rtol=1e-6, atol=1e-7)
    assert fast.min() >= 0.01 - 1e-7 and fast.max() <= 1.0


@pytest.mark.skipif(not native.available(), reason="C kernels turned off (O3DVIS_NATIVE=0)")
def test_affinity_kernel_checks_its_arguments():
    table = native.affinity_table(torch.rand(3, 10))
    assert table.shape == (10, 16) and not table[:, 3:].any()
    near = torch.zeros(4, 2, dtype=torch.long)
    with pytest.raises(ValueError, match="multiple of 16"):
        native.visibility_affinity(table[:, :8].contiguous(), 3, near, 0, 0.1, 0.01)
    with pytest.raises(ValueError, match="past the table"):
        native.visibility_affinity(table, 3, near, 7, 0.1, 0.01)
    with pytest.raises(IndexError, match="neighbours"):
        native.visibility_affinity(table, 3, near + 10, 0, 0.1, 0.01)


def test_training_draws_the_first_pass_normals_for_the_share_asked(tmp_path):
    """Augmentation(estimated_normals=1) gives each cloud the normals normals='estimate' computes
    (unit, mostly on the side of the exact ones, not equal to them: 5 000 points of a procedural
    shape); the points, cameras and labels are the draw of estimated_normals=0, which draws as before."""
    torch = pytest.importorskip("torch")
    from o3dvis.training.data.dataset import Augmentation, VisibilityDataset
    from o3dvis.training.data.prepare import label_mesh
    from o3dvis.training.data.sample import save_sample
    from o3dvis.training.data.shapes import write_shapes

    mesh = write_shapes(str(tmp_path / "meshes"), 1, seed=6)[0]
    sample = label_mesh(mesh, num_points=6000, num_views=4)
    save_sample(sample, tmp_path / "s.npz")
    draw = dict(min_points=5000, max_points=5001, noise_prob=0.0)
    exact = VisibilityDataset([tmp_path / "s.npz"], Augmentation(**draw), seed=2, length=2)
    estimated = VisibilityDataset([tmp_path / "s.npz"], Augmentation(**draw, estimated_normals=1.0), seed=2, length=2)
    for k in range(2):
        (p0, n0, c0, l0), (p1, n1, c1, l1) = exact[k], estimated[k]
        assert torch.equal(p0, p1) and torch.equal(c0, c1) and torch.equal(l0, l1)
        torch.testing.assert_close(n1.norm(dim=1), torch.ones(len(n1)), rtol=0, atol=1e-5)
        cosine = (n0 * n1).sum(dim=1)
        assert not torch.allclose(n0, n1, atol=1e-3) and (cosine > 0).float().mean() > 0.7  # random: 0.5
