"""Delaunay triangulation of points in the plane: a sweep in C with exact predicates
(``delaunay.c``), faster than scipy's Qhull on the few thousand points a view shows;
Qhull where the C library was not built (see :mod:`o3dvis.clib`).
"""

from __future__ import annotations

import ctypes

import numpy as np
from scipy.spatial import Delaunay, QhullError

from .. import clib

__all__ = ["MAX_POINTS", "available", "delaunay_triangles", "view_surface"]

# half-edge indices (6 a point) are int32
MAX_POINTS = 1 << 28
_PTR = ctypes.c_void_p
_LIBRARY = clib.load(f"{__package__}._delaunay",
                     {"o3dvis_delaunay": ([ctypes.c_int64, _PTR, _PTR], ctypes.c_int64),
                      "o3dvis_view_surface": ([ctypes.c_int64] + [_PTR] * 6, ctypes.c_int64)})


def available() -> bool:
    """Whether the C library is built and loaded."""
    return _LIBRARY is not None


def _coords(coords: np.ndarray) -> np.ndarray:
    coords = np.ascontiguousarray(coords, dtype=np.float64)
    if coords.ndim != 2 or coords.shape[1] != 2:
        raise ValueError(f"coords must be of shape (M, 2), got {coords.shape}")
    if not np.isfinite(coords).all():
        raise ValueError("coords must be finite")
    if len(coords) > MAX_POINTS:
        raise ValueError(f"at most {MAX_POINTS} points can be triangulated, got {len(coords)}")
    return coords


def _check_count(count: int, coords: np.ndarray) -> None:
    if count == -1:
        raise MemoryError(f"not enough memory to triangulate {len(coords)} points")
    if count < 0:
        raise ValueError(f"coords must be finite, and span a range whose size and inverse are finite "
                         f"doubles, got a span of {np.ptp(coords, axis=0)}")


def delaunay_triangles(coords: np.ndarray) -> np.ndarray:
    """The triangles of the Delaunay triangulation of ``coords``.

    Coordinates are snapped to a grid of 2^26 steps over their extent first (in C), so that the
    answer is exact for the snapped points: points on one grid node are triangulated once, and
    points near a line not along the grid (doubles seldom lie exactly on one) may give triangles
    thinner than a grid step, as Qhull gives degenerate ones.

    Args:
        coords: (M, 2) finite coordinates.

    Returns:
        (T, 3) int64 indices into ``coords``, counter-clockwise; none when fewer than three
        distinct points are given or all lie on one line.

    Raises:
        ValueError: for coordinates not of shape (M, 2), not finite, spanning more than the
            largest double or less than about 2^-1000, or more than 2^28 points.
    """
    coords = _coords(coords)
    if len(coords) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    if _LIBRARY is None:
        try:
            return Delaunay(coords).simplices.astype(np.int64)
        except (QhullError, ValueError):  # all on one line, or fewer than three distinct
            return np.zeros((0, 3), dtype=np.int64)
    out = np.empty((max(2 * len(coords) - 5, 1), 3), dtype=np.int32)
    count = _LIBRARY.o3dvis_delaunay(len(coords), coords.ctypes.data, out.ctypes.data)
    _check_count(count, coords)
    return out[:count].astype(np.int64)


def view_surface(coords: np.ndarray, points: np.ndarray, max_edge: np.ndarray, camera: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`delaunay_triangles` of ``coords`` whose edges are short enough in 3D, facing
    ``camera``, and their unit normals, in one pass of C (where :func:`available`; see
    :func:`o3dvis.apps.triangulation.delaunay_surface`, which falls back to numpy).

    Args:
        coords: (M, 2) image-plane coordinates.
        points: (M, 3) the points' positions.
        max_edge: (M,) longest edge allowed at each point.
        camera: (3,) camera position.

    Returns:
        (T, 3) int64 indices and (T, 3) unit normals.
    """
    coords = _coords(coords)
    points = np.ascontiguousarray(points, dtype=np.float64)
    max_edge = np.ascontiguousarray(max_edge, dtype=np.float64)
    camera = np.ascontiguousarray(camera, dtype=np.float64)
    if points.shape != (len(coords), 3) or max_edge.shape != (len(coords),) or camera.shape != (3,):
        raise ValueError(f"need points ({len(coords)}, 3), max_edge ({len(coords)},) and camera (3,), got "
                         f"{points.shape}, {max_edge.shape} and {camera.shape}")
    if len(coords) < 3:
        return np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3))
    rows = max(2 * len(coords) - 5, 1)
    triangles, normals = np.empty((rows, 3), dtype=np.int32), np.empty((rows, 3))
    count = _LIBRARY.o3dvis_view_surface(len(coords), coords.ctypes.data, points.ctypes.data, max_edge.ctypes.data,
                                         camera.ctypes.data, triangles.ctypes.data, normals.ctypes.data)
    _check_count(count, coords)
    return triangles[:count].astype(np.int64), normals[:count]
