"""The shipped models against Open3D HPR with its best radius, on fixed procedural shapes at 8k points.

Shapes, points and viewpoints come from fixed seeds (never tuned to the result); HPR gets its best
radius of the sweep over the whole set, as in ``o3dvis eval``; the networks have no parameter.
"""

import numpy as np
import pytest

from o3dvis.baselines import sweep
from o3dvis.data.prepare import label_mesh
from o3dvis.data.shapes import write_shapes
from o3dvis.methods import neural_method


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


@pytest.mark.xfail(strict=True, reason="issue 3 open: the points-only default is 1.1 points below "
                                       "best-radius HPR on these shapes (92.0 % vs 93.1 %)")
def test_default_model_beats_best_radius_hpr(procedural_samples, best_hpr):
    neural = _pooled_accuracy(neural_method(), procedural_samples)
    assert neural > best_hpr[1], f"default model {neural:.4f} vs HPR {best_hpr}"
