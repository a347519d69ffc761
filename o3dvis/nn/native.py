"""A view's projection, the predictor's inputs and its MLP in a few passes of C, for queries on the
CPU; and for the encoding the octree's Morton keys, their sort and neighbours, the U-Net's input
and, on CPUs with AVX-512 bfloat16 dot products, its convolutions, each in one pass. The
convolutions, up-samplings, view margins and the keys' sort share the blocks of one call with helper
threads of the kernels' own (see :func:`kernel_threads`).

``kernels.c`` computes what :class:`~o3dvis.nn.cues.ViewProjection` and the view
embedding times the projected features compute in some seventy eager torch
ops, each a pass over memory, and runs the predictor's MLP on those inputs
while they are in cache (``docs/results.md`` measures what it saves).
It is C with no dependency, built with the package for a baseline CPU, AVX2,
AVX-512 with bfloat16 (the U-Net's gathered convolutions) and AMX (those and the MLP's
hidden layers on its tiles), and called through ``ctypes`` (see :mod:`o3dvis.clib`).
Where it was not built, or with ``O3DVIS_NATIVE=0`` in the environment, queries
run the torch ops instead, with a warning; gradients and CUDA always do.
This module only checks shapes and passes pointers; the callers own the tensors.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import torch
from torch import Tensor

from .. import clib
from ..threads import usable_cores
from .features import LeafFeatures

__all__ = ["MAX_POINTS", "MAX_RESIDUAL", "MAX_THREADS", "SHARED_WORK", "SHARED_KEYS", "available", "variant", "usable",
           "kernel_threads", "has_view_margin", "bounds", "normalize",
           "morton_keys", "sort_keys", "leaf_means",
           "upsample", "has_gather_conv", "pack_conv", "conv_entries", "gather_conv", "cell_thickness",
           "run_flatness", "project",
           "surfels", "surfel_zbuffer", "plane_splat", "PackedMLP", "pack_mlp", "view_margin", "fuse_margin",
           "fit_planes", "visibility_affinity", "affinity_table", "votes", "brute_knn", "key_table",
           "grid_knn", "OctreeLevels", "octree_levels", "child_neighbours"]

_I64, _I32, _PTR = ctypes.c_int64, ctypes.c_int32, ctypes.c_void_p


class _View(ctypes.Structure):
    """``struct view`` of ``kernels.c``: what the per-view kernels read of a view and its points."""

    _fields_ = [("rows", _PTR), ("start", _I64), ("dirs", _PTR), ("dirs_stride", _I64), ("proj", _PTR),
                ("proj_ld", _I64), ("frequencies", ctypes.c_int), ("zbufs", _PTR), ("corners", _PTR),
                ("widths", _PTR), ("depth", _PTR), ("rpix", _PTR), ("perspective", ctypes.c_int),
                ("scales", ctypes.c_int), ("empty", ctypes.c_float), ("normals", _PTR), ("leaf", _PTR),
                ("points", _PTR), ("point_weight", _PTR)]


_VIEW = ctypes.POINTER(_View)
_SIGNATURES = {  # name: (argument types, result type)
    "o3dvis_bounds": ([_I64, _PTR, _PTR], None),
    "o3dvis_normalize": ([_I64, _PTR, _PTR, ctypes.c_double, _PTR, _PTR, _PTR, _PTR], None),
    "o3dvis_morton_keys": ([_I64, _PTR, _I32, _PTR], None),
    "o3dvis_sort_keys": ([_I64, _PTR, _PTR, _PTR, _PTR, _PTR, _I32], ctypes.c_int),
    "o3dvis_cell_thickness": ([_I64, _PTR, _I32, _I64, _PTR], _I64),
    "o3dvis_run_flatness": ([_I64, _PTR, _I32, _PTR, _PTR], None),
    "o3dvis_leaf_means": ([_I64, _PTR, _PTR, _PTR, _I32, _I64, _PTR, _PTR], ctypes.c_int),
    "o3dvis_upsample": ([_I64, _PTR, _I64, _I32, _PTR, _PTR, _I32, _PTR, _PTR, _I32, _PTR, _I32, _PTR], ctypes.c_int),
    "o3dvis_has_gather_conv": ([], ctypes.c_int),
    "o3dvis_unet": ([_I32, _PTR, _I64, _I32, _PTR, _I32, _I64, _PTR, _PTR], ctypes.c_int),
    "o3dvis_octree_counts": ([_I64, _PTR, _I32, _I32, _PTR], ctypes.c_int),
    "o3dvis_octree_fill": ([_I64, _PTR, _I32, _I32, _PTR, _PTR, _PTR], None),
    "o3dvis_conv_entries": ([_I64, _PTR, _I32, _I64, _PTR, _PTR], ctypes.c_int64),
    "o3dvis_gather_conv": ([_I64, _PTR, _I64, _I32, _PTR, _I32, _PTR, _PTR, _I64, _PTR, _I32, _PTR, _PTR, _I32, _I32,
                            _PTR], ctypes.c_int),
    "o3dvis_project": ([_I64, _PTR, _PTR, _PTR, _I32, _PTR] + [_PTR] * 6, ctypes.c_int),
    "o3dvis_plane_splat": ([_I64, _PTR, _PTR, _PTR, _PTR, _I32, _PTR, _PTR, _PTR, _PTR, _PTR, ctypes.c_float,
                            ctypes.c_float, _PTR], ctypes.c_int),
    "o3dvis_surfels": ([_I64, _PTR, _PTR, _I32, _I32, _I64, _PTR, _PTR], ctypes.c_int),
    "o3dvis_surfel_zbuffer": ([_I64, _PTR, _PTR, _PTR, _I32, _I32, _I32, ctypes.c_float, _PTR], ctypes.c_int),
    "o3dvis_has_view_margin_bf16": ([], ctypes.c_int),
    "o3dvis_view_margin_bf16": ([_I64, _VIEW, _I32, _PTR, _PTR, _PTR, _I32, _PTR], ctypes.c_int),
    "o3dvis_view_margin_f32": ([_I64, _VIEW, _I32, _PTR, _PTR, _PTR, _I32, _PTR], ctypes.c_int),
    "o3dvis_fuse_margin": ([_I64, _PTR, _I64, _PTR, _PTR, _I32, _PTR, _PTR, _PTR, _PTR], ctypes.c_int),
    "o3dvis_fit_planes": ([_I64, _I64, _I32, _PTR, _PTR, _PTR, _PTR, _PTR], None),
    "o3dvis_visibility_affinity": ([_I64, _I32, _I32, _I32, _I64, _PTR, _PTR, ctypes.c_float, ctypes.c_float, _PTR],
                                   None),
    "o3dvis_votes": ([_I64, _I64, _I64, _I32, _PTR, _PTR, _PTR, _PTR, _PTR, _PTR], None),
    "o3dvis_key_table": ([_I64, _PTR, _I64, _PTR], None),
    "o3dvis_brute_knn": ([_I64, _PTR, _I64, _PTR, _I32, _PTR], None),
    "o3dvis_child_neighbours": ([_I64, _PTR, _PTR, _PTR, _I64, _PTR, _PTR, _PTR, _PTR], ctypes.c_int),
    "o3dvis_grid_knn": ([_PTR, _PTR, _PTR, _PTR, _I64, _PTR, _I32, _PTR, ctypes.c_double, ctypes.c_double, _I32,
                         _I64, _I64, _PTR, _PTR, _PTR, _PTR], None),
}
# the most points a view of the kernels takes: its depth buffers (about 1.4 values a point over four
# scales) are then indexed by int32
MAX_POINTS = 1 << 30
# the largest magnitude of a residual the per-view kernels take before asinh (their pieces of it
# cover up to 2^13 with AVX-512)
MAX_RESIDUAL = 8192.0
# the most threads a kernel's work is shared out among: the caller's and the helpers of kernels.c's crew
MAX_THREADS = 65
_LIBRARY = clib.load(f"{__package__}._kernels", _SIGNATURES)


def available() -> bool:
    """Whether the C kernels are built and loaded."""
    return _LIBRARY is not None


def variant() -> str | None:
    """The variant of the kernels loaded (a key of :data:`o3dvis.clib.VARIANTS`), None where none is."""
    return None if _LIBRARY is None else _LIBRARY.variant


def usable(*tensors: Tensor | None) -> bool:
    """Whether the kernels can stand in for torch ops on these tensors: float32 on the CPU,
    autograd off (``no_grad`` or ``inference_mode``), and the kernels built."""
    given = [t for t in tensors if t is not None]
    return (not torch.is_grad_enabled() and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in given)
            and available())


def _check(name: str, t: Tensor, shape: tuple[int, ...], dtype: torch.dtype = torch.float32) -> None:
    if t.shape != shape or t.dtype != dtype or not t.is_contiguous() or not t.is_cpu:
        raise ValueError(f"{name} must be a contiguous {shape} {dtype} CPU tensor, got "
                         f"{tuple(t.shape)} {t.dtype} on {t.device}")


def bounds(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(lo, hi, sum)``, each (3,) float64: the per-axis minimum, maximum (NaN where an axis has
    one, as ``min``/``max`` give) and sum of ``points`` (N, 3) float64, in one pass."""
    _check("points", points, (points.shape[0], 3), torch.float64)
    out = points.new_empty(9)
    _LIBRARY.o3dvis_bounds(points.shape[0], points.data_ptr(), out.data_ptr())
    return out[:3], out[3:6], out[6:]


