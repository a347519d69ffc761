"""Oriented normals from visibility: what a camera sees of a cloud is a height field it can mesh.

For each of ``num_views`` cameras around the cloud, the visible points are
triangulated in the image plane (:mod:`.triangulation`); every triangle faces
its camera, so its normal is oriented. Averaged over triangles and views, they
give each point an oriented normal, with no tangent-plane propagation.

With an Open3D search parameter instead, each point's normal is a plane fitted
to its neighbours as ``PointCloud.estimate_normals`` fits it, but each
neighbour weighted by how many of the point's views also see it: the far
side of a thin wall, never seen with the point, drops out. The cameras that
see the point then orient it. No triangulation, so faster (``docs/results.md``).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from ..baselines import distinct_points
from ..cameras import viewpoints_around
from ..clouds import cloud_normals, cloud_points, set_cloud_normals
from ..methods import resolve_method
from ..orientation import complete_orientation, fit_planes, orient_by_vote, row_chunks, vote
from ..threads import plan_threads, threaded_map
from .triangulation import DEFAULT_EDGE_FACTOR, facing_triangles, local_spacing

__all__ = ["estimate_normals_neural", "orient_normals_neural", "multiview_normals",
           "covisible_normals", "neighbourhoods"]

_FIT_NEIGHBOURS = 16  # neighbours of the plane fitted where no triangle gives a normal
_BIT_COUNT = np.array([bin(byte).count("1") for byte in range(256)], dtype=np.uint8)


def _add_triangle_normals(total: np.ndarray, points: np.ndarray, cameras: np.ndarray,
                          visibility: np.ndarray, max_edge: np.ndarray, subset: np.ndarray | None,
                          progress: bool, desc: str) -> None:
    """Adds to ``total`` the unit normals of the triangles each view makes at each point.

    The views are triangulated on the threads :func:`~o3dvis.threads.plan_threads` gives (the
    triangulation releases the GIL), each worker also making its triangles' unit normals, and
    added in order.
    """
    from tqdm import tqdm

    def triangulate(view: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        cam, vis = view
        return facing_triangles(points, cam, np.flatnonzero(vis if subset is None else vis & subset), max_edge)

    views, workers = list(zip(cameras, visibility)), plan_threads(len(cameras), 2)
    for triangles, unit in tqdm(threaded_map(triangulate, views, workers) if workers > 1 else map(triangulate, views),
                                total=len(cameras), disable=not progress, desc=desc, unit="view"):
        for corner in triangles.T:
            np.add.at(total, corner, unit)


def neighbourhoods(points: np.ndarray, search_param, tree: cKDTree | None = None) -> np.ndarray:
    """(N, K) indices of each point's neighbours (itself included) as Open3D's search finds them.

    Args:
        points: (N, 3) points.
        search_param: ``o3d.geometry.KDTreeSearchParamKNN`` (the ``knn`` nearest)
            or ``KDTreeSearchParamHybrid`` (at most ``max_nn`` within ``radius``;
            slots beyond the points found hold ``N``).
        tree: a ``scipy.spatial.cKDTree`` of ``points`` to reuse (default: one is built).

    Raises:
        TypeError: another search parameter (a plain radius search has no bound on its size).
        ValueError: a count below 1 or a radius that is not positive and finite.
    """
    if isinstance(search_param, o3d.geometry.KDTreeSearchParamKNN):
        count, radius = search_param.knn, np.inf
    elif isinstance(search_param, o3d.geometry.KDTreeSearchParamHybrid):
        count, radius = search_param.max_nn, search_param.radius
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"the search radius must be positive and finite, got {radius}")
    else:
        raise TypeError("search_param must be o3d.geometry.KDTreeSearchParamKNN or "
                        f"KDTreeSearchParamHybrid, got {type(search_param).__name__}")
    if count < 1:
        raise ValueError(f"the search must take at least 1 neighbour, got {count}")
    tree = cKDTree(points) if tree is None else tree
    _, index = tree.query(points, k=min(count, len(points)), distance_upper_bound=radius, workers=-1)
    return index.reshape(len(points), -1)


def covisible_normals(points: np.ndarray, visibility: np.ndarray, neighbours: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Unoriented unit normals of planes fitted to co-visible neighbours.

    Each neighbour of a point is weighted by the share of the views seeing the
    point that also see the neighbour (all weigh 1 for a point no view sees):
    points on the far side of a thin wall, never seen with it, drop out of its fit.

    Args:
        points: (N, 3) points.
        visibility: (V, N) bool, which points each view sees.
        neighbours: (N, K) indices from :func:`neighbourhoods` (``N``: no neighbour).

    Returns:
        (N, 3) unit normals and (N,) bool: whether at least three neighbours
        off one line weighed in (elsewhere the normal is arbitrary).
    """
    # which views see each point, 8 a byte: the views two points share are the bits of an AND
    codes = np.packbits(np.pad(visibility, ((0, 0), (0, 1))), axis=0)  # (bytes, N + 1), last: none
    views = visibility.sum(axis=0)
    real = neighbours < len(points)
    weight = np.empty(neighbours.shape)
    for rows in row_chunks(len(neighbours)):
        shared = np.zeros(weight[rows].shape, dtype=np.int32)  # uint8 would wrap past 255 views
        for byte in codes:
            shared += _BIT_COUNT[byte[neighbours[rows]] & byte[rows, None]]
        weight[rows] = np.where(views[rows, None] > 0, shared / np.maximum(views[rows], 1)[:, None],
                                real[rows])
    # no weight at all only where a seen point's search returned none of its views' points (> K
    # duplicates of it, unseen): the fit counts as undefined
    return fit_planes(points, neighbours, weight)


