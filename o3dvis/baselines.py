"""Hidden Point Removal baselines with the common ``(V, N) bool`` mask interface.

* :func:`hidden_point_removal_mask`: Katz et al. 2007 as implemented by Open3D
  (spherical flip of radius ``radius`` around the camera, convex hull with the
  camera), called per view on a checked, de-duplicated cloud so that it cannot
  crash on degenerate input.
* :func:`exponential_hpr_mask`: Katz & Tal 2015 with the exponential kernel
  ``f(d) = d**gamma``, ``gamma < 0`` (scale-free), convex hull by scipy/qhull.

* :func:`zbuffer_mask`: surfel splatting into an equirectangular depth buffer
  around the camera (it answers for cameras anywhere, inside the cloud too).

All return ``mask[v, i]`` = point ``i`` is visible from ``cameras[v]``. Exact
duplicate points share one answer. Clouds that are flat or collinear together
with the camera are solved in their own plane or line (HPR is defined there
too), so no qhull precision error escapes.

:func:`hpr_method` and :func:`exponential_method` turn one parameter into a
visibility method ``method(points, cameras) -> (V, N) bool``; :data:`SWEEPS`
holds the parameter grids that the evaluation tunes over.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from .cameras import real_array
from .geometry import diagonal

__all__ = ["hidden_point_removal_mask", "exponential_hpr_mask", "zbuffer_mask", "hpr_method",
           "exponential_method", "zbuffer_method", "SWEEPS", "sweep", "Method", "distinct_points"]

Method = Callable[[np.ndarray, np.ndarray], np.ndarray]

_RANK_TOL = 1e-9


def _check(points, cameras) -> tuple[np.ndarray, np.ndarray]:
    points = real_array(points, "points", "an (N, 3) array")
    cameras = np.atleast_2d(real_array(cameras, "cameras", "a (3,) or (V, 3) array"))
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    if len(points) == 0:
        raise ValueError("points is empty")
    if cameras.ndim != 2 or cameras.shape[1] != 3 or len(cameras) == 0:
        raise ValueError(f"cameras must have shape (3,) or (V, 3), got {cameras.shape}")
    if not (np.isfinite(points).all() and np.isfinite(cameras).all()):
        raise ValueError("points and cameras must be finite (no NaN or inf)")
    return points, cameras


def distinct_points(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first of each set of exact duplicates, and where each point's answer is among them.

    Sorting a random linear key keeps this O(N log N) on one float column;
    only runs of equal keys (exact duplicates, or astronomically rare key
    collisions) are resolved exactly.

    Args:
        points: (N, 3) points.

    Returns:
        ``(keep, slot)``: (M,) ascending indices of the first occurrence of each
        distinct point, and (N,) each point's position in ``keep``, so that
        ``answer[slot]`` spreads an answer for ``points[keep]`` to all points.
    """
    key = points[:, 0] * 0.7548776662 + points[:, 1] * 0.5698402910 + points[:, 2] * 0.3263524026
    order = np.argsort(key, kind="stable")
    skey = key[order]
    run_start = np.r_[True, skey[1:] != skey[:-1]]
    rep = order[np.maximum.accumulate(np.where(run_start, np.arange(len(order)), 0))]
    tied = ~(run_start & np.r_[run_start[1:], True])
    if tied.any():  # exact grouping inside runs of equal keys
        idx = order[tied]
        _, first, inverse = np.unique(points[idx], axis=0, return_index=True, return_inverse=True)
        rep[tied] = idx[first[inverse.ravel()]]
    representative = np.empty(len(points), dtype=np.int64)
    representative[order] = rep
    keep = np.flatnonzero(representative == np.arange(len(points)))
    slot = np.empty(len(points), dtype=np.int64)
    slot[keep] = np.arange(len(keep))
    return keep, slot[representative]


