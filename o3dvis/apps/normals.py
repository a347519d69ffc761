"""Oriented normals from visibility: what a camera sees of a cloud is a height field it can mesh.

For each of ``num_views`` cameras around the cloud, the visible points are
triangulated in the image plane (:mod:`.triangulation`); every triangle faces
its camera, so its normal is oriented. Averaged over triangles and views, they
give each point an oriented normal, with no tangent-plane propagation.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .camera import cloud_points, viewpoints_around
from .methods import resolve_method
from .triangulation import DEFAULT_EDGE_FACTOR, local_spacing, triangle_normals, visible_triangles

__all__ = ["estimate_normals_neural", "orient_normals_neural", "multiview_normals"]


def _get_normals(pcd) -> np.ndarray | None:
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


def multiview_normals(points: np.ndarray, cameras: np.ndarray, visibility: np.ndarray,
                      edge_factor: float = DEFAULT_EDGE_FACTOR, progress: bool = False) -> np.ndarray:
    """Oriented unit normals from per-view triangulations of the visible points.

    Args:
        points: (N, 3) points.
        cameras: (V, 3) camera positions.
        visibility: (V, N) bool, which points each camera sees.
        edge_factor: triangles with an edge longer than ``edge_factor`` times the
            local point spacing (distance to the 6th neighbour) are dropped.
        progress: show a progress bar over the views.

    Returns:
        (N, 3) unit normals, each facing the cameras that see its point; points
        in no kept triangle take the normal of the nearest point that has one.

    Raises:
        ValueError: when no view yields a triangle (e.g. all points collinear).
    """
    from tqdm import tqdm

    max_edge = edge_factor * local_spacing(points)
    total = np.zeros((len(points), 3))
    for cam, vis in tqdm(zip(cameras, visibility), total=len(cameras), disable=not progress,
                         desc="normals", unit="view"):
        triangles = visible_triangles(points, cam, np.flatnonzero(vis), max_edge)
        normals = triangle_normals(points, triangles)
        length = np.linalg.norm(normals, axis=1)
        ok = length > 0
        unit, corners = normals[ok] / length[ok, None], triangles[ok].ravel()
        for k in range(3):
            total[:, k] += np.bincount(corners, np.repeat(unit[:, k], 3), minlength=len(points))
    length = np.linalg.norm(total, axis=1)
    known = length > 1e-9
    if not known.any():
        raise ValueError("no view of the points could be triangulated: the points are too few "
                         "or all on one line")
    normals = np.zeros_like(total)
    normals[known] = total[known] / length[known, None]
    return _fill_from_nearest(points, normals, known)


def estimate_normals_neural(pcd, num_views: int = 26, method=None, *,
                            edge_factor: float = DEFAULT_EDGE_FACTOR, progress: bool = False):
    """Estimates oriented normals from visibility, in place, like ``pcd.estimate_normals()``.

    Cameras sit on a Fibonacci sphere of radius = bounding-box diagonal around
    the cloud. Normals face the cameras that see their points, so they point
    out of closed surfaces with no ``orient_normals_*`` step.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor); its normals are replaced.
        num_views: number of cameras.
        method: the visibility method (default: the pretrained neural network);
            see :func:`o3dvis.apps.methods.resolve_method`.
        edge_factor: triangles with an edge longer than this many local point
            spacings are dropped (they bridge gaps or depth jumps).
        progress: show a progress bar.

    Returns:
        ``pcd``, with unit normals set.
    """
    points = cloud_points(pcd)
    _get_normals(pcd)
    if num_views < 1:
        raise ValueError(f"num_views must be at least 1, got {num_views}")
    cameras = viewpoints_around(points, num_views)
    visibility = resolve_method(method)(points, cameras)
    _set_normals(pcd, multiview_normals(points, cameras, visibility, edge_factor, progress))
    return pcd


def orient_normals_neural(pcd, num_views: int = 26, method=None):
    """Flips the normals a cloud already has to face the cameras that see their points.

    Each point's orientation is voted by the cameras that see it, weighted by
    the cosine between the normal and the direction to the camera; points that
    no camera sees follow their nearest voted neighbour.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor) with normals.
        num_views: number of cameras on a sphere of radius = bounding-box diagonal.
        method: the visibility method (default: the pretrained neural network).

    Returns:
        ``pcd``, with its normals oriented in place.
    """
    points = cloud_points(pcd)
    normals = _get_normals(pcd)
    if normals is None or len(normals) != len(points):
        raise ValueError("the point cloud has no normals to orient: call estimate_normals first")
    if num_views < 1:
        raise ValueError(f"num_views must be at least 1, got {num_views}")
    normals = np.array(normals, dtype=np.float64)
    cameras = viewpoints_around(points, num_views)
    visibility = resolve_method(method)(points, cameras)
    vote = np.zeros(len(points))
    for cam, vis in zip(cameras, visibility):
        towards = cam - points[vis]
        cosine = np.einsum("ij,ij->i", normals[vis], towards) / np.linalg.norm(towards, axis=1)
        vote[vis] += cosine
    normals[vote < 0] *= -1
    known = vote != 0
    guide = _fill_from_nearest(points, normals, known)
    normals[np.einsum("ij,ij->i", normals, guide) < 0] *= -1
    _set_normals(pcd, normals)
    return pcd
