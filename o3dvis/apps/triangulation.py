"""The surface seen from one camera: visible points projected to the image plane, Delaunay
triangulated, triangles with edges longer than the local point spacing allows dropped.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from . import delaunay
from .pinhole import look_at

__all__ = ["local_spacing", "delaunay_surface", "visible_triangles", "facing_triangles"]

DEFAULT_EDGE_FACTOR = 3.0


def local_spacing(points: np.ndarray, k: int = 6, tree: cKDTree | None = None) -> np.ndarray:
    """Per-point sampling scale: the distance to the ``k``-th nearest other point, (N,).

    Where duplicates make that distance 0, the distance to the nearest distinct point is used.
    ``tree``: a ``cKDTree`` of ``points`` the caller has already (default: one is built).
    """
    if len(points) < 2:
        return np.zeros(len(points))
    k = min(k, len(points) - 1)
    dist, _ = (cKDTree(points) if tree is None else tree).query(points, k=k + 1, workers=-1)
    dist = dist[:, 1:]
    positive = np.where(dist > 0, dist, np.inf).min(axis=1)
    return np.maximum(dist[:, -1], np.where(np.isfinite(positive), positive, 0))


def delaunay_surface(points: np.ndarray, coords: np.ndarray, max_edge: np.ndarray,
                     camera_location: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Delaunay triangles of 2D ``coords`` whose edges are short enough in 3D, facing the camera,
    and their unit normals.

    A triangle is kept when each of its edges is no longer, in 3D, than the
    larger ``max_edge`` of the edge's two end points, and its area is not zero.
    In one pass of C where it is built (:func:`~o3dvis.apps.delaunay.view_surface`),
    else in numpy with the same rounding.

    Args:
        points: (M, 3) positions of the triangulated points.
        coords: (M, 2) their image-plane coordinates.
        max_edge: (M,) longest edge allowed at each point.
        camera_location: (3,) the camera the triangles are turned to face.

    Returns:
        (T, 3) int64 indices into ``points`` (none when the coordinates are too
        few or all collinear), ordered so that their normals ``(b - a) x (c - a)``
        point to the camera's side, and (T, 3) those normals, unit.
    """
    if delaunay.available():
        return delaunay.view_surface(coords, points, max_edge, camera_location)
    s = delaunay.delaunay_triangles(coords)
    a, b, c = (points[s[:, k]] for k in range(3))
    la, lb, lc = (max_edge[s[:, k]] for k in range(3))
    ab, ac, bc = b - a, c - a, c - b
    keep = ((np.einsum("ij,ij->i", ab, ab) <= np.maximum(la, lb) ** 2)
            & (np.einsum("ij,ij->i", bc, bc) <= np.maximum(lb, lc) ** 2)
            & (np.einsum("ij,ij->i", ac, ac) <= np.maximum(lc, la) ** 2))
    s, a, ab, ac = s[keep], a[keep], ab[keep], ac[keep]
    normals = np.empty_like(ab)  # np.cross, without its copies
    normals[:, 0] = ab[:, 1] * ac[:, 2] - ab[:, 2] * ac[:, 1]
    normals[:, 1] = ab[:, 2] * ac[:, 0] - ab[:, 0] * ac[:, 2]
    normals[:, 2] = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    length = np.sqrt(np.einsum("ij,ij->i", normals, normals))
    area = length > 0
    s, normals, length = s[area], normals[area], length[area]
    away = np.einsum("ij,ij->i", normals, camera_location - a[area]) < 0
    s[away] = s[away][:, [0, 2, 1]]
    normals[away] *= -1  # the normal of the reversed triangle
    return s, normals / length[:, None]


def visible_triangles(points: np.ndarray, camera_location: np.ndarray, indices: np.ndarray,
                      max_edge: np.ndarray) -> np.ndarray:
    """Triangles over the points seen from one camera, facing that camera.

    The points ``points[indices]`` are projected through a pinhole looking at
    their centroid, triangulated (Delaunay) in the image plane, and triangles
    longer than ``max_edge`` allows are dropped.

    Args:
        points: (N, 3) all points.
        camera_location: (3,) camera position.
        indices: (M,) indices of the points visible from the camera.
        max_edge: (N,) longest edge allowed at each point.

    Returns:
        (T, 3) int64 indices into ``points``, ordered counter-clockwise as seen
        from the camera (their normals point towards it).
    """
    return facing_triangles(points, camera_location, indices, max_edge)[0]


def facing_triangles(points: np.ndarray, camera_location: np.ndarray, indices: np.ndarray,
                     max_edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`visible_triangles` and their unit normals (towards the camera), (T, 3) each."""
    indices = np.asarray(indices, dtype=np.int64)
    sub = points[indices]
    if len(sub) < 3:
        return np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3))
    extrinsic = look_at(camera_location, sub.mean(axis=0))
    cam = sub @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    front = cam[:, 2] > 1e-12 * max(1.0, float(np.abs(cam).max()))
    indices, sub, cam = indices[front], sub[front], cam[front]
    s, normals = delaunay_surface(sub, cam[:, :2] / cam[:, 2:3], max_edge[indices], camera_location)
    return indices[s], normals