def multiview_normals(points: np.ndarray, method, num_views: int = 26, refine_views: int = 0,
                      edge_factor: float = DEFAULT_EDGE_FACTOR, progress: bool = False,
                      search_param=None) -> np.ndarray:
    """Oriented unit normals from per-view triangulations of the visible points.

    With ``search_param``, from planes fitted to co-visible neighbours instead
    (:func:`covisible_normals`), oriented towards the cameras that see them.

    Args:
        points: (N, 3) points.
        method: the visibility source, as ``model=`` of :func:`estimate_normals_neural`.
        num_views: cameras on a Fibonacci sphere of radius = bounding-box diagonal.
        refine_views: more cameras for the points that no triangle of the first
            ones covers (in concavities few directions see); only those points
            and their neighbours are triangulated again. Default 0: those
            points get the side propagated from the covered ones, which on the
            bench's meshes orients as many right in less time.
        edge_factor: triangles with an edge longer than ``edge_factor`` times the
            local point spacing (distance to the 6th neighbour) are dropped.
        progress: show progress bars over the views (with ``search_param``:
            over the three steps).
        search_param: an Open3D KNN or hybrid search parameter: fit planes to
            the neighbours it finds instead of triangulating (``edge_factor``
            is then unused).

    Returns:
        (N, 3) unit normals, each facing the cameras that see its point; a point
        in no kept triangle gets the normal of a plane through its 16 nearest
        points, turned to the side propagated along the surface from the
        triangulated points (the nearest one's normal where no plane fits).
        Exact duplicates of a point get its normal.

    Raises:
        ValueError: when no view yields a triangle (e.g. all points collinear),
            or, with ``search_param``, no point has a plane fitted.
    """
    _check_views(num_views, refine_views)
    keep, slot = distinct_points(points)
    if len(keep) < len(points):  # solved once per distinct point, then spread to its duplicates
        return multiview_normals(points[keep], method, num_views, refine_views, edge_factor, progress,
                                 search_param)[slot]
    method = resolve_method(method)
    cameras = viewpoints_around(points, num_views)
    tree = cKDTree(points)  # the searches over all the points below share it
    if search_param is not None:
        return _covisible_path(points, method, cameras, refine_views, search_param, tree, progress)
    max_edge = edge_factor * local_spacing(points, tree=tree)
    total = np.zeros((len(points), 3))
    _add_triangle_normals(total, points, cameras, method(points, cameras), max_edge, None,
                          progress, "normals")
    missing = np.linalg.norm(total, axis=1) <= 1e-9
    if refine_views and missing.any() and not missing.all():
        _, neighbours = tree.query(points[missing], k=min(16, len(points)), workers=-1)
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
    defined = known.copy()
    loose = np.flatnonzero(~known)
    if len(loose):  # a plane through the nearest points, its side taken from the triangulated ones
        _, neighbours = tree.query(points[loose], k=min(_FIT_NEIGHBOURS, len(points)), workers=-1)
        neighbours = neighbours.reshape(len(loose), -1)
        normals[loose], defined[loose] = fit_planes(points, neighbours)
    return complete_orientation(points, normals, known, defined, tree)


def _covisible_path(points: np.ndarray, method, cameras: np.ndarray, refine_views: int, search_param,
                    tree: cKDTree, progress: bool) -> np.ndarray:
    """:func:`multiview_normals` with ``search_param``: co-visible planes, oriented by the views."""
    from tqdm import tqdm

    with tqdm(total=3, disable=not progress, desc="normals", unit="step") as bar:
        bar.set_postfix_str("visibility")
        neighbours = neighbourhoods(points, search_param, tree)
        visibility = method(points, cameras)
        bar.update()
        bar.set_postfix_str("planes")
        normals, fitted = covisible_normals(points, visibility, neighbours)
        if not fitted.any():
            raise ValueError("no point has three neighbours off one line to fit a plane to: the "
                             "points are too few, all on one line, or the search radius too small")
        bar.update()
        bar.set_postfix_str("orientation")
        normals = _orient(points, normals, fitted, method, cameras, visibility, refine_views, tree)
        bar.update()
    return normals


