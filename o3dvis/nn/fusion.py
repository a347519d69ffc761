"""Fusion of the network's answer with the surfel z-buffer's test, fitted after training.

The predictor reads depth buffers of about one pixel per point, in which a point
near the camera, far from its neighbours in the image, shows hidden points
through the holes between its pixels. The surfel z-buffer (:mod:`.zbuffer`)
renders every point as a disc at a resolution set by the points' spacing and
tests each point along its own ray: sharper on clean clouds, but misled by
noise. A small MLP maps each (point, camera) pair's margin and z-buffer answer
to the fused margin; it is fitted on training scenes with the network frozen
(``o3dvis fuse``), and applied by :class:`~o3dvis.VisibilityField` to every view
from a camera position (a viewing direction keeps the network's margin).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .noise import NUM_NOISE_CUES
from .zbuffer import NUM_ZBUFFER_FEATURES

__all__ = ["NUM_FUSION_INPUTS", "ZBufferFusion", "fusion_inputs"]

NUM_FUSION_INPUTS = 1 + (NUM_ZBUFFER_FEATURES + 1) + NUM_NOISE_CUES
_MAX_MARGIN = 15.0  # margins beyond this are certain either way (and saturate a float32 probability)


def fusion_inputs(margin: Tensor, zbuffer: Tensor, noise: Tensor) -> Tensor:
    """(..., 8) inputs of the fusion MLP: the margin (clamped to +-15), whether the point's own
    disc is in front, its distance beyond the front plane on two scales (``tanh`` of it over 2 and
    over 8 spacings), the log of its spacing in pixels, how squarely it faces the camera, and the
    cloud's noise cues: these tell how far the z-buffer's test can be trusted.

    Args:
        margin: (...) the network's margins.
        zbuffer: (..., 4) the :func:`~o3dvis.nn.zbuffer.surfel_zbuffer` answers of the same pairs.
        noise: (2,) the cloud's :func:`~o3dvis.nn.noise.noise_cues`, or (..., 2) each pair's cloud's.
    """
    beyond = zbuffer[..., 1]
    first = torch.stack([margin.clamp(-_MAX_MARGIN, _MAX_MARGIN), zbuffer[..., 0], torch.tanh(beyond / 2),
                         torch.tanh(beyond / 8), zbuffer[..., 2].clamp_min(1e-6).log(), zbuffer[..., 3]], dim=-1)
    return torch.cat([first, noise.to(first).expand(*first.shape[:-1], NUM_NOISE_CUES)], dim=-1)


class ZBufferFusion(nn.Module):
    """The fused margin of :func:`fusion_inputs`: an MLP of one hidden layer on the inputs
    standardised by the buffers ``mean`` and ``std`` (set when it is fitted).

    Args:
        hidden: width of the hidden layer.
    """

    def __init__(self, hidden: int = 16):
        super().__init__()
        self.register_buffer("mean", torch.zeros(NUM_FUSION_INPUTS))
        self.register_buffer("std", torch.ones(NUM_FUSION_INPUTS))
        self.mlp = nn.Sequential(nn.Linear(NUM_FUSION_INPUTS, hidden), nn.ReLU(), nn.Linear(hidden, 1))

    def forward(self, margin: Tensor, zbuffer: Tensor, noise: Tensor) -> Tensor:
        """(...) fused margins of (...) ``margin``, (..., 4) ``zbuffer`` answers and the noise cues
        (see :func:`fusion_inputs`)."""
        x = fusion_inputs(margin, zbuffer.to(margin.dtype), noise)
        return self.mlp(((x - self.mean.to(x.dtype)) / self.std.to(x.dtype)).to(self.mlp[0].weight.dtype))[..., 0] \
            .to(margin.dtype)
