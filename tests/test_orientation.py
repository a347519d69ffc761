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


def test_training_draws_the_first_pass_normals_for_the_share_asked(tmp_path):
    """Augmentation(estimated_normals=1) gives each cloud the normals normals='estimate' computes
    (unit, mostly on the side of the exact ones, not equal to them: 5 000 points of a shape with thin
    parts, where a fifth of them flip); the points, cameras and labels
    are the draw of estimated_normals=0, which draws as before."""
    torch = pytest.importorskip("torch")
    from o3dvis.training.data.dataset import Augmentation, VisibilityDataset
    from o3dvis.training.data.prepare import _save, label_mesh
    from o3dvis.training.data.shapes import write_shapes

    mesh = write_shapes(str(tmp_path / "meshes"), 1, seed=3)[0]
    sample = label_mesh(mesh, num_points=6000, num_views=4)
    _save(sample, tmp_path / "s.npz")
    draw = dict(min_points=5000, max_points=5001, noise_prob=0.0)
    exact = VisibilityDataset([tmp_path / "s.npz"], Augmentation(**draw), seed=2, length=2)
    estimated = VisibilityDataset([tmp_path / "s.npz"], Augmentation(**draw, estimated_normals=1.0), seed=2, length=2)
    for k in range(2):
        (p0, n0, c0, l0), (p1, n1, c1, l1) = exact[k], estimated[k]
        assert torch.equal(p0, p1) and torch.equal(c0, c1) and torch.equal(l0, l1)
        torch.testing.assert_close(n1.norm(dim=1), torch.ones(len(n1)), rtol=0, atol=1e-5)
        cosine = (n0 * n1).sum(dim=1)
        assert not torch.allclose(n0, n1, atol=1e-3) and (cosine > 0).float().mean() > 0.7  # random: 0.5
