"""A small octree U-Net: one view-independent feature per finest-level node."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from . import native
from .conv import (STEPS, ConvBnRelu, NativeLayer, OctreeDownsample, OctreeUpsample, ResBlock, pad_channels,
                   step_conditions)
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
        downs, stages, ups, decoder, up_leaf, body = ((self.down, self.enc, self.up, self.dec, self.up_leaf, None)
                                                      if training else self._steps(signal))
        if body is not None:  # every layer but the leaves' in one call of C
            return self.head(up_leaf(body(signal, octree), octree, octree.depth - 1, self.skip_leaf(signal)))
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
        ``signal``, as :meth:`forward` walks them, and the :class:`_NativeBody` of those below the
        leaves where the C kernels run every one of them (else None); kept until a weight changes
        (one check for the whole network, not one per layer)."""
        def make() -> tuple:
            downs = [down.step(signal) for down in self.down]
            stages = [[block.step(signal) for block in stage] for stage in self.enc]
            ups, decoder = [up.step(signal) for up in self.up], [block.step(signal) for block in self.dec]
            return downs, stages, ups, decoder, self.up_leaf.step(signal), _NativeBody.of(downs, stages, ups, decoder)
        return STEPS.get(self, step_conditions(self.down[0].conv, signal), make)


_DOWN, _CONV, _UP = range(3)
"""How a layer of :class:`_NativeBody` takes its level's index: a down-sampling's children, a
convolution's neighbours, an up-sampling's octant rows."""


class _NativeBody:
    """The U-Net's down-samplings, encoder, up-samplings and decoder in inference as one call of the C
    kernels (:func:`~o3dvis.nn.native.unet`), their answers those of the layers' steps one by one:
    the table of the layers, made once from their steps, and per call the rows, indices and lists
    of the octree's levels.

    Args:
        table: (layers, :data:`~o3dvis.nn.native.UNET_FIELDS`) the layers, their octree's fields zero.
        plan: per layer, how it takes its level's index (``_DOWN``, ``_CONV`` or ``_UP``) and its
            input's level below the octree's depth.
        weights: the layers' :class:`~o3dvis.nn.conv.NativeLayer`, kept for the table's addresses.
    """

    def __init__(self, table: Tensor, plan: list[tuple[int, int]], weights: list[NativeLayer]):
        self.table, self.plan, self.weights = table, plan, weights

    @classmethod
    def of(cls, downs: list, stages: list, ups: list, decoder: list) -> "_NativeBody | None":
        """The body of a U-Net's steps, or None where one of its layers is not the kernels'."""
        blocks = [block for stage in stages for block in stage] + decoder
        layers = downs + ups + [layer for block in blocks for layer in getattr(block, "layers", (block,))]
        if not all(hasattr(layer, "native") for layer in layers):
            return None
        rows, plan, weights, skips = [], [], [], []

        def add(step, how: int, below: int, source: int, residual: int = -1, addend: int = -1) -> int:
            layer = step.native
            rows.append([layer.kind, source, residual, addend, layer.channels, layer.outputs, layer.taps,
                         int(layer.relu or residual >= 0), layer.weight.data_ptr(), layer.shift.data_ptr(),
                         0, 0, 0, 0, 0])
            plan.append((how, below))
            weights.append(layer)
            return len(rows)  # the buffer of its output

        def add_block(block, below: int, source: int) -> int:
            a, b = block.layers
            return add(b, _CONV, below, add(a, _CONV, below, source), residual=source)

        x = 0
        for s, (down, stage) in enumerate(zip(downs, stages)):
            x = add(down, _DOWN, s, x)
            for block in stage:
                x = add_block(block, s + 1, x)
            skips.append(x)
        for d, (up, block, skip) in enumerate(zip(ups, decoder, reversed(skips[:-1]))):
            below = len(stages) - d
            x = add_block(block, below - 1, add(up, _UP, below, x, addend=skip))
        return cls(torch.tensor(rows, dtype=torch.long), plan, weights)

    def __call__(self, signal: Tensor, octree: Octree) -> Tensor:
        """(nodes of the level above the leaves, channels) the decoder's output for ``signal``."""
        fields, indices = [], []  # indices: alive until the call returns (the octree keeps the lists)
        for (how, below), layer in zip(self.plan, self.weights):
            level = octree.depth - below
            if how == _UP:
                index = octree.octant_rows(level + 1).contiguous()
                indices.append(index)
                fields += (index.shape[0], index.data_ptr(), 0, 0, 0)
                continue
            index = (octree.child_rows(level - 1) if how == _DOWN else octree.neighbours(level)).contiguous()
            indices.append(index)
            nodes = octree.num_nodes(level)
            entries = octree.derived(("conv entries", layer.taps, level), lambda: native.conv_entries(index, nodes))
            lists = -(-index.shape[0] // native.CONV_BLOCK) * layer.taps
            fields += (index.shape[0], index.data_ptr(), entries.data_ptr(), entries.data_ptr() + 8 * (lists + 1),
                       entries.shape[0] - lists - 1)
        table = self.table.clone()
        table[:, 10:] = torch.tensor(fields, dtype=torch.long).view(-1, 5)
        last = self.weights[-1]
        signal = pad_channels(signal, self.weights[0].channels)  # an odd count: a channel of zeros (see ConvBnRelu)
        return native.unet(table, signal, signal.new_empty(int(table[-1, 10]), last.outputs))
