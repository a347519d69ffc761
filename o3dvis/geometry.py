"""Small geometry helpers of numpy and torch alone (no Open3D): the bounding-box diagonal,
rotations and the Fibonacci lattice, shared by the runtime and by what runs where Open3D may be
missing (training, the GPU benchmark)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["bounds", "diagonal", "box_diagonal", "lengths", "within_range", "random_rotation", "fixed_rotations", "fibonacci_sphere"]


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest corners (D,) of the axis-aligned bounding box of points (N, D), N > 0.

    A column at a time: numpy reduces an (N, 3) array along its rows three values per step, many
    times slower than along each column (NaN propagates alike).
    """
    if not len(points):
        raise ValueError("the bounding box of no points is undefined")
    return (np.array([column.min() for column in points.T]), np.array([column.max() for column in points.T]))


def diagonal(points: np.ndarray) -> float:
    """Length of the diagonal of the axis-aligned bounding box."""
    return box_diagonal(*bounds(points))


def box_diagonal(lo: np.ndarray, hi: np.ndarray) -> float:
    """Length of the diagonal from corner ``lo`` to ``hi``, by ``hypot``: no square underflows
    (below 1e-154) or overflows (above 1e154)."""
    return float(np.hypot.reduce(hi - lo))


def lengths(vectors: Tensor) -> Tensor:
    """(N,) Euclidean lengths of (N, D) float vectors, each divided by its largest coordinate before it
    is squared: no square underflows (below 1e-154 in float64) or overflows (above 1e154); a length
    beyond the dtype's range is inf."""
    largest = vectors.abs().amax(dim=1, keepdim=True)
    return largest[:, 0] * (vectors / largest.clamp_min(torch.finfo(vectors.dtype).tiny)).norm(dim=1)


def within_range(points: Tensor, camera: Tensor, reach: float) -> Tensor:
    """(M,) int64: the rows of (N, 3) ``points`` within ``reach`` of the (3,) ``camera``, in order
    (a range crop, as a LiDAR's)."""
    return torch.nonzero(lengths(points - camera) <= reach)[:, 0]


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed 3x3 rotation matrix."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def fixed_rotations(count: int) -> Tensor:
    """(count, 3, 3) float64 rotations: the identity, then uniformly random ones from fixed seeds.

    The same on every machine and every call, so that an ensemble over them is
    deterministic, and the first ``k`` of them are ``fixed_rotations(k)``.
    """
    turns = [np.eye(3)] + [random_rotation(np.random.default_rng([0, k])) for k in range(1, count)]
    return torch.from_numpy(np.stack(turns))


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` nearly evenly spread unit vectors (a Fibonacci lattice), (count, 3)."""
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = i * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
