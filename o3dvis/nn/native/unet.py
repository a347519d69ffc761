"""The U-Net in inference in C (``o3dvis/nn/csrc/unet.c``): its input per leaf, its up-samplings
for the nodes that exist, and its layers one after the other in one call (see :mod:`o3dvis.nn.unet`)."""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from . import _library
from ._library import check
from .threads import SHARED_WORK, kernel_threads


def leaf_means(points: Tensor, normals: Tensor | None, leaf: Tensor, depth: int, leaves: int) -> Tensor:
    """(leaves, 6 or 9) the mean of ``[coordinates in the point's cell of a 2^depth grid, point,
    normal]`` over each leaf's points (see ``unet.c``), in one pass over ``points`` (N, 3) and
    ``normals`` (N, 3) or None, float32; ``leaf``: (N,) int64, each point's leaf.

    Raises:
        ValueError: tensors of the wrong shape or type, a depth out of [1, 21], a leaf out of
            range, or a leaf without points.
    """
    n = points.shape[0]
    check("points", points, (n, 3))
    if normals is not None:
        check("normals", normals, (n, 3))
    check("leaf", leaf, (n,), torch.long)
    if not 1 <= depth <= 21:
        raise ValueError(f"depth must lie in [1, 21], got {depth}")
    counts = torch.zeros(leaves)
    out = torch.zeros(leaves, 6 if normals is None else 9)
    code = _library.LIBRARY.o3dvis_leaf_means(n, points.data_ptr(), None if normals is None else normals.data_ptr(),
                                              leaf.data_ptr(), depth, leaves, counts.data_ptr(), out.data_ptr())
    if code == -1:
        raise ValueError(f"leaves must lie in [0, {leaves})")
    if code:
        raise ValueError("every leaf needs a point")
    return out


def upsample(x: Tensor, rows: Tensor, weight: Tensor, shift: Tensor, relu: bool, threads: int | None = None, *,
             residual: Tensor | None = None, addend: Tensor | None = None) -> Tensor:
    """(n, O) float32: an up-sampling (:class:`~o3dvis.nn.conv.OctreeUpsample` with its batch norm
    folded into ``weight`` and ``shift``) for the rows that exist only: row ``i`` is parent
    ``rows[i] // 8`` of ``x`` times the columns of octant ``rows[i] % 8`` of ``weight``, plus
    ``shift``, plus ``residual``, through a ReLU where ``relu``, plus ``addend``; in one pass
    instead of a product for all eight octants of every parent, a gather and the adds.

    Args:
        x: (parents, C) float32.
        rows: (n,) int64 in [0, 8 parents), the octree's ``octant_rows``.
        weight: (C, 8 O) float32, columns (octant, channel).
        shift: (O,) float32.
        threads: the rows are shared out among up to this many threads (see :func:`kernel_threads`);
            each row's sums are the same on any number.
        residual, addend: (n, O) float32 or None, added before and after the ReLU (each sum rounded
            as torch's add rounds it).

    Raises:
        ValueError: tensors of the wrong shape or type, a row or a thread count out of range.
    """
    parents, channels = x.shape
    outputs = weight.shape[1] // 8
    check("x", x, (parents, channels))
    check("rows", rows, (rows.shape[0],), torch.long)
    check("weight", weight, (channels, 8 * outputs))
    check("shift", shift, (outputs,))
    n = rows.shape[0]
    for name, t in (("residual", residual), ("addend", addend)):
        if t is not None:
            check(name, t, (n, outputs))
    out = x.new_empty(n, outputs)
    if _library.LIBRARY.o3dvis_upsample(n, x.data_ptr(), parents, channels, rows.data_ptr(), weight.data_ptr(), outputs,
                                        shift.data_ptr(), None if residual is None else residual.data_ptr(), int(relu),
                                        None if addend is None else addend.data_ptr(),
                                        kernel_threads(threads, n * channels * outputs), out.data_ptr()):
        raise ValueError(f"rows must lie in [0, {8 * parents})")
    return out


UNET_FIELDS = 15
"""The int64 fields of a layer of :func:`unet`'s table, in order: kind (0 a convolution of
:func:`gather_conv`, 1 an up-sampling of :func:`upsample`), input, residual and addend buffers (-1:
none; buffer 0 is the input ``x``, buffer ``i + 1`` the output of layer ``i``), input channels,
outputs, taps, ReLU, the addresses of the weight (:func:`pack_conv`'s, or the up-sampling's) and the
shift, output rows, the address of the index (a convolution's (rows, taps), an up-sampling's
rows), and a convolution's :func:`conv_entries` as :func:`gather_conv` passes them: the addresses of
the offsets and the entries, and the number listed."""


def unet(table: Tensor, x: Tensor, out: Tensor, threads: int | None = None) -> Tensor:
    """Runs the layers of ``table`` one after the other in one call: each as :func:`gather_conv` or
    :func:`upsample` computes it (the same sums), its blocks shared out among up to ``threads``
    threads where its multiply-adds reach :data:`SHARED_WORK`; the last layer's output in ``out``.
    The tensors at the table's addresses are the caller's to keep alive and right (made by
    :func:`pack_conv`, :func:`conv_entries` and the octree); the kernel checks that the layers hold
    together (buffers, channels, the shapes of residuals and addends) and every index as the layers
    do, before or while they run.

    Args:
        table: (layers, :data:`UNET_FIELDS`) int64.
        x: (rows, C) float32, buffer 0.
        out: (rows of the last layer, its outputs) float32.
        threads: as in :func:`kernel_threads` (None: the calling thread's torch count).

    Returns:
        ``out``.

    Raises:
        ValueError: tensors of the wrong shape or type, a table that does not hold together, or an
            index out of range.
        RuntimeError: no AVX-512 bfloat16 kernels here (see :func:`has_gather_conv`).
    """
    layers = table.shape[0]
    check("table", table, (layers, UNET_FIELDS), torch.long)
    check("x", x, tuple(x.shape))
    if x.ndim != 2 or layers == 0:
        raise ValueError(f"x must be (rows, C) and the table hold layers, got {tuple(x.shape)} and {layers}")
    last = table[-1]
    check("out", out, (int(last[10]), int(last[5])))
    failed = ctypes.c_int32(-1)
    code = _library.LIBRARY.o3dvis_unet(layers, table.data_ptr(), x.shape[0], x.shape[1], x.data_ptr(),
                                        kernel_threads(threads), SHARED_WORK, out.data_ptr(), ctypes.byref(failed))
    if code == -2:
        raise RuntimeError("unet needs the AVX-512 bfloat16 kernels (see has_gather_conv)")
    if code == -1 and (failed.value < 0 or int(table[failed.value, 0]) == 0):
        raise MemoryError("unet: out of memory")
    if code == -6:
        raise ValueError(f"unet: layer {failed.value} of the table does not hold together with those before it")
    if code:
        raise ValueError(f"unet: layer {failed.value} failed with code {code} (an index out of range)")
    return out
