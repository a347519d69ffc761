"""The surfel z-buffer of a camera in one pass of C (``o3dvis/nn/csrc/zbuffer.c``; see
:mod:`o3dvis.nn.zbuffer`)."""

from __future__ import annotations

from torch import Tensor

from . import _library
from ._library import check


def surfel_zbuffer(points: Tensor, surfels: Tensor, camera: Tensor, rows: int, max_half: int, max_wide: int,
                   clip: float) -> Tensor:
    """(N, 4) :func:`o3dvis.nn.zbuffer.surfel_zbuffer` of ``points`` (N, 3) float32 with their
    ``surfels`` (N, 5), seen from ``camera`` (3,), in one pass over the points and one over the buffer.

    Raises:
        ValueError: tensors of the wrong shapes or types, or a buffer out of [1, 2^15) rows.
        MemoryError: no memory for the buffer.
    """
    n = points.shape[0]
    check("points", points, (n, 3))
    check("surfels", surfels, (n, 5))
    check("camera", camera, (3,))
    if not 1 <= rows < 1 << 15 or max_half < 0 or max_wide < 0:
        raise ValueError(f"rows must lie in [1, 32768) and the disc bounds be >= 0, got {rows}, {max_half}, "
                         f"{max_wide}")
    out = points.new_empty(n, 4)
    if n and _library.LIBRARY.o3dvis_surfel_zbuffer(n, points.data_ptr(), surfels.data_ptr(), camera.data_ptr(), rows,
                                                    max_half, max_wide, clip, out.data_ptr()):
        raise MemoryError(f"no memory for a {rows} x {2 * rows} surfel z-buffer")
    return out
