"""Best and worst views (``o3dvis.apps.views``): both searches against brute force on a
differentiable stand-in, the candidates scored from one encoding, progress, refusals, the network field."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from o3dvis.apps import best_view, fibonacci_sphere

from conftest import _box, _sample


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
