"""Open3D drop-ins: neural hidden point removal with Open3D's signature, and visible subsets.

``_, pt_map = pcd.hidden_point_removal(camera, radius)`` becomes
``_, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, radius)``;
:func:`register` also makes it a method of Open3D's point clouds.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from . import encodings
from .cameras import Views, as_views
from .clouds import cloud_arrays, cloud_device, unit_normals
from .field import checked_range
from .geometry import diagonal, within_range
from .models import torch_device
from .pretrained import resolve_model

__all__ = ["hidden_point_removal_neural", "select_visible", "register", "RadiusError"]

_FAR = 1e6  # an orthographic view's triangulating camera, in extents of the visible points


class RadiusError(ValueError, RuntimeError):
    """A radius Open3D's ``hidden_point_removal`` refuses: a ``ValueError``, as this package's
    bad values raise, and a ``RuntimeError``, as Open3D raises it, so either ``except`` catches it."""


def _one_view(camera_location, direction, frustum: bool) -> Views:
    """The one view of a drop-in's camera, in any form :func:`~o3dvis.cameras.as_views` takes."""
    views = as_views(camera_location, direction, frustum=frustum)
    if len(views) != 1:
        raise ValueError(f"give one camera, got {len(views)}: the drop-ins answer one view, as Open3D's "
                         f"signature does; NeuralVisibility.encode(pcd).query(cameras) answers a batch "
                         f"from one encoding")
    return views


def _visible_indices(pcd, views: Views, threshold: float, model, device, normals,
                     max_range: float | None = None, quality: str = "fast") -> np.ndarray:
    """Sorted int64 indices of the points of ``pcd`` visible from the one view ``views``.

    With ``max_range``, only the points within it of the camera are encoded and
    answered (the octree's cells then fit the crop, not the whole cloud)."""
    max_range = checked_range(max_range)
    device = torch_device(device) if device is not None else cloud_device(pcd)
    model = resolve_model(model, device)
    if max_range is None:
        field = encodings.encode(model, pcd, normals, views, quality)
        return np.flatnonzero(field.query(views, threshold=threshold)[0]).astype(np.int64)
    if views.positions is None:
        raise ValueError("max_range needs a camera position, not a viewing direction")
    cloud = cloud_arrays(pcd)
    near = within_range(cloud.points, views.positions[0].detach().to(cloud.points.device), max_range)
    if len(near) == 0:
        return np.zeros(0, dtype=np.int64)
    if normals is not None and not isinstance(normals, (bool, str)):  # explicit normals: those of the crop
        normals = unit_normals(normals, len(cloud.points)).index_select(0, near.to(cloud.points.device))
    field = model.encode(cloud.crop(near), normals, views=views, quality=quality)
    return near.cpu().numpy()[np.flatnonzero(field.query(views, threshold=threshold)[0])].astype(np.int64)


def _surface_triangles(vertices: np.ndarray, views: Views) -> np.ndarray:
    """Triangles over ``vertices`` as the one view sees them, facing it (see :mod:`.apps.triangulation`).

    An orthographic view is triangulated from a camera ``_FAR`` times the vertices' extent away
    along its direction, whose perspective differs from the parallel projection by about its inverse."""
    from .apps.triangulation import DEFAULT_EDGE_FACTOR, local_spacing, visible_triangles

    if views.positions is not None:
        camera = views.positions[0].detach().cpu().numpy()
    elif len(vertices) < 3:  # no triangle
        return np.zeros((0, 3), dtype=np.int64)
    else:  # a zero extent (coincident points) has no triangle either: any distance will do
        extent = diagonal(vertices) or 1.0
        camera = vertices.mean(axis=0) - _FAR * extent * views.directions[0].detach().cpu().numpy()
    return visible_triangles(vertices, camera, np.arange(len(vertices)),
                             DEFAULT_EDGE_FACTOR * local_spacing(vertices))


def _checked_radius(radius) -> None:
    """Refuses what Open3D's ``hidden_point_removal`` refuses: a radius that is not a positive,
    finite number (None: not given)."""
    if radius is None:
        return
    if isinstance(radius, bool) or not isinstance(radius, (int, float, np.integer, np.floating)):
        raise TypeError(f"radius must be a number, got {type(radius).__name__}")
    if not 0 < radius < np.inf:
        raise RadiusError(f"radius must be larger than zero and finite, as Open3D's hidden_point_removal "
                          f"requires, got {radius}")


