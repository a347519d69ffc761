"""Rotations stored as quaternions ``(w, x, y, z)``, as E57 scan poses and COLMAP images store them."""

from __future__ import annotations

import numpy as np

__all__ = ["QUATERNION_TOL", "rotation_matrix"]

QUATERNION_TOL = 1e-3
"""How far from 1 the norm of a stored quaternion may be: files round them (COLMAP's documentation
shows 6 digits), so one within this is normalised; one further off is no rotation."""


def rotation_matrix(q, what: str) -> np.ndarray:
    """The rotation matrix of a unit quaternion ``(w, x, y, z)`` in the Hamilton convention (Eigen's,
    E57's and COLMAP's), normalised first.

    Args:
        q: the 4 numbers.
        what: names the quaternion in an error, e.g. ``"cloud.e57: scan 0's pose rotation"``.

    Returns:
        (3, 3) float64 orthonormal matrix with determinant +1.

    Raises:
        ValueError: NaN or infinite numbers, or a norm further than ``QUATERNION_TOL`` from 1.
    """
    q = np.asarray(q, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(q).all():
        raise ValueError(f"{what} {q.tolist()} has NaN or infinite numbers")
    if abs(norm - 1.0) > QUATERNION_TOL:
        raise ValueError(f"{what} {q.tolist()} is not a unit quaternion (norm {norm:g}), so no rotation")
    w, x, y, z = q / norm
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
