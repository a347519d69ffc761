"""Sparse convolutions on the non-empty nodes of an :class:`~o3dvis.nn.octree.Octree`.

Each op gathers the features it needs through the octree's index tables and
runs one dense matmul, so the cost is linear in the number of nodes.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable, Iterator
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..threads import torch_threads
from . import native
from .octree import Octree
from .state import Derived

__all__ = ["OctreeConv", "OctreeDownsample", "OctreeUpsample", "ConvBnRelu", "ResBlock", "LayerStep", "NativeLayer",
           "STEPS", "gather_rows", "pad_channels", "products_in", "step_conditions"]

_PRODUCTS = threading.local()


@contextlib.contextmanager
def products_in(dtype: torch.dtype) -> Iterator[None]:
    """Runs the convolutions' matrix products of this thread in ``dtype`` (e.g. ``torch.bfloat16``,
    accumulated in float32 by the kernels) where no gradient is asked for; their outputs and
    everything between them stay float32."""
    previous = getattr(_PRODUCTS, "dtype", None)
    _PRODUCTS.dtype = dtype
    try:
        yield
    finally:
        _PRODUCTS.dtype = previous


def _pad(x: Tensor) -> Tensor:
    return torch.cat([x, x.new_zeros(1, x.shape[1])], dim=0)


_CHUNK_ELEMENTS = 1 << 20
"""Gathered values per chunk of a convolution (4 MB in float32): temporaries this size are reused
from the heap by the allocator and stay in cache, where larger ones are mapped and page-faulted
afresh on every call, which would cost as much as the products themselves on large clouds."""


_SERIAL_ROWS = 2048
"""Matrix products of fewer rows than this run on one thread. With several threads the CPU kernels
split such products along their inner dimension, which changes the order of the sums with the
thread count; in bfloat16 the rounded outputs then differ, and the answers for one cloud would
depend on how many threads the machine's load left free."""


def gather_rows(x: Tensor, index: Tensor) -> Tensor:
    """``x[index]`` for a (M, C) ``x`` and an integer ``index`` of any shape, by ``index_select``
    (faster than advanced indexing on the CPU)."""
    return x.index_select(0, index.reshape(-1)).view(*index.shape, x.shape[1])


