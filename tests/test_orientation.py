"""Oriented normals from visibility (``o3dvis.orientation``): planes through neighbours, in closed
form and in C, voted by the cameras that see them, sides of thin walls, the visibility affinity."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

from o3dvis.apps.normals import neighbourhoods
from o3dvis.cameras import viewpoints_around
from o3dvis.neighbours import nearest_neighbours
from o3dvis.nn import native
from o3dvis.orientation import (fit_planes, layer_sides, smallest_eigenvectors, surface_variation,
                                visibility_affinity, vote, voted_normals)

from conftest import _sphere


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
