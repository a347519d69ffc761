"""Camera inputs in every form Open3D users have, brought to one canonical form.

A view is either a camera position (perspective) or a viewing direction
(orthographic). Positions come as a 3-vector or a ``(V, 3)`` batch (list,
tuple, numpy, torch, ``o3d.core.Tensor``) or as
``o3d.camera.PinholeCameraParameters`` (one, a list, or a
``PinholeCameraTrajectory``), whose intrinsic and image size also define a
frustum: points that project outside the image, or lie behind the camera, are
not visible.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch
from torch import Tensor

__all__ = ["Frustum", "Views", "as_views", "as_vectors", "real_array", "frustum_from_pinhole"]

_ORTHONORMAL_TOL = 1e-4


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

    def contains(self, points_n: Tensor, center: Tensor, scale: Tensor) -> Tensor:
        """Which points project into the image from in front of the camera.

        A pixel ``(i, j)`` covers ``[i - 0.5, i + 0.5)`` of the image plane, so a
        point is inside when its projection rounds to a pixel of the image.

        Args:
            points_n: (N, 3) points in normalised coordinates,
                ``world = points_n * scale + center``.
            center: (3,) float64 centre of the normalisation.
            scale: float64 scalar scale of the normalisation.

        Returns:
            (N,) bool tensor on the device of ``points_n``.
        """
        # x_cam = R (s x_n + c) + t = s (R x_n + (R c + t) / s): the scale changes
        # neither the sign of z nor the projected pixel, so work in normalised units.
        rotation = torch.tensor(self.extrinsic[:3, :3], dtype=torch.float64, device=points_n.device)
        shift = (rotation @ center.to(points_n.device) + torch.as_tensor(
            self.extrinsic[:3, 3].copy(), dtype=torch.float64, device=points_n.device)) / scale
        k = torch.tensor(self.intrinsic, dtype=torch.float64, device=points_n.device)
        cam = points_n @ rotation.to(points_n.dtype).T + shift.to(points_n.dtype)
        uvw = cam @ k.to(points_n.dtype).T
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
    if isinstance(value, o3d.core.Tensor):
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
    if not torch.isfinite(tensor.detach()).all():
        raise ValueError(f"{name} has NaN or Inf coordinates")
    return tensor


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
            (orthonormal rotation, last row ``0 0 0 1``), or the intrinsic is singular.
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
    k = np.asarray(intrinsic.intrinsic_matrix, dtype=np.float64)
    if not np.isfinite(k).all() or abs(np.linalg.det(k)) == 0:
        raise ValueError("PinholeCameraParameters.intrinsic has a singular or non-finite matrix")
    return position, Frustum(extrinsic.copy(), k, int(intrinsic.width), int(intrinsic.height))


def _pinholes(cameras) -> Sequence[o3d.camera.PinholeCameraParameters] | None:
    if isinstance(cameras, o3d.camera.PinholeCameraParameters):
        return [cameras]
    if isinstance(cameras, o3d.camera.PinholeCameraTrajectory):
        return list(cameras.parameters)
    if isinstance(cameras, (list, tuple)) and cameras and all(
            isinstance(c, o3d.camera.PinholeCameraParameters) for c in cameras):
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
