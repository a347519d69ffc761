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

from typing import Callable

import torch
from torch import Tensor, nn

from . import native
from .noise import NUM_NOISE_CUES
from .zbuffer import NUM_ZBUFFER_FEATURES

__all__ = ["NUM_FUSION_INPUTS", "ZBufferFusion", "zbuffer_inputs", "fusion_inputs"]

NUM_FUSION_PAIR_INPUTS = NUM_ZBUFFER_FEATURES + 1  # the zbuffer_inputs of a (point, camera) pair
NUM_FUSION_INPUTS = 1 + NUM_FUSION_PAIR_INPUTS + NUM_NOISE_CUES
_MAX_MARGIN = 15.0  # margins beyond this are certain either way (and saturate a float32 probability)


def zbuffer_inputs(zbuffer: Tensor) -> Tensor:
    """(..., 5) the fusion's inputs from the z-buffer's answers: whether the point's own disc is in
    front, its distance beyond the front plane on two scales (``tanh`` of it over 2 and over 8
    spacings), the log of its spacing in pixels and how squarely it faces the camera. A field
    computes them chunk by chunk of points, where the temporaries stay in cache.

    Args:
        zbuffer: (..., 4) :func:`~o3dvis.nn.zbuffer.surfel_zbuffer` answers.
    """
    beyond = zbuffer[..., 1:2]
    return torch.cat([zbuffer[..., :1], torch.tanh(torch.cat([beyond / 2, beyond / 8], dim=-1)),
                      zbuffer[..., 2:3].clamp_min(1e-6).log(), zbuffer[..., 3:]], dim=-1)


def fusion_inputs(margin: Tensor, inputs: Tensor, noise: Tensor) -> Tensor:
    """(..., 8) inputs of the fusion MLP: the margin (clamped to +-15), the :func:`zbuffer_inputs`
    and the cloud's noise cues, which tell how far the z-buffer's test can be trusted.

    Args:
        margin: (...) the network's margins.
        inputs: (..., 5) the :func:`zbuffer_inputs` of the same pairs.
        noise: (2,) the cloud's :func:`~o3dvis.nn.noise.noise_cues`, or (..., 2) each pair's cloud's.
    """
    inputs = inputs.to(margin.dtype)
    return torch.cat([margin.clamp(-_MAX_MARGIN, _MAX_MARGIN)[..., None], inputs,
                      noise.to(inputs).expand(*inputs.shape[:-1], NUM_NOISE_CUES)], dim=-1)


class ZBufferFusion(nn.Module):
    """The fused margin of :func:`fusion_inputs`: an MLP of one hidden layer on the inputs
    standardised by the buffers ``mean`` and ``std`` (set when it is fitted; folded into the
    first layer's weights when it runs).

    Args:
        hidden: width of the hidden layer.
    """

    def __init__(self, hidden: int = 16):
        super().__init__()
        self.register_buffer("mean", torch.zeros(NUM_FUSION_INPUTS))
        self.register_buffer("std", torch.ones(NUM_FUSION_INPUTS))
        self.mlp = nn.Sequential(nn.Linear(NUM_FUSION_INPUTS, hidden), nn.ReLU(), nn.Linear(hidden, 1))

    def _folded(self) -> tuple[Tensor, Tensor]:
        """The first layer's weight and bias with the standardisation folded in."""
        first = self.mlp[0]
        weight = first.weight / self.std.to(first.weight)
        return weight, first.bias - weight @ self.mean.to(first.weight)

    def forward(self, margin: Tensor, inputs: Tensor, noise: Tensor) -> Tensor:
        """(...) fused margins of (...) ``margin``, (..., 5) :func:`zbuffer_inputs` and the noise
        cues (see :func:`fusion_inputs`)."""
        last = self.mlp[2]
        weight, bias = self._folded()
        x = fusion_inputs(margin, inputs, noise).to(weight.dtype)
        hidden = torch.addmm(bias, x.reshape(-1, x.shape[-1]), weight.t()).relu_()
        return torch.addmm(last.bias, hidden, last.weight.t()).view(margin.shape).to(margin.dtype)

    def bind(self, noise: Tensor) -> Callable[[Tensor, Tensor, slice | Tensor], Tensor]:
        """The fusion of one cloud, ``fuse(margin, zbuffer, rows)``: (n,) fused margins of the
        points ``rows`` (a slice or (n,) indices) with margins ``margin`` (n,) and a camera's
        z-buffer answers ``zbuffer`` (N, 4). Where :func:`~o3dvis.nn.native.usable` (float32 on the
        CPU, autograd off) one pass of C per call, in place of ``margin``, with the cloud's noise
        cues folded into the first layer's biases; else this module's torch ops.

        Args:
            noise: (2,) the cloud's :func:`~o3dvis.nn.noise.noise_cues`.
        """
        mlp = None
        if native.usable(self.mlp[0].weight) and noise.device.type == "cpu":
            weight, bias = self._folded()
            bias = bias + weight[:, 1 + NUM_FUSION_PAIR_INPUTS:] @ noise.to(weight)
            last = self.mlp[2]
            mlp = native.pack_mlp([(weight[:, :1 + NUM_FUSION_PAIR_INPUTS], bias), (last.weight, last.bias)],
                                  torch.float32)

        def fuse(margin: Tensor, zbuffer: Tensor, rows: slice | Tensor) -> Tensor:
            if mlp is not None and native.usable(margin, zbuffer) and margin.is_contiguous():
                native.fuse_margin(rows, zbuffer, margin, mlp, margin)
                return margin
            return self(margin, zbuffer_inputs(zbuffer[rows]), noise)

        return fuse
