"""Oriented normals from visibility: what a camera sees of a cloud is a height field it can mesh.

For each of ``num_views`` cameras around the cloud, the visible points are
triangulated in the image plane (:mod:`.triangulation`); every triangle faces
its camera, so its normal is oriented. Averaged over triangles and views, they
give each point an oriented normal, with no tangent-plane propagation.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .camera import cloud_points, viewpoints_around
from ..methods import resolve_method
from .triangulation import DEFAULT_EDGE_FACTOR, local_spacing, triangle_normals, visible_triangles

__all__ = ["estimate_normals_neural", "orient_normals_neural", "multiview_normals"]


def _get_normals(pcd) -> np.ndarray | None:
    """The cloud's normals, None when it has none; TypeError for anything but a PointCloud."""
    if isinstance(pcd, o3d.geometry.PointCloud):
        return np.asarray(pcd.normals) if pcd.has_normals() else None
    if isinstance(pcd, o3d.t.geometry.PointCloud):
        return pcd.point.normals.numpy().astype(np.float64) if "normals" in pcd.point else None
    raise TypeError(f"expected an open3d PointCloud, got {type(pcd).__name__}")


def _set_normals(pcd, normals: np.ndarray) -> None:
    if isinstance(pcd, o3d.geometry.PointCloud):
        pcd.normals = o3d.utility.Vector3dVector(normals)
    else:
        dtype = pcd.point.positions.dtype
        pcd.point.normals = o3d.core.Tensor(normals.astype(np.float32 if dtype == o3d.core.float32
                                                           else np.float64))


