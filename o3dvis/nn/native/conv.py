"""The U-Net's gathered convolutions with bfloat16 dot products (``o3dvis/nn/csrc/conv.c``; see
:class:`o3dvis.nn.conv.ConvBnRelu`), on CPUs with AVX-512 bfloat16 (on the AMX tiles where there
are some)."""

from __future__ import annotations

import torch
from torch import Tensor

from . import _library
from ._library import check
from .threads import kernel_threads


def has_gather_conv() -> bool:
    """Whether :func:`gather_conv` runs here: a variant of the kernels with AVX-512 bfloat16 dot
    products is loaded (the AMX one runs it on the tiles where the operating system grants them)."""
    library = _library.LIBRARY
    if library is None:
        return False
    if getattr(library, "gather_conv", None) is None:
        library.gather_conv = bool(library.o3dvis_has_gather_conv())
    return library.gather_conv


def pack_conv(weight: Tensor, taps: int) -> Tensor:
    """A gathered convolution's (taps x C, O) weight as :func:`gather_conv` reads it: rounded to
    bfloat16, zero-padded to a multiple of 32 rows and of 16 columns, and cut into tiles of 16
    pairs of rows x 16 columns (a pair of bfloat16 per int32), row tiles outermost."""
    k, outputs = weight.shape
    if k % taps:
        raise ValueError(f"the weight's {k} rows are not {taps} taps of the same channels")
    kp, op = -(-k // 32) * 32, -(-outputs // 16) * 16
    padded = weight.detach().new_zeros(kp, op, dtype=torch.bfloat16)
    padded[:k, :outputs] = weight.detach()
    tiles = padded.view(kp // 32, 16, 2, op // 16, 16).permute(0, 3, 1, 4, 2).contiguous()
    return tiles.view(torch.int16).view(torch.int32).flatten().cpu()


CONV_BLOCK = 64
"""Output rows of a block of :func:`gather_conv` (``CONV_BLOCK`` of ``conv.c``)."""


def conv_entries(index: Tensor, rows: int) -> Tensor:
    """The lists by which :func:`gather_conv` (without the AMX tiles) takes an ``index``: for each block
    of 64 output rows and each tap, the rows that have that neighbour (an index below ``rows``), so
    that the products with a missing one, which add nothing, are skipped. Made once for the
    convolutions over the same index (a level's 3x3x3 neighbours serve four).

    Args:
        index: (n, taps) int64 in [0, rows].
        rows: the gathered input's rows (an index of ``rows``: a row of zeros).

    Returns:
        (L,) int64: the offsets of the lists, then their entries (see ``o3dvis_conv_entries``).

    Raises:
        ValueError: an index of the wrong shape or type, or out of [0, rows].
        RuntimeError: no AVX-512 bfloat16 kernels here (see :func:`has_gather_conv`).
    """
    n, taps = index.shape
    check("index", index, (n, taps), torch.long)
    lists = -(-n // CONV_BLOCK) * taps
    out = index.new_empty(lists + 1 + n * taps + 8 * (lists + 1))
    listed = _library.LIBRARY.o3dvis_conv_entries(n, index.data_ptr(), taps, rows, out.data_ptr(),
                                                  out[lists + 1:].data_ptr())
    if listed == -3:
        raise ValueError(f"index must lie in [0, {rows}]")
    if listed < 0:
        raise RuntimeError("conv_entries needs the AVX-512 bfloat16 kernels (see has_gather_conv)")
    return out[:lists + 1 + listed]


def gather_conv(x: Tensor, index: Tensor, packed: Tensor, taps: int, outputs: int, shift: Tensor,
                residual: Tensor | None = None, relu: bool = False, entries: Tensor | None = None,
                threads: int | None = None) -> Tensor:
    """(n, outputs) float32: each row's ``taps`` rows of ``x`` gathered (an index of ``len(x)``: a
    row of zeros) times the weight :func:`pack_conv` packed, in bfloat16 with float32 sums (on
    the AMX tiles where there are some, else AVX-512 dot products in the same order, the products
    with a row of zeros skipped) and the result rounded to bfloat16, then plus ``shift``, plus
    ``residual``, and through a ReLU where ``relu``: a :class:`~o3dvis.nn.conv.ConvBnRelu` in
    inference in one pass.

    Args:
        x: (rows, C) float32.
        index: (n, taps) int64 in [0, rows].
        packed: :func:`pack_conv` of the (taps x C, outputs) weight.
        shift: (outputs,) float32.
        residual: (n, outputs) float32 or None.
        entries: :func:`conv_entries` of ``index``, where the caller keeps them for several
            convolutions (None: made here).
        threads: the rows' blocks are shared out among up to this many threads (see
            :func:`kernel_threads`); each row's sums are the same on any number.

    Raises:
        ValueError: tensors of the wrong shape or type, an index out of range, or entries that are
            not lists of rows and neighbours in range.
        RuntimeError: no AVX-512 bfloat16 kernels here (see :func:`has_gather_conv`).
    """
    rows, channels = x.shape
    n = index.shape[0]
    check("x", x, (rows, channels))
    check("index", index, (n, taps), torch.long)
    check("packed", packed, ((-(-taps * channels // 32) * 32) * (-(-outputs // 16) * 16) // 2,), torch.int32)
    check("shift", shift, (outputs,))
    if residual is not None:
        check("residual", residual, (n, outputs))
    if channels % 2 or outputs % 16:
        raise ValueError(f"need an even number of channels and a multiple of 16 outputs, got {channels} and {outputs}")
    threads = kernel_threads(threads, n * taps * channels * outputs)
    if entries is None:
        entries = conv_entries(index, rows)
    lists = -(-n // CONV_BLOCK) * taps
    if entries.ndim != 1 or len(entries) <= lists:
        raise ValueError(f"entries must be conv_entries of the index: at least {lists + 1} values, got "
                         f"{tuple(entries.shape)}")
    check("entries", entries, (len(entries),), torch.long)
    out = x.new_empty(n, outputs)
    code = _library.LIBRARY.o3dvis_gather_conv(n, x.data_ptr(), rows, channels, index.data_ptr(), taps,
                                               entries.data_ptr(), entries[lists + 1:].data_ptr(),
                                               entries.shape[0] - lists - 1,
                                               packed.data_ptr(), outputs, shift.data_ptr(),
                                               None if residual is None else residual.data_ptr(), int(relu), threads,
                                               out.data_ptr())
    if code == -3:
        raise ValueError(f"index must lie in [0, {rows}]")
    if code == -4:
        raise ValueError("entries must be conv_entries of the index")
    if code == -2:
        raise RuntimeError("gather_conv needs the AVX-512 bfloat16 kernels (see has_gather_conv)")
    if code:
        raise MemoryError("gather_conv: out of memory")
    return out
