"""Driving logs: a road network, a vehicle driving it, LiDAR sweeps accumulated into one map, camera frames.

:func:`drive_log` builds what the users of a driving log hold: a map accumulated
from the sweeps of a spinning LiDAR carried along a trajectory, the vehicle's
poses, and forward-looking pinhole frames (``o3d.camera.PinholeCameraParameters``);
:func:`frame_truth` labels the points of a frame by ray casting the scene's mesh.

The world is a main road along +x with side streets branching off it, buildings
along both, cars parked at the kerbs, trees (trunk and crown) and lamp poles on
the pavements, on gently uneven ground. It is made of 50 m segments, each drawn
from its own seed, and reaches past both ends of the trajectory farther than the
LiDAR sees: a longer log of the same seed extends a shorter one, whose sweeps,
map points and frames it repeats, so that accuracy can be followed as a log grows
on the very same frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import torch

from ....apps.pinhole import PinholeView, camera_location_of, look_at
from ....geometry import within_range
from ..perturb import add_noise
from .scene import HeightField, Scene, SceneBuilder
from .sampling import sample_lidar
from .streets import add_building, add_car, building_plots

__all__ = ["DriveLog", "drive_log", "frame_view", "frame_truth", "SEGMENT", "LIDAR_HEIGHT", "CAMERA_HEIGHT"]

SEGMENT = 50.0
"""Metres of main road drawn from one seed."""
LIDAR_HEIGHT = 1.8
"""Height of the spinning LiDAR above the road, metres."""
CAMERA_HEIGHT = 1.6
"""Height of the forward-looking camera above the road, metres."""
_BEFORE = 2  # segments before the start of the trajectory (100 m: more than the LiDAR's range)
_ROAD_HALF = 7.0  # main road: two driving lanes and a parking lane each side
_PAVEMENT = 3.0
_LANE = -1.75  # the vehicle drives the right-hand lane (+x is forward, -y is right)
_SIDE_REACH = 70.0  # the longest side street, from the main road's kerb
_BLOCK_DEPTH = 16.0  # the deepest building along the main road, from the back of the pavement
_GROUND_SPACING = 1.5
_TRUTH_TOLERANCE = 0.02  # metres: a point is visible when the first hit is no nearer than this


@dataclass
class DriveLog:
    """A driving log: its scene, the vehicle's trajectory, the accumulated map and the camera frames.

    Attributes:
        scene: the world (mesh ray-cast for ground truth), in its own axes: the main road along +x.
        rotation: (3, 3) turn about z from the scene's axes to the map's (``map = scene @ rotation.T``).
        poses: (T, 4, 4) vehicle-to-map transforms along the trajectory, one a metre.
        sweeps: (S, 3) LiDAR positions of the sweeps, in the map.
        points: (N, 3) float32 map points, the sweeps' hits accumulated, in the map.
        sweep_of: (N,) int32 the sweep each point comes from.
        frames: pinhole frames (``o3d.camera.PinholeCameraParameters``) looking forward from the vehicle.
        frame_distance: (F,) distance along the trajectory of each frame, metres.
        length: length of the trajectory, metres.
        lidar_range: the LiDAR's range, metres (no point lies farther from its sweep).
    """

    scene: Scene
    rotation: np.ndarray
    poses: np.ndarray
    sweeps: np.ndarray
    points: np.ndarray
    sweep_of: np.ndarray
    frames: list[o3d.camera.PinholeCameraParameters]
    frame_distance: np.ndarray
    length: float
    lidar_range: float

    def window(self, centre: np.ndarray, reach: float) -> slice:
        """The rows of the map that hold every point within ``reach`` of ``centre``: the points come
        sweep by sweep, and no point lies farther than ``lidar_range`` from its sweep."""
        close = np.flatnonzero(np.linalg.norm(self.sweeps - centre, axis=1) <= reach + self.lidar_range)
        if not len(close):
            return slice(0, 0)
        return slice(int(np.searchsorted(self.sweep_of, close[0], "left")),
                     int(np.searchsorted(self.sweep_of, close[-1], "right")))

    def camera(self, index: int) -> np.ndarray:
        """(3,) position of frame ``index``'s camera in the map."""
        return camera_location_of(self.frames[index])

    def noisy(self, level: float, seed: int = 0) -> np.ndarray:
        """The map with noise: each point moved in a random direction by up to ``level`` times its range
        from its sweep's sensor (calibration and pose errors turn rays: the error grows with range).
        Each sweep's noise is drawn from its own seed, so that a longer log's noisy map extends a
        shorter one's too.

        Returns:
            (N, 3) float32 points (the map itself when ``level`` is 0).
        """
        if not level:
            return self.points
        reach = np.linalg.norm(self.points - self.sweeps[self.sweep_of].astype(np.float32), axis=1)
        out = np.empty_like(self.points)
        ends = np.searchsorted(self.sweep_of, np.arange(len(self.sweeps)), "right")
        for sweep, (start, stop) in enumerate(zip(np.r_[0, ends[:-1]], ends)):
            rng = np.random.default_rng([seed, 3, round(level * 1e6), sweep])
            out[start:stop] = add_noise(self.points[start:stop], level, reach[start:stop, None], rng)
        return out