def _fill_from_nearest(points: np.ndarray, values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Rows of ``values`` where ``known`` is False copied from the nearest known point."""
    if known.all() or not known.any():
        return values
    _, nearest = cKDTree(points[known]).query(points[~known])
    values = values.copy()
    values[~known] = values[known][nearest]
    return values


def _add_triangle_normals(total: np.ndarray, points: np.ndarray, cameras: np.ndarray,
                          visibility: np.ndarray, max_edge: np.ndarray, subset: np.ndarray | None,
                          progress: bool, desc: str) -> None:
    """Adds to ``total`` the unit normals of the triangles each view makes at each point.

    The views are triangulated on all cores (Qhull releases the GIL) and added in order.
    """
    from tqdm import tqdm

    def triangulate(view: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        cam, vis = view
        return visible_triangles(points, cam, np.flatnonzero(vis if subset is None else vis & subset),
                                 max_edge)

    with ThreadPoolExecutor(max(1, min(len(cameras), os.cpu_count() or 1))) as pool:
        for triangles in tqdm(pool.map(triangulate, zip(cameras, visibility)), total=len(cameras),
                              disable=not progress, desc=desc, unit="view"):
            normals = triangle_normals(points, triangles)
            length = np.linalg.norm(normals, axis=1)
            ok = length > 0
            unit, corners = normals[ok] / length[ok, None], triangles[ok].ravel()
            slots = (3 * corners[:, None] + np.arange(3)).ravel()  # (corner, component) pairs
            total += np.bincount(slots, np.repeat(unit, 3, axis=0).ravel(),
                                 minlength=total.size).reshape(total.shape)


def multiview_normals(points: np.ndarray, method, num_views: int = 26, refine_views: int = 64,
                      edge_factor: float = DEFAULT_EDGE_FACTOR, progress: bool = False) -> np.ndarray:
    """Oriented unit normals from per-view triangulations of the visible points.

    Args:
        points: (N, 3) points.
        method: the visibility method (see :func:`o3dvis.methods.resolve_method`).
        num_views: cameras on a Fibonacci sphere of radius = bounding-box diagonal.
        refine_views: more cameras for the points that no triangle of the first
            ones covers (in concavities few directions see); only those points
            and their neighbours are triangulated again. 0 turns this off.
        edge_factor: triangles with an edge longer than ``edge_factor`` times the
            local point spacing (distance to the 6th neighbour) are dropped.
        progress: show progress bars over the views.

    Returns:
        (N, 3) unit normals, each facing the cameras that see its point; points
        in no kept triangle take the normal of the nearest point that has one.

    Raises:
        ValueError: when no view yields a triangle (e.g. all points collinear).
    """
    if num_views < 1 or refine_views < 0:
        raise ValueError(f"num_views must be at least 1 and refine_views at least 0, got "
                         f"{num_views} and {refine_views}")
    method = resolve_method(method)
    max_edge = edge_factor * local_spacing(points)
    total = np.zeros((len(points), 3))
    cameras = viewpoints_around(points, num_views)
    _add_triangle_normals(total, points, cameras, method(points, cameras), max_edge, None,
                          progress, "normals")
    missing = np.linalg.norm(total, axis=1) <= 1e-9
    if refine_views and missing.any() and not missing.all():
        _, neighbours = cKDTree(points).query(points[missing], k=min(16, len(points)))
        around = np.zeros(len(points), dtype=bool)
        around[neighbours.ravel()] = True
        extra = np.zeros_like(total)
        cameras = viewpoints_around(points, refine_views)
        visibility = np.zeros((len(cameras), len(points)), dtype=bool)
        visibility[:, around] = method(points, cameras, np.flatnonzero(around))
        _add_triangle_normals(extra, points, cameras, visibility, max_edge, around,
                              progress, "refine")
        total[missing] = extra[missing]
    length = np.linalg.norm(total, axis=1)
    known = length > 1e-9
    if not known.any():
        raise ValueError("no view of the points could be triangulated: the points are too few "
                         "or all on one line")
    normals = np.zeros_like(total)
    normals[known] = total[known] / length[known, None]
    return _fill_from_nearest(points, normals, known)


def estimate_normals_neural(pcd, num_views: int = 26, method=None, *, refine_views: int = 64,
                            edge_factor: float = DEFAULT_EDGE_FACTOR, progress: bool = False):
    """Estimates oriented normals from visibility, in place, like ``pcd.estimate_normals()``.

    Cameras sit on a Fibonacci sphere of radius = bounding-box diagonal around
    the cloud. Normals face the cameras that see their points, so they point
    out of closed surfaces with no ``orient_normals_*`` step.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor); its normals are replaced.
        num_views: number of cameras.
        method: the visibility method (default: the pretrained neural network);
            see :func:`o3dvis.methods.resolve_method`.
        refine_views: more cameras for the points the first ``num_views`` leave
            without a triangle (0: none); those points and their neighbours alone
            are asked about and triangulated again.
        edge_factor: triangles with an edge longer than this many local point
            spacings are dropped (they bridge gaps or depth jumps).
        progress: show progress bars.

    Returns:
        ``pcd``, with unit normals set.
    """
    points = cloud_points(pcd)
    _get_normals(pcd)  # only clouds can take normals
    _set_normals(pcd, multiview_normals(points, method, num_views, refine_views, edge_factor, progress))
    return pcd


def _vote(points: np.ndarray, normals: np.ndarray, cameras: np.ndarray, visibility: np.ndarray
          ) -> np.ndarray:
    """Sum over the cameras that see each point of cos(normal, direction to the camera), (N,)."""
    vote = np.zeros(len(points))
    for cam, vis in zip(cameras, visibility):
        towards = cam - points[vis]
        vote[vis] += np.einsum("ij,ij->i", normals[vis], towards) / np.linalg.norm(towards, axis=1)
    return vote


def orient_normals_neural(pcd, num_views: int = 26, method=None, *, refine_views: int = 64):
    """Flips the normals a cloud already has to face the cameras that see their points.

    Each point's orientation is voted by the cameras that see it, weighted by
    the cosine between the normal and the direction to the camera; points that
    no camera sees follow their nearest voted neighbour.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor) with normals.
        num_views: number of cameras on a sphere of radius = bounding-box diagonal.
        method: the visibility method (default: the pretrained neural network).
        refine_views: more cameras asked about the points the first ones do not
            see (0: none).

    Returns:
        ``pcd``, with its normals oriented in place.
    """
    points = cloud_points(pcd)
    normals = _get_normals(pcd)
    if normals is None or len(normals) != len(points):
        raise ValueError("the point cloud has no normals to orient: call estimate_normals first")
    if num_views < 1 or refine_views < 0:
        raise ValueError(f"num_views must be at least 1 and refine_views at least 0, got "
                         f"{num_views} and {refine_views}")
    normals = np.array(normals, dtype=np.float64)
    method = resolve_method(method)
    cameras = viewpoints_around(points, num_views)
    vote = _vote(points, normals, cameras, method(points, cameras))
    if refine_views and (vote == 0).any():
        unseen = vote == 0
        cameras = viewpoints_around(points, refine_views)
        vote[unseen] = _vote(points[unseen], normals[unseen], cameras,
                             method(points, cameras, np.flatnonzero(unseen)))
    normals[vote < 0] *= -1
    known = vote != 0
    guide = _fill_from_nearest(points, normals, known)
    normals[np.einsum("ij,ij->i", normals, guide) < 0] *= -1
    _set_normals(pcd, normals)
    return pcd
