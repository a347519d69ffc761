"""The kernels' shared library as ``ctypes`` loads it (see :mod:`o3dvis.clib`): the signature of
each function of ``o3dvis/nn/csrc`` (whose ``kernels.h`` declares them), the ``struct view`` its
per-view kernels read, and the argument checks every wrapper of this package makes before it passes
pointers. :data:`LIBRARY` is None where the kernels were not built or are turned off."""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from ... import clib

_I64, _I32, _PTR = ctypes.c_int64, ctypes.c_int32, ctypes.c_void_p


class View(ctypes.Structure):
    """``struct view`` of ``kernels.h``: what the per-view kernels read of a view and its points."""

    _fields_ = [("rows", _PTR), ("start", _I64), ("dirs", _PTR), ("dirs_stride", _I64), ("proj", _PTR),
                ("proj_ld", _I64), ("frequencies", ctypes.c_int), ("zbufs", _PTR), ("corners", _PTR),
                ("widths", _PTR), ("depth", _PTR), ("rpix", _PTR), ("perspective", ctypes.c_int),
                ("scales", ctypes.c_int), ("empty", ctypes.c_float), ("normals", _PTR), ("leaf", _PTR),
                ("points", _PTR), ("point_weight", _PTR)]


_VIEW = ctypes.POINTER(View)
SIGNATURES = {  # name: (argument types, result type), by the file of o3dvis/nn/csrc that defines it
    # octree.c
    "o3dvis_bounds": ([_I64, _PTR, _PTR], None),
    "o3dvis_normalize": ([_I64, _PTR, _PTR, ctypes.c_double, _PTR, _PTR, _PTR, _PTR], None),
    "o3dvis_morton_keys": ([_I64, _PTR, _I32, _PTR], None),
    "o3dvis_sort_keys": ([_I64, _PTR, _PTR, _PTR, _PTR, _PTR, _I32], ctypes.c_int),
    "o3dvis_octree_counts": ([_I64, _PTR, _I32, _I32, _PTR], ctypes.c_int),
    "o3dvis_octree_fill": ([_I64, _PTR, _I32, _I32, _PTR, _PTR, _PTR], None),
    "o3dvis_child_neighbours": ([_I64, _PTR, _PTR, _PTR, _I64, _PTR, _PTR, _PTR, _PTR], ctypes.c_int),
    # noise.c
    "o3dvis_cell_thickness": ([_I64, _PTR, _I32, _I64, _PTR], _I64),
    "o3dvis_run_flatness": ([_I64, _PTR, _I32, _PTR, _PTR], None),
    # unet.c
    "o3dvis_leaf_means": ([_I64, _PTR, _PTR, _PTR, _I32, _I64, _PTR, _PTR], ctypes.c_int),
    "o3dvis_upsample": ([_I64, _PTR, _I64, _I32, _PTR, _PTR, _I32, _PTR, _PTR, _I32, _PTR, _I32, _PTR], ctypes.c_int),
    "o3dvis_unet": ([_I32, _PTR, _I64, _I32, _PTR, _I32, _I64, _PTR, _PTR], ctypes.c_int),
    # conv.c
    "o3dvis_has_gather_conv": ([], ctypes.c_int),
    "o3dvis_conv_entries": ([_I64, _PTR, _I32, _I64, _PTR, _PTR], ctypes.c_int64),
    "o3dvis_gather_conv": ([_I64, _PTR, _I64, _I32, _PTR, _I32, _PTR, _PTR, _I64, _PTR, _I32, _PTR, _PTR, _I32, _I32,
                            _PTR], ctypes.c_int),
    # views.c
    "o3dvis_project": ([_I64, _PTR, _PTR, _PTR, _I32, _PTR] + [_PTR] * 6, ctypes.c_int),
    "o3dvis_surfels": ([_I64, _PTR, _PTR, _I32, _I32, _I64, _PTR, _PTR], ctypes.c_int),
    "o3dvis_plane_splat": ([_I64, _PTR, _PTR, _PTR, _PTR, _I32, _PTR, _PTR, _PTR, _PTR, _PTR, ctypes.c_float,
                            ctypes.c_float, _PTR], ctypes.c_int),
    # zbuffer.c
    "o3dvis_surfel_zbuffer": ([_I64, _PTR, _PTR, _PTR, _I32, _I32, _I32, ctypes.c_float, _PTR], ctypes.c_int),
    # mlp.c
    "o3dvis_has_view_margin_bf16": ([], ctypes.c_int),
    "o3dvis_view_margin_bf16": ([_I64, _VIEW, _I32, _PTR, _PTR, _PTR, _I32, _PTR], ctypes.c_int),
    "o3dvis_view_margin_f32": ([_I64, _VIEW, _I32, _PTR, _PTR, _PTR, _I32, _PTR], ctypes.c_int),
    # fusion.c
    "o3dvis_fuse_margin": ([_I64, _PTR, _I64, _PTR, _PTR, _I32, _PTR, _PTR, _PTR, _PTR], ctypes.c_int),
    # orientation.c
    "o3dvis_fit_planes": ([_I64, _I64, _I32, _PTR, _PTR, _PTR, _PTR, _PTR], None),
    "o3dvis_visibility_affinity": ([_I64, _I32, _I32, _I32, _I64, _PTR, _PTR, ctypes.c_float, ctypes.c_float, _PTR],
                                   None),
    "o3dvis_votes": ([_I64, _I64, _I64, _I32, _PTR, _PTR, _PTR, _PTR, _PTR, _PTR], None),
    # knn.c
    "o3dvis_key_table": ([_I64, _PTR, _I64, _PTR], None),
    "o3dvis_brute_knn": ([_I64, _PTR, _I64, _PTR, _I32, _PTR], None),
    "o3dvis_grid_knn": ([_PTR, _PTR, _PTR, _PTR, _I64, _PTR, _I32, _PTR, ctypes.c_double, ctypes.c_double, _I32,
                         _I64, _I64, _PTR, _PTR, _PTR, _PTR], None),
}
# the library built from o3dvis/nn/csrc, in its widest variant this CPU runs (None: not built, or off)
LIBRARY = clib.load("o3dvis.nn._kernels", SIGNATURES)


def check(name: str, t: Tensor, shape: tuple[int, ...], dtype: torch.dtype = torch.float32) -> None:
    """Raises ValueError unless ``t`` is a contiguous CPU tensor of ``shape`` and ``dtype``: what a
    kernel reads through a pointer."""
    if t.shape != shape or t.dtype != dtype or not t.is_contiguous() or not t.is_cpu:
        raise ValueError(f"{name} must be a contiguous {shape} {dtype} CPU tensor, got "
                         f"{tuple(t.shape)} {t.dtype} on {t.device}")


def rows_of(rows: slice | Tensor, n_points: int) -> tuple[int, int, Tensor | None]:
    """(count, start, long tensor or None) of ``rows``, a slice with step 1 or an index tensor of
    ``n_points`` rows, checked."""
    if isinstance(rows, slice):
        start, stop, step = rows.indices(n_points)
        if step != 1:
            raise ValueError("rows must be a slice with step 1 or an index tensor")
        return max(0, stop - start), start, None
    rows = rows.to(device="cpu", dtype=torch.long).contiguous()
    if len(rows) and (int(rows.min()) < 0 or int(rows.max()) >= n_points):
        raise IndexError(f"rows must lie in [0, {n_points})")
    return len(rows), 0, rows
