"""The package's C kernels (``o3dvis/nn/csrc``), for the encoding and the queries on the CPU: the
octree's Morton keys, their sort and neighbours, the U-Net's input and, on CPUs with AVX-512
bfloat16 dot products, its convolutions, each in one pass; a view's projection, the predictor's
inputs and its MLP in a few passes instead of some seventy eager torch ops, each a pass over
memory, run while the inputs are in cache (``docs/results.md`` measures what it saves); the surfel
z-buffer and its fusion; and the plane fits, weights, votes and neighbour searches of the normals'
orientation. The convolutions, up-samplings, view margins and the keys' sort share the blocks of
one call with helper threads of the kernels' own (see :func:`kernel_threads`).

The kernels are one shared library built from C files by concept, with the package, for a
baseline CPU, AVX2, AVX-512 with bfloat16 (the U-Net's gathered convolutions) and AMX (those and
the MLP's hidden layers on its tiles), and called through ``ctypes`` (see :mod:`o3dvis.clib`).
Where it was not built, or with ``O3DVIS_NATIVE=0`` in the environment, queries run the torch ops
instead, with a warning; gradients and CUDA always do. The modules of this package mirror the C
files: each only checks shapes and passes pointers; the callers own the tensors.
"""

from __future__ import annotations

import torch
from torch import Tensor

from . import _library
from .conv import CONV_BLOCK, conv_entries, gather_conv, has_gather_conv, pack_conv
from .fusion import fuse_margin
from .knn import brute_knn, grid_knn, key_table
from .margin import MAX_RESIDUAL, PackedMLP, has_view_margin, pack_mlp, view_margin
from .noise import cell_thickness, run_flatness
from .octree import (SHARED_KEYS, OctreeLevels, bounds, child_neighbours, morton_keys, normalize, octree_levels,
                     sort_keys)
from .orientation import affinity_table, fit_planes, visibility_affinity, votes
from .threads import MAX_THREADS, SHARED_WORK, kernel_threads
from .unet import UNET_FIELDS, leaf_means, unet, upsample
from .views import MAX_POINTS, plane_splat, project, surfels
from .zbuffer import surfel_zbuffer

__all__ = ["MAX_POINTS", "MAX_RESIDUAL", "MAX_THREADS", "SHARED_WORK", "SHARED_KEYS", "CONV_BLOCK", "UNET_FIELDS",
           "available", "variant", "usable", "kernel_threads", "has_view_margin", "bounds", "normalize",
           "morton_keys", "sort_keys", "leaf_means", "upsample", "unet", "has_gather_conv", "pack_conv",
           "conv_entries", "gather_conv", "cell_thickness", "run_flatness", "project", "surfels", "surfel_zbuffer",
           "plane_splat", "PackedMLP", "pack_mlp", "view_margin", "fuse_margin", "fit_planes", "visibility_affinity",
           "affinity_table", "votes", "brute_knn", "key_table", "grid_knn", "OctreeLevels", "octree_levels",
           "child_neighbours"]


def available() -> bool:
    """Whether the C kernels are built and loaded."""
    return _library.LIBRARY is not None


def variant() -> str | None:
    """The variant of the kernels loaded (a key of :data:`o3dvis.clib.VARIANTS`), None where none is."""
    return None if _library.LIBRARY is None else _library.LIBRARY.variant


def usable(*tensors: Tensor | None) -> bool:
    """Whether the kernels can stand in for torch ops on these tensors: float32 on the CPU,
    autograd off (``no_grad`` or ``inference_mode``), and the kernels built."""
    given = [t for t in tensors if t is not None]
    return (not torch.is_grad_enabled() and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in given)
            and available())
