"""One word for accuracy against time: ``quality="fast" | "balanced" | "best"`` on ``encode``, the
drop-ins and ``o3dvis visible``."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis import encodings
from o3dvis.cameras import viewpoints_around
from o3dvis.cli import main
from o3dvis.nn import NetworkConfig, VisibilityNetwork

from conftest import SMALL, _camera


@pytest.fixture(scope="module")
def paired(network) -> o3dvis.NeuralVisibility:
    """The small random network with a normals model beside it."""
    torch.manual_seed(5)
    return o3dvis.NeuralVisibility(network, VisibilityNetwork(NetworkConfig(**SMALL, use_normals=True)).eval())


@pytest.fixture(scope="module")
def sphere() -> np.ndarray:
    """20 000 points on a unit sphere: dense and clean, where two passes are taken."""
    points = np.random.default_rng(0).normal(size=(20_000, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def test_fast_is_one_pass_and_best_two_passes_over_four_turned_copies(paired, sphere):
    cameras = viewpoints_around(sphere, 6)
    fast = paired.encode(sphere, quality="fast")
    assert fast.encoders == (paired.network,) and not fast.rotated
    best = paired.encode(sphere, quality="best")
    assert best.encoders == (paired.network, paired.normals_network) and len(best.rotated) == 3
    four = o3dvis.NeuralVisibility(paired.network, paired.normals_network, num_rotations=4)
    torch.testing.assert_close(best.probabilities(cameras),
                               four.encode(sphere, normals="estimate").probabilities(cameras))
    ones = paired.encode(sphere, normals=False, quality="best")  # one pass, asked for: still four turns
    assert ones.encoders == (paired.network,) and len(ones.rotated) == 3
    eight = o3dvis.NeuralVisibility(paired.network, paired.normals_network, num_rotations=8)
    assert len(eight.encode(sphere, quality="best").rotated) == 7  # a model with more turns keeps them


def test_balanced_takes_two_passes_where_they_pay_and_fast_is_the_default(paired, sphere):
    two = (paired.network, paired.normals_network)
    assert paired.encode(sphere).encoders == (paired.network,)  # by default, fast
    balanced = paired.encode(sphere, quality="balanced")
    assert balanced.encoders == two and not balanced.rotated
    cameras = viewpoints_around(sphere, 6)
    torch.testing.assert_close(balanced.probabilities(cameras),
                               paired.encode(sphere, normals="estimate").probabilities(cameras))
    noisy = sphere * (1 + 0.05 * np.random.default_rng(1).uniform(-1, 1, (len(sphere), 1)))
    assert paired.encode(noisy, quality="balanced").encoders == (paired.network,)  # where they do not pay
    assert paired.encode(sphere[:900], quality="best").encoders == (paired.network,)  # too sparse
    assert paired.encode(sphere, normals=False, quality="balanced").encoders == (paired.network,)
    given = paired.encode(sphere, normals=sphere, quality="balanced")  # a cloud's own normals: used
    assert given.encoders == (paired.normals_network,)
    alone = o3dvis.NeuralVisibility(paired.network)  # no normals model: one pass
    assert alone.encode(sphere, quality="balanced").encoders == (paired.network,)


def test_an_unknown_quality_is_refused_everywhere(paired, sphere, tmp_path, capsys):
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sphere[:500]))
    for call in (lambda: paired.encode(sphere, quality="good"),
                 lambda: o3dvis.hidden_point_removal_neural(cloud, [0, 0, 3.0], model=paired, quality="Best"),
                 lambda: o3dvis.select_visible(cloud, [0, 0, 3.0], model=paired, quality=None)):
        with pytest.raises(ValueError, match="quality must be one of 'fast', 'balanced', 'best'"):
            call()
    path = tmp_path / "in.ply"
    o3d.io.write_point_cloud(str(path), cloud)
    with pytest.raises(SystemExit) as exit_info:
        main(["visible", str(path), "--camera", "0", "0", "3", "-o", str(tmp_path / "out.ply"), "--quality", "good"])
    assert exit_info.value.code == 2 and "invalid choice: 'good'" in capsys.readouterr().err


def test_the_drop_in_keeps_an_encoding_per_quality_and_normals_choice(paired, sphere, monkeypatch):
    calls = []
    encode = o3dvis.NeuralVisibility.encode

    def spy(self, *args, **kwargs):
        calls.append(kwargs.get("quality"))
        return encode(self, *args, **kwargs)

    monkeypatch.setattr(o3dvis.NeuralVisibility, "encode", spy)
    encodings.clear()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sphere))
    cameras = [_camera(sphere, d) for d in ((0, 0, 1), (1, 0, 0), (0, 1, 1))]
    estimated = [o3dvis.hidden_point_removal_neural(cloud, c, model=paired, normals="estimate")[1] for c in cameras]
    assert calls == ["fast"]  # a loop over cameras with normals="estimate" encodes once
    best = [o3dvis.hidden_point_removal_neural(cloud, c, model=paired, quality="best")[1] for c in cameras]
    assert calls == ["fast", "best"]
    o3dvis.hidden_point_removal_neural(cloud, cameras[0], model=paired, quality="balanced")
    assert calls == ["fast", "best", "balanced"]
    encodings.clear()
    monkeypatch.setattr(o3dvis.NeuralVisibility, "encode", encode)
    for c, two, turned in zip(cameras, estimated, best):
        assert two == np.flatnonzero(paired.encode(sphere, normals="estimate").query(c)[0]).tolist()
        assert turned == np.flatnonzero(paired.encode(sphere, quality="best").query(c)[0]).tolist()
