"""Surfaces from point clouds: the mesh one camera sees, and Poisson with visibility-oriented normals."""

from __future__ import annotations

import math
import os

import numpy as np
import open3d as o3d

from .pinhole import camera_location_of
from ..clouds import cloud_points, legacy_cloud
from ..methods import resolve_method
from .normals import estimate_normals_neural
from .triangulation import DEFAULT_EDGE_FACTOR, local_spacing, visible_triangles

__all__ = ["reconstruct_view_dependent", "reconstruct_poisson"]

POISSON_MAX_DEPTH = 16
"""Open3D's Poisson octree addresses a cell by 16-bit offsets: from depth 17 its samples fall outside the tree
(it reports them as bad sample nodes) and far deeper it crashes the process."""
POISSON_BYTES_PER_POINT_LEVEL = 4096
"""Memory of Open3D's Poisson per point and per octree level finer than the points fill (about 3.7 kB measured)."""


def reconstruct_view_dependent(pcd, camera, model=None, *,
                               edge_factor: float = DEFAULT_EDGE_FACTOR) -> o3d.geometry.TriangleMesh:
    """The surface a camera sees, as a mesh over the visible points.

    The visible points are projected to the camera's image plane and Delaunay
    triangulated; triangles with an edge longer than ``edge_factor`` local
    point spacings (bridges over gaps and depth jumps) are dropped.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor); colours carry over.
        camera: a (3,) camera location, a 4x4 extrinsic or
            ``o3d.camera.PinholeCameraParameters``.
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        edge_factor: longest edge allowed, in local point spacings.

    Returns:
        ``o3d.geometry.TriangleMesh`` whose vertices are the visible points that
        belong to a triangle, with triangles facing the camera and vertex normals.
    """
    pcd = legacy_cloud(pcd)
    points = cloud_points(pcd)
    location = camera_location_of(camera)
    visible = np.flatnonzero(resolve_method(model)(points, location[None])[0])
    triangles = visible_triangles(points, location, visible, edge_factor * local_spacing(points))
    used, triangles = np.unique(triangles, return_inverse=True)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(points[used]),
                                     o3d.utility.Vector3iVector(triangles.reshape(-1, 3)))
    if pcd.has_colors():
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.asarray(pcd.colors)[used])
    mesh.compute_vertex_normals()
    return mesh


def reconstruct_poisson(pcd, depth: int = 8, model=None, *, num_views: int = 26,
                        refine_views: int = 0, width: float = 0,
                        scale: float = 1.1, linear_fit: bool = False, n_threads: int = 1,
                        progress: bool = False, search_param=None
                        ) -> tuple[o3d.geometry.TriangleMesh, o3d.utility.DoubleVector]:
    """Screened Poisson reconstruction on normals oriented by visibility.

    Normals come from :func:`~o3dvis.apps.normals.estimate_normals_neural` on a
    copy of the cloud (``pcd`` is left unchanged), then Open3D's
    ``TriangleMesh.create_from_point_cloud_poisson`` runs with the given
    arguments.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor).
        depth, width, scale, linear_fit: as in Open3D's
            ``create_from_point_cloud_poisson``.
        n_threads: threads of the Poisson solver. The default 1 gives the
            same mesh on every run; more threads (-1: all cores, Open3D's
            default) may give slightly different meshes from run to run.
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        num_views, refine_views: cameras used to estimate the normals (see
            :func:`~o3dvis.apps.normals.estimate_normals_neural`).
        progress: show a progress bar while estimating the normals.
        search_param: an Open3D KNN or hybrid search parameter: fit the normals
            to co-visible neighbours instead of triangulating (faster; see
            :func:`~o3dvis.apps.normals.estimate_normals_neural`).

    Returns:
        The mesh and the per-vertex densities, as Open3D returns them.

    Raises:
        ValueError: an octree of fewer than 2 levels (``depth`` < 2, or a
            ``width`` near the cloud's size), on which Open3D fails and then
            aborts the process at exit; a ``depth`` beyond what the cloud and
            the memory allow (see :func:`check_poisson_depth`); ``scale`` <= 0.
    """
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 2:
        raise ValueError(f"depth must be an int >= 2, got {depth!r}")
    if not (np.isfinite(width) and width >= 0 and np.isfinite(scale) and scale > 0):
        raise ValueError(f"width must be >= 0 and scale > 0, got width={width} and scale={scale}")
    cloud = o3d.geometry.PointCloud(legacy_cloud(pcd))
    check_poisson_depth(int(depth), len(cloud.points))
    size = float(cloud.get_axis_aligned_bounding_box().get_extent().max()) if cloud.has_points() else 0.0
    if width > 0 and scale * size <= 2 * width:  # Open3D's depth from width: ceil(log2(scale size / width))
        raise ValueError(f"width={width} gives an octree of fewer than 2 levels over a cloud {size:g} "
                         f"wide (scale={scale}); use a smaller width or width=0 with depth")
    estimate_normals_neural(cloud, search_param, num_views, model, refine_views=refine_views, progress=progress)
    # Open3D's Poisson loses precision far from the origin (georeferenced clouds): solve centred
    center = cloud.get_axis_aligned_bounding_box().get_center()
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud.translate(-center), depth=depth, width=width, scale=scale, linear_fit=linear_fit,
        n_threads=n_threads)
    return mesh.translate(center), densities


def check_poisson_depth(depth: int, num_points: int) -> None:
    """Refuses a Poisson octree depth that Open3D cannot build, the cloud cannot fill or memory cannot hold.

    Three limits: :data:`POISSON_MAX_DEPTH`, Open3D's own; ``ceil(log2(n)) + 2`` for ``n`` points (at
    least 8, Open3D's default), past which the finest cells are smaller than the points' spacing even
    along a curve, so deeper levels fit nothing and only cost time; and the memory available now, against
    :data:`POISSON_BYTES_PER_POINT_LEVEL` per point for each level finer than ``log4(n)`` (where the
    cells of a surface outnumber its points).

    Args:
        depth: the requested octree depth.
        num_points: the number of points of the cloud.

    Raises:
        ValueError: naming the depth, the limit it passes and why.
    """
    if depth > POISSON_MAX_DEPTH:
        raise ValueError(f"depth={depth} is beyond {POISSON_MAX_DEPTH}, the deepest octree Open3D's Poisson "
                         "addresses (deeper, it misplaces the samples or crashes)")
    useful = max(8, math.ceil(math.log2(max(num_points, 1))) + 2)
    if depth > useful:
        raise ValueError(f"depth={depth} is beyond {useful}, the deepest octree {num_points} points fill "
                         "(deeper cells are finer than the points' spacing); use a smaller depth")
    levels = max(1.0, depth - math.log(max(num_points, 1), 4))
    needed = POISSON_BYTES_PER_POINT_LEVEL * num_points * levels
    available = _available_memory()
    if available is not None and needed > available:
        raise ValueError(f"depth={depth} needs about {needed / 2**30:.1f} GiB for {num_points} points, more than "
                         f"the {available / 2**30:.1f} GiB of memory available; use a smaller depth")


def _available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux's MemAvailable, else the free pages), or None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return None
