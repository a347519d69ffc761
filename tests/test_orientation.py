"""Oriented normals from visibility: planes through neighbours, voted by the cameras that see them."""

from __future__ import annotations

import numpy as np
import pytest

from o3dvis.cameras import viewpoints_around
from o3dvis.orientation import voted_normals


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


def test_no_plane_to_fit_is_a_clear_error():
    line = np.linspace(0, 1, 50)[:, None] * np.array([[1.0, 2.0, 3.0]])
    cameras = np.array([[5.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="one line"):
        voted_normals(line, cameras, np.ones((1, 50), dtype=bool))
    with pytest.raises(ValueError, match="at least 3 neighbours"):
        voted_normals(_sphere(100), cameras, np.ones((1, 100), dtype=bool), neighbours=2)
