"""A view's margins in one pass of C (``o3dvis/nn/csrc/inputs.c`` and ``mlp.c``): the predictor's
first-layer inputs, a block of points at a time, and its MLP on them while they are in cache (see
:meth:`o3dvis.nn.cues.ViewProjection.margin`)."""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import torch
from torch import Tensor

from ..features import LeafFeatures
from . import _library
from ._library import View, check, rows_of
from .threads import kernel_threads


# the largest magnitude of a residual the per-view kernels take before asinh (their pieces of it
# cover up to 2^13 with AVX-512)
MAX_RESIDUAL = 8192.0


def has_view_margin(dtype: torch.dtype) -> bool:
    """Whether :func:`view_margin` runs here in ``dtype``: the kernels are built, and for
    bfloat16 this CPU has bfloat16 dot products (AVX512-BF16)."""
    if _library.LIBRARY is None or dtype not in (torch.float32, torch.bfloat16):
        return False
    return dtype == torch.float32 or bool(_library.LIBRARY.o3dvis_has_view_margin_bf16())


def _view(rows: slice | Tensor, dirs: Tensor, projected: Tensor | LeafFeatures, num_frequencies: int,
          buffers: Tensor, corners: Tensor, sides: list[int], depth: Tensor, rpix: Tensor, perspective: bool,
          empty: float, normals: Tensor | None = None) -> tuple[int, View]:
    """The number of points and the kernels' ``struct view`` of them (see :func:`view_margin`), all
    checked; the struct holds on to the tensors made here that it points into."""
    n_points, scales = corners.shape
    n, start, rows = rows_of(rows, n_points)
    if not abs(empty) < MAX_RESIDUAL:  # NaN fails too
        raise ValueError(f"empty must be a residual of magnitude under {MAX_RESIDUAL}, got {empty}")
    rows_pointer = None if rows is None else rows.data_ptr()
    e = 3 + 6 * num_frequencies
    leaves = isinstance(projected, LeafFeatures)
    if leaves:  # the leaves' rows, each point's leaf (in range: LeafFeatures checks it) and its term
        check("leaves", projected.leaves, (e, projected.leaves.shape[1]))
        check("leaf", projected.leaf, (n_points,), torch.long)
        check("point_weight", projected.point_weight, (e, 3))
        check("points", projected.points, (n_points, 3))
        stored, ld = projected.leaves, projected.leaves.stride(0)
    # the kernel reads each channel of the features as a contiguous row (as encode() stores them):
    # copying other layouts here would copy all N points for every chunk
    elif projected.shape != (n_points, e) or projected.stride(0) != 1 or any(
            t.dtype != torch.float32 or t.device.type != "cpu" for t in (projected, dirs)):
        raise ValueError(f"projected must be ({n_points}, {e}) stored channels first (strides (1, N)), float32 on "
                         f"the CPU, got {tuple(projected.shape)} {projected.dtype} strides {projected.stride()}")
    else:
        stored, ld = projected, projected.stride(1)
    if dirs.shape != (n_points, 3) or dirs.stride(1) != 1 or dirs.dtype != torch.float32 or dirs.device.type != "cpu":
        raise ValueError(f"dirs must be ({n_points}, 3) with contiguous rows, float32 on the CPU, got "
                         f"{tuple(dirs.shape)} {dirs.dtype} strides {dirs.stride()}")
    check("buffers", buffers, (sum((res + 2) ** 2 for res in sides),))
    check("corners", corners, (n_points, len(sides)), torch.int32)
    check("depth", depth, (n_points,))
    check("rpix", rpix, (scales,))
    if normals is not None:
        check("normals", normals, (n_points, 3))
    widths = torch.tensor([res + 2 for res in sides], dtype=torch.long)
    view = View(rows_pointer, start, dirs.data_ptr(), dirs.stride(0), stored.data_ptr(), ld,
                 num_frequencies, buffers.data_ptr(), corners.data_ptr(), widths.data_ptr(), depth.data_ptr(),
                 rpix.data_ptr(), perspective, scales, empty, normals.data_ptr() if normals is not None else None,
                 *((projected.leaf.data_ptr(), projected.points.data_ptr(), projected.point_weight.data_ptr())
                   if leaves else (None, None, None)))
    view.tensors = (rows, widths)
    return n, view


@dataclass(frozen=True)
class PackedMLP:
    """An MLP's weights as :func:`view_margin` reads them (see :func:`pack_mlp`)."""

    dtype: torch.dtype  # of the products: float32 or bfloat16
    sizes: Tensor  # (layers + 2,) int32: the inputs, each hidden layer's outputs, the last's (padded)
    weights: Tensor  # each layer's, float32 (outputs, inputs), or int32 (inputs / 2, outputs) pairs of bfloat16
    biases: Tensor  # float32: each layer's (rounded to bfloat16 for bfloat16 products)


