"""Point cloud inputs and conversions: legacy and tensor Open3D clouds, numpy and torch arrays."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from torch import Tensor

from .cameras import as_vectors, is_open3d, require_open3d

if TYPE_CHECKING:
    import open3d as o3d

__all__ = ["Cloud", "cloud_arrays", "cloud_points", "cloud_normals", "set_cloud_normals", "legacy_cloud",
           "cloud_device", "unit_normals"]


class Cloud(NamedTuple):
    """A cloud's checked points and normals as (N, 3) float64 tensors (normals None: none).

    What :func:`cloud_arrays` makes of any cloud, once; every function that takes a cloud
    takes a ``Cloud`` as it is.
    """

    points: Tensor
    normals: Tensor | None

    def crop(self, rows: Tensor) -> "Cloud":
        """The cloud of the points ``rows`` (a long tensor) alone, with their normals."""
        normals = None if self.normals is None else self.normals.index_select(0, rows.to(self.normals.device))
        return Cloud(self.points.index_select(0, rows.to(self.points.device)), normals)


def cloud_arrays(pcd) -> Cloud:
    """Points and normals (when the cloud has them) of a cloud, as float64 tensors.

    Args:
        pcd: ``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud``, an
            (N, 3) numpy array / torch tensor / ``o3d.core.Tensor`` of points, or
            a :class:`Cloud` (returned as it is).

    Returns:
        The :class:`Cloud`: (N, 3) float64 tensors on the cloud's device;
        ``normals`` is None when the cloud has none (always for arrays).

    Raises:
        TypeError: an unsupported type or non-real dtype.
        ValueError: an empty cloud, a wrong shape, NaN or Inf coordinates.
    """
    if isinstance(pcd, Cloud):
        return pcd
    normals = None
    if is_open3d(pcd, "geometry.PointCloud"):
        points = np.asarray(pcd.points)
        if pcd.has_normals():
            normals = np.asarray(pcd.normals)
    elif is_open3d(pcd, "t.geometry.PointCloud"):
        if pcd.is_empty():
            raise ValueError("point cloud is empty")
        points = pcd.point.positions
        if "normals" in pcd.point:
            normals = pcd.point.normals
    elif isinstance(pcd, (np.ndarray, Tensor)) or is_open3d(pcd, "core.Tensor"):
        points = pcd
    else:
        raise TypeError(f"expected an Open3D PointCloud or an (N, 3) array, got {type(pcd).__name__}")
    shape = tuple(points.shape)
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {shape}")
    if shape[0] == 0:
        raise ValueError("point cloud is empty")
    points = as_vectors(points, "points")
    return Cloud(points, None if normals is None else as_vectors(normals, "normals").to(points.device))


def cloud_points(pcd) -> np.ndarray:
    """The (N, 3) float64 numpy points of a cloud (see :func:`cloud_arrays`)."""
    return cloud_arrays(pcd)[0].cpu().numpy()


def legacy_cloud(pcd) -> o3d.geometry.PointCloud:
    """The legacy PointCloud of a legacy or tensor one."""
    if is_open3d(pcd, "t.geometry.PointCloud"):
        return pcd.to_legacy()
    if is_open3d(pcd, "geometry.PointCloud"):
        return pcd
    raise TypeError(f"expected an open3d PointCloud, got {type(pcd).__name__}")


def cloud_normals(pcd) -> np.ndarray | None:
    """The cloud's (N, 3) float64 normals, None when it has none; TypeError for anything but a PointCloud."""
    if is_open3d(pcd, "geometry.PointCloud"):
        return np.asarray(pcd.normals) if pcd.has_normals() else None
    if is_open3d(pcd, "t.geometry.PointCloud"):
        return pcd.point.normals.numpy().astype(np.float64) if "normals" in pcd.point else None
    raise TypeError(f"expected an open3d PointCloud, got {type(pcd).__name__}")


def set_cloud_normals(pcd, normals: np.ndarray) -> None:
    """Sets the normals of a legacy or tensor cloud (in the dtype of a tensor cloud's positions)."""
    o3d = require_open3d("setting a cloud's normals")
    if isinstance(pcd, o3d.geometry.PointCloud):
        pcd.normals = o3d.utility.Vector3dVector(normals)
    else:
        dtype = pcd.point.positions.dtype
        pcd.point.normals = o3d.core.Tensor(normals.astype(np.float32 if dtype == o3d.core.float32
                                                           else np.float64))


def unit_normals(normals, num_points: int) -> Tensor:
    """Checks (N, 3) normals and scales them to unit length.

    Args:
        normals: array-like of shape (num_points, 3).
        num_points: number of points of the cloud.

    Returns:
        (N, 3) float64 tensor of unit vectors.

    Raises:
        ValueError: wrong shape, NaN/Inf or zero-length normals.
        TypeError: non-real dtype.
    """
    normals = as_vectors(normals, "normals")
    if normals.shape[0] != num_points:
        raise ValueError(f"normals must have shape ({num_points}, 3), got {tuple(normals.shape)}")
    length = normals.norm(dim=1, keepdim=True)
    if (length == 0).any():
        raise ValueError(f"{int((length == 0).sum())} normals have zero length")
    return normals / length


def cloud_device(pcd) -> torch.device:
    """The torch device where a cloud's data lives (CPU for legacy clouds and numpy)."""
    if isinstance(pcd, Tensor):
        return pcd.device
    tensor = pcd.point.positions if is_open3d(pcd, "t.geometry.PointCloud") and not pcd.is_empty() else pcd
    if is_open3d(tensor, "core.Tensor") and tensor.device.get_type().name == "CUDA":
        return torch.device("cuda", tensor.device.get_id())
    return torch.device("cpu")
