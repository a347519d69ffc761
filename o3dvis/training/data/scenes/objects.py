"""Objects that furnish a scene: meshes from a folder or procedural shapes, sized and placed."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import open3d as o3d

from ..shapes import random_shape

__all__ = ["random_object", "fit_extent", "place_footprint"]


@functools.lru_cache(maxsize=64)
def _read_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    mesh = o3d.io.read_triangle_mesh(path)
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if len(triangles) == 0 or not np.isfinite(vertices).all():
        raise ValueError(f"{path}: no usable triangles")
    return vertices, triangles


def _rotation(rng: np.random.Generator, upright: bool) -> np.ndarray:
    """A random yaw (upright) or a uniformly random rotation."""
    if upright:
        a = rng.uniform(0, 2 * np.pi)
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_object(rng: np.random.Generator, meshes: Sequence[str], primitives: Sequence[str],
                  mesh_share: float) -> tuple[np.ndarray, np.ndarray]:
    """A mesh from the folder list (with probability ``mesh_share``) or a procedural shape, turned at random."""
    if meshes and rng.random() < mesh_share:
        vertices, triangles = _read_mesh(str(meshes[rng.integers(len(meshes))]))
    else:
        shape = random_shape(rng, int(rng.integers(1, 4)), primitives)
        vertices, triangles = np.asarray(shape.vertices), np.asarray(shape.triangles)
    return vertices @ _rotation(rng, rng.random() < 0.5).T, triangles


def fit_extent(vertices: np.ndarray, size: float, limit: np.ndarray) -> np.ndarray:
    """Scales so that the largest extent is ``size`` and every extent at most ``limit``; min corner at 0."""
    extent = np.maximum(vertices.max(axis=0) - vertices.min(axis=0), 1e-9)
    scale = min(size / extent.max(), *(limit / extent))
    v = vertices * scale
    return v - v.min(axis=0)


def place_footprint(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, extent: np.ndarray,
                    taken: list[np.ndarray], tries: int = 10) -> np.ndarray | None:
    """A corner (x, y) for a footprint of ``extent`` inside [lo, hi] overlapping no footprint in ``taken``."""
    if (extent > hi - lo).any():
        return None
    for _ in range(tries):
        corner = rng.uniform(lo, hi - extent)
        box = np.stack([corner, corner + extent])
        if all((box[1] <= t[0]).any() or (box[0] >= t[1]).any() for t in taken):
            taken.append(box)
            return corner
    return None
