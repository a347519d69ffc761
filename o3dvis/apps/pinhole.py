"""Pinhole views for renders and shadow maps: a camera that projects points to pixels, framed
to a cloud from a camera given the ways Open3D users give one.

Conventions follow Open3D (see :mod:`o3dvis.cameras`): an extrinsic is the 4x4 world-to-camera
matrix with x to the right, y down and z forward; an intrinsic is the 3x3 pinhole matrix with
the centre of pixel (row, col) at (u, v) = (col, row).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..cameras import Frustum, as_camera_location, frustum_from_pinhole, intrinsic_matrix, is_open3d, require_open3d
from ..geometry import bounds

__all__ = ["PinholeView", "make_view", "look_at", "camera_location_of", "MAX_PIXELS"]

MAX_PIXELS = 1 << 28
"""The most pixels an image of :func:`make_view` may have (16384 x 16384): a render's per-pixel buffers
(the point each pixel shows, its depth, its colour in float64) take some 40 bytes a pixel, 10 GiB here."""
_PIXEL_BYTES = 40


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
class PinholeView(Frustum):
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


def camera_location_of(camera) -> np.ndarray:
    """The position of a camera given as a (3,) location, a 4x4 extrinsic or PinholeCameraParameters."""
    return _extrinsic_of(camera)[0]


def _extrinsic_of(camera) -> tuple[np.ndarray, np.ndarray | None, Frustum | None]:
    """(location, extrinsic or None for a bare location, pinhole frustum or None)."""
    if is_open3d(camera, "camera.PinholeCameraParameters"):
        location, frustum = frustum_from_pinhole(camera)
        return location.numpy(), np.asarray(camera.extrinsic, dtype=np.float64), frustum
    if isinstance(camera, (list, tuple, np.ndarray)) and np.shape(camera) == (4, 4):
        params = require_open3d("a camera given as an extrinsic").camera.PinholeCameraParameters()
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
              intrinsic=None, up=None, margin: float = 0.05) -> PinholeView:
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
        A :class:`PinholeView`.

    Raises:
        ValueError: a width or height below 1, or more than :data:`MAX_PIXELS` pixels.
    """
    location, extrinsic, frustum = _extrinsic_of(camera)
    if extrinsic is None:
        lo, hi = bounds(points)
        extrinsic = look_at(location, (lo + hi) / 2, up)
    if intrinsic is None and frustum is not None:
        intrinsic, width, height = frustum.intrinsic, frustum.width, frustum.height
    if is_open3d(intrinsic, "camera.PinholeCameraIntrinsic"):
        width, height = intrinsic.width, intrinsic.height
    if width is None or height is None or int(width) < 1 or int(height) < 1:
        raise ValueError(f"the image needs a positive width and height, got {width} x {height}")
    width, height = int(width), int(height)
    if width * height > MAX_PIXELS:
        raise ValueError(f"a {width} x {height} image has {width * height} pixels, more than the {MAX_PIXELS} "
                         f"(16384 x 16384) an image may have: its buffers alone would need "
                         f"{width * height * _PIXEL_BYTES / 2**30:.3g} GiB")
    if intrinsic is None:
        cam = points @ extrinsic[:3, :3].T + extrinsic[:3, 3]
        intrinsic = _fit_intrinsic(cam, width, height, margin)
    return PinholeView(extrinsic, intrinsic_matrix(intrinsic), width, height)
