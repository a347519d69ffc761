"""A small octree U-Net: one view-independent feature per finest-level node."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from .conv import STEPS, ConvBnRelu, OctreeDownsample, OctreeUpsample, ResBlock, step_conditions
from .octree import Octree

__all__ = ["OctreeUNet"]


class OctreeUNet(nn.Module):
    """Encoder-decoder over the octree levels ``depth - 1, depth - 2, ...``.

    The finest level, where most nodes are, only sees a stride-2 down-sampling,
    a transposed up-sampling and a linear skip of the input signal; the 3x3x3
    residual blocks run on the coarser levels. This keeps the cost of a
    200 k-point cloud low on a CPU.

    Args:
        in_channels: channels of the input signal at the finest level.
        channels: widths of the stages; stage ``i`` runs at level ``depth - 1 - i``.
        blocks: residual blocks per encoder stage (the decoder uses one).
        out_channels: width of the output feature.
    """

    def __init__(self, in_channels: int, channels: Sequence[int] = (32, 48, 64, 96, 128),
                 blocks: int = 1, out_channels: int = 32):
        super().__init__()
        self.channels = tuple(channels)
        widths = [in_channels, *channels]
        self.down = nn.ModuleList(ConvBnRelu(widths[i], widths[i + 1], OctreeDownsample)
                                  for i in range(len(channels)))
        self.enc = nn.ModuleList(nn.Sequential(*[ResBlock(c) for c in [width] * blocks])
                                 for width in channels)
        self.up = nn.ModuleList(ConvBnRelu(channels[i], channels[i - 1], OctreeUpsample)
                                for i in range(len(channels) - 1, 0, -1))
        self.dec = nn.ModuleList(ResBlock(channels[i - 1]) for i in range(len(channels) - 1, 0, -1))
        self.up_leaf = ConvBnRelu(channels[0], out_channels, OctreeUpsample, relu=False)
        self.skip_leaf = nn.Linear(in_channels, out_channels)
        self.head = nn.Linear(out_channels, out_channels)

    def forward(self, signal: Tensor, octree: Octree) -> Tensor:
        """Returns (n, out_channels) features of the nodes at ``octree.depth``."""
        if octree.depth - len(self.channels) < 1:
            raise ValueError(f"octree depth {octree.depth} too shallow for {len(self.channels)} stages")
        training = self.training or torch.is_grad_enabled()
        downs, stages, ups, decoder, up_leaf = ((self.down, self.enc, self.up, self.dec, self.up_leaf) if training
                                                else self._steps(signal))
        level, x, skips = octree.depth, signal, []
        for down, stage in zip(downs, stages):
            x = down(x, octree, level)
            level -= 1
            for block in stage:
                x = block(x, octree, level)
            skips.append(x)
        for up, block, skip in zip(ups, decoder, reversed(skips[:-1])):
            x = up(x, octree, level, None, skip)  # the skip added after the ReLU
            level += 1
            x = block(x, octree, level)
        x = up_leaf(x, octree, level, self.skip_leaf(signal))  # relu(up-sampled + skip)
        return self.head(x)

    def _steps(self, signal: Tensor) -> tuple:
        """The layers in inference (their :meth:`~o3dvis.nn.conv.ConvBnRelu.step`) for the input
        ``signal``, as :meth:`forward` walks them; kept until a weight changes (one check for the
        whole network, not one per layer)."""
        return STEPS.get(self, step_conditions(self.down[0].conv, signal), lambda: (
            [down.step(signal) for down in self.down], [[block.step(signal) for block in stage] for stage in self.enc],
            [up.step(signal) for up in self.up], [block.step(signal) for block in self.dec],
            self.up_leaf.step(signal)))