class _Ground:
    """Gentle relief (0.1-0.5 m, three long waves) defined everywhere, drawn from the log's seed alone."""

    def __init__(self, rng: np.random.Generator):
        angles = rng.uniform(0, 2 * np.pi, 3)
        self.waves = 2 * np.pi / rng.uniform(20, 80, 3)[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
        self.phases = rng.uniform(0, 2 * np.pi, 3)
        self.amplitude = rng.uniform(0.1, 0.5) / 3

    def field(self, lo: np.ndarray, hi: np.ndarray) -> HeightField:
        """The height field over [lo, hi] on a lattice anchored at the origin (so extents agree where they overlap)."""
        start = np.floor(lo / _GROUND_SPACING) * _GROUND_SPACING
        n = np.ceil((hi - start) / _GROUND_SPACING).astype(int) + 1
        i, j = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
        xy = np.stack([start[0] + i * _GROUND_SPACING, start[1] + j * _GROUND_SPACING], axis=-1)
        heights = self.amplitude * np.sin(xy @ self.waves.T + self.phases).sum(axis=-1)
        return HeightField(start, _GROUND_SPACING, heights)


def _tree(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, xy: np.ndarray) -> None:
    """A trunk 2-3.5 m high and a crown (a flattened sphere 1.2-2.5 m across) on top of it."""
    base = float(ground.height(xy[None])[0])
    height, radius = rng.uniform(2.0, 3.5), rng.uniform(1.2, 2.5)
    trunk = o3d.geometry.TriangleMesh.create_cylinder(rng.uniform(0.12, 0.25), height + 0.5, 10)
    trunk.translate((*xy, base + height / 2 + 0.25))
    b.thing(np.asarray(trunk.vertices), np.asarray(trunk.triangles))
    crown = o3d.geometry.TriangleMesh.create_sphere(1.0, 10)
    vertices = np.asarray(crown.vertices) * [radius, radius, radius * rng.uniform(0.7, 1.1)]
    b.thing(vertices + [*xy, base + height + 0.6 * radius], np.asarray(crown.triangles))


def _lamp(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, xy: np.ndarray, toward: np.ndarray) -> None:
    """A lamp pole 5-8 m high with an arm reaching over the road (``toward``: unit direction)."""
    base = float(ground.height(xy[None])[0])
    height = rng.uniform(5.0, 8.0)
    pole = o3d.geometry.TriangleMesh.create_cylinder(0.1, height, 8)
    pole.translate((*xy, base + height / 2))
    b.thing(np.asarray(pole.vertices), np.asarray(pole.triangles))
    end = xy + 1.5 * toward
    lo, hi = np.minimum(xy, end) - 0.06, np.maximum(xy, end) + 0.06
    b.box((*lo, base + height - 0.15), (*hi, base + height), solid=False)


def _kerb(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, start: float, stop: float,
          kerb: float, axis: int, side: float, skip: tuple[float, float] | None) -> None:
    """Parked cars along one kerb, from ``start`` to ``stop`` along ``axis``, ``kerb`` across it
    (the road's edge, the pavement on the ``side`` sign beyond it), then trees and lamps on the
    pavement; nothing in the span ``skip`` (a side street's mouth)."""
    def clear(u0: float, u1: float) -> bool:
        return skip is None or u1 <= skip[0] or u0 >= skip[1]

    def at(u: float, across: float) -> np.ndarray:
        return np.array([u, across]) if axis == 0 else np.array([across, u])

    u = start + rng.uniform(0, 5)
    while u < stop - 6:
        if rng.random() < 0.6 and clear(u, u + 5.5):
            add_car(b, rng, ground, at(u + 2.75, kerb - side * 1.15), axis == 0)
        u += 5.5 + (rng.uniform(0.5, 4) if rng.random() < 0.5 else 0.3)
    u = start + rng.uniform(2, 10)
    while u < stop - 2:
        if clear(u - 3, u + 3):
            _tree(b, rng, ground, at(u, kerb + side * _PAVEMENT * rng.uniform(0.45, 0.6)))
        u += rng.uniform(8, 18)
    u = start + rng.uniform(5, 20)
    while u < stop - 2:
        if clear(u - 1, u + 1):
            _lamp(b, rng, ground, at(u, kerb + side * 0.4), at(0.0, -side))
        u += rng.uniform(25, 40)


def _frontage(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, span: tuple[float, float],
              centre: float, near: float, depth: tuple[float, float], axis: int, side: float, skip) -> None:
    """A row of buildings along ``axis`` over ``span`` (gaps at random, none across ``skip``), their fronts
    ``near`` (+ a setback of up to 2 m) from the road's axis at ``centre``, on the ``side`` sign, as deep
    as ``depth`` draws."""
    for u0, u1 in building_plots(rng, *span, skip):
        front = near + rng.uniform(0, 2)
        across = sorted((centre + side * front, centre + side * (front + rng.uniform(*depth))))
        lo, hi = np.zeros(2), np.zeros(2)
        lo[axis], hi[axis] = u0, u1
        lo[1 - axis], hi[1 - axis] = across
        add_building(b, rng, ground, lo, hi)


def _side_street(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, x0: float, axis_x: float,
                 half: float, side: float) -> None:
    """A side street of half-width ``half`` along y at ``x = axis_x``, 30-70 m long on the ``side`` sign of
    the main road: buildings behind the main road's along both its edges (within the segment from ``x0``),
    cars, trees and lamps."""
    reach = _ROAD_HALF + rng.uniform(30, _SIDE_REACH)
    first = _ROAD_HALF + _PAVEMENT + _BLOCK_DEPTH + 1  # behind the main road's buildings
    rows = (first, reach) if side > 0 else (-reach, -first)
    kerbs = sorted((side * (_ROAD_HALF + 6), side * (reach - 2)))
    for edge in (-1.0, 1.0):
        front = axis_x + edge * (half + _PAVEMENT)
        room = (front - x0 if edge < 0 else x0 + SEGMENT - front) - 3  # the segment's edge, less the setback
        if room >= 5:
            _frontage(b, rng, ground, rows, axis_x, half + _PAVEMENT, (4.0, min(room, 14.0)), 1, edge, None)
        _kerb(b, rng, ground, kerbs[0], kerbs[1], axis_x + edge * half, 1, edge, None)


def _segment(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, x0: float) -> None:
    """Segment [x0, x0 + SEGMENT) of the main road: perhaps a side street to either side or both (a
    crossing), buildings along both sides, parked cars, trees and lamps."""
    axis_x, half = x0 + rng.uniform(20, 30), rng.uniform(3.5, 5.0)
    mouth = (axis_x - half - _PAVEMENT, axis_x + half + _PAVEMENT)
    for side in (-1.0, 1.0):
        street = rng.random() < 0.45
        skip = mouth if street else None
        _frontage(b, rng, ground, (x0, x0 + SEGMENT), 0.0, _ROAD_HALF + _PAVEMENT, (8.0, _BLOCK_DEPTH - 2), 0,
                  side, skip)
        _kerb(b, rng, ground, x0, x0 + SEGMENT, side * _ROAD_HALF, 0, side, skip)
        if street:
            _side_street(b, rng, ground, x0, axis_x, half, side)


class _Route:
    """The vehicle's path: the right-hand lane of the main road, weaving gently (up to 0.3 m over 80-200 m)."""

    def __init__(self, rng: np.random.Generator, ground: HeightField):
        self.ground = ground
        self.amplitude = rng.uniform(0, 0.3)
        self.wave = 2 * np.pi / rng.uniform(80, 200)
        self.phase = rng.uniform(0, 2 * np.pi)

    def at(self, s: np.ndarray, height: float) -> tuple[np.ndarray, np.ndarray]:
        """(T, 3) positions ``height`` above the road and (T,) headings (radians) at distances ``s``."""
        y = _LANE + self.amplitude * np.sin(self.wave * s + self.phase)
        heading = np.arctan(self.amplitude * self.wave * np.cos(self.wave * s + self.phase))
        xy = np.column_stack([s, y])
        return np.column_stack([xy, self.ground.height(xy) + height]), heading


def _world(seed: int, length: float, reach: float) -> tuple[Scene, _Route]:
    """The scene around a trajectory of ``length`` from x = 0, built past both ends by more than ``reach``."""
    rng = np.random.default_rng([seed, 0])
    relief, route_rng = _Ground(rng), np.random.default_rng([seed, 4])
    first, last = -int(np.ceil(reach / SEGMENT)), int(np.ceil((length + reach) / SEGMENT))
    across = _ROAD_HALF + _SIDE_REACH + 10
    ground = relief.field(np.array([first * SEGMENT, -across]), np.array([(last + 1) * SEGMENT, across]))
    b = SceneBuilder()
    b.add(*ground.mesh())
    for k in range(first, last + 1):
        _segment(b, np.random.default_rng([seed, 1, k % (1 << 32)]), ground, k * SEGMENT)
    region = [[first * SEGMENT, -_ROAD_HALF, 1.0], [(last + 1) * SEGMENT, _ROAD_HALF, 4.0]]
    return b.scene("drive", region, ground, elevation=(-25.0, 15.0)), _Route(route_rng, ground)


def _turn(heading: float) -> np.ndarray:
    a = np.radians(heading)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _frames(route: _Route, rotation: np.ndarray, s: np.ndarray, width: int, height: int, fov: float) -> list:
    """Forward-looking pinhole frames at distances ``s``, level, ``fov`` degrees across."""
    eyes, headings = route.at(s, CAMERA_HEIGHT)
    focal = width / 2 / np.tan(np.radians(fov) / 2)
    intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, focal, focal, (width - 1) / 2, (height - 1) / 2)
    frames = []
    for eye, h in zip(eyes @ rotation.T, headings):
        params = o3d.camera.PinholeCameraParameters()
        params.intrinsic = intrinsic
        params.extrinsic = look_at(eye, eye + rotation @ [np.cos(h), np.sin(h), 0.0])
        frames.append(params)
    return frames


