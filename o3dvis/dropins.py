"""Open3D drop-ins: neural hidden point removal with Open3D's signature, and visible subsets.

``_, pt_map = pcd.hidden_point_removal(camera, radius)`` becomes
``_, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, radius)``;
:func:`register` also makes it a method of Open3D's point clouds.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import torch

from . import encodings
from .cameras import as_camera_location, as_views
from .clouds import cloud_arrays, cloud_device
from .field import checked_range
from .geometry import lengths
from .models import torch_device
from .pretrained import resolve_model

__all__ = ["hidden_point_removal_neural", "select_visible", "register"]


def _visible_indices(pcd, cameras, direction, threshold: float, model, device, normals,
                     frustum: bool = True, max_range: float | None = None) -> np.ndarray:
    """Sorted int64 indices of the points of ``pcd`` visible from one view.

    With ``max_range``, only the points within it of the camera are encoded and
    answered (the octree's cells then fit the crop, not the whole cloud)."""
    views = as_views(cameras, direction, frustum=frustum)
    if len(views) != 1:
        raise ValueError(f"give one camera, got {len(views)}")
    max_range = checked_range(max_range)
    device = torch_device(device) if device is not None else cloud_device(pcd)
    model = resolve_model(model, device)
    camera = None if views.positions is None else views.positions[0]
    if max_range is None:
        field = encodings.encode(model, pcd, normals, camera)
        return np.flatnonzero(field.query(views, threshold=threshold)[0]).astype(np.int64)
    if views.positions is None:
        raise ValueError("max_range needs a camera position, not a viewing direction")
    points, cloud_normals = cloud_arrays(pcd)
    estimate = isinstance(normals, str)  # "estimate": estimated on the crop (encode checks the value)
    _, unit = model._network_and_normals(cloud_normals, False if estimate else normals, points.shape[0])
    camera = camera.detach().to(points.device)
    near = torch.nonzero(lengths(points - camera) <= max_range)[:, 0]
    if len(near) == 0:
        return np.zeros(0, dtype=np.int64)
    cropped = normals if estimate else False if unit is None else unit[near.to(unit.device)]
    field = model._encode(points[near], cropped, camera)
    return near.cpu().numpy()[np.flatnonzero(field.query(views, threshold=threshold)[0])].astype(np.int64)


def _surface_triangles(vertices: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """Triangles over ``vertices`` as the camera sees them, facing it (see :mod:`.apps.triangulation`)."""
    from .apps.triangulation import DEFAULT_EDGE_FACTOR, local_spacing, visible_triangles

    return visible_triangles(vertices, camera, np.arange(len(vertices)),
                             DEFAULT_EDGE_FACTOR * local_spacing(vertices))


def hidden_point_removal_neural(pcd, camera_location, radius: float | None = None, *,
                                threshold: float = 0.5, model=None, device=None, triangulate: bool = False,
                                max_range: float | None = None, normals=None):
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
    Called again with the same, unchanged cloud (another camera), it reuses the
    cloud's encoding (see :mod:`o3dvis.encodings`) and costs a query only.

    Args:
        pcd: ``o3d.geometry.PointCloud`` or ``o3d.t.geometry.PointCloud``.
        camera_location: (3,) camera position (list, tuple, numpy, torch or
            ``o3d.core.Tensor``), anywhere but on a point of the cloud: outside
            it, or inside a room, a street or a scan.
        radius: unused; accepted so that existing calls work unchanged.
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

    Returns:
        ``(mesh, pt_map)``: for a legacy cloud an ``o3d.geometry.TriangleMesh``
        and a ``list[int]``; for a tensor cloud an ``o3d.t.geometry.TriangleMesh``
        and an Int64 ``o3d.core.Tensor``.

    Raises:
        ValueError: an empty cloud, NaN/Inf, a camera on a point of the cloud,
            a camera that is not one position, a max_range that is not positive.
        TypeError: ``pcd`` is not an Open3D PointCloud, or bad dtypes.
        FileNotFoundError: no installed model and no ``model`` given.
    """
    if not isinstance(pcd, (o3d.geometry.PointCloud, o3d.t.geometry.PointCloud)):
        raise TypeError(f"pcd must be an Open3D PointCloud (legacy or tensor), got {type(pcd).__name__}")
    eye = as_camera_location(camera_location)
    index = _visible_indices(pcd, eye, None, threshold, model, device, normals, max_range=max_range)
    if isinstance(pcd, o3d.geometry.PointCloud):
        vertices = np.asarray(pcd.points)[index]
        mesh = o3d.geometry.TriangleMesh()
        mesh.vertices = o3d.utility.Vector3dVector(vertices)
        if triangulate:
            mesh.triangles = o3d.utility.Vector3iVector(_surface_triangles(vertices, eye))
        return mesh, index.tolist()
    positions = pcd.point.positions
    pt_map = o3d.core.Tensor(index, dtype=o3d.core.Dtype.Int64, device=positions.device)
    mesh = o3d.t.geometry.TriangleMesh(positions.device)
    mesh.vertex.positions = positions[pt_map]
    if triangulate:
        triangles = _surface_triangles(mesh.vertex.positions.cpu().numpy().astype(np.float64), eye)
        mesh.triangle.indices = o3d.core.Tensor(triangles, dtype=o3d.core.Dtype.Int64,
                                                device=positions.device)
    return mesh, pt_map


def select_visible(pcd, camera=None, *, direction=None, threshold: float = 0.5, model=None,
                   device=None, normals=None, frustum: bool = True, max_range: float | None = None):
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

    Returns:
        A cloud of the same kind as ``pcd`` (a legacy ``PointCloud`` for arrays)
        holding the visible points in their original order.

    Raises:
        ValueError: an empty cloud, NaN/Inf, a camera on a point of the cloud,
            more than one camera, a max_range that is not positive or given with a direction.
        TypeError: unsupported input types or dtypes.
    """
    index = _visible_indices(pcd, camera, direction, threshold, model, device, normals, frustum, max_range)
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
