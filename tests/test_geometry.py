"""The geometry helpers (``o3dvis.geometry``): fixed rotations and bounds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from o3dvis.geometry import bounds, fixed_rotations


def test_fixed_rotations_are_rotations_and_the_same_each_call():
    r = fixed_rotations(5)
    assert r.shape == (5, 3, 3) and r.dtype == torch.float64
    torch.testing.assert_close(r[0], torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(5, 3, 3))
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(5, dtype=torch.float64))
    torch.testing.assert_close(fixed_rotations(3), r[:3], rtol=0, atol=0)
    assert (r[1:] - torch.eye(3, dtype=torch.float64)).abs().amax(dim=(1, 2)).min() > 0.1


def test_bounds_are_numpy_s_min_and_max_along_the_rows():
    points = np.random.default_rng(0).normal(size=(1000, 3)) * [1.0, 1e6, 1e-6]
    for lo, hi in [bounds(points), bounds(points[:, :2]), bounds(points[:1])]:
        assert lo.shape == hi.shape and lo.dtype == np.float64
    np.testing.assert_array_equal(np.stack(bounds(points)), np.stack([points.min(axis=0), points.max(axis=0)]))
    points[7, 1] = np.nan
    lo, hi = bounds(points)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and np.isfinite(lo[[0, 2]]).all()
    with pytest.raises(ValueError, match="no points"):
        bounds(np.empty((0, 3)))