def _affine_basis(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre and orthonormal basis (rows) of the affine hull of ``x`` (rank-revealing)."""
    centre = x.mean(axis=0)
    _, s, vt = np.linalg.svd(x - centre, full_matrices=False)
    return centre, vt[:int((s > _RANK_TOL * s[0]).sum()) if s[0] > 0 else 0]


def _hull_vertices(x: np.ndarray) -> np.ndarray:
    """Indices of the convex-hull vertices of ``x`` in its own affine dimension (0-3)."""
    centre, basis = _affine_basis(x)
    y = (x - centre) @ basis.T
    if basis.shape[0] == 0:
        return np.arange(len(x))
    if basis.shape[0] == 1:
        return np.unique([np.argmin(y[:, 0]), np.argmax(y[:, 0])])
    try:
        return ConvexHull(y).vertices
    except QhullError:  # nearly degenerate: joggled input still gives the hull's vertices
        try:
            return ConvexHull(y, qhull_options="QJ").vertices
        except QhullError as e:
            raise ValueError(f"convex hull failed on a degenerate cloud: {str(e).splitlines()[0]}") from e


def _visible_from_mapped(mapped: np.ndarray) -> np.ndarray:
    """HPR's decision: points whose image lies on the hull of the images plus the camera (origin)."""
    x = np.vstack([mapped, np.zeros((1, 3))])
    try:
        vertices = ConvexHull(x).vertices
    except QhullError:
        vertices = _hull_vertices(x)
    mask = np.zeros(len(x), dtype=bool)
    mask[vertices] = True
    return mask[:-1]


def _offsets(points: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    offset = points - camera
    dist = np.linalg.norm(offset, axis=1)
    if dist.min() <= _RANK_TOL * max(dist.max(), 1e-300):
        raise ValueError(f"a point coincides with the camera at {camera.tolist()}")
    return offset, dist


def _per_view(points, cameras, prepare: Callable[[np.ndarray], Callable[[np.ndarray], np.ndarray]]) -> np.ndarray:
    """Runs ``prepare(distinct_points)(camera) -> (M,) bool`` per camera and spreads it to duplicates."""
    points, cameras = _check(points, cameras)
    keep, slot = distinct_points(points)
    visible = prepare(points[keep])
    out = np.empty((len(cameras), len(points)), dtype=bool)
    for v, camera in enumerate(cameras):
        out[v] = visible(camera)[slot]
    return out


def hidden_point_removal_mask(points, cameras, radius: float) -> np.ndarray:
    """Open3D's Hidden Point Removal as a ``(V, N)`` mask.

    Args:
        points: (N, 3) points.
        cameras: (3,) or (V, 3) camera locations.
        radius: spherical-flip radius (absolute, as in
            ``o3d.geometry.PointCloud.hidden_point_removal``); must be > 0.

    Returns:
        (V, N) bool array, True where the point is visible.

    Raises:
        ValueError: bad shapes, non-finite values, radius <= 0, or a point at a camera.
    """
    import open3d as o3d

    if not np.isfinite(radius) or radius <= 0:
        raise ValueError(f"radius must be a positive number, got {radius}")

    def prepare(unique: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(unique))
        flat = _affine_basis(unique)[1].shape[0] < 3

        def visible(camera: np.ndarray) -> np.ndarray:
            offset, dist = _offsets(unique, camera)
            # Open3D only gets what qhull can take in 3-D: >= 4 points not coplanar with the camera.
            if len(unique) >= 4 and (not flat or _affine_basis(np.vstack([unique, camera]))[1].shape[0] == 3):
                try:
                    mask = np.zeros(len(unique), dtype=bool)
                    mask[np.asarray(pcd.hidden_point_removal(camera, radius)[1], dtype=np.int64)] = True
                    return mask
                except RuntimeError:  # qhull precision trouble: same flip, solved below
                    pass
            return _visible_from_mapped(offset + 2.0 * (radius - dist)[:, None] * offset / dist[:, None])

        return visible

    return _per_view(points, cameras, prepare)


def exponential_hpr_mask(points, cameras, gamma: float) -> np.ndarray:
    """Katz & Tal 2015 HPR with the exponential kernel ``f(d) = d**gamma`` as a ``(V, N)`` mask.

    Each point ``p`` (camera at the origin) maps to ``f(|p|) p / |p|``; it is
    visible when its image is a vertex of the convex hull of the images and
    the camera. Distances are divided by their maximum first, which changes
    nothing (the kernel is scale-free) but keeps the numbers tame.

    Args:
        points: (N, 3) points.
        cameras: (3,) or (V, 3) camera locations.
        gamma: kernel exponent, < 0; closer to 0 marks more points visible.

    Returns:
        (V, N) bool array, True where the point is visible.
    """
    if not np.isfinite(gamma) or gamma >= 0:
        raise ValueError(f"gamma must be a negative number, got {gamma}")

    def prepare(unique: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        def visible(camera: np.ndarray) -> np.ndarray:
            offset, dist = _offsets(unique, camera)
            return _visible_from_mapped(offset * ((dist / dist.max()) ** gamma / dist)[:, None])
        return visible

    return _per_view(points, cameras, prepare)


def _surfels(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Each point's spacing (mean distance to its ``k`` nearest neighbours) and PCA normal."""
    from scipy.spatial import cKDTree

    k = min(k, len(points) - 1)
    if k < 2:
        return np.ones(len(points)), np.tile([0.0, 0.0, 1.0], (len(points), 1))
    distance, neighbour = cKDTree(points).query(points, k=k + 1)
    local = points[neighbour] - points[neighbour].mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))[1][:, :, 0]
    return distance[:, 1:].mean(axis=1), normals


def zbuffer_mask(points, cameras, splat: float = 1.0, tolerance: float = 1.0, neighbours: int = 8,
                 max_rows: int = 2048) -> np.ndarray:
    """Visibility by splatting oriented discs (surfels) into a depth buffer around each camera.

    Every point becomes a disc of radius ``splat`` x its spacing (mean distance
    to its ``neighbours`` nearest points), in the plane of its PCA normal. Each
    camera renders the discs into an equirectangular (latitude-longitude) depth
    buffer over the full sphere, whose resolution follows the median angular
    spacing of the points seen from it (1.5 pixels per spacing, at most
    ``max_rows`` rows). A point is visible when its distance exceeds, by at most
    ``tolerance`` x its spacing, the depth along its own ray of the plane of the
    disc nearest at its pixel (its own disc makes it visible). The buffer is the
    library's (:func:`o3dvis.nn.zbuffer.surfel_zbuffer`) with these discs.

    Args:
        points: (N, 3) points.
        cameras: (3,) or (V, 3) camera positions, anywhere not on a point.
        splat: disc radius in units of the point spacing, > 0.
        tolerance: depth tolerance in units of the point spacing, >= 0.
        neighbours: neighbours that give the spacing and the normal.
        max_rows: largest number of buffer rows (the buffer has twice as many columns).

    Returns:
        (V, N) bool array, True where the point is visible.
    """
    import torch

    from .nn.zbuffer import surfel_zbuffer

    if not (np.isfinite(splat) and splat > 0 and np.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"splat must be > 0 and tolerance >= 0, got {splat} and {tolerance}")

    def prepare(unique: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        spacing, normals = _surfels(unique, neighbours)
        centre = unique.mean(axis=0)
        scale = max(float(np.abs(unique - centre).max()), 1e-300)  # float32 coordinates of order one
        points32 = torch.from_numpy((unique - centre) / scale).float()
        surfels = torch.from_numpy(np.column_stack([spacing, normals, splat * spacing]) / [scale, 1, 1, 1, scale])

        def visible(camera: np.ndarray) -> np.ndarray:
            _, dist = _offsets(unique, camera)
            rows = int(np.clip(1.5 * np.pi / np.median(spacing / dist), 16, max_rows))
            with torch.inference_mode():
                answer = surfel_zbuffer(points32, surfels, torch.from_numpy((camera - centre) / scale),
                                        rows).numpy()
            # the distance beyond the front plane comes in disc radii, the tolerance in spacings
            return (answer[:, 0] > 0) | (answer[:, 1] * splat <= tolerance)

        return visible

    return _per_view(points, cameras, prepare)


def hpr_method(exponent: float) -> Method:
    """Open3D HPR with ``radius = bbox diagonal * 10**exponent`` as a visibility method."""
    def method(points, cameras):
        points, cameras = _check(points, cameras)
        # a single distinct point is visible whatever the radius
        return hidden_point_removal_mask(points, cameras, (diagonal(points) or 1.0) * 10.0 ** exponent)
    method.__name__ = f"hpr(k={exponent:g})"
    return method


def exponential_method(gamma: float) -> Method:
    """Katz–Tal exponential-kernel HPR with exponent ``gamma`` as a visibility method."""
    def method(points, cameras):
        return exponential_hpr_mask(points, cameras, gamma)
    method.__name__ = f"hpr-exp(gamma={gamma:g})"
    return method


def zbuffer_method(splat: float) -> Method:
    """Surfel z-buffer visibility (:func:`zbuffer_mask`) with discs of ``splat`` x the point spacing."""
    def method(points, cameras):
        return zbuffer_mask(points, cameras, splat)
    method.__name__ = f"zbuffer(splat={splat:g})"
    return method


SWEEPS: dict[str, tuple[str, Callable[[float], Method], tuple[float, ...]]] = {
    "hpr": ("k", hpr_method, (1.5, 2.0, 2.5, 3.0, 3.5)),
    "hpr-exp": ("gamma", exponential_method, (-0.0003, -0.001, -0.003, -0.01)),
    "zbuffer": ("splat", zbuffer_method, (0.75, 1.0)),
}


def sweep(name: str, values=None) -> dict[str, Method]:
    """The parameter sweep of a baseline: ``{"k=2": method, ...}``.

    Args:
        name: ``"hpr"`` (radius = diagonal * 10**k) or ``"hpr-exp"`` (gamma).
        values: parameter values replacing the default grid of ``SWEEPS``.

    Returns:
        Ordered mapping from a parameter label to a visibility method.
    """
    if name not in SWEEPS:
        raise ValueError(f"unknown baseline {name!r}; choose from {sorted(SWEEPS)}")
    param, make, default = SWEEPS[name]
    return {f"{param}={v:g}": make(float(v)) for v in (default if values is None else values)}
