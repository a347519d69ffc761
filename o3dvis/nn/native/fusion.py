"""The fusion of a view's margins with the surfel z-buffer's answers in one pass of C
(``o3dvis/nn/csrc/fusion.c``; see :class:`o3dvis.nn.fusion.ZBufferFusion`)."""

from __future__ import annotations

import torch
from torch import Tensor

from . import _library
from ._library import check, rows_of
from .margin import PackedMLP


def fuse_margin(rows: slice | Tensor, zbuffer: Tensor, margin: Tensor, mlp: PackedMLP, out: Tensor) -> None:
    """Writes the fused margins of the points ``rows`` for one camera into ``out`` (see
    :class:`~o3dvis.nn.fusion.ZBufferFusion`; ``fusion.c`` says what the inputs are).

    Args:
        rows: the points, a slice with step 1 or a (n,) long tensor.
        zbuffer: (N, 4) the camera's :func:`surfel_zbuffer` answers.
        margin: (n,) the network's margins of those points; ``out`` may be the same tensor.
        mlp: the fusion's float32 MLP on the 6 inputs of a pair (its noise cues in the biases).
        out: (n,) float32.

    Raises:
        ValueError: tensors of the wrong shape, dtype or layout, or an MLP that does not fit.
        IndexError: rows out of range.
    """
    check("zbuffer", zbuffer, (zbuffer.shape[0], 4))
    n, start, index = rows_of(rows, zbuffer.shape[0])
    check("margin", margin, (n,))
    check("out", out, (n,))
    if mlp.dtype != torch.float32:
        raise ValueError(f"the fusion's MLP must be packed in float32, got {mlp.dtype}")
    if n and _library.LIBRARY.o3dvis_fuse_margin(n, None if index is None else index.data_ptr(), start,
                                                 zbuffer.data_ptr(), margin.data_ptr(), len(mlp.sizes) - 2,
                                                 mlp.sizes.data_ptr(),
                                                 mlp.weights.data_ptr(), mlp.biases.data_ptr(), out.data_ptr()):
        raise ValueError(f"the MLP (sizes {mlp.sizes.tolist()}) does not take a pair's 6 inputs, or it has a "
                         f"layer wider than 128")
