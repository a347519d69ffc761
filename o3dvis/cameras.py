"""Cameras in every form Open3D users have, brought to one canonical form, and pinhole views.

A view is either a camera position (perspective) or a viewing direction
(orthographic). Positions come as a 3-vector or a ``(V, 3)`` batch (list,
tuple, numpy, torch, ``o3d.core.Tensor``) or as
``o3d.camera.PinholeCameraParameters`` (one, a list, or a
``PinholeCameraTrajectory``), whose intrinsic and image size also define a
frustum: points that project outside the image, or lie behind the camera, are
not visible.

Conventions follow Open3D: an extrinsic is the 4x4 world-to-camera matrix with
x to the right, y down and z forward; an intrinsic is the 3x3 pinhole matrix
with the centre of pixel (row, col) at (u, v) = (col, row). :class:`View` is a
pinhole camera that projects and renders; :func:`make_view` frames a cloud from a
camera given any of the ways Open3D users give one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ._open3d import is_open3d, require_open3d
from .geometry import bounds, box_diagonal, fibonacci_sphere

if TYPE_CHECKING:
    import open3d as o3d

__all__ = ["Frustum", "Views", "as_views", "as_vectors", "all_finite", "as_camera_location", "real_array",
           "frustum_from_pinhole", "intrinsic_matrix", "View", "make_view", "look_at", "fibonacci_sphere",
           "viewpoints_around", "camera_location_of", "MAX_PIXELS"]

_ORTHONORMAL_TOL = 1e-4
MAX_PIXELS = 1 << 28
"""The most pixels an image of :func:`make_view` may have (16384 x 16384): a render's per-pixel buffers
(the point each pixel shows, its depth, its colour in float64) take some 40 bytes a pixel, 10 GiB here."""
_PIXEL_BYTES = 40


@dataclass(frozen=True)
class Frustum:
    """The image of a pinhole camera: world-to-camera transform, intrinsic, image size.

    Attributes:
        extrinsic: (4, 4) world-to-camera matrix (Open3D convention: the camera
            looks along +z, x to the right, y down).
        intrinsic: (3, 3) intrinsic matrix.
        width: image width in pixels.
        height: image height in pixels.
    """

    extrinsic: np.ndarray
    intrinsic: np.ndarray
    width: int
    height: int

    def contains(self, points: Tensor, center: Tensor, scale: Tensor) -> Tensor:
        """Which points project into the image from in front of the camera.

        A pixel ``(i, j)`` covers ``[i - 0.5, i + 0.5)`` of the image plane, so a
        point is inside when its projection rounds to a pixel of the image.

        Args:
            points: (N, 3) points in normalised coordinates,
                ``world = points * scale + center``.
            center: (3,) float64 centre of the normalisation.
            scale: float64 scalar scale of the normalisation.

        Returns:
            (N,) bool tensor on the device of ``points``.
        """
        # x_cam = R (s x_n + c) + t = s (R x_n + (R c + t) / s): the scale changes
        # neither the sign of z nor the projected pixel, so work in normalised units, in float64,
        # where a camera any distance away still tells the points apart.
        rotation = torch.tensor(self.extrinsic[:3, :3], dtype=torch.float64, device=points.device)
        shift = (rotation @ center.to(points.device) + torch.as_tensor(
            self.extrinsic[:3, 3].copy(), dtype=torch.float64, device=points.device)) / scale
        k = torch.tensor(self.intrinsic, dtype=torch.float64, device=points.device)
        cam = points.double() @ rotation.T + shift
        uvw = cam @ k.T
        z = uvw[:, 2]
        front = cam[:, 2] > 0
        safe_z = torch.where(front, z, torch.ones_like(z))
        u, v = uvw[:, 0] / safe_z, uvw[:, 1] / safe_z
        return front & (u >= -0.5) & (u < self.width - 0.5) & (v >= -0.5) & (v < self.height - 0.5)


@dataclass(frozen=True)
class Views:
    """V viewpoints in world coordinates: positions or directions, not both.

    Attributes:
        positions: (V, 3) float64 camera positions (keeps autograd), or None.
        directions: (V, 3) float64 unit viewing directions (from the camera
            into the scene) of orthographic views, or None.
        frustums: one :class:`Frustum` or None (no culling) per view.
    """

    positions: Tensor | None
    directions: Tensor | None
    frustums: tuple[Frustum | None, ...]

    def __len__(self) -> int:
        return len(self.frustums)


def as_vectors(value, name: str = "camera") -> Tensor:
    """Converts a 3-vector or a (V, 3) batch to a (V, 3) float64 torch tensor.

    Torch tensors keep their device and autograd history, so a camera tensor
    with ``requires_grad`` stays differentiable.

    Args:
        value: list, tuple, numpy array, torch tensor or ``o3d.core.Tensor`` of
            real numbers, shape (3,) or (V, 3) with V >= 1.
        name: what the value is, for error messages.

    Returns:
        (V, 3) float64 tensor.

    Raises:
        TypeError: not an array-like of real numbers (bool, complex, strings...).
        ValueError: wrong shape, no vectors, NaN or Inf.
    """
    if is_open3d(value, "core.Tensor"):
        value = torch.utils.dlpack.from_dlpack(value.contiguous().to_dlpack())
    if isinstance(value, Tensor):
        if value.dtype == torch.bool or value.is_complex():
            raise TypeError(f"{name} must hold real numbers, got a torch tensor of {value.dtype}")
        tensor = value.to(torch.float64)
    else:
        tensor = torch.from_numpy(real_array(value, name, "a 3-vector or a (V, 3) array"))
    if tensor.ndim == 1:
        tensor = tensor[None]
    if tensor.ndim != 2 or tensor.shape[1] != 3:
        raise ValueError(f"{name} must have shape (3,) or (V, 3), got {tuple(np.shape(value))}")
    if tensor.shape[0] == 0:
        raise ValueError(f"{name} holds no vectors (shape (0, 3))")
    if not all_finite(tensor.detach()):
        raise ValueError(f"{name} has NaN or Inf coordinates")
    return tensor


def all_finite(tensor: Tensor) -> bool:
    """Whether every entry of ``tensor`` is finite.

    Its sum is finite only when every entry is (a NaN or an infinity makes it NaN or
    infinite), so one reduction settles most clouds; only a sum that overflows, or a
    cloud that is not finite, is checked entry by entry."""
    return bool(torch.isfinite(tensor.sum())) or bool(torch.isfinite(tensor).all())


def as_camera_location(camera, name: str = "camera_location") -> np.ndarray:
    """One finite position, (3,) float64 (any array-like, torch or ``o3d.core.Tensor``)."""
    location = as_vectors(camera, name)
    if location.shape[0] != 1:
        raise ValueError(f"{name} must be one position of shape (3,), got {tuple(location.shape)}")
    return location[0].detach().cpu().numpy()


def real_array(value, name: str, expected: str = "an array of numbers") -> np.ndarray:
    """Converts an array-like of real numbers to a float64 numpy array of any shape.

    Unlike ``np.asarray(value, dtype=np.float64)``, it refuses what is not a
    real number instead of casting it (bool, complex, strings, objects).

    Args:
        value: list, tuple, numpy array or anything ``np.asarray`` takes.
        name: what the value is, for error messages.
        expected: the shape expected, for the message on ragged sequences.

    Returns:
        float64 array.

    Raises:
        TypeError: not an array-like of real numbers.
        ValueError: ragged nested sequences.
    """
    try:
        array = np.asarray(value)
    except ValueError as e:  # ragged nested sequences
        raise ValueError(f"{name} must be {expected}: {e}") from None
    if array.dtype == bool or array.dtype.kind not in "iuf":
        raise TypeError(f"{name} must hold real numbers, got {type(value).__name__} of dtype {array.dtype}")
    return array.astype(np.float64)


def intrinsic_matrix(intrinsic) -> np.ndarray:
    """The checked 3x3 matrix of a pinhole intrinsic.

    Args:
        intrinsic: ``o3d.camera.PinholeCameraIntrinsic`` or a 3x3 matrix
            ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.

    Returns:
        (3, 3) float64 array.

    Raises:
        ValueError: not 3x3, not finite, not of that form, or a focal length
            that is not positive (a negative one turns the image by 180 degrees).
    """
    if is_open3d(intrinsic, "camera.PinholeCameraIntrinsic"):
        intrinsic = intrinsic.intrinsic_matrix
    k = real_array(intrinsic, "intrinsic", "a 3x3 matrix")
    if k.shape != (3, 3) or not np.isfinite(k).all():
        raise ValueError(f"the intrinsic must be a finite 3x3 matrix, got shape {k.shape}")
    if k[1, 0] != 0 or not np.array_equal(k[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"the intrinsic must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {k.tolist()}")
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise ValueError(f"the intrinsic's focal lengths must be positive, got fx={k[0, 0]:g}, fy={k[1, 1]:g}")
    return k


def frustum_from_pinhole(params: o3d.camera.PinholeCameraParameters) -> tuple[Tensor, Frustum | None]:
    """Camera position and frustum of ``PinholeCameraParameters``.

    The position is ``C = -R^T t`` for the extrinsic ``[R | t]``. The frustum is
    None when the intrinsic has no image size (width or height <= 0), as in a
    default-constructed intrinsic.

    Args:
        params: Open3D pinhole camera parameters.

    Returns:
        ``(position, frustum)``: a (3,) float64 tensor and a :class:`Frustum` or None.

    Raises:
        ValueError: the extrinsic is not finite or not a rigid transform
            (orthonormal rotation, last row ``0 0 0 1``), or a bad intrinsic
            (see :func:`intrinsic_matrix`).
    """
    extrinsic = np.asarray(params.extrinsic, dtype=np.float64)
    if extrinsic.shape != (4, 4) or not np.isfinite(extrinsic).all():
        raise ValueError("PinholeCameraParameters.extrinsic must be a finite 4x4 matrix")
    rotation, t = extrinsic[:3, :3], extrinsic[:3, 3]
    if (not np.allclose(extrinsic[3], [0, 0, 0, 1])
            or not np.allclose(rotation.T @ rotation, np.eye(3), atol=_ORTHONORMAL_TOL)
            or np.linalg.det(rotation) <= 0):
        raise ValueError("PinholeCameraParameters.extrinsic is not a rigid transform "
                         "(needs an orthonormal rotation with det +1 and last row 0 0 0 1)")
    position = torch.from_numpy(-rotation.T @ t)
    intrinsic = params.intrinsic
    if intrinsic.width <= 0 or intrinsic.height <= 0:
        return position, None
    return position, Frustum(extrinsic.copy(), intrinsic_matrix(intrinsic), int(intrinsic.width),
                             int(intrinsic.height))


def _pinholes(cameras) -> Sequence[o3d.camera.PinholeCameraParameters] | None:
    if is_open3d(cameras, "camera.PinholeCameraParameters"):
        return [cameras]
    if is_open3d(cameras, "camera.PinholeCameraTrajectory"):
        return list(cameras.parameters)
    if isinstance(cameras, (list, tuple)) and cameras and all(
            is_open3d(c, "camera.PinholeCameraParameters") for c in cameras):
        return list(cameras)
    return None


def as_views(cameras=None, direction=None, *, frustum: bool = True) -> Views:
    """Brings camera positions, pinhole cameras or viewing directions to :class:`Views`.

    Args:
        cameras: a 3-vector or (V, 3) batch of positions (list, tuple, numpy,
            torch, ``o3d.core.Tensor``), ``o3d.camera.PinholeCameraParameters``,
            a list of them, a ``PinholeCameraTrajectory``, or :class:`Views`
            (returned as is); None when ``direction`` is given.
        direction: a 3-vector or (V, 3) batch of viewing directions (from the
            camera into the scene) of orthographic views.
        frustum: cull points outside the image of pinhole cameras that have an
            image size; False keeps only their positions.

    Returns:
        The canonical :class:`Views`.

    Raises:
        ValueError: both or neither of ``cameras`` and ``direction``, bad
            shapes, NaN/Inf, zero directions, invalid pinhole parameters.
        TypeError: values that are not real numbers.
    """
    if isinstance(cameras, Views) and direction is None:
        return cameras
    if (cameras is None) == (direction is None):
        raise ValueError("give exactly one of cameras (positions) and direction (orthographic)")
    if direction is not None:
        directions = as_vectors(direction, "direction")
        norms = directions.norm(dim=1, keepdim=True)
        if (norms.detach() == 0).any():
            raise ValueError("direction has a zero vector")
        return Views(None, directions / norms, (None,) * directions.shape[0])
    pinholes = _pinholes(cameras)
    if pinholes is None:
        positions = as_vectors(cameras, "camera")
        return Views(positions, None, (None,) * positions.shape[0])
    if not pinholes:
        raise ValueError("the camera trajectory holds no cameras")
    parsed = [frustum_from_pinhole(p) for p in pinholes]
    frustums = tuple(f if frustum else None for _, f in parsed)
    return Views(torch.stack([p for p, _ in parsed]), None, frustums)


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
    lo, hi = bounds(points)
    if distance is None:
        distance = box_diagonal(lo, hi)
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
        o3d = require_open3d("View.to_open3d")
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
    return View(extrinsic, intrinsic_matrix(intrinsic), width, height)