class _GatherMatmul(nn.Module):
    """A layer that gathers ``taps`` rows per output row and multiplies them by one weight of
    shape (taps * in_channels, out_channels), with fan-in init: the base of the octree convolutions."""

    def __init__(self, taps: int, in_channels: int, out_channels: int):
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.weight = nn.Parameter(torch.empty(taps * in_channels, out_channels))
        nn.init.normal_(self.weight, std=math.sqrt(2.0 / (taps * in_channels)))

    def product_dtype(self, x: Tensor) -> torch.dtype:
        """The dtype of this layer's matrix products for the input ``x``: that of
        :func:`products_in` where one is set and no gradient is asked for, else ``x``'s."""
        dtype = getattr(_PRODUCTS, "dtype", None)
        return x.dtype if dtype is None or torch.is_grad_enabled() else dtype

    def gather_matmul(self, x: Tensor, index: Tensor, weight: Tensor | None = None) -> Tensor:
        """``x[index].reshape(n, -1) @ weight`` for an (n, taps) ``index``, in chunks of rows, in
        :meth:`product_dtype` (the output in ``x``'s dtype).

        ``weight``: another weight of this layer's shape, already in :meth:`product_dtype`
        (default: the layer's own)."""
        out_dtype = x.dtype
        if weight is None:
            dtype = self.product_dtype(x)
            weight = self.weight if dtype == self.weight.dtype else self._weight_in(dtype)
        x = x.to(weight.dtype)
        step = max(1, _CHUNK_ELEMENTS // (index.shape[1] * x.shape[1]))
        parts = []
        for a in range(0, len(index), step):
            rows = gather_rows(x, index[a:a + step]).flatten(1)
            with torch_threads(1) if len(rows) < _SERIAL_ROWS else contextlib.nullcontext():
                parts.append(rows @ weight)
        out = parts[0] if len(parts) == 1 else torch.cat(parts)
        return out.to(out_dtype)

    def _weight_in(self, dtype: torch.dtype) -> Tensor:
        """The weight in ``dtype``, converted once per change of the weight."""
        key = (dtype, self.weight._version, self.weight.data_ptr())
        cached = self.__dict__.get("_converted")
        if cached is None or cached[0] != key:
            cached = self.__dict__["_converted"] = (key, self.weight.detach().to(dtype))
        return cached[1]


class OctreeConv(_GatherMatmul):
    """3x3x3 convolution on the nodes of one level (same semantics as ``conv3d``, padding 1).

    The weight row ``o * in_channels + c`` is the tap at offset index ``o`` of
    :data:`~o3dvis.nn.octree._OFFSETS`, i.e. ``conv3d`` weight ``[:, c, i, j, k]``
    with ``o = 9 i + 3 j + k``.
    """

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(27, in_channels, out_channels)

    def forward(self, x: Tensor, octree: Octree, level: int, weight: Tensor | None = None) -> Tensor:
        return self.gather_matmul(_pad(x), self.index(octree, level), weight)

    @staticmethod
    def index(octree: Octree, level: int) -> Tensor:
        """(n, 27) the rows of the input each output row gathers (the input's length: zeros)."""
        return octree.neighbours(level)


class OctreeDownsample(_GatherMatmul):
    """Stride-2 convolution with a 2x2x2 kernel: level ``level`` -> ``level - 1``."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(8, in_channels, out_channels)

    def forward(self, x: Tensor, octree: Octree, level: int, weight: Tensor | None = None) -> Tensor:
        return self.gather_matmul(_pad(x), self.index(octree, level), weight)

    @staticmethod
    def index(octree: Octree, level: int) -> Tensor:
        """(n, 8) the rows of the input each output row gathers (the input's length: zeros)."""
        return octree.child_rows(level - 1)


class OctreeUpsample(_GatherMatmul):
    """Transposed stride-2 convolution: level ``level`` -> ``level + 1``."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__(1, in_channels, 8 * out_channels)

    def product_dtype(self, x: Tensor) -> torch.dtype:
        """Always ``x``'s: one product per coarse node, too few to round."""
        return x.dtype

    def forward(self, x: Tensor, octree: Octree, level: int, weight: Tensor | None = None) -> Tensor:
        weight = self.weight if weight is None else weight
        per_octant = (x @ weight).view(x.shape[0] * 8, self.out_channels // 8)
        return gather_rows(per_octant, octree.octant_rows(level + 1))


LayerStep = Callable[..., Tensor]
"""A layer in inference, ``step(x, octree, level)``; a :class:`ConvBnRelu`'s also takes a
``residual`` and an ``addend``: see :meth:`ConvBnRelu.step`."""

STEPS = Derived()
"""The layers' kept steps (and the U-Net's lists of them)."""


class NativeLayer(NamedTuple):
    """A layer's step as the C kernels run it (see :data:`o3dvis.nn.native.UNET_FIELDS`): ``kind`` 0
    a convolution of :func:`~o3dvis.nn.native.gather_conv` (``weight`` packed for it), 1 an
    up-sampling of :func:`~o3dvis.nn.native.upsample`; its folded ``shift``, input ``channels``,
    ``taps``, ``outputs`` and ReLU."""

    kind: int
    weight: Tensor
    shift: Tensor
    channels: int
    taps: int
    outputs: int
    relu: bool


class ConvBnRelu(nn.Module):
    """A convolution, batch norm and ReLU; in inference (eval mode, no gradient) the batch norm is
    folded into the convolution's weight, scaled per output channel, and a shift."""

    def __init__(self, in_channels: int, out_channels: int, conv: type[_GatherMatmul] = OctreeConv,
                 relu: bool = True):
        super().__init__()
        self.conv = conv(in_channels, out_channels)
        self.bn = nn.BatchNorm1d(out_channels)
        self.relu = relu

    def forward(self, x: Tensor, octree: Octree, level: int, residual: Tensor | None = None,
                addend: Tensor | None = None) -> Tensor:
        """``relu(bn(conv(x)) + residual) + addend``: without a ``residual``, the ReLU only where the
        layer has one; without an ``addend``, nothing added after it."""
        if self.training or torch.is_grad_enabled():
            x = self.bn(self.conv(x, octree, level))
            x = torch.relu(x + residual) if residual is not None else torch.relu(x) if self.relu else x
            return x if addend is None else x + addend
        return self.inference_step(x)(x, octree, level, residual, addend)

    def inference_step(self, x: Tensor) -> LayerStep:
        """:meth:`step` for inputs like ``x``, kept until the weights change."""
        return STEPS.get(self, step_conditions(self.conv, x), lambda: self.step(x))

    def step(self, x: Tensor) -> LayerStep:
        """This layer in inference for inputs like ``x``, with its weights as they are now:
        ``step(x, octree, level, residual=None, addend=None)``, with a ``residual`` ``relu(residual +
        convolution + shift)`` (a :class:`ResBlock`'s end), with an ``addend`` the result plus it
        after the ReLU (a U-Net's skip). The batch norm is folded into the weight (rounded to
        the layer's :meth:`~_GatherMatmul.product_dtype`) and a shift. One pass of C where the
        kernels take it: an up-sampling for the nodes that exist only (:func:`~o3dvis.nn.native.upsample`,
        the same float32 sums), a convolution in bfloat16 dot products (:func:`~o3dvis.nn.native.gather_conv`,
        for outputs a multiple of 16, an odd number of inputs padded with zeros, on a CPU with AVX-512
        bfloat16, its rows shared out among the threads of :func:`~o3dvis.nn.native.kernel_threads`);
        torch ops elsewhere."""
        dtype = self.conv.product_dtype(x)
        weight, shift = self._folded(dtype)
        in_c = x.device.type == "cpu" and x.dtype == torch.float32 and native.available()
        return (self._native_step(weight, shift) if in_c else None) or self._torch_step(weight, shift)

    def _native_step(self, weight: Tensor, shift: Tensor) -> LayerStep | None:
        """:meth:`step` in one pass of C with the folded ``weight`` and ``shift``, or None where the
        kernels do not take this layer."""
        conv, relu = self.conv, self.relu
        if isinstance(conv, OctreeUpsample):
            weight, shift = weight.contiguous(), shift.contiguous()

            def upsample(x: Tensor, octree: Octree, level: int, residual: Tensor | None = None,
                         addend: Tensor | None = None) -> Tensor:
                rows = octree.octant_rows(level + 1).contiguous()
                return native.upsample(x.contiguous(), rows, weight, shift, relu or residual is not None,
                                       residual=None if residual is None else residual.contiguous(),
                                       addend=None if addend is None else addend.contiguous())
            upsample.native = NativeLayer(1, weight, shift, conv.in_channels, 1, conv.out_channels // 8, relu)
            return upsample
        if weight.dtype != torch.bfloat16 or conv.out_channels % 16 or not native.has_gather_conv():
            return None
        taps, outputs = len(weight) // conv.in_channels, conv.out_channels
        channels = conv.in_channels + conv.in_channels % 2
        # the kernels take the channels in pairs: an odd count gets a channel of zeros, in the weight and the input
        weight = F.pad(weight.view(taps, conv.in_channels, outputs), (0, 0, 0, channels - conv.in_channels))
        packed, shift = native.pack_conv(weight.view(taps * channels, outputs), taps), shift.float().contiguous()

        def gathered(x: Tensor, octree: Octree, level: int, residual: Tensor | None = None,
                     addend: Tensor | None = None) -> Tensor:
            index = conv.index(octree, level).contiguous()
            entries = octree.derived(("conv entries", taps, level), lambda: native.conv_entries(index, len(x)))
            out = native.gather_conv(pad_channels(x, channels), index, packed, taps, outputs, shift,
                                     None if residual is None else residual.contiguous(),
                                     relu=relu or residual is not None, entries=entries)
            return out if addend is None else out.add_(addend)
        gathered.native = NativeLayer(0, packed, shift, channels, taps, outputs, relu)
        return gathered

    def _torch_step(self, weight: Tensor, shift: Tensor) -> LayerStep:
        """:meth:`step` in torch ops with the folded ``weight`` and ``shift``."""
        conv, finish = self.conv, self._finish

        def torch_ops(x: Tensor, octree: Octree, level: int, residual: Tensor | None = None,
                      addend: Tensor | None = None) -> Tensor:
            out = finish(conv(x, octree, level, weight).add_(shift), residual)
            return out if addend is None else out.add_(addend)
        return torch_ops

    def _finish(self, out: Tensor, residual: Tensor | None) -> Tensor:
        """A convolution plus shift ``out`` (in place) plus ``residual`` through the ReLU, or without
        one through this layer's ReLU where it has one."""
        if residual is not None:
            return out.add_(residual).relu_()
        return out.relu_() if self.relu else out

    def _folded(self, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """The convolution's weight times the batch norm's scale (in ``dtype``) and the batch norm's shift."""
        bn, weight = self.bn, self.conv.weight
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        shift = bn.bias - bn.running_mean * scale
        # an up-sampling's columns are (octant, channel): its scale repeats per octant
        folded = (weight * scale.repeat(weight.shape[1] // scale.shape[0])).to(dtype)
        return folded.detach(), shift.detach()


def pad_channels(x: Tensor, channels: int) -> Tensor:
    """``x`` (rows, C) contiguous, with columns of zeros up to ``channels`` (>= C)."""
    return F.pad(x, (0, channels - x.shape[1])) if x.shape[1] < channels else x.contiguous()


def step_conditions(conv: _GatherMatmul, x: Tensor) -> tuple:
    """What a layer's :meth:`ConvBnRelu.step` depends on besides its weights."""
    return conv.product_dtype(x), x.dtype, x.device, native.available(), native.has_gather_conv()


class ResBlock(nn.Module):
    """Two 3x3x3 conv + batch norm layers with an identity shortcut."""

    def __init__(self, channels: int):
        super().__init__()
        self.a = ConvBnRelu(channels, channels)
        self.b = ConvBnRelu(channels, channels, relu=False)

    def forward(self, x: Tensor, octree: Octree, level: int) -> Tensor:
        if self.training or torch.is_grad_enabled():
            return torch.relu(x + self.b(self.a(x, octree, level), octree, level))
        return self.b.inference_step(x)(self.a(x, octree, level), octree, level, x)

    def step(self, x: Tensor) -> LayerStep:
        """This block in inference for inputs like ``x`` (see :meth:`ConvBnRelu.step`); its two
        layers' steps are the step's ``layers``."""
        a, b = self.a.step(x), self.b.step(x)

        def block(x: Tensor, octree: Octree, level: int) -> Tensor:
            return b(a(x, octree, level), octree, level, x)
        block.layers = (a, b)  # what a caller that runs the layers itself reads
        return block
