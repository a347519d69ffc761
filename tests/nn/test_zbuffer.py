"""The surfel z-buffer (``o3dvis.nn.zbuffer``): the torch ops answer as the C kernels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from o3dvis.nn import native

from conftest import box_surface


@pytest.mark.skipif(not native.available(), reason="no C kernels here")
def test_the_torch_zbuffer_answers_the_cameras_inside_as_the_kernels():
    """The surfel z-buffer in torch ops rounds as the kernels do (their arctangent, sums and tables of
    rays): each disc in their pixels and the same front disc of every pixel, so the same answers.
    Rounded as torch rounds, dozens of points of a view inside this box had another front disc."""
    from o3dvis.nn import zbuffer
    from o3dvis.nn.cues import point_surfels

    rng = np.random.default_rng(1)
    points = torch.tensor(box_surface((-0.9, -0.8, -0.7), (0.9, 0.8, 0.7), 30_000, rng), dtype=torch.float32)
    surfels = point_surfels(points, areas=True)
    for camera in torch.tensor(rng.uniform(-0.85, 0.85, (14, 3)), dtype=torch.float32):
        rows = zbuffer.buffer_rows(points, surfels[:, 4], camera)
        kernels = zbuffer.surfel_zbuffer(points, surfels, camera, rows)
        torch_ops = zbuffer._surfel_zbuffer_torch(points, surfels, camera, rows)
        assert torch.equal(kernels[:, 0], torch_ops[:, 0]), f"another front disc from {camera.tolist()}"
        torch.testing.assert_close(torch_ops, kernels, rtol=1e-5, atol=1e-5)
