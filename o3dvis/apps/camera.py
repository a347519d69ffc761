"""Pinhole views of a point cloud: camera frames, projection, viewpoints around a cloud.

Conventions follow Open3D: an extrinsic is the 4x4 world-to-camera matrix with
x to the right, y down and z forward; an intrinsic is the 3x3 pinhole matrix
with the centre of pixel (row, col) at (u, v) = (col, row).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from ..cameras import Frustum, as_vectors, frustum_from_pinhole
from ..clouds import cloud_arrays

__all__ = ["View", "make_view", "look_at", "fibonacci_sphere", "viewpoints_around",
           "cloud_points", "legacy_cloud", "as_camera_location", "camera_location_of"]


def cloud_points(pcd) -> np.ndarray:
    """The (N, 3) float64 numpy points of a cloud (see :func:`o3dvis.clouds.cloud_arrays`)."""
    return cloud_arrays(pcd)[0].cpu().numpy()


def legacy_cloud(pcd) -> o3d.geometry.PointCloud:
    """The legacy PointCloud of a legacy or tensor one."""
    if isinstance(pcd, o3d.t.geometry.PointCloud):
        return pcd.to_legacy()
    if isinstance(pcd, o3d.geometry.PointCloud):
        return pcd
    raise TypeError(f"expected an open3d PointCloud, got {type(pcd).__name__}")


def as_camera_location(camera, name: str = "camera_location") -> np.ndarray:
    """One finite position, (3,) float64 (any array-like, torch or ``o3d.core.Tensor``)."""
    location = as_vectors(camera, name)
    if location.shape[0] != 1:
        raise ValueError(f"{name} must be one position of shape (3,), got {tuple(location.shape)}")
    return location[0].detach().cpu().numpy()


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` nearly evenly spread unit vectors (a Fibonacci lattice), (count, 3)."""
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = i * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def viewpoints_around(points: np.ndarray, count: int, distance: float | None = None) -> np.ndarray:
    """Camera positions on a Fibonacci sphere around the bounding-box centre.

    Args:
        points: (N, 3) points.
        count: number of viewpoints.
        distance: distance from the centre (default: the bounding-box diagonal,
            the distance the visibility network is trained at).

    Returns:
        (count, 3) positions.
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    if distance is None:
        distance = float(np.linalg.norm(hi - lo))
    if not distance > 0:
        raise ValueError("the points span no volume: viewpoints need a positive distance")
    return (lo + hi) / 2 + distance * fibonacci_sphere(count)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """The 4x4 world-to-camera extrinsic of a camera at ``eye`` looking at ``target``.

    ``up`` (default +z, or +y when looking along z) points up in the image.
    """
    forward = np.asarray(target, np.float64) - eye
    norm = np.linalg.norm(forward)
    if norm == 0:
        raise ValueError("the camera is at the point it looks at")
    forward /= norm
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, np.float64)
    if np.linalg.norm(np.cross(forward, up)) < 1e-6 * np.linalg.norm(up):
        up = np.array([0.0, 1.0, 0.0]) if abs(forward[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    extrinsic = np.eye(4)
    extrinsic[:3, :3] = np.stack([right, np.cross(forward, right), forward])
    extrinsic[:3, 3] = -extrinsic[:3, :3] @ eye
    return extrinsic


@dataclass(frozen=True)
class View(Frustum):
    """A pinhole camera (extrinsic, intrinsic, image size) that projects and renders world points."""

    @property
    def location(self) -> np.ndarray:
        """The camera centre in world coordinates."""
        rotation, translation = self.extrinsic[:3, :3], self.extrinsic[:3, 3]
        return -rotation.T @ translation

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points in camera coordinates (z = depth along the optical axis)."""
        return points @ self.extrinsic[:3, :3].T + self.extrinsic[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) as (u, v) = (column, row) and depths (N,).

        Points at or behind the camera get depth <= 0 and meaningless pixels.
        """
        cam = self.to_camera(points)
        depth = cam[:, 2]
        safe = np.where(depth > 0, depth, 1.0)
        k = self.intrinsic
        u = k[0, 0] * cam[:, 0] / safe + k[0, 1] * cam[:, 1] / safe + k[0, 2]
        v = k[1, 1] * cam[:, 1] / safe + k[1, 2]
        return np.stack([u, v], axis=1), depth

    def to_open3d(self) -> o3d.camera.PinholeCameraParameters:
        """The same camera as Open3D ``PinholeCameraParameters``."""
        params = o3d.camera.PinholeCameraParameters()
        k = self.intrinsic
        params.intrinsic = o3d.camera.PinholeCameraIntrinsic(
            self.width, self.height, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        params.extrinsic = self.extrinsic
        return params


def camera_location_of(camera) -> np.ndarray:
    """The position of a camera given as a (3,) location, a 4x4 extrinsic or PinholeCameraParameters."""
    return _extrinsic_of(camera)[0]


def _extrinsic_of(camera) -> tuple[np.ndarray, np.ndarray | None, Frustum | None]:
    """(location, extrinsic or None for a bare location, pinhole frustum or None)."""
    if isinstance(camera, o3d.camera.PinholeCameraParameters):
        location, frustum = frustum_from_pinhole(camera)
        return location.numpy(), np.asarray(camera.extrinsic, dtype=np.float64), frustum
    if isinstance(camera, (list, tuple, np.ndarray)) and np.shape(camera) == (4, 4):
        params = o3d.camera.PinholeCameraParameters()
        params.extrinsic = np.asarray(camera, dtype=np.float64)
        return frustum_from_pinhole(params)[0].numpy(), params.extrinsic, None
    return as_camera_location(camera, "camera"), None, None


def _fit_intrinsic(cam: np.ndarray, width: int, height: int, margin: float) -> np.ndarray:
    """A centred pinhole whose image holds every point in front of the camera."""
    front = cam[cam[:, 2] > 0]
    if len(front) == 0:
        raise ValueError("no point lies in front of the camera")
    half_u = np.abs(front[:, 0] / front[:, 2]).max()
    half_v = np.abs(front[:, 1] / front[:, 2]).max()
    extent = max(half_u / width, half_v / height, 1e-12)
    focal = 0.5 / (extent * (1 + margin))
    return np.array([[focal, 0, width / 2 - 0.5], [0, focal, height / 2 - 0.5], [0, 0, 1]])


def make_view(points: np.ndarray, camera, width: int | None = None, height: int | None = None,
              intrinsic=None, up=None, margin: float = 0.05) -> View:
    """A pinhole view of ``points`` from a camera given the ways Open3D users give one.

    Args:
        points: (N, 3) points to frame.
        camera: a (3,) camera location (looking at the bounding-box centre), a 4x4
            world-to-camera extrinsic, or ``o3d.camera.PinholeCameraParameters``.
        width, height: image size in pixels (taken from the intrinsic when one is given).
        intrinsic: ``o3d.camera.PinholeCameraIntrinsic`` or a 3x3 matrix (with
            ``width``/``height``); default: the tightest centred pinhole that frames
            the points, with ``margin`` to spare.
        up: the world direction shown upwards when ``camera`` is a location.
        margin: relative border around the framed points.

    Returns:
        A :class:`View`.
    """
    location, extrinsic, frustum = _extrinsic_of(camera)
    if extrinsic is None:
        lo, hi = points.min(axis=0), points.max(axis=0)
        extrinsic = look_at(location, (lo + hi) / 2, up)
    if intrinsic is None and frustum is not None:
        intrinsic, width, height = frustum.intrinsic, frustum.width, frustum.height
    if isinstance(intrinsic, o3d.camera.PinholeCameraIntrinsic):
        width, height = intrinsic.width, intrinsic.height
        intrinsic = np.asarray(intrinsic.intrinsic_matrix, dtype=np.float64)
    if width is None or height is None or int(width) < 1 or int(height) < 1:
        raise ValueError(f"the image needs a positive width and height, got {width} x {height}")
    width, height = int(width), int(height)
    if intrinsic is None:
        cam = points @ extrinsic[:3, :3].T + extrinsic[:3, 3]
        intrinsic = _fit_intrinsic(cam, width, height, margin)
    intrinsic = np.asarray(intrinsic, dtype=np.float64)
    if intrinsic.shape != (3, 3):
        raise ValueError(f"intrinsic must be 3x3, got {intrinsic.shape}")
    return View(extrinsic, intrinsic, width, height)