def drive_log(length: float, seed: int = 0, *, points_per_metre: float = 3400.0, sweep_every: float = 5.0,
              frame_every: float = 5.0, lidar_range: float = 70.0, channels: int = 64, heading: float = 0.0,
              width: int = 640, height: int = 480, fov: float = 90.0) -> DriveLog:
    """A procedural driving log: a vehicle drives ``length`` metres of a street network, a LiDAR on its
    roof sweeps every ``sweep_every`` metres, the sweeps accumulate into one map, and a forward camera
    takes a frame every ``frame_every`` metres.

    Each sweep is a spinning LiDAR ``LIDAR_HEIGHT`` above the road (``channels`` rings from -25 to
    +15 degrees, hits up to ``lidar_range``), of ``points_per_metre * sweep_every`` points: density
    falls with range, and surfaces no sweep saw (the backs of buildings) have no points. A log is
    a function of ``seed`` and its arguments; a longer log of the same seed and settings extends a
    shorter one (the same sweeps and frames first, then more).

    Args:
        length: metres of trajectory (> 0).
        seed: the log's seed.
        points_per_metre: map points per metre of trajectory (3 400: 400 k points over 120 m).
        sweep_every, frame_every: metres between sweeps, and between frames.
        lidar_range: the LiDAR's range, metres.
        channels: the LiDAR's rings.
        heading: the map's turn about z, degrees: 0 runs the main road along +x, as the scene's axes.
        width, height, fov: the frames' image size and horizontal field of view (degrees).

    Returns:
        A :class:`DriveLog`.

    Raises:
        ValueError: a length, spacing, range or density that is not positive, or an image that is empty.
    """
    for name, value in (("length", length), ("points_per_metre", points_per_metre), ("sweep_every", sweep_every),
                        ("frame_every", frame_every), ("lidar_range", lidar_range), ("fov", fov)):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value}")
    if width < 1 or height < 1 or not fov < 180:
        raise ValueError(f"the frames need a positive image size and a field of view below 180 degrees, "
                         f"got {width} x {height} at {fov} degrees")
    scene, route = _world(seed, length, lidar_range)
    rotation = _turn(heading)
    sensors, _ = route.at(np.arange(0.0, length + 1e-9, sweep_every), LIDAR_HEIGHT)
    per_sweep = max(1, round(points_per_metre * sweep_every))
    points = [sample_lidar(scene, per_sweep, sensor[None], np.random.default_rng([seed, 2, i]), lidar_range,
                           channels)[0].astype(np.float32) for i, sensor in enumerate(sensors)]
    steps = np.arange(0.0, length + 1e-9, 1.0)
    where, headings = route.at(steps, 0.0)
    poses = np.tile(np.eye(4), (len(steps), 1, 1))
    poses[:, :3, :3] = rotation @ np.stack([_turn(np.degrees(h)) for h in headings])
    poses[:, :3, 3] = where @ rotation.T
    along = np.arange(0.0, length + 1e-9, frame_every)
    return DriveLog(scene, rotation, poses, sensors @ rotation.T,
                    np.concatenate(points) @ rotation.T.astype(np.float32),
                    np.repeat(np.arange(len(points), dtype=np.int32), [len(p) for p in points]),
                    _frames(route, rotation, along, width, height, fov), along, float(length), float(lidar_range))