def pack_mlp(layers: list[tuple[Tensor, Tensor]], dtype: torch.dtype) -> PackedMLP:
    """Packs ``[(weight (O, K), bias (O,)), ...]``, ReLU between layers and one output at the end,
    for :func:`view_margin` in ``dtype`` (see ``mlp.c``): float32 with each layer's outputs
    padded to a multiple of 4; bfloat16 with weights and biases rounded to it, the inputs padded
    to an even count and the hidden outputs to a multiple of 16. Padding weighs zero."""
    if layers[-1][0].shape[0] != 1:
        raise ValueError(f"the last layer must have one output, got {layers[-1][0].shape[0]}")
    if dtype not in (torch.float32, torch.bfloat16):
        raise ValueError(f"dtype must be float32 or bfloat16, got {dtype}")
    pairs = dtype == torch.bfloat16
    inputs = layers[0][0].shape[1] + (layers[0][0].shape[1] % 2 if pairs else 0)
    sizes, weights, biases = [inputs], [], []
    for l, (weight, bias) in enumerate(layers):
        last = l == len(layers) - 1
        outputs = (1 if last else -(-weight.shape[0] // 16) * 16) if pairs else -(-weight.shape[0] // 4) * 4
        w = weight.detach().new_zeros(outputs, inputs)
        w[:weight.shape[0], :weight.shape[1]] = weight.detach()
        b = bias.detach().new_zeros(outputs)
        b[:len(bias)] = bias.detach()
        if pairs:
            # a pair of bfloat16 read as one int32 is (first | second << 16) on a little-endian CPU,
            # which every CPU with bfloat16 dot products is
            w = w.to(torch.bfloat16).view(torch.int16).view(outputs, inputs // 2, 2).view(torch.int32)[..., 0].T
            b = b.to(torch.bfloat16).float()
        sizes.append(outputs)
        weights.append(w.contiguous().flatten())
        biases.append(b)
        inputs = outputs
    return PackedMLP(dtype, torch.tensor(sizes, dtype=torch.int32), torch.cat(weights).cpu(), torch.cat(biases).cpu())


def view_margin(rows: slice | Tensor, dirs: Tensor, projected: Tensor | LeafFeatures, num_frequencies: int,
                buffers: Tensor, corners: Tensor, sides: list[int], depth: Tensor, rpix: Tensor, perspective: bool,
                empty: float, normals: Tensor | None, mlp: PackedMLP, out: Tensor, threads: int | None = None) -> None:
    """Writes the margins of the points ``rows`` for one view into ``out``.

    The MLP ``mlp`` runs on the first layer's inputs of each point: ``projected[rows]`` times
    the view embedding of ``dirs[rows]``, then the depth-buffer cues, then with ``normals`` the
    normal cue; its products in ``mlp.dtype`` with float32 sums (only where :func:`has_view_margin`).

    Args:
        rows: the points, a slice with step 1 or a (n,) long tensor.
        dirs: (N, 3) view directions, rows contiguous (a direction expanded to N rows will do).
        projected: the projected features (:meth:`VisibilityPredictor.project`), E = 3 + 6
            ``num_frequencies``: stored per leaf (float32 on the CPU, contiguous), or (N, E) stored
            channels first (strides (1, N)).
        buffers, corners, depth, rpix: the view's, as :func:`project` returns them for ``sides``.
        perspective: a view from a camera (True) or along a direction.
        empty: the residual an empty pixel takes before ``asinh``, of magnitude under
            :data:`MAX_RESIDUAL` (the others are clamped to +-50).
        normals: (N, 3) unit normals for a model that takes them, else None.
        mlp: the predictor's MLP as :func:`pack_mlp` packs it.
        out: (n,) float32.
        threads: the points' blocks are shared out among up to this many threads (see
            :func:`kernel_threads`); the margins are the same on any number.

    Raises:
        ValueError: tensors of the wrong shape, dtype, layout or device; an MLP that does not match
            the inputs or has a layer wider than 128; an ``empty`` out of range; a thread count
            out of range.
        IndexError: rows out of range.
        RuntimeError: no kernel for ``mlp.dtype`` in this build.
    """
    n, view = _view(rows, dirs, projected, num_frequencies, buffers, corners, sides, depth, rpix, perspective, empty,
                    normals)
    check("out", out, (n,))
    if not has_view_margin(mlp.dtype):
        raise RuntimeError(f"the C kernels here have no view_margin in {mlp.dtype} (bfloat16 needs AVX512-BF16)")
    library = _library.LIBRARY
    kernel = library.o3dvis_view_margin_bf16 if mlp.dtype == torch.bfloat16 else library.o3dvis_view_margin_f32
    if kernel(n, ctypes.byref(view), len(mlp.sizes) - 2, mlp.sizes.data_ptr(), mlp.weights.data_ptr(),
              mlp.biases.data_ptr(), kernel_threads(threads), out.data_ptr()):
        raise ValueError(f"the MLP (sizes {mlp.sizes.tolist()}) does not match the view's inputs, or it has a "
                         f"layer wider than 128")