def estimate_normals_neural(pcd, search_param=None, num_views: int = 26, model=None, *, refine_views: int = 0,
                            edge_factor: float = DEFAULT_EDGE_FACTOR, progress: bool = False):
    """Estimates oriented normals from visibility, in place, like ``pcd.estimate_normals()``.

    Cameras sit on a Fibonacci sphere of radius = bounding-box diagonal around
    the cloud. Normals face the cameras that see their points, so they point
    out of closed surfaces with no ``orient_normals_*`` step.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor); its normals are replaced.
        search_param: None to triangulate what each camera sees, or
            ``o3d.geometry.KDTreeSearchParamKNN(knn)`` /
            ``KDTreeSearchParamHybrid(radius, max_nn)`` (Open3D's first argument
            of ``estimate_normals``): fit each normal to the neighbours this
            search finds, as ``pcd.estimate_normals(search_param)`` does, but
            weighting each by the share of the point's views that see it too,
            then orient it towards the cameras that see it. Faster than
            triangulating, slightly less accurate (``docs/results.md`` measures both).
        num_views: number of cameras.
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        refine_views: more cameras for the points the first ``num_views`` leave
            without a triangle (default 0: none, their side is propagated from
            the others); those points and their neighbours alone are asked
            about and triangulated again.
        edge_factor: triangles with an edge longer than this many local point
            spacings are dropped (they bridge gaps or depth jumps).
        progress: show progress bars.

    Returns:
        ``pcd``, with unit normals set.

    Raises:
        TypeError: ``search_param`` is not None nor an Open3D KNN or hybrid
            search parameter (e.g. a number of views given where Open3D's
            ``search_param`` comes first).
    """
    if search_param is not None and not isinstance(
            search_param, (o3d.geometry.KDTreeSearchParamKNN, o3d.geometry.KDTreeSearchParamHybrid)):
        raise TypeError("search_param, the first argument after the cloud as in Open3D's estimate_normals, must "
                        "be None, KDTreeSearchParamKNN or KDTreeSearchParamHybrid, got "
                        f"{type(search_param).__name__} (give num_views= and model= by name)")
    points = cloud_points(pcd)
    cloud_normals(pcd)  # only clouds can take normals
    set_cloud_normals(pcd, multiview_normals(points, model, num_views, refine_views, edge_factor, progress,
                                             search_param))
    return pcd


def _check_views(num_views: int, refine_views: int) -> None:
    if num_views < 1 or refine_views < 0:
        raise ValueError(f"num_views must be at least 1 and refine_views at least 0, got "
                         f"{num_views} and {refine_views}")


def orient_normals_neural(pcd, num_views: int = 26, model=None, *, refine_views: int = 0):
    """Flips the normals a cloud already has to face the cameras that see their points.

    Each point's orientation is voted by the cameras that see it, weighted by
    the cosine between the normal and the direction to the camera; points that
    no camera sees take the side propagated along the surface from the voted
    ones, as ``orient_normals_consistent_tangent_plane`` propagates it.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor) with normals.
        num_views: number of cameras on a sphere of radius = bounding-box diagonal.
        model: the visibility source (default: the pretrained neural network); see
            :func:`o3dvis.methods.resolve_method`.
        refine_views: more cameras asked about the points the first ones do not
            see (0: none).

    Returns:
        ``pcd``, with its normals oriented in place.
    """
    points = cloud_points(pcd)
    normals = cloud_normals(pcd)
    if normals is None or len(normals) != len(points):
        raise ValueError("the point cloud has no normals to orient: call estimate_normals first")
    _check_views(num_views, refine_views)
    method = resolve_method(model)
    cameras = viewpoints_around(points, num_views)
    normals = np.array(normals, dtype=np.float64)
    set_cloud_normals(pcd, _orient(points, normals, np.ones(len(points), dtype=bool), method, cameras,
                              method(points, cameras), refine_views, None))
    return pcd


def _orient(points: np.ndarray, normals: np.ndarray, defined: np.ndarray, method, cameras: np.ndarray,
            visibility: np.ndarray, refine_views: int, tree: cKDTree | None) -> np.ndarray:
    """``normals`` flipped to face the cameras that see their points, (N, 3).

    ``refine_views`` more cameras vote on the points the first ones do not see;
    the side of the others is propagated from them (:func:`complete_orientation`). Where
    ``defined`` is False the normal is replaced by the nearest voted defined point's.
    """
    votes = vote(points, normals, cameras, visibility)
    if refine_views and (votes == 0).any():
        unseen = votes == 0
        cameras = viewpoints_around(points, refine_views)
        votes[unseen] = vote(points[unseen], normals[unseen], cameras,
                             method(points, cameras, np.flatnonzero(unseen)))
    return orient_by_vote(points, normals, defined, votes, tree)
