"""Cameras in every form Open3D users have, brought to one canonical form: the views a query answers.

A view is either a camera position (perspective) or a viewing direction
(orthographic). Positions come as a 3-vector or a ``(V, 3)`` batch (list,
tuple, numpy, torch, ``o3d.core.Tensor``) or as
``o3d.camera.PinholeCameraParameters`` (one, a list, or a
``PinholeCameraTrajectory``), whose intrinsic and image size also define a
frustum: points that project outside the image, or lie behind the camera, are
not visible.

Conventions follow Open3D: an extrinsic is the 4x4 world-to-camera matrix with
x to the right, y down and z forward; an intrinsic is the 3x3 pinhole matrix
with the centre of pixel (row, col) at (u, v) = (col, row).

Open3D's types are recognised through :func:`is_open3d`, which imports nothing: the torch core
and training also run where Open3D is not installed (a GPU machine that trains, given arrays).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from .geometry import bounds, box_diagonal, fibonacci_sphere

if TYPE_CHECKING:
    import open3d as o3d

__all__ = ["Frustum", "Views", "as_views", "as_vectors", "all_finite", "as_camera_location", "real_array",
           "frustum_from_pinhole", "intrinsic_matrix", "fibonacci_sphere", "viewpoints_around", "open3d_or_none",
           "require_open3d", "is_open3d"]

_ORTHONORMAL_TOL = 1e-4


@functools.cache
def open3d_or_none() -> ModuleType | None:
    """The ``open3d`` module, or None where it is not installed."""
    try:
        return importlib.import_module("open3d")
    except ImportError:
        return None


def require_open3d(purpose: str) -> ModuleType:
    """The ``open3d`` module.

    Args:
        purpose: what needs it, for the error.

    Raises:
        ImportError: where Open3D is not installed.
    """
    o3d = open3d_or_none()
    if o3d is None:
        raise ImportError(f"{purpose} needs Open3D; install it with: pip install open3d")
    return o3d


def is_open3d(value, *names: str) -> bool:
    """Whether ``value`` is an instance of one of Open3D's types, named by their paths in the module
    (``"geometry.PointCloud"``, ``"core.Tensor"``); False where Open3D is not installed.
    """
    o3d = open3d_or_none()
    if o3d is None:
        return False
    return isinstance(value, tuple(functools.reduce(getattr, name.split("."), o3d) for name in names))


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
