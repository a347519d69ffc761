"""Cameras in every form (``o3dvis.cameras``): each form of a view gives the same answer, bad cameras
are refused with a clear error, and the finiteness check is exact."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

from o3dvis.cameras import all_finite

from conftest import _pinhole


@pytest.fixture(scope="module")
def vis(small_vis):
    """The small random network's model here, not the shipped one."""
    return small_vis


def test_each_camera_form_gives_the_same_answer(vis, points):
    field = vis.encode(points)
    eye = np.array([0.0, 0.0, 4.0])
    reference = field.probabilities(eye)
    forms = [eye.tolist(), tuple(eye), eye.astype(np.float32), eye.astype(np.int64), eye[None],
             torch.tensor(eye), torch.tensor(eye, dtype=torch.float32), o3d.core.Tensor(eye),
             o3d.core.Tensor(eye[None].astype(np.float32)),
             _pinhole(eye, points.mean(0)), [_pinhole(eye, points.mean(0))]]
    for form in forms:
        torch.testing.assert_close(field.probabilities(form), reference, atol=1e-6, rtol=1e-6)
    trajectory = o3d.camera.PinholeCameraTrajectory()
    trajectory.parameters = [_pinhole(eye, points.mean(0)), _pinhole(-eye, points.mean(0))]
    torch.testing.assert_close(field.probabilities(trajectory), field.probabilities([eye, -eye]),
                               atol=1e-6, rtol=1e-6)


BAD_CAMERAS = [
    ([np.nan, 0, 5], ValueError, "NaN or Inf"),
    ([np.inf, 0, 5], ValueError, "NaN or Inf"),
    ([0, 5], ValueError, r"shape \(3,\) or \(V, 3\)"),
    (np.zeros((2, 2)), ValueError, r"shape \(3,\) or \(V, 3\)"),
    (np.zeros((0, 3)), ValueError, "no vectors"),
    ([[0, 0, 5], [0, 5]], ValueError, "3-vector"),
    (np.array([True, False, True]), TypeError, "real numbers"),
    ("0,0,5", TypeError, "real numbers"),
    (torch.tensor([1j, 0, 5]), TypeError, "real numbers"),
]


def test_all_finite_is_exact_where_the_sum_overflows_or_cancels():
    """The sum decides only when it is finite: finite entries whose sum overflows still pass, and
    +inf beside -inf (a NaN sum) or a NaN fail."""
    huge = torch.full((4, 3), 1e308, dtype=torch.float64)
    assert not torch.isfinite(huge.sum()) and all_finite(huge)
    assert all_finite(torch.zeros(5, 3)) and all_finite(torch.tensor([[1.0, -2.0, 3.0]]))
    for bad in ([np.inf, -np.inf, 0.0], [np.nan, 1.0, 2.0], [1e308, 1e308, np.inf]):
        assert not all_finite(torch.tensor([bad], dtype=torch.float64))


@pytest.mark.parametrize("camera, error, message", BAD_CAMERAS)
def test_bad_cameras_raise_clear_errors(vis, points, camera, error, message):
    with pytest.raises(error, match=message):
        vis.encode(points).query(camera)
