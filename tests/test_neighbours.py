"""Nearest neighbours (``o3dvis.neighbours``): the grid search and its fallbacks against a k-d tree,
searches for some points, and the C searches' argument checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from o3dvis.neighbours import nearest_neighbours
from o3dvis.nn import native
from o3dvis.nn.octree import morton_order, normalize_points

from conftest import _sphere


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