def hidden_point_removal_neural(pcd, camera_location=None, radius: float | None = None, *,
                                direction=None, threshold: float = 0.5, model=None, device=None,
                                triangulate: bool = False, max_range: float | None = None, normals=None,
                                frustum: bool = True, quality: str = "fast"):
    """Removes hidden points with the neural network: a drop-in for ``hidden_point_removal``.

    Returns what Open3D's ``PointCloud.hidden_point_removal`` returns, so
    ``mesh, pt_map = pcd.hidden_point_removal(camera, radius)`` can become
    ``mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, radius)``.
    The mesh's vertices are exactly ``points[pt_map]``. By default it has no
    triangles (most callers use only ``pt_map``, and triangulating costs about
    as much as the visibility query); with ``triangulate=True`` its triangles
    are the surface the camera sees: a Delaunay triangulation of those points
    in the image plane without the triangles whose edges are much longer than
    the local point spacing, ordered counter-clockwise as seen from the camera
    (none when fewer than 3 points are visible or they project onto a line). Unlike Open3D, ``pt_map`` is sorted.
    With the shipped models, point normals are used when the cloud has them
    and they face out (unoriented ones are estimated anew, with a warning);
    ``normals="estimate"`` estimates oriented normals in a first pass instead
    (more accurate on dense, clean clouds; see :meth:`NeuralVisibility.encode`).
    ``quality`` trades time for accuracy in one word: ``"fast"`` (default) one
    pass, ``"balanced"`` two passes over a cloud without normals where they pay,
    ``"best"`` those and four turned copies of the cloud.
    Called again with the same, unchanged cloud (another camera), it reuses the
    cloud's encoding (see :mod:`o3dvis.encodings`) and costs a query only.

    The camera takes the forms :func:`select_visible` and :meth:`VisibilityField.query`
    take, but one view only: Open3D's signature returns one ``(mesh, pt_map)``, and a
    list of them for a batch would change the result's type with the input's shape.
    For several cameras, ``NeuralVisibility.encode(pcd).query(cameras)`` answers them
    all from one encoding (a loop over this function also encodes once).

    Args:
        pcd: ``o3d.geometry.PointCloud`` or ``o3d.t.geometry.PointCloud``.
        camera_location: one camera position, (3,) or (1, 3) (list, tuple, numpy,
            torch or ``o3d.core.Tensor``), anywhere but on a point of the cloud:
            outside it, or inside a room, a street or a scan; or one
            ``o3d.camera.PinholeCameraParameters`` (with an image size, the
            points outside the image are dropped too). None with ``direction``.
        radius: unused; accepted so that existing calls work unchanged. As in
            Open3D, it must be positive and finite when given.
        direction: instead of ``camera_location``, the (3,) viewing direction of
            an orthographic view; its triangles face that direction.
        threshold: a point is visible when its probability exceeds this.
        model: None (the shipped default), a model name or checkpoint path, a
            :class:`NeuralVisibility` or a ``VisibilityNetwork``.
        device: torch device, e.g. ``"cuda"`` (default: where the cloud lives, else CPU).
        triangulate: also triangulate the visible surface (see above).
        max_range: only the points within this distance of the camera are
            considered (as a LiDAR's range): the others are not visible and hide
            nothing; None: all points.
        normals: as in :meth:`NeuralVisibility.encode`: None (default) uses
            the cloud's normals if it has them and they face out; ``"estimate"`` estimates
            oriented normals in a first pass where that is more accurate;
            False ignores normals.
        frustum: False ignores the image bounds of a pinhole camera.
        quality: ``"fast"`` (default), ``"balanced"`` or ``"best"``, as in
            :meth:`NeuralVisibility.encode`.

    Returns:
        ``(mesh, pt_map)``: for a legacy cloud an ``o3d.geometry.TriangleMesh``
        and a ``list[int]``; for a tensor cloud an ``o3d.t.geometry.TriangleMesh``
        and an Int64 ``o3d.core.Tensor``.

    Raises:
        ValueError: an empty cloud, NaN/Inf, a camera on a point of the cloud,
            more than one camera, both or neither of a camera and a direction,
            a max_range that is not positive, an unknown quality.
        RadiusError: a radius that is not positive and finite (a ``ValueError``
            and, as Open3D raises, a ``RuntimeError``).
        TypeError: ``pcd`` is not an Open3D PointCloud, or bad dtypes.
        FileNotFoundError: no installed model and no ``model`` given.
    """
    if not isinstance(pcd, (o3d.geometry.PointCloud, o3d.t.geometry.PointCloud)):
        raise TypeError(f"pcd must be an Open3D PointCloud (legacy or tensor), got {type(pcd).__name__}")
    _checked_radius(radius)
    views = _one_view(camera_location, direction, frustum)
    index = _visible_indices(pcd, views, threshold, model, device, normals, max_range, quality)
    return _hpr_result(pcd, index, views if triangulate else None)


