"""Ground-truth visibility by ray casting against a triangle mesh (Open3D, Embree)."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from .cameras import real_array

__all__ = ["visibility_from_mesh", "sample_viewpoints", "as_legacy_mesh", "orient_normals"]


def as_legacy_mesh(mesh) -> o3d.geometry.TriangleMesh:
    """Accepts a legacy or tensor TriangleMesh, or a ``(vertices, triangles)`` pair of arrays."""
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        return mesh
    if isinstance(mesh, o3d.t.geometry.TriangleMesh):
        return mesh.to_legacy()
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        vertices = real_array(mesh[0], "mesh vertices", "a (V, 3) array")
        triangles = np.asarray(mesh[1])
        if triangles.size and triangles.dtype.kind not in "iu":
            raise TypeError(f"mesh triangles must hold integer vertex indices, got dtype {triangles.dtype}")
        triangles = triangles.astype(np.int32)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
            raise ValueError("mesh arrays must be vertices (V, 3) and triangles (T, 3)")
        if triangles.size and (triangles.min() < 0 or triangles.max() >= len(vertices)):
            raise ValueError("triangle indices out of range of the vertices")
        return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices),
                                         o3d.utility.Vector3iVector(triangles))
    raise TypeError(f"expected an open3d TriangleMesh or (vertices, triangles), got {type(mesh).__name__}")


def visibility_from_mesh(mesh, points, cameras, tolerance: float = 1e-4) -> np.ndarray:
    """Which points of a mesh's surface each camera sees.

    A point is visible from a camera when the first hit of the ray from the
    camera towards the point lies no nearer than the point itself, up to
    ``tolerance`` times the mesh's bounding-box diagonal.

    Args:
        mesh: ``o3d.geometry.TriangleMesh`` (legacy or tensor) or ``(vertices, triangles)``.
        points: (N, 3) points on the mesh surface.
        cameras: (3,) or (V, 3) camera positions.
        tolerance: depth tolerance relative to the bounding-box diagonal.

    Returns:
        (V, N) bool array.
    """
    legacy = as_legacy_mesh(mesh)
    if len(legacy.triangles) == 0:
        raise ValueError("mesh has no triangles")
    if not np.isfinite(np.asarray(legacy.vertices)).all():
        raise ValueError("mesh vertices must be finite (no NaN or Inf)")
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be a finite number >= 0, got {tolerance}")
    points = real_array(points, "points", "an (N, 3) array")
    cameras = np.atleast_2d(real_array(cameras, "cameras", "a (3,) or (V, 3) array"))
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if cameras.ndim != 2 or cameras.shape[1] != 3:
        raise ValueError(f"cameras must have shape (3,) or (V, 3), got {cameras.shape}")
    if not (np.isfinite(points).all() and np.isfinite(cameras).all()):
        raise ValueError("points and cameras must be finite")
    # Embree works in float32: cast in a frame centred on the mesh, and start each ray where it
    # enters the mesh's bounding sphere, so that meshes and cameras far from the origin keep precision.
    lo, hi = legacy.get_min_bound(), legacy.get_max_bound()
    centre, reach = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    vertices = np.asarray(legacy.vertices) - centre
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                        o3d.core.Tensor(np.asarray(legacy.triangles).astype(np.uint32)))
    eps = tolerance * 2 * reach
    points = points - centre
    out = np.empty((len(cameras), len(points)), dtype=bool)
    for v, cam in enumerate(cameras - centre):
        offset = points - cam
        dist = np.linalg.norm(offset, axis=1)
        dirs = offset / np.maximum(dist, 1e-300)[:, None]
        start = max(0.0, float(np.linalg.norm(cam)) - 1.01 * reach - eps)
        rays = np.concatenate([cam + start * dirs, dirs], axis=1).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        out[v] = start + t_hit >= dist - eps
    return out


def sample_viewpoints(num_views: int, center, radius: float, rng: np.random.Generator) -> np.ndarray:
    """``num_views`` positions uniform on the sphere of ``radius`` around ``center``."""
    d = rng.normal(size=(num_views, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(center, dtype=np.float64) + radius * d


def orient_normals(points: np.ndarray, normals: np.ndarray, cameras: np.ndarray,
                   visibility: np.ndarray) -> np.ndarray:
    """Normals flipped, where needed, towards most of the cameras that see their point.

    Args:
        points: (N, 3) points.
        normals: (N, 3) unoriented normals.
        cameras: (V, 3) camera positions.
        visibility: (V, N) bool, which camera sees which point.

    Returns:
        (N, 3) normals (a new array).
    """
    facing = np.einsum("vnk,nk->vn", cameras[:, None, :] - points[None], normals)
    flip = np.where(visibility, np.sign(facing), 0).sum(axis=0) < 0
    out = np.array(normals, copy=True)
    out[flip] *= -1
    return out
