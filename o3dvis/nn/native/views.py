"""A view's projection, the points' planes and their footprints' splats in passes of C
(``o3dvis/nn/csrc/views.c``; see :class:`o3dvis.nn.cues.ViewProjection`)."""

from __future__ import annotations

import torch
from torch import Tensor

from . import _library
from ._library import check


# the most points a view of the kernels takes: its depth buffers (about 1.4 values a point over four
# scales) are then indexed by int32
MAX_POINTS = 1 << 30


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
    check("points", points, (n, 3))
    view = camera if camera is not None else direction
    check("camera" if camera is not None else "direction", view, (3,))
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
    if _library.LIBRARY.o3dvis_project(n, points.data_ptr(), camera.data_ptr() if camera is not None else None,
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
    check("points", points, (n, 3))
    check("keys", keys, (n,), torch.long)
    if not 1 <= coarsest <= finest <= 21:
        raise ValueError(f"levels must lie in [1, 21], coarsest first, got {coarsest}, {finest}")
    out = points.new_empty(n, 4)
    spread = points.new_empty(n) if areas else None
    if n and _library.LIBRARY.o3dvis_surfels(n, points.data_ptr(), keys.data_ptr(), finest, coarsest, count,
                                             out.data_ptr(), spread.data_ptr() if areas else None):
        raise MemoryError("no memory for the surfels' scratch buffers")
    return torch.cat([out, spread[:, None]], dim=1) if areas else out


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
    check("points", points, (n, 3))
    check("surfels", surfels, (n, 4))
    check("depth", depth, (n,))
    check("frame", frame, (3, 3))
    if camera is not None:
        check("camera", camera, (3,))
    if level.dtype != torch.int8 or level.shape != (n,) or corners.dtype != torch.int32 or len(sides) != scales:
        raise ValueError("level must be (N,) int8, corners (N, scales) int32 and sides one per scale")
    firsts = [sum((res + 2) ** 2 for res in sides[:s]) for s in range(scales)]
    if out.dtype != torch.float32 or not out.is_contiguous() or out.shape != (firsts[-1],):
        raise ValueError(f"out must be the contiguous float32 buffers of all scales but the coarsest, "
                         f"({firsts[-1]},), got {tuple(out.shape)} {out.dtype}")
    firsts, sizes = torch.tensor(firsts, dtype=torch.long), torch.tensor(sides, dtype=torch.long)
    level, corners = level.contiguous(), corners.contiguous()
    if _library.LIBRARY.o3dvis_plane_splat(n, points.data_ptr(), surfels.data_ptr(), depth.data_ptr(), level.data_ptr(),
                                           scales, sizes.data_ptr(), corners.data_ptr(), firsts.data_ptr(),
                                           camera.data_ptr() if camera is not None else None, frame.data_ptr(), half,
                                           slope, out.data_ptr()):
        raise MemoryError("no memory for the splat's scratch buffers")