def _hpr_result(pcd, index: np.ndarray, views: Views | None):
    """What Open3D's ``hidden_point_removal`` returns for the visible points ``index`` of ``pcd``,
    with the triangles of :func:`_surface_triangles` for ``views`` (None: no triangles)."""
    triangulate = views is not None
    if isinstance(pcd, o3d.geometry.PointCloud):
        vertices = np.asarray(pcd.points)[index]
        mesh = o3d.geometry.TriangleMesh()
        mesh.vertices = o3d.utility.Vector3dVector(vertices)
        if triangulate:
            mesh.triangles = o3d.utility.Vector3iVector(_surface_triangles(vertices, views))
        return mesh, index.tolist()
    positions = pcd.point.positions
    pt_map = o3d.core.Tensor(index, dtype=o3d.core.Dtype.Int64, device=positions.device)
    mesh = o3d.t.geometry.TriangleMesh(positions.device)
    mesh.vertex.positions = positions[pt_map]
    if triangulate:
        triangles = _surface_triangles(mesh.vertex.positions.cpu().numpy().astype(np.float64), views)
        mesh.triangle.indices = o3d.core.Tensor(triangles, dtype=o3d.core.Dtype.Int64,
                                                device=positions.device)
    return mesh, pt_map


def select_visible(pcd, camera=None, *, direction=None, threshold: float = 0.5, model=None,
                   device=None, normals=None, frustum: bool = True, max_range: float | None = None,
                   quality: str = "fast"):
    """The points of a cloud that one camera sees, as a point cloud.

    Colours, normals and every other per-point attribute are kept. Like
    :func:`hidden_point_removal_neural`, it reuses the encoding of the same,
    unchanged cloud asked again.

    Args:
        pcd: ``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud``, or an
            (N, 3) numpy array / torch tensor of points.
        camera: one camera position (3,) or ``o3d.camera.PinholeCameraParameters``
            (with an image size, points outside the image are dropped too).
        direction: instead of ``camera``, the (3,) viewing direction of an
            orthographic view.
        threshold: a point is visible when its probability exceeds this.
        model: None (the shipped default), a model name or checkpoint path, a
            :class:`NeuralVisibility` or a ``VisibilityNetwork``.
        device: torch device (default: where the cloud lives, else CPU).
        normals: as in :meth:`NeuralVisibility.encode`.
        frustum: False ignores the image bounds of a pinhole camera.
        max_range: only the points within this distance of the camera are
            considered; None: all points. Camera positions only.
        quality: ``"fast"`` (default), ``"balanced"`` or ``"best"``, as in
            :meth:`NeuralVisibility.encode`.

    Returns:
        A cloud of the same kind as ``pcd`` (a legacy ``PointCloud`` for arrays)
        holding the visible points in their original order.

    Raises:
        ValueError: an empty cloud, NaN/Inf, a camera on a point of the cloud,
            more than one camera, a max_range that is not positive or given with a direction,
            an unknown quality.
        TypeError: unsupported input types or dtypes.
    """
    views = _one_view(camera, direction, frustum)
    index = _visible_indices(pcd, views, threshold, model, device, normals, max_range, quality)
    if isinstance(pcd, o3d.geometry.PointCloud):
        return pcd.select_by_index(index.tolist())
    if isinstance(pcd, o3d.t.geometry.PointCloud):
        device = pcd.point.positions.device
        return pcd.select_by_index(o3d.core.Tensor(index, dtype=o3d.core.Dtype.Int64, device=device))
    points, _ = cloud_arrays(pcd)
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.detach().cpu().numpy()[index]))


def register() -> None:
    """Adds ``hidden_point_removal_neural`` as a method of Open3D's point clouds.

    Open3D's pybind11 classes accept new Python attributes, so after this call
    ``pcd.hidden_point_removal_neural(camera_location, radius)`` works on both
    ``o3d.geometry.PointCloud`` and ``o3d.t.geometry.PointCloud``.
    """
    for cls in (o3d.geometry.PointCloud, o3d.t.geometry.PointCloud):
        cls.hidden_point_removal_neural = hidden_point_removal_neural