def frame_view(frame) -> PinholeView:
    """The :class:`~o3dvis.apps.pinhole.PinholeView` of ``o3d.camera.PinholeCameraParameters``, to project points."""
    intrinsic = frame.intrinsic
    return PinholeView(np.asarray(frame.extrinsic), np.asarray(intrinsic.intrinsic_matrix), intrinsic.width,
                       intrinsic.height)


def frame_truth(log: DriveLog, index: int, points: np.ndarray | None = None, max_range: float = 40.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """The points of frame ``index`` (within ``max_range`` of its camera and inside its image) and which it sees.

    A point is visible when the ray from the camera towards its true place (the log's own map)
    first hits the scene's mesh no nearer than 2 cm before it. Which points are the frame's is
    decided on ``points``, the map a method is given (a noisy one, see :meth:`DriveLog.noisy`).

    Args:
        log: the driving log.
        index: the frame.
        points: (N, 3) the map as held, in the log's order (default: the log's own).
        max_range: the frame's range, metres.

    Returns:
        ``(indices, visible)``: (M,) int64 ascending indices of the frame's points in the map,
        (M,) bool whether the camera sees each.

    Raises:
        ValueError: ``points`` of another shape than the log's map, or a range that is not positive.
        IndexError: no such frame.
    """
    held = log.points if points is None else np.asarray(points)
    if held.shape != log.points.shape:
        raise ValueError(f"points must be the log's map as held, shape {log.points.shape}, got {held.shape}")
    if not max_range > 0:
        raise ValueError(f"max_range must be positive, got {max_range}")
    view = frame_view(log.frames[index])
    camera = view.location
    window = log.window(camera, max_range)
    near = window.start + within_range(torch.from_numpy(held[window]), torch.from_numpy(camera.astype(held.dtype)),
                                       max_range).numpy()
    origin = torch.zeros(3, dtype=torch.float64)
    inside = view.contains(torch.from_numpy(held[near].astype(np.float64)), origin,
                           torch.tensor(1.0, dtype=torch.float64))
    indices = near[inside.numpy()]
    offset = (log.points[indices].astype(np.float64) - camera) @ log.rotation  # into the scene's axes
    distance = np.linalg.norm(offset, axis=1)
    rays = np.column_stack([np.broadcast_to(camera @ log.rotation, offset.shape),
                            offset / np.maximum(distance, 1e-12)[:, None]])
    hit = log.scene.raycaster().cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    return indices.astype(np.int64), hit >= distance - _TRUTH_TOLERANCE
