"""Cameras and points of a scene: free positions, uniform and LiDAR-like samplings, labelled samples."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ....groundtruth import orient_normals, sample_viewpoints, visibility_from_mesh
from ..sample import Sample, sample_surface
from .scene import Scene, in_boxes

__all__ = ["SAMPLINGS", "free_positions", "sample_uniform", "sample_lidar", "scene_sample"]

SAMPLINGS = ("uniform", "lidar")
"""The point samplings of :func:`scene_sample`."""


def free_positions(scene: Scene, count: int, rng: np.random.Generator, margin: float = 0.3,
                   tries: int = 100) -> np.ndarray:
    """Random positions in the scene's camera region, at least ``margin`` from every surface and
    outside every solid and obstacle box grown by ``margin``.

    Raises:
        RuntimeError: ``tries`` rounds of candidates did not give ``count`` positions.
    """
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    lo, hi = scene.region
    found: list[np.ndarray] = []
    have = 0
    for _ in range(tries):
        if have >= count:
            break
        n = max(64, 4 * (count - have))
        xy = rng.uniform(lo[:2], hi[:2], (n, 2))
        p = np.column_stack([xy, scene.floor(xy) + rng.uniform(lo[2], hi[2], n)])
        p = p[~in_boxes(p, scene.solids, margin) & ~in_boxes(p, scene.obstacles, margin)]
        if len(p):
            distance = scene.raycaster().compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()
            p = p[distance >= margin]
        found.append(p)
        have += len(p)
    if have < count:
        raise RuntimeError(f"found {have} free positions in the {scene.kind} scene, {count} were asked for")
    return np.concatenate(found)[:count] if count else np.zeros((0, 3))


def sample_uniform(scene: Scene, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points uniform on the scene's exposed surfaces (by area; buried ones dropped) and
    their triangle normals."""
    vertices, triangles = np.asarray(scene.mesh.vertices), np.asarray(scene.mesh.triangles)
    points, normals, have = [], [], 0
    for _ in range(100):
        if have >= count:
            break
        p, n = sample_surface(vertices, triangles, int(1.2 * (count - have)) + 16, rng)
        keep = ~scene.buried(p)
        points.append(p[keep])
        normals.append(n[keep])
        have += int(keep.sum())
    if have < count:
        raise RuntimeError(f"the {scene.kind} scene has almost no exposed surface")
    return np.concatenate(points)[:count], np.concatenate(normals)[:count]


def _directions(rng: np.random.Generator, count: int, elevation: tuple[float, float],
                channels: int) -> np.ndarray:
    """Ray directions: uniform on the sphere over the whole range, else ``channels`` rings of elevation."""
    azimuth = rng.uniform(0, 2 * np.pi, count)
    lo, hi = np.radians(elevation)
    if lo <= -np.pi / 2 and hi >= np.pi / 2:
        z = rng.uniform(-1, 1, count)
    else:
        ring = (rng.integers(0, channels, count) + 0.5) / channels
        z = np.sin(lo + (hi - lo) * ring + rng.normal(scale=1e-4, size=count))
    r = np.sqrt(np.maximum(1 - z * z, 0))
    return np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), z])