_SCATTER_ENTRIES = torch.tensor([0, 1, 2, 1, 3, 4, 2, 4, 5])
"""The (3, 3) scatter matrix's entries among the six sums of ``o3dvis_normalize``."""


def normalize(points: Tensor, center: Tensor, scale: float, mean: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(normalised, keys, scatter)`` of ``points`` (N, 3) float64 in one pass: ``((points - center)
    / scale).float()``, the (N,) Morton keys of those float32 points on the finest grid
    (:func:`morton_keys` at depth 21), and the (3, 3) sum of the outer products of the float64
    offsets ``(points - center) / scale - mean``."""
    n = points.shape[0]
    _check("points", points, (n, 3), torch.float64)
    _check("center", center, (3,), torch.float64)
    _check("mean", mean, (3,), torch.float64)
    out, keys, sums = torch.empty(n, 3), torch.empty(n, dtype=torch.long), points.new_empty(6)
    _LIBRARY.o3dvis_normalize(n, points.data_ptr(), center.data_ptr(), float(scale), mean.data_ptr(),
                              out.data_ptr(), keys.data_ptr(), sums.data_ptr())
    return out, keys, sums.index_select(0, _SCATTER_ENTRIES).view(3, 3)


def morton_keys(points: Tensor, depth: int) -> Tensor:
    """(N,) int64 Morton keys of the cells of a ``2^depth`` grid over [-1, 1]^3 holding ``points``
    (N, 3) float32, as :func:`~o3dvis.nn.octree.morton_encode` of
    :func:`~o3dvis.nn.octree.grid_cells` computes them, in one pass."""
    _check("points", points, (points.shape[0], 3))
    if not 1 <= depth <= 21:
        raise ValueError(f"depth must lie in [1, 21], got {depth}")
    keys = torch.empty(points.shape[0], dtype=torch.long)
    _LIBRARY.o3dvis_morton_keys(points.shape[0], points.data_ptr(), depth, keys.data_ptr())
    return keys


def sort_keys(keys: Tensor, threads: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """``torch.sort(keys, stable=True)`` of (N,) non-negative int64 keys by a radix sort:
    ``(sorted, permutation, its inverse)``, the inverse the place of each key. ``threads``: the
    buckets of the highest byte in which the keys differ are shared out among up to this many
    threads (see :func:`kernel_threads`; by default from :data:`SHARED_KEYS` keys on).

    Raises:
        ValueError: keys of another shape or dtype, 2^32 or more of them, or a negative one; a
            thread count out of range.
    """
    _check("keys", keys, (keys.shape[0],), torch.long)
    n = keys.shape[0]
    if n >= 1 << 32:
        raise ValueError(f"at most 2^32 - 1 keys, got {n}")
    out, order, rank, scratch = (torch.empty_like(keys), torch.empty_like(keys), torch.empty_like(keys),
                                 keys.new_empty(4 * n))
    threads = kernel_threads(threads) if threads is not None or n >= SHARED_KEYS else 1
    if _LIBRARY.o3dvis_sort_keys(n, keys.data_ptr(), out.data_ptr(), order.data_ptr(), rank.data_ptr(),
                                 scratch.data_ptr(), threads):
        raise ValueError("keys must be non-negative")
    return out, order, rank


def leaf_means(points: Tensor, normals: Tensor | None, leaf: Tensor, depth: int, leaves: int) -> Tensor:
    """(leaves, 6 or 9) the mean of ``[coordinates in the point's cell of a 2^depth grid, point,
    normal]`` over each leaf's points (see ``kernels.c``), in one pass over ``points`` (N, 3) and
    ``normals`` (N, 3) or None, float32; ``leaf``: (N,) int64, each point's leaf.

    Raises:
        ValueError: tensors of the wrong shape or type, a depth out of [1, 21], a leaf out of
            range, or a leaf without points.
    """
    n = points.shape[0]
    _check("points", points, (n, 3))
    if normals is not None:
        _check("normals", normals, (n, 3))
    _check("leaf", leaf, (n,), torch.long)
    if not 1 <= depth <= 21:
        raise ValueError(f"depth must lie in [1, 21], got {depth}")
    counts = torch.zeros(leaves)
    out = torch.zeros(leaves, 6 if normals is None else 9)
    code = _LIBRARY.o3dvis_leaf_means(n, points.data_ptr(), None if normals is None else normals.data_ptr(),
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
    _check("x", x, (parents, channels))
    _check("rows", rows, (rows.shape[0],), torch.long)
    _check("weight", weight, (channels, 8 * outputs))
    _check("shift", shift, (outputs,))
    n = rows.shape[0]
    for name, t in (("residual", residual), ("addend", addend)):
        if t is not None:
            _check(name, t, (n, outputs))
    out = x.new_empty(n, outputs)
    if _LIBRARY.o3dvis_upsample(n, x.data_ptr(), parents, channels, rows.data_ptr(), weight.data_ptr(), outputs,
                                shift.data_ptr(), None if residual is None else residual.data_ptr(), int(relu),
                                None if addend is None else addend.data_ptr(),
                                kernel_threads(threads, n * channels * outputs), out.data_ptr()):
        raise ValueError(f"rows must lie in [0, {8 * parents})")
    return out


def has_gather_conv() -> bool:
    """Whether :func:`gather_conv` runs here: a variant of the kernels with AVX-512 bfloat16 dot
    products is loaded (the AMX one runs it on the tiles where the operating system grants them)."""
    if _LIBRARY is None:
        return False
    if getattr(_LIBRARY, "gather_conv", None) is None:
        _LIBRARY.gather_conv = bool(_LIBRARY.o3dvis_has_gather_conv())
    return _LIBRARY.gather_conv


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
"""Output rows of a block of :func:`gather_conv` (``CONV_BLOCK`` of ``kernels.c``)."""


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
    _check("index", index, (n, taps), torch.long)
    lists = -(-n // CONV_BLOCK) * taps
    out = index.new_empty(lists + 1 + n * taps + 8 * (lists + 1))
    listed = _LIBRARY.o3dvis_conv_entries(n, index.data_ptr(), taps, rows, out.data_ptr(),
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
    _check("x", x, (rows, channels))
    _check("index", index, (n, taps), torch.long)
    _check("packed", packed, ((-(-taps * channels // 32) * 32) * (-(-outputs // 16) * 16) // 2,), torch.int32)
    _check("shift", shift, (outputs,))
    if residual is not None:
        _check("residual", residual, (n, outputs))
    if channels % 2 or outputs % 16:
        raise ValueError(f"need an even number of channels and a multiple of 16 outputs, got {channels} and {outputs}")
    threads = kernel_threads(threads, n * taps * channels * outputs)
    if entries is None:
        entries = conv_entries(index, rows)
    lists = -(-n // CONV_BLOCK) * taps
    if entries.ndim != 1 or len(entries) <= lists:
        raise ValueError(f"entries must be conv_entries of the index: at least {lists + 1} values, got "
                         f"{tuple(entries.shape)}")
    _check("entries", entries, (len(entries),), torch.long)
    out = x.new_empty(n, outputs)
    code = _LIBRARY.o3dvis_gather_conv(n, x.data_ptr(), rows, channels, index.data_ptr(), taps, entries.data_ptr(),
                                       entries[lists + 1:].data_ptr(), entries.shape[0] - lists - 1,
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
    _check("table", table, (layers, UNET_FIELDS), torch.long)
    _check("x", x, tuple(x.shape))
    if x.ndim != 2 or layers == 0:
        raise ValueError(f"x must be (rows, C) and the table hold layers, got {tuple(x.shape)} and {layers}")
    last = table[-1]
    _check("out", out, (int(last[10]), int(last[5])))
    failed = ctypes.c_int32(-1)
    code = _LIBRARY.o3dvis_unet(layers, table.data_ptr(), x.shape[0], x.shape[1], x.data_ptr(), kernel_threads(threads),
                                SHARED_WORK, out.data_ptr(), ctypes.byref(failed))
    if code == -2:
        raise RuntimeError("unet needs the AVX-512 bfloat16 kernels (see has_gather_conv)")
    if code == -1 and (failed.value < 0 or int(table[failed.value, 0]) == 0):
        raise MemoryError("unet: out of memory")
    if code == -6:
        raise ValueError(f"unet: layer {failed.value} of the table does not hold together with those before it")
    if code:
        raise ValueError(f"unet: layer {failed.value} failed with code {code} (an index out of range)")
    return out


def cell_thickness(points: Tensor, level: int, min_count: int) -> Tensor:
    """(M,) float64: for each cell of a ``2^level`` grid over [-1, 1]^3 (``1 <= level <= 10``) with at
    least ``min_count`` of ``points`` (N, 3) float32, in the points' order, its thickness in point
    spacings (the noise cue's cell term, see ``kernels.c``: the smallest eigenvalue of its
    covariance in closed form). The points of each cell must be contiguous, as along a Morton curve.

    Raises:
        ValueError: points of the wrong shape or type, or a level out of [1, 10].
    """
    _check("points", points, (points.shape[0], 3))
    if not 1 <= level <= 10:
        raise ValueError(f"level must lie in [1, 10], got {level}")
    out = points.new_empty(points.shape[0], dtype=torch.float64)
    full = _LIBRARY.o3dvis_cell_thickness(points.shape[0], points.data_ptr(), level, min_count, out.data_ptr())
    return out[:full]


def run_flatness(points: Tensor, starts: Tensor, run: int) -> Tensor:
    """(R,) float64: for each run of ``run`` points of ``points`` (N, 3) float32 from ``starts`` (R,)
    int64, the square root of the smallest over the middle eigenvalue of its scatter about its
    mean (closed form, see ``kernels.c``).

    Raises:
        ValueError: tensors of the wrong shape or type, or a run that leaves the points.
    """
    _check("points", points, (points.shape[0], 3))
    _check("starts", starts, (starts.shape[0],), torch.long)
    if run < 1 or (len(starts) and (int(starts.min()) < 0 or int(starts.max()) + run > points.shape[0])):
        raise ValueError(f"runs of {run} points from starts must lie in the {points.shape[0]} points")
    out = points.new_empty(starts.shape[0], dtype=torch.float64)
    _LIBRARY.o3dvis_run_flatness(starts.shape[0], starts.data_ptr(), run, points.data_ptr(), out.data_ptr())
    return out


def project(points: Tensor, camera: Tensor | None, direction: Tensor | None,
            sides: list[int]) -> tuple[Tensor | None, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """One view's projection (see :class:`~o3dvis.nn.cues.ViewProjection`).

    Args:
        points: (N, 3) float32 points, N >= 1.
        camera: (3,) camera position, or None with ``direction``: (3,) unit viewing direction.
        sides: the depth buffers' resolutions, one per scale.

    Returns:
        ``dirs`` (N, 3) unit vectors from the camera (None with ``direction``),
        ``depth`` (N,), ``buffers`` each scale's min-depth image inside a
        border, (side + 2)^2 values in rows of side + 2, one after the other,
        NaN where empty and on the border, ``corners`` (N, S) int32 the index in
        ``buffers`` of the top-left pixel of the 3x3 around each point's pixel,
        ``rpix`` (S,) 1 / pixel size (a residual's scale is -rpix / depth for a camera,
        -rpix for a direction), ``uv`` (N, 2) each point's image position from the
        image's corner (the image is ``sides[s] / rpix[s]`` wide).
    """
    n, scales = points.shape[0], len(sides)
    _check("points", points, (n, 3))
    view = camera if camera is not None else direction
    _check("camera" if camera is not None else "direction", view, (3,))
    if n < 1 or not sides or min(sides) < 1:
        raise ValueError(f"need points and positive sides, got {n} points, sides {sides}")
    if n > MAX_POINTS or sum((res + 2) ** 2 for res in sides) >= 1 << 31:
        raise ValueError(f"the C kernels take at most {MAX_POINTS} points and 2^31 buffer values, got {n} points, "
                         f"sides {sides}")
    dirs = points.new_empty(n, 3) if camera is not None else None
    depth, uv = points.new_empty(n), points.new_empty(n, 2)
    buffers = points.new_empty(sum((res + 2) ** 2 for res in sides))
    corners, rpix = torch.empty(n, scales, dtype=torch.int32), points.new_empty(scales)
    sizes = torch.tensor(sides, dtype=torch.long)  # referenced until the call has returned
    if _LIBRARY.o3dvis_project(n, points.data_ptr(), camera.data_ptr() if camera is not None else None,
                                direction.data_ptr() if direction is not None else None, scales,
                                sizes.data_ptr(),
                                dirs.data_ptr() if dirs is not None else None, depth.data_ptr(), uv.data_ptr(),
                                buffers.data_ptr(), corners.data_ptr(), rpix.data_ptr()):
        raise ValueError(f"the C kernel takes at most 7 scales, got {scales}")
    return dirs, depth, buffers, corners, rpix, uv


def surfels(points: Tensor, keys: Tensor, finest: int, coarsest: int, count: int,
            areas: bool = False) -> Tensor:
    """(N, 4) :func:`o3dvis.nn.cues.point_surfels` of ``points`` (N, 3) float32 sorted by their
    ``keys`` (N,) int64, the Morton keys of their cells at level ``finest``, in one pass; with
    ``areas``, (N, 5): their area spacing follows.

    Raises:
        ValueError: tensors of the wrong shapes or types, or levels out of [1, 21].
        MemoryError: no memory for the kernel's scratch buffers.
    """
    n = points.shape[0]
    _check("points", points, (n, 3))
    _check("keys", keys, (n,), torch.long)
    if not 1 <= coarsest <= finest <= 21:
        raise ValueError(f"levels must lie in [1, 21], coarsest first, got {coarsest}, {finest}")
    out = points.new_empty(n, 4)
    spread = points.new_empty(n) if areas else None
    if n and _LIBRARY.o3dvis_surfels(n, points.data_ptr(), keys.data_ptr(), finest, coarsest, count, out.data_ptr(),
                                     spread.data_ptr() if areas else None):
        raise MemoryError("no memory for the surfels' scratch buffers")
    return torch.cat([out, spread[:, None]], dim=1) if areas else out


def surfel_zbuffer(points: Tensor, surfels: Tensor, camera: Tensor, rows: int, max_half: int, max_wide: int,
                   clip: float) -> Tensor:
    """(N, 4) :func:`o3dvis.nn.zbuffer.surfel_zbuffer` of ``points`` (N, 3) float32 with their
    ``surfels`` (N, 5), seen from ``camera`` (3,), in one pass over the points and one over the buffer.

    Raises:
        ValueError: tensors of the wrong shapes or types, or a buffer out of [1, 2^15) rows.
        MemoryError: no memory for the buffer.
    """
    n = points.shape[0]
    _check("points", points, (n, 3))
    _check("surfels", surfels, (n, 5))
    _check("camera", camera, (3,))
    if not 1 <= rows < 1 << 15 or max_half < 0 or max_wide < 0:
        raise ValueError(f"rows must lie in [1, 32768) and the disc bounds be >= 0, got {rows}, {max_half}, "
                         f"{max_wide}")
    out = points.new_empty(n, 4)
    if n and _LIBRARY.o3dvis_surfel_zbuffer(n, points.data_ptr(), surfels.data_ptr(), camera.data_ptr(), rows,
                                            max_half, max_wide, clip, out.data_ptr()):
        raise MemoryError(f"no memory for a {rows} x {2 * rows} surfel z-buffer")
    return out


def plane_splat(points: Tensor, surfels: Tensor, depth: Tensor, level: Tensor, sides: list[int], corners: Tensor,
                frame: Tensor, half: float, camera: Tensor | None, slope: float, out: Tensor) -> None:
    """Splats the points of a native view as their planes into the bordered buffers ``out``
    (see :func:`o3dvis.nn.cues._splat_footprints`).

    Args:
        points: (N, 3) float32 points; surfels: (N, 4) their spacing and unit normal.
        depth, corners: as :func:`project` gives them for the scales of ``sides``.
        level: (N,) each point's splat scale, 0 for none.
        frame: (3, 3) the image's forward, right and up vectors; half: half its width.
        camera: (3,) the camera, or None for a viewing direction.
        slope: the bound on a plane's depth, in lateral distances from its point.
        out: the bordered buffers of all scales but the coarsest, laid out as :func:`project`
            lays out those scales (a copy of the start of its buffers).

    Raises:
        ValueError: tensors of the wrong shapes, sizes or types.
        MemoryError: no memory for the kernel's scratch buffers.
    """
    n, scales = corners.shape
    _check("points", points, (n, 3))
    _check("surfels", surfels, (n, 4))
    _check("depth", depth, (n,))
    _check("frame", frame, (3, 3))
    if camera is not None:
        _check("camera", camera, (3,))
    if level.dtype != torch.int8 or level.shape != (n,) or corners.dtype != torch.int32 or len(sides) != scales:
        raise ValueError("level must be (N,) int8, corners (N, scales) int32 and sides one per scale")
    firsts = [sum((res + 2) ** 2 for res in sides[:s]) for s in range(scales)]
    if out.dtype != torch.float32 or not out.is_contiguous() or out.shape != (firsts[-1],):
        raise ValueError(f"out must be the contiguous float32 buffers of all scales but the coarsest, "
                         f"({firsts[-1]},), got {tuple(out.shape)} {out.dtype}")
    firsts, sizes = torch.tensor(firsts, dtype=torch.long), torch.tensor(sides, dtype=torch.long)
    level, corners = level.contiguous(), corners.contiguous()
    if _LIBRARY.o3dvis_plane_splat(n, points.data_ptr(), surfels.data_ptr(), depth.data_ptr(), level.data_ptr(),
                                   scales, sizes.data_ptr(), corners.data_ptr(), firsts.data_ptr(),
                                   camera.data_ptr() if camera is not None else None, frame.data_ptr(), half,
                                   slope, out.data_ptr()):
        raise MemoryError("no memory for the splat's scratch buffers")


SHARED_WORK = 1 << 24
"""Multiply-adds of a kernel call from which it shares its blocks with helper threads by default
(see :func:`kernel_threads`)."""

SHARED_KEYS = 1 << 16
"""Keys from which :func:`sort_keys` shares its buckets with helper threads by default."""


def kernel_threads(threads: int | None = None, work: int | None = None) -> int:
    """The threads a kernel's work is shared out among: the calling thread and up to ``threads - 1``
    helpers of the kernels' crew, kept for the process's life and asleep between kernels (work is
    claimed block by block, so a helper that starts late takes less of it).

    Args:
        threads: a count in [1, :data:`MAX_THREADS`]; None: torch's intra-op thread count of the
            calling thread (what :func:`o3dvis.threads.torch_threads` sets), at most the cores
            this process may use, and one for a call of less ``work`` than :data:`SHARED_WORK`.
        work: the call's multiply-adds, where known.

    Raises:
        ValueError: a count out of range.
    """
    if threads is None:
        if work is not None and work < SHARED_WORK:
            return 1
        return max(1, min(torch.get_num_threads(), usable_cores(), MAX_THREADS))
    if isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= MAX_THREADS:
        raise ValueError(f"threads must be an int in [1, {MAX_THREADS}], got {threads!r}")
    return threads


def has_view_margin(dtype: torch.dtype) -> bool:
    """Whether :func:`view_margin` runs here in ``dtype``: the kernels are built, and for
    bfloat16 this CPU has bfloat16 dot products (AVX512-BF16)."""
    if _LIBRARY is None or dtype not in (torch.float32, torch.bfloat16):
        return False
    return dtype == torch.float32 or bool(_LIBRARY.o3dvis_has_view_margin_bf16())


def _rows_of(rows: slice | Tensor, n_points: int) -> tuple[int, int, Tensor | None]:
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


def _view(rows: slice | Tensor, dirs: Tensor, projected: Tensor | LeafFeatures, num_frequencies: int,
          buffers: Tensor, corners: Tensor, sides: list[int], depth: Tensor, rpix: Tensor, perspective: bool,
          empty: float, normals: Tensor | None = None) -> tuple[int, _View]:
    """The number of points and the kernels' ``struct view`` of them (see :func:`view_margin`), all
    checked; the struct holds on to the tensors made here that it points into."""
    n_points, scales = corners.shape
    n, start, rows = _rows_of(rows, n_points)
    if not abs(empty) < MAX_RESIDUAL:  # NaN fails too
        raise ValueError(f"empty must be a residual of magnitude under {MAX_RESIDUAL}, got {empty}")
    rows_pointer = None if rows is None else rows.data_ptr()
    e = 3 + 6 * num_frequencies
    leaves = isinstance(projected, LeafFeatures)
    if leaves:  # the leaves' rows, each point's leaf (in range: LeafFeatures checks it) and its term
        _check("leaves", projected.leaves, (e, projected.leaves.shape[1]))
        _check("leaf", projected.leaf, (n_points,), torch.long)
        _check("point_weight", projected.point_weight, (e, 3))
        _check("points", projected.points, (n_points, 3))
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
    _check("buffers", buffers, (sum((res + 2) ** 2 for res in sides),))
    _check("corners", corners, (n_points, len(sides)), torch.int32)
    _check("depth", depth, (n_points,))
    _check("rpix", rpix, (scales,))
    if normals is not None:
        _check("normals", normals, (n_points, 3))
    widths = torch.tensor([res + 2 for res in sides], dtype=torch.long)
    view = _View(rows_pointer, start, dirs.data_ptr(), dirs.stride(0), stored.data_ptr(), ld,
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
    for :func:`view_margin` in ``dtype`` (see ``kernels.c``): float32 with each layer's outputs
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
    _check("out", out, (n,))
    if not has_view_margin(mlp.dtype):
        raise RuntimeError(f"the C kernels here have no view_margin in {mlp.dtype} (bfloat16 needs AVX512-BF16)")
    kernel = _LIBRARY.o3dvis_view_margin_bf16 if mlp.dtype == torch.bfloat16 else _LIBRARY.o3dvis_view_margin_f32
    if kernel(n, ctypes.byref(view), len(mlp.sizes) - 2, mlp.sizes.data_ptr(), mlp.weights.data_ptr(),
              mlp.biases.data_ptr(), kernel_threads(threads), out.data_ptr()):
        raise ValueError(f"the MLP (sizes {mlp.sizes.tolist()}) does not match the view's inputs, or it has a "
                         f"layer wider than 128")


def fuse_margin(rows: slice | Tensor, zbuffer: Tensor, margin: Tensor, mlp: PackedMLP, out: Tensor) -> None:
    """Writes the fused margins of the points ``rows`` for one camera into ``out`` (see
    :class:`~o3dvis.nn.fusion.ZBufferFusion`; ``kernels.c`` says what the inputs are).

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
    _check("zbuffer", zbuffer, (zbuffer.shape[0], 4))
    n, start, index = _rows_of(rows, zbuffer.shape[0])
    _check("margin", margin, (n,))
    _check("out", out, (n,))
    if mlp.dtype != torch.float32:
        raise ValueError(f"the fusion's MLP must be packed in float32, got {mlp.dtype}")
    if n and _LIBRARY.o3dvis_fuse_margin(n, None if index is None else index.data_ptr(), start, zbuffer.data_ptr(),
                                         margin.data_ptr(), len(mlp.sizes) - 2, mlp.sizes.data_ptr(),
                                         mlp.weights.data_ptr(), mlp.biases.data_ptr(), out.data_ptr()):
        raise ValueError(f"the MLP (sizes {mlp.sizes.tolist()}) does not take a pair's 6 inputs, or it has a "
                         f"layer wider than 128")


def fit_planes(points: Tensor, neighbours: Tensor, weight: Tensor | None) -> tuple[Tensor, Tensor]:
    """(M, 3) unit normals and (M,) bool: :func:`o3dvis.orientation.fit_planes` of ``points``
    (N, 3) float64, rows of ``neighbours`` (M, K) int64 and ``weight`` (M, K) float64 (None: all
    1), in one pass (an index N stands for no point, as the numpy ops' padding: give it weight 0).

    Raises:
        ValueError: tensors of the wrong shapes or types.
        IndexError: neighbours out of range.
    """
    m, k = neighbours.shape
    _check("points", points, (points.shape[0], 3), torch.float64)
    _check("neighbours", neighbours, (m, k), torch.long)
    if weight is not None:
        _check("weight", weight, (m, k), torch.float64)
    if neighbours.numel() and (int(neighbours.min()) < 0 or int(neighbours.max()) > points.shape[0]):
        raise IndexError(f"neighbours must lie in [0, {points.shape[0]}]")
    normals, planar = points.new_empty(m, 3), torch.empty(m, dtype=torch.uint8)
    if m:
        _LIBRARY.o3dvis_fit_planes(points.shape[0], m, k, points.data_ptr(), neighbours.data_ptr(),
                                   None if weight is None else weight.data_ptr(), normals.data_ptr(),
                                   planar.data_ptr())
    return normals, planar.bool()


def visibility_affinity(table: Tensor, cameras: int, neighbours: Tensor, first: int, scale: float, floor: float
                        ) -> Tensor:
    """(M, K) float64: :func:`o3dvis.orientation.visibility_affinity` of the points
    ``first .. first + M`` and their rows of ``neighbours`` (M, K) int64, from ``table`` (N, S)
    float32: a row a point, its answers from the ``cameras`` cameras then zeros up to S, a
    multiple of 16 (what :func:`affinity_table` makes); in one pass.

    Raises:
        ValueError: tensors of the wrong shapes or types, or rows past the table.
        IndexError: neighbours out of range.
    """
    (n, stride), (m, k) = table.shape, neighbours.shape
    _check("table", table, (n, stride))
    _check("neighbours", neighbours, (m, k), torch.long)
    if stride % 16 or not 0 < cameras <= stride:
        raise ValueError(f"the table's rows must hold the {cameras} cameras' answers padded to a multiple "
                         f"of 16, got {stride}")
    if not 0 <= first <= n - m:
        raise ValueError(f"rows {first}..{first + m} lie past the table's {n}")
    if neighbours.numel() and (int(neighbours.min()) < 0 or int(neighbours.max()) >= n):
        raise IndexError(f"neighbours must lie in [0, {n})")
    weight = torch.empty(m, k, dtype=torch.float64)
    if m:
        _LIBRARY.o3dvis_visibility_affinity(m, k, cameras, stride, first, table.data_ptr(), neighbours.data_ptr(),
                                            1.0 / scale ** 2, floor, weight.data_ptr())
    return weight


def votes(points: Tensor, normals: Tensor, cameras: Tensor, visibility: Tensor, rows: slice
          ) -> tuple[Tensor, Tensor]:
    """``(vote, agreement)``, each (M,) float64: :func:`o3dvis.orientation.vote` and its agreement
    for the points ``rows`` (a slice with step 1) of ``points`` and ``normals`` (N, 3) float64, from
    ``cameras`` (V, 3) float64 and their probabilities ``visibility`` (V, N) float32; in one pass.

    Raises:
        ValueError: tensors of the wrong shapes or types, or rows past the points.
    """
    n, v = points.shape[0], cameras.shape[0]
    _check("points", points, (n, 3), torch.float64)
    _check("normals", normals, (n, 3), torch.float64)
    _check("cameras", cameras, (v, 3), torch.float64)
    _check("visibility", visibility, (v, n))
    first, last, step = rows.indices(n)
    if step != 1:
        raise ValueError(f"rows must be a slice with step 1, got {rows}")
    m = max(0, last - first)
    vote, agreement = points.new_empty(m), points.new_empty(m)
    if m:
        _LIBRARY.o3dvis_votes(first, m, n, v, points.data_ptr(), normals.data_ptr(), cameras.data_ptr(),
                              visibility.data_ptr(), vote.data_ptr(), agreement.data_ptr())
    return vote, agreement


def brute_knn(points: Tensor, rows: Tensor, k: int) -> Tensor:
    """(M, k) int64: the ``k`` nearest of ``points`` (N, 3) float64 to each of the points ``rows``
    (M,) int64, nearest first (ties: the lower index), by their distances to all points.

    Raises:
        ValueError: tensors of the wrong shapes or types, or ``k`` outside [1, min(N, 64)].
        IndexError: rows out of range.
    """
    n, m = points.shape[0], rows.shape[0]
    _check("points", points, (n, 3), torch.float64)
    _check("rows", rows, (m,), torch.long)
    if not 1 <= k <= min(n, 64):
        raise ValueError(f"k must lie in [1, {min(n, 64)}], got {k}")
    if m and (int(rows.min()) < 0 or int(rows.max()) >= n):
        raise IndexError(f"rows must lie in [0, {n})")
    out = torch.empty(m, k, dtype=torch.long)
    if m:
        _LIBRARY.o3dvis_brute_knn(n, points.data_ptr(), m, rows.data_ptr(), k, out.data_ptr())
    return out


def affinity_table(visibility: Tensor) -> Tensor:
    """The (N, S) table :func:`visibility_affinity` reads of answers ``visibility`` (V, N): each
    point's row, padded with zeros to S, the multiple of 16 from V up."""
    v, n = visibility.shape
    table = visibility.new_zeros(n, -(-v // 16) * 16, dtype=torch.float32)
    table[:, :v] = visibility.T
    return table


def key_table(keys: Tensor) -> Tensor:
    """An open-addressing hash table of distinct int64 ``keys`` (M,): (S,) int64, S a power of two of
    at least 2 M, each slot -1 or the index of the key hashed there (what :func:`grid_knn` reads)."""
    _check("keys", keys, (keys.shape[0],), torch.long)
    table = torch.full((1 << max(1, 2 * keys.shape[0] - 1).bit_length(),), -1, dtype=torch.long)
    _LIBRARY.o3dvis_key_table(keys.shape[0], keys.data_ptr(), table.shape[0], table.data_ptr())
    return table


@dataclass
class OctreeLevels:
    """What :func:`octree_levels` gives, per level ``0 .. depth`` (lists of tensors)."""

    point_leaf: Tensor  # (N,) each point's leaf
    keys: list[Tensor]  # (n_l,) sorted cell keys
    parent: list[Tensor]  # (n_l,) each node's parent, -1 at the root
    octant_rows: list[Tensor]  # (n_l,) 8 * parent + octant
    children: list[Tensor]  # (n_l, 8) but at depth, -1 where empty
    child_rows: list[Tensor]  # (n_l, 8) but at depth, n_{l+1} where empty


def octree_levels(keys: Tensor, depth: int, full_depth: int) -> OctreeLevels | None:
    """The levels of the octree of one cloud (what :class:`~o3dvis.nn.octree.Octree` builds with some
    forty torch ops) from its points' cell keys at ``depth``, in two passes: every node up to
    ``full_depth``, the cells that hold points below.

    Args:
        keys: (N,) int64 cell keys at ``depth`` (1 <= depth <= 16), sorted.

    Returns:
        The levels, or None where ``keys`` are out of order or out of [0, 8^depth).

    Raises:
        ValueError: keys of the wrong shape or type, or depths out of range.
    """
    n = keys.shape[0]
    _check("keys", keys, (n,), torch.long)
    if not 1 <= full_depth < depth <= 16:
        raise ValueError(f"need 1 <= full_depth < depth <= 16, got {full_depth}, {depth}")
    counts = keys.new_empty(depth + 1)
    if _LIBRARY.o3dvis_octree_counts(n, keys.data_ptr(), depth, full_depth, counts.data_ptr()):
        return None
    nodes = counts.tolist()
    flat = keys.new_empty(sum(3 * c for c in nodes) + sum(16 * c for c in nodes[:-1]))
    point_leaf = keys.new_empty(n)
    _LIBRARY.o3dvis_octree_fill(n, keys.data_ptr(), depth, full_depth, counts.data_ptr(), point_leaf.data_ptr(),
                                flat.data_ptr())
    levels, at = OctreeLevels(point_leaf, [], [], [], [], []), 0
    for level, count in enumerate(nodes):
        for table in (levels.keys, levels.parent, levels.octant_rows):
            table.append(flat[at:at + count])
            at += count
        if level < depth:
            for table in (levels.children, levels.child_rows):
                table.append(flat[at:at + 8 * count].view(count, 8))
                at += 8 * count
    return levels


def child_neighbours(keys: Tensor, parent: Tensor, above: Tensor, children: Tensor, parent_offset: Tensor,
                     offset_octant: Tensor) -> Tensor:
    """(n, 27) the 3x3x3 neighbours of the n nodes of an octree level from those of their parents,
    n where missing, in one pass (what :meth:`o3dvis.nn.octree.Octree.neighbours` computes with torch
    ops below the full levels).

    Args:
        keys: (n,) int64 the level's keys (their low three bits: each node's octant).
        parent: (n,) int64 each node's parent, in the level above.
        above: (m, 27) int64 the level above's neighbours, m where missing.
        children: (m, 8) int64 the level above's children, -1 where empty.
        parent_offset: (8, 27) int64 by octant, the offset at the level above whose node holds each
            neighbour.
        offset_octant: (8, 27) int64 by octant, the neighbour's octant in that node.

    Raises:
        ValueError: a tensor of another shape or dtype, not contiguous or not on the CPU, or a parent
            index out of range.
    """
    n, m = keys.shape[0], above.shape[0]
    _check("keys", keys, (n,), torch.long)
    _check("parent", parent, (n,), torch.long)
    _check("above", above, (m, 27), torch.long)
    _check("children", children, (m, 8), torch.long)
    _check("parent_offset", parent_offset, (8, 27), torch.long)
    _check("offset_octant", offset_octant, (8, 27), torch.long)
    out = torch.empty((n, 27), dtype=torch.long)
    if _LIBRARY.o3dvis_child_neighbours(n, keys.data_ptr(), parent.data_ptr(), above.data_ptr(), m,
                                        children.data_ptr(), parent_offset.data_ptr(), offset_octant.data_ptr(),
                                        out.data_ptr()):
        raise ValueError(f"parent indices must lie in [0, {m}), parent_offset in [0, 27) and offset_octant in [0, 8)")
    return out


def grid_knn(points: Tensor, cells: Tensor, keys: Tensor, starts: Tensor, table: Tensor, level: int, lo: Tensor,
             side: float, slack: float, k: int, cell_range: tuple[int, int], neighbours: Tensor,
             exact: Tensor, cell_list: Tensor | None = None, wanted: Tensor | None = None) -> None:
    """The ``k`` nearest of ``points`` to each point of the cells ``cell_range`` (or of the cells
    ``cell_list[cell_range[0]:cell_range[1]]``; of their points only those where ``wanted`` (N,)
    bool is set) among the 27 cells around it, written to rows of ``neighbours`` (N, k) int64 and
    ``exact`` (N,) uint8 (see ``o3dvis_grid_knn`` in kernels.c;
    :class:`o3dvis.orientation.NeighbourSearch` prepares them).

    Args:
        points: (N, 3) float64, sorted by cell.
        cells: (M, 3) int64 integer coordinates of the occupied cells of a ``2^level`` grid.
        keys: (M,) int64 their Morton keys, distinct.
        starts: (M + 1,) int64 where each cell's points begin, then N.
        table: the :func:`key_table` of ``keys``.
        lo: (3,) float64 the grid's corner; side: its cells' side.
        slack: how far from its cell a point may lie (keys computed in a lower precision).

    Raises:
        ValueError: tensors of the wrong shapes or types, or ``k`` outside [1, 64].
    """
    n, m = points.shape[0], cells.shape[0]
    if not 1 <= k <= 64:
        raise ValueError(f"k must lie in [1, 64], got {k}")
    size = table.shape[0]
    if size < 2 * m or size & (size - 1):
        raise ValueError(f"table must have a power of two of at least {2 * m} slots, got {size}")
    for name, t, shape, dtype in (("points", points, (n, 3), torch.float64), ("cells", cells, (m, 3), torch.long),
                                  ("keys", keys, (m,), torch.long), ("starts", starts, (m + 1,), torch.long),
                                  ("table", table, (size,), torch.long), ("lo", lo, (3,), torch.float64),
                                  ("neighbours", neighbours, (n, k), torch.long), ("exact", exact, (n,), torch.uint8)):
        _check(name, t, shape, dtype)
    first, last = cell_range
    if cell_list is not None:
        _check("cell_list", cell_list, (cell_list.shape[0],), torch.long)
        if len(cell_list) and (int(cell_list.min()) < 0 or int(cell_list.max()) >= m):
            raise ValueError(f"cell_list must lie in [0, {m})")
    if wanted is not None:
        _check("wanted", wanted, (n,), torch.bool)
    if not 0 <= first <= last <= (m if cell_list is None else len(cell_list)):
        raise ValueError(f"cell range {cell_range} outside [0, {m if cell_list is None else len(cell_list)}]")
    _LIBRARY.o3dvis_grid_knn(points.data_ptr(), cells.data_ptr(), keys.data_ptr(), starts.data_ptr(), size,
                             table.data_ptr(), level, lo.data_ptr(), side, slack, k, first, last,
                             None if cell_list is None else cell_list.data_ptr(),
                             None if wanted is None else wanted.data_ptr(), neighbours.data_ptr(), exact.data_ptr())
