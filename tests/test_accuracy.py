"""The shipped models against Open3D HPR with its best radius, on fixed procedural shapes at 8k points,
and against the exact answer on a sphere inside a sphere.

Shapes, points and viewpoints come from fixed seeds (never tuned to the result); HPR gets its best
radius of the sweep over the whole set, as in ``o3dvis eval``; the networks have no parameter.
"""

import numpy as np
import pytest

from o3dvis.baselines import sweep
from o3dvis.training.data.prepare import label_mesh
from o3dvis.training.data.shapes import write_shapes
from o3dvis.evaluation.methods import neural_method


@pytest.fixture(scope="module")
def procedural_samples(tmp_path_factory):
    files = write_shapes(str(tmp_path_factory.mktemp("shapes")), 8, seed=12345)
    return [label_mesh(f, num_points=8192, num_views=8, seed=1) for f in files]


@pytest.fixture(scope="module")
def best_hpr(procedural_samples) -> tuple[str, float]:
    accuracy = {k: _pooled_accuracy(m, procedural_samples) for k, m in sweep("hpr").items()}
    best = max(accuracy, key=accuracy.get)
    return best, accuracy[best]


def _pooled_accuracy(method, samples, use_normals: bool = False) -> float:
    correct = total = 0
    for s in samples:
        extra = {"normals": s.normals.astype(np.float64)} if use_normals else {}
        pred = method(s.points.astype(np.float64), s.cameras.astype(np.float64), **extra)
        correct += int((pred == s.visibility).sum())
        total += s.visibility.size
    return correct / total


def test_normals_model_beats_best_radius_hpr(procedural_samples, best_hpr):
    neural = _pooled_accuracy(neural_method(use_normals=True), procedural_samples, use_normals=True)
    assert neural > best_hpr[1], f"normals model {neural:.4f} vs HPR {best_hpr}"


@pytest.mark.xfail(strict=True, reason="issue 3 open: the points-only default is 1.0 point below "
                                       "best-radius HPR on these shapes (92.2 % vs 93.1 %)")
def test_default_model_beats_best_radius_hpr(procedural_samples, best_hpr):
    neural = _pooled_accuracy(neural_method(), procedural_samples)
    assert neural > best_hpr[1], f"default model {neural:.4f} vs HPR {best_hpr}"


def _sphere(n: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` evenly spread points on a sphere about the origin (Fibonacci lattice), and their normals."""
    i = np.arange(n) + 0.5
    z, phi = 1 - 2 * i / n, np.pi * (1 + 5 ** 0.5) * i
    unit = np.c_[np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z]
    return radius * unit, unit


@pytest.mark.parametrize("use_normals", [False, True])
def test_models_hide_a_sphere_inside_a_sphere(use_normals):
    """Exact answer: none of the inner sphere, and the cap of the outer one that faces the camera."""
    (outer, n_out), (inner, n_in) = _sphere(8000, 1.0), _sphere(4000, 0.5)
    points, normals = np.r_[outer, inner], np.r_[n_out, n_in]
    cameras = np.random.default_rng(0).normal(size=(8, 3))
    cameras *= 3 / np.linalg.norm(cameras, axis=1, keepdims=True)
    extra = {"normals": normals} if use_normals else {}
    pred = neural_method(use_normals=use_normals)(points, cameras, **extra)
    truth = outer @ cameras.T > 1  # a point of the unit sphere sees the camera c iff p . c > 1
    assert pred[:, len(outer):].mean() < 0.03, "inner sphere called visible"
    assert (pred[:, :len(outer)] == truth.T).mean() > 0.97, "outer sphere"