def sample_lidar(scene: Scene, count: int, sensors: np.ndarray, rng: np.random.Generator,
                 max_range: float | None = None, channels: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` points where rays cast from the sensors first hit the scene.

    Each sensor casts rays in random directions (within the scene's elevation
    range, on ``channels`` rings when it is not the whole sphere); ``count`` of
    all hits are kept at random, so density falls with range as in accumulated
    scans, and surfaces no sensor saw have no points.

    Args:
        scene: the scene.
        count: number of points.
        sensors: (S, 3) sensor positions.
        rng: numpy random generator.
        max_range: hits farther than this from their sensor are dropped.
        channels: rings of a sensor with a limited elevation range.

    Returns:
        points (count, 3), normals (count, 3) facing their sensor, and the index of each point's sensor.

    Raises:
        RuntimeError: the sensors hit too little to give ``count`` points.
    """
    sensors = np.atleast_2d(np.asarray(sensors, dtype=np.float64))
    if sensors.ndim != 2 or sensors.shape[1] != 3 or len(sensors) == 0:
        raise ValueError(f"sensors must have shape (S, 3) with S >= 1, got {sensors.shape}")
    if max_range is not None and not max_range > 0:
        raise ValueError(f"max_range must be > 0, got {max_range}")
    points, normals, owner, have = [], [], [], 0
    for _ in range(20):
        if have >= count:
            break
        per = int(1.3 * (count - have) / len(sensors)) + 64
        for s, origin in enumerate(sensors):
            d = _directions(rng, per, scene.elevation, channels).astype(np.float32)
            rays = np.concatenate([np.broadcast_to(origin.astype(np.float32), d.shape), d], axis=1)
            hit = scene.raycaster().cast_rays(o3d.core.Tensor(rays))
            t = hit["t_hit"].numpy().astype(np.float64)
            keep = np.isfinite(t) & (t <= (max_range or np.inf))
            d64 = d[keep].astype(np.float64)
            n = hit["primitive_normals"].numpy()[keep].astype(np.float64)
            n[np.einsum("ij,ij->i", n, d64) > 0] *= -1  # face the sensor
            points.append(origin + t[keep, None] * d64)
            normals.append(n)
            owner.append(np.full(int(keep.sum()), s))
            have += int(keep.sum())
    if have < count:
        raise RuntimeError(f"the sensors hit {have} points of the {scene.kind} scene, {count} were asked for")
    pick = np.sort(rng.choice(have, count, replace=False))
    return np.concatenate(points)[pick], np.concatenate(normals)[pick], np.concatenate(owner)[pick]


def scene_sample(scene: Scene, sampling: str, num_points: int, inside: int, outside: int,
                 rng: np.random.Generator, sensors: int | None = None, max_range: float | None = None,
                 name: str = "scene") -> Sample:
    """A labelled sample of a scene: points, normals, cameras and ray-cast visibility.

    Args:
        scene: the scene.
        sampling: ``"uniform"`` (area-weighted on the exposed surfaces) or
            ``"lidar"`` (hits of rays from 1-5 sensors at free positions).
        num_points: number of points.
        inside: cameras at free positions inside (see :func:`free_positions`).
        outside: cameras outside, on the upper half of the sphere of radius =
            bounding-box diagonal around the box's centre (as for objects).
        rng: numpy random generator.
        sensors: number of LiDAR-like sensors (default: 1-5 at random).
        max_range: LiDAR-like range limit (default: none).
        name: the sample's name.

    Returns:
        A :class:`~o3dvis.training.data.sample.Sample`; the inside cameras come first.
    """
    if sampling not in SAMPLINGS:
        raise ValueError(f"unknown sampling {sampling!r}; choose from {', '.join(SAMPLINGS)}")
    if inside < 0 or outside < 0 or inside + outside == 0:
        raise ValueError(f"need at least one camera, got inside={inside}, outside={outside}")
    if sampling == "uniform":
        points, normals = sample_uniform(scene, num_points, rng)
    else:
        origins = free_positions(scene, int(rng.integers(1, 6)) if sensors is None else sensors, rng)
        points, normals, _ = sample_lidar(scene, num_points, origins, rng, max_range)
    lo, hi = scene.mesh.get_min_bound(), scene.mesh.get_max_bound()
    around = sample_viewpoints(outside, (lo + hi) / 2, float(np.linalg.norm(hi - lo)), rng)
    around[:, 2] = (lo[2] + hi[2]) / 2 + np.abs(around[:, 2] - (lo[2] + hi[2]) / 2)
    cameras = np.concatenate([free_positions(scene, inside, rng), around])
    visibility = visibility_from_mesh(scene.mesh, points, cameras)
    if sampling == "uniform":
        normals = orient_normals(points, normals, cameras, visibility)
    return Sample(points.astype(np.float32), normals.astype(np.float32), cameras.astype(np.float32),
                  visibility, name)
