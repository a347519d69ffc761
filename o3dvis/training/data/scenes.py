"""Procedural scenes for cameras inside the cloud: furnished rooms and streets, in metres.

A :class:`Scene` is one triangle mesh and what the samplers must know about it:
its solid boxes (wall, floor and ceiling slabs, buildings, car bodies; a surface
point strictly inside one is buried and never sampled, and no camera stands in
one), the bounding boxes of its other objects (no camera stands in them either),
and where cameras stand (a range of x, y and of heights above the floor or the
ground).

* :func:`random_rooms`: a building of one to six rooms 3-8 m wide, with slab
  walls that have thickness, interior walls with door gaps, windows, sometimes a
  corridor, no ceiling now and then, and furniture: meshes from a folder and
  procedural shapes scaled to furniture size, tables, cabinets and sofas.
* :func:`random_street`: a street 30-100 m long, or an open yard, between blocks
  of buildings, on uneven ground (a height field), with cars, trees, poles and
  clutter.
* :func:`free_positions`: random camera (or sensor) positions inside, away from
  every surface and outside every object.
* :func:`sample_uniform` (area-weighted on the surfaces) and :func:`sample_lidar`
  (the hits of rays cast from a few sensor positions: density falls with range,
  surfaces no sensor saw have no points).
* :func:`scene_sample`: a labelled :class:`~o3dvis.training.data.prepare.Sample` of a
  scene: points, normals, cameras inside and outside, ray-cast visibility.

Everything is a function of the random generator passed in.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from ...groundtruth import orient_normals, sample_viewpoints, visibility_from_mesh
from .prepare import Sample, sample_surface
from .shapes import DEFAULT_PRIMITIVES, random_shape

__all__ = ["Scene", "HeightField", "SAMPLINGS", "KINDS", "box_scene", "random_rooms", "random_street",
           "random_scene", "free_positions", "sample_uniform", "sample_lidar", "scene_sample"]

SAMPLINGS = ("uniform", "lidar")
"""The point samplings of :func:`scene_sample`."""

KINDS = ("rooms", "street")
"""The scene generators of :func:`random_scene`."""

_BURIED = 1e-4  # metres: a point this far inside a solid box is buried
_BOX_TRIANGLES = np.asarray(o3d.geometry.TriangleMesh.create_box().triangles)
_BOX_CORNERS = np.asarray(o3d.geometry.TriangleMesh.create_box().vertices)


@dataclass
class HeightField:
    """Ground heights ``heights[i, j]`` at ``origin + (i, j) * spacing``, linear on each triangle.

    Its mesh splits every cell along the same diagonal as :meth:`height` does,
    so the two agree exactly.
    """

    origin: np.ndarray
    spacing: float
    heights: np.ndarray

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height under each (x, y) (clamped to the grid's extent)."""
        nx, ny = self.heights.shape
        g = (np.asarray(xy, dtype=np.float64) - self.origin) / self.spacing
        i = np.clip(np.floor(g[:, 0]).astype(np.int64), 0, nx - 2)
        j = np.clip(np.floor(g[:, 1]).astype(np.int64), 0, ny - 2)
        fx, fy = np.clip(g[:, 0] - i, 0, 1), np.clip(g[:, 1] - j, 0, 1)
        h = self.heights
        h00, h10, h01, h11 = h[i, j], h[i + 1, j], h[i, j + 1], h[i + 1, j + 1]
        lower = fx + fy <= 1  # triangle (00, 10, 01), else (10, 11, 01)
        return np.where(lower, h00 + fx * (h10 - h00) + fy * (h01 - h00),
                        h11 + (1 - fx) * (h01 - h11) + (1 - fy) * (h10 - h11))

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices and triangles (normals up)."""
        nx, ny = self.heights.shape
        i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
        vertices = np.column_stack([self.origin[0] + i.ravel() * self.spacing,
                                    self.origin[1] + j.ravel() * self.spacing, self.heights.ravel()])
        a = (i[:-1, :-1] * ny + j[:-1, :-1]).ravel()
        b, c, d = a + ny, a + 1, a + ny + 1  # (i+1, j), (i, j+1), (i+1, j+1)
        triangles = np.concatenate([np.column_stack([a, b, c]), np.column_stack([b, d, c])])
        return vertices, triangles


@dataclass
class Scene:
    """A procedural scene.

    Args:
        mesh: every surface, one triangle mesh.
        kind: ``"rooms"``, ``"street"`` or a caller's name.
        solids: (S, 2, 3) axis-aligned boxes (min, max) that are solid: points
            strictly inside are buried, cameras stay out.
        obstacles: (O, 2, 3) bounding boxes of the other objects: cameras stay out.
        region: (2, 3) where cameras stand: x and y ranges, and the range of
            heights above the floor (or the ground).
        ground: the uneven ground, if any (points below it are buried).
        underside: points at or below this height are buried (a building's
            floor slab rests on the ground; nobody sees its underside).
        elevation: elevation range (degrees) of the LiDAR-like sensor's rays.
    """

    mesh: o3d.geometry.TriangleMesh
    kind: str
    solids: np.ndarray
    obstacles: np.ndarray
    region: np.ndarray
    ground: HeightField | None = None
    underside: float = -np.inf
    elevation: tuple[float, float] = (-90.0, 90.0)
    _caster: o3d.t.geometry.RaycastingScene | None = field(default=None, repr=False, compare=False)

    def floor(self, xy: np.ndarray) -> np.ndarray:
        """Height of the floor or ground under each (x, y)."""
        return self.ground.height(xy) if self.ground is not None else np.zeros(len(xy))

    def buried(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: strictly inside a solid box, or below the ground."""
        out = _in_boxes(points, self.solids, -_BURIED) | (points[:, 2] <= self.underside + _BURIED)
        if self.ground is not None:
            out |= points[:, 2] < self.floor(points[:, :2]) - 1e-3
        return out

    def raycaster(self) -> o3d.t.geometry.RaycastingScene:
        """The mesh in an Open3D ray-casting scene (built once)."""
        if self._caster is None:
            self._caster = o3d.t.geometry.RaycastingScene()
            self._caster.add_triangles(
                o3d.core.Tensor(np.asarray(self.mesh.vertices, dtype=np.float32)),
                o3d.core.Tensor(np.asarray(self.mesh.triangles, dtype=np.uint32)))
        return self._caster


def _in_boxes(points: np.ndarray, boxes: np.ndarray, pad: float, chunk: int = 1 << 20) -> np.ndarray:
    """(N,) bool: each point lies strictly inside some box grown by ``pad`` (< 0: shrunk)."""
    out = np.zeros(len(points), dtype=bool)
    if len(boxes) == 0:
        return out
    lo, hi = boxes[:, 0] - pad, boxes[:, 1] + pad
    step = max(1, chunk // len(boxes))
    for s in range(0, len(points), step):
        p = points[s:s + step, None, :]
        out[s:s + step] = ((p > lo) & (p < hi)).all(axis=2).any(axis=1)
    return out


def _boxes(boxes) -> np.ndarray:
    return np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)


class _Builder:
    """Collects triangle soups, solid boxes and obstacle boxes."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.count = 0
        self.solids: list[np.ndarray] = []
        self.obstacles: list[np.ndarray] = []

    def add(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices.append(np.asarray(vertices, dtype=np.float64))
        self.triangles.append(np.asarray(triangles, dtype=np.int64) + self.count)
        self.count += len(vertices)

    def box(self, lo, hi, solid: bool = True) -> None:
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        self.add(lo + _BOX_CORNERS * (hi - lo), _BOX_TRIANGLES)
        (self.solids if solid else self.obstacles).append(np.stack([lo, hi]))

    def thing(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        """An object that is not a box: its bounding box keeps cameras out."""
        self.add(vertices, triangles)
        self.obstacles.append(np.stack([vertices.min(axis=0), vertices.max(axis=0)]))

    def scene(self, kind: str, region, ground: HeightField | None = None, underside: float = -np.inf,
              elevation: tuple[float, float] = (-90.0, 90.0)) -> Scene:
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.concatenate(self.vertices)),
                                         o3d.utility.Vector3iVector(np.concatenate(self.triangles).astype(np.int32)))
        return Scene(mesh, kind, _boxes(self.solids), _boxes(self.obstacles),
                     np.asarray(region, dtype=np.float64), ground, underside, elevation)


def box_scene(solids, region, objects: Sequence[o3d.geometry.TriangleMesh] = (), kind: str = "boxes") -> Scene:
    """A scene made of solid axis-aligned boxes and other objects.

    Points strictly inside a box are buried; make boxes that meet overlap
    (a wall reaching into the floor slab), so that no face lies on another.

    Args:
        solids: (S, 2, 3) boxes (min corner, max corner).
        region: (2, 3) where cameras stand (x, y ranges; heights above z = 0).
        objects: other meshes (their bounding boxes keep cameras out).
        kind: the scene's name.
    """
    solids = _boxes(solids)
    if not (solids[:, 1] > solids[:, 0]).all():
        raise ValueError("every solid box needs min < max on each axis")
    b = _Builder()
    for lo, hi in solids:
        b.box(lo, hi)
    for mesh in objects:
        b.thing(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    return b.scene(kind, region)


# --- furniture and objects -------------------------------------------------------------------------

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


def _object(rng: np.random.Generator, meshes: Sequence[str], primitives: Sequence[str],
            mesh_share: float) -> tuple[np.ndarray, np.ndarray]:
    """A mesh from the folder list (with probability ``mesh_share``) or a procedural shape, turned at random."""
    if meshes and rng.random() < mesh_share:
        vertices, triangles = _read_mesh(str(meshes[rng.integers(len(meshes))]))
    else:
        shape = random_shape(rng, int(rng.integers(1, 4)), primitives)
        vertices, triangles = np.asarray(shape.vertices), np.asarray(shape.triangles)
    return vertices @ _rotation(rng, rng.random() < 0.5).T, triangles


def _fit(vertices: np.ndarray, size: float, limit: np.ndarray) -> np.ndarray:
    """Scales so that the largest extent is ``size`` and every extent at most ``limit``; min corner at 0."""
    extent = np.maximum(vertices.max(axis=0) - vertices.min(axis=0), 1e-9)
    scale = min(size / extent.max(), *(limit / extent))
    v = vertices * scale
    return v - v.min(axis=0)


def _table(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    w, d, h = rng.uniform(0.8, 2.0), rng.uniform(0.6, 1.2), rng.uniform(0.7, 0.8)
    top, leg = rng.uniform(0.03, 0.06), rng.uniform(0.04, 0.08)
    boxes = [((0, 0, h - top), (w, d, h))]
    for x in (0, w - leg):
        for y in (0, d - leg):
            boxes.append(((x, y, 0), (x + leg, y + leg, h - top)))
    return [(np.array(lo, float), np.array(hi, float)) for lo, hi in boxes]


def _cabinet(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(np.zeros(3), np.array([rng.uniform(0.6, 2.0), rng.uniform(0.3, 0.6), rng.uniform(0.8, 2.2)]))]


def _sofa(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    w, d = rng.uniform(1.4, 2.4), rng.uniform(0.8, 1.0)
    back = rng.uniform(0.15, 0.25)
    return [(np.zeros(3), np.array([w, d, rng.uniform(0.4, 0.5)])),
            (np.zeros(3), np.array([w, back, rng.uniform(0.8, 1.0)]))]


def _place(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, extent: np.ndarray,
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


def _furnish(b: _Builder, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, floor: float,
             height: float, count: int, meshes: Sequence[str], primitives: Sequence[str]) -> None:
    """Puts ``count`` pieces of furniture on the floor of the room with footprint [lo, hi]."""
    taken: list[np.ndarray] = []
    for _ in range(count):
        pick = rng.random()
        if pick < 0.3:
            parts = (_table, _cabinet, _sofa)[rng.integers(3)](rng)
            extent = np.max([hi_ for _, hi_ in parts], axis=0)
            turn = rng.random() < 0.5  # a quarter turn keeps the boxes axis-aligned
            if turn:
                parts = [(lo_[[1, 0, 2]], hi_[[1, 0, 2]]) for lo_, hi_ in parts]
                extent = extent[[1, 0, 2]]
            corner = _place(rng, lo, hi, extent[:2], taken)
            if corner is not None and extent[2] < height - 0.3:
                base = np.array([*corner, floor])
                for part_lo, part_hi in parts:
                    b.box(base + part_lo, base + part_hi)
            continue
        vertices, triangles = _object(rng, meshes, primitives, mesh_share=0.6)
        limit = np.array([*(0.8 * (hi - lo)), height - 0.5])
        vertices = _fit(vertices, rng.uniform(0.4, 2.0), limit)
        extent = vertices.max(axis=0)
        corner = _place(rng, lo, hi, extent[:2], taken)
        if corner is not None:
            b.thing(vertices + np.array([*corner, floor]), triangles)


# --- rooms -------------------------------------------------------------------------------------------

def _wall(b: _Builder, axis: int, at: float, s0: float, s1: float, thickness: float, z0: float, z1: float,
          openings: list[tuple[float, float, float, float]]) -> None:
    """A slab wall along ``axis`` (0: x, 1: y) at the other coordinate ``at``, from s0 to s1 (grown by half
    its thickness at both ends), z0 to z1, with openings (u0, u1, v0, v1): along the wall and in height."""
    half = thickness / 2

    def piece(u0: float, u1: float, v0: float, v1: float) -> None:
        if u1 - u0 > 1e-6 and v1 - v0 > 1e-6:
            lo, hi = np.zeros(3), np.zeros(3)
            lo[axis], hi[axis] = u0, u1
            lo[1 - axis], hi[1 - axis] = at - half, at + half
            lo[2], hi[2] = v0, v1
            b.box(lo, hi)

    u = s0 - half
    for o0, o1, v0, v1 in sorted(openings):
        piece(u, o0, z0, z1)
        piece(o0, o1, z0, v0)
        piece(o0, o1, v1, z1)
        u = o1
    piece(u, s1 + half, z0, z1)


def _opening(rng: np.random.Generator, s0: float, s1: float, margin: float, width: tuple[float, float],
             bottom: tuple[float, float], top: tuple[float, float]) -> tuple[float, float, float, float] | None:
    w = rng.uniform(*width)
    if s1 - s0 - 2 * margin < w:
        return None
    u0 = rng.uniform(s0 + margin, s1 - margin - w)
    return (u0, u0 + w, rng.uniform(*bottom), rng.uniform(*top))


def random_rooms(rng: np.random.Generator, meshes: Sequence[str | Path] = (),
                 primitives: Sequence[str] = DEFAULT_PRIMITIVES) -> Scene:
    """A furnished building: a grid of 1-3 x 1-2 rooms 3-8 m wide, sometimes with a corridor.

    Walls are slabs 8-40 cm thick, 2.5-3.5 m high; interior walls mostly have a
    door gap, exterior ones windows and sometimes a door; one building in five
    has no ceiling. Each room holds 0-5 pieces of furniture 0.4-2 m in size.

    Args:
        rng: numpy random generator (the scene is a function of its state).
        meshes: mesh files to draw furniture from (none: procedural shapes only).
        primitives: parts of the procedural shapes (see :mod:`o3dvis.training.data.shapes`).

    Returns:
        A :class:`Scene` of kind ``"rooms"``, floor at z = 0, centred on x = y = 0.
    """
    meshes = [str(m) for m in meshes]
    cols = rng.uniform(3, 8, int(rng.integers(1, 4)))
    rows = list(rng.uniform(3, 8, int(rng.integers(1, 3))))
    corridor = -1
    if rng.random() < 0.4:
        corridor = int(rng.integers(len(rows) + 1))
        rows.insert(corridor, rng.uniform(1.2, 2.2))
    xs = np.concatenate([[0], np.cumsum(cols)])
    ys = np.concatenate([[0], np.cumsum(rows)])
    xs, ys = xs - xs[-1] / 2, ys - ys[-1] / 2
    height = rng.uniform(2.5, 3.5)
    outer, inner = rng.uniform(0.15, 0.4), rng.uniform(0.08, 0.2)
    slab = rng.uniform(0.15, 0.3)
    ceiling = rng.random() < 0.8
    top = height + slab if ceiling else height
    b = _Builder()
    grow = outer / 2
    b.box((xs[0] - grow, ys[0] - grow, -slab), (xs[-1] + grow, ys[-1] + grow, 0))
    if ceiling:
        b.box((xs[0] - grow, ys[0] - grow, height), (xs[-1] + grow, ys[-1] + grow, height + slab))
    door = dict(width=(0.8, 1.2), bottom=(-slab - 1, -slab - 1), top=(2.0, min(2.2, height - 0.2)))
    window = dict(width=(0.8, 2.0), bottom=(0.8, 1.0), top=(min(2.0, height - 0.3), min(2.3, height - 0.2)))
    front_door = rng.random() < 0.3
    for axis, lines, spans in ((0, ys, xs), (1, xs, ys)):
        for k, at in enumerate(lines):
            exterior = k in (0, len(lines) - 1)
            for s0, s1 in zip(spans[:-1], spans[1:]):
                if not exterior and axis == 1 and corridor >= 0 and np.isclose(s0, ys[corridor]):
                    continue  # no wall across the corridor
                openings = []
                if exterior:
                    kind = door if front_door and axis == 0 and k == 0 else window
                    front_door = front_door and not (axis == 0 and k == 0)
                    if kind is door or rng.random() < 0.5:
                        openings.append(_opening(rng, s0, s1, outer + 0.2, **kind))
                elif rng.random() < 0.85:
                    openings.append(_opening(rng, s0, s1, inner + 0.2, **door))
                _wall(b, axis, at, s0, s1, outer if exterior else inner, -slab, top,
                      [o for o in openings if o is not None])
    for i in range(len(cols)):
        for j in range(len(rows)):
            lo = np.array([xs[i], ys[j]]) + inner / 2 + 0.05
            hi = np.array([xs[i + 1], ys[j + 1]]) - inner / 2 - 0.05
            count = int(rng.integers(0, 2)) if j == corridor else int(rng.integers(0, 6))
            _furnish(b, rng, lo, hi, 0.0, height, count, meshes, primitives)
    region = [[xs[0] + grow, ys[0] + grow, 0.4], [xs[-1] - grow, ys[-1] - grow, height - 0.3]]
    return b.scene("rooms", region, underside=-slab)


# --- streets and yards -----------------------------------------------------------------------------

def _ground(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray) -> HeightField:
    """Smooth random relief (a few long waves, 0.1-1 m) with small bumps."""
    spacing = rng.uniform(1.0, 2.0)
    n = np.ceil((hi - lo) / spacing).astype(int) + 1
    i, j = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
    xy = np.stack([lo[0] + i * spacing, lo[1] + j * spacing], axis=-1)
    heights = np.zeros(i.shape)
    amplitude = rng.uniform(0.1, 1.0)
    for _ in range(3):
        direction = rng.normal(size=2)
        k = 2 * np.pi / rng.uniform(10, 60) * direction / np.linalg.norm(direction)
        heights += amplitude / 3 * np.sin(xy @ k + rng.uniform(0, 2 * np.pi))
    heights += rng.normal(scale=rng.uniform(0.0, 0.04), size=heights.shape)
    return HeightField(np.asarray(lo, dtype=np.float64), spacing, heights)


def _row(rng: np.random.Generator, start: float, stop: float, skip: tuple[float, float] | None
         ) -> list[tuple[float, float]]:
    """Building frontages (u0, u1) along a row, with random gaps, avoiding the span ``skip``."""
    out, u = [], start + rng.uniform(0, 4)
    while u < stop - 4:
        w = min(rng.uniform(6, 25), stop - u)
        if skip is None or u + w <= skip[0] or u >= skip[1]:
            out.append((u, u + w))
        u += w + (rng.uniform(2, 6) if rng.random() < 0.4 else 0.0)
    return out


def _car(b: _Builder, rng: np.random.Generator, ground: HeightField, centre: np.ndarray, along_x: bool) -> None:
    length, width = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9)
    size = np.array([length, width] if along_x else [width, length])
    lo_xy = centre - size / 2
    corners = lo_xy + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) * size
    base = float(ground.height(corners).max())
    wheel = 0.3
    body = rng.uniform(0.6, 0.8)
    b.box((*lo_xy, base + wheel), (*(lo_xy + size), base + wheel + body))
    cabin = np.array([rng.uniform(0.45, 0.65) * length, 0.85 * width])
    cabin = cabin if along_x else cabin[::-1]
    c_lo = centre - cabin / 2
    b.box((*c_lo, base + wheel + body - 0.05), (*(c_lo + cabin), base + wheel + body + rng.uniform(0.5, 0.7)))
    for sx in (-0.35, 0.35):
        for sy in (-0.5, 0.5):
            offset = np.array([sx * length, sy * width]) if along_x else np.array([sy * width, sx * length])
            tyre = o3d.geometry.TriangleMesh.create_cylinder(wheel, 0.22, 16)
            tyre.rotate(o3d.geometry.get_rotation_matrix_from_xyz((np.pi / 2, 0, 0) if along_x
                                                                  else (0, np.pi / 2, 0)), center=(0, 0, 0))
            tyre.translate((*(centre + offset), base + wheel))
            b.thing(np.asarray(tyre.vertices), np.asarray(tyre.triangles))


def _street_object(b: _Builder, rng: np.random.Generator, ground: HeightField, xy: np.ndarray,
                   meshes: Sequence[str], primitives: Sequence[str]) -> None:
    """A tree, a pole, or an object 0.5-2.5 m (from the mesh list or procedural) standing at ``xy``."""
    base = float(ground.height(xy[None])[0])
    pick = rng.random()
    if pick < 0.4:
        trunk = rng.uniform(2, 4)
        pole = o3d.geometry.TriangleMesh.create_cylinder(rng.uniform(0.08, 0.25), trunk, 12)
        pole.translate((*xy, base + trunk / 2))
        b.thing(np.asarray(pole.vertices), np.asarray(pole.triangles))
        if pick < 0.25:
            r = rng.uniform(1.0, 3.0)
            crown = o3d.geometry.TriangleMesh.create_sphere(r, 16)
            crown.translate((*xy, base + trunk + 0.8 * r))
            b.thing(np.asarray(crown.vertices), np.asarray(crown.triangles))
        return
    vertices, triangles = _object(rng, meshes, primitives, mesh_share=0.5)
    vertices = _fit(vertices, rng.uniform(0.5, 2.5), np.full(3, 2.5))
    extent = vertices.max(axis=0)
    corner = xy - extent[:2] / 2
    footprint = corner + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) * extent[:2]
    b.thing(vertices + np.array([*corner, ground.height(footprint).max()]), triangles)


def _building(b: _Builder, rng: np.random.Generator, ground: HeightField, lo: np.ndarray, hi: np.ndarray) -> None:
    """A block (sometimes with a narrower upper storey) from below the ground to 4-30 m above it."""
    grid = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 6), np.linspace(lo[1], hi[1], 6)), -1).reshape(-1, 2)
    heights = ground.height(grid)
    top = heights.max() + rng.uniform(4, 30)
    b.box((*lo, heights.min() - 0.5), (*hi, top))
    if rng.random() < 0.3:
        inset = rng.uniform(0.1, 0.3) * (hi - lo)
        b.box((*(lo + inset), top - 0.05), (*(hi - inset), top + rng.uniform(2, 8)))


def random_street(rng: np.random.Generator, meshes: Sequence[str | Path] = (),
                  primitives: Sequence[str] = DEFAULT_PRIMITIVES) -> Scene:
    """A street 30-100 m long (sometimes with a cross street), or an open yard 20-60 m wide, between
    blocks of buildings 4-30 m high, on uneven ground, with cars, trees, poles and objects.

    Args:
        rng: numpy random generator (the scene is a function of its state).
        meshes: mesh files for some of the objects (none: procedural shapes only).
        primitives: parts of the procedural shapes.

    Returns:
        A :class:`Scene` of kind ``"street"``, centred on x = y = 0.
    """
    meshes = [str(m) for m in meshes]
    yard = rng.random() < 0.3
    depth, setback = rng.uniform(8, 16), rng.uniform(0, 4)
    if yard:
        open_half = np.full(2, rng.uniform(20, 60) / 2)
    else:
        open_half = np.array([rng.uniform(30, 100) / 2, rng.uniform(8, 20) / 2])
    half = open_half + setback + depth
    half[0] = half[0] if yard else open_half[0]
    ground = _ground(rng, -half - 2, half + 2)
    b = _Builder()
    b.add(*ground.mesh())
    rows = [(0, s) for s in (-1, 1)] + ([(1, s) for s in (-1, 1)] if yard else [])
    cross = None
    if not yard and rng.random() < 0.4:
        c = rng.uniform(-open_half[0] + 10, open_half[0] - 10)
        cross = (c - open_half[1], c + open_half[1])
    for axis, side in rows:
        span = open_half[axis]
        for u0, u1 in _row(rng, -span, span, cross):
            d = depth * rng.uniform(0.6, 1.0)
            near = open_half[1 - axis] + setback
            lo, hi = np.zeros(2), np.zeros(2)
            lo[axis], hi[axis] = u0, u1
            lo[1 - axis], hi[1 - axis] = (near, near + d) if side > 0 else (-near - d, -near)
            _building(b, rng, ground, lo, hi)
    taken: list[np.ndarray] = []
    # cars: parked along the kerbs of a street, anywhere in a yard; axis-aligned so that they are solid boxes
    for _ in range(int(rng.integers(2, 4 + int(open_half.prod() / 60)))):
        along_x = bool(rng.random() < 0.8) if not yard else bool(rng.random() < 0.5)
        size = np.array([5.0, 2.2] if along_x else [2.2, 5.0])
        if yard:
            lo_xy, hi_xy = -open_half + 1, open_half - 1
        else:
            y = open_half[1] - 1.5 if rng.random() < 0.5 else rng.uniform(-open_half[1] + 1.5, open_half[1] - 1.5)
            y *= rng.choice([-1, 1])
            lo_xy = np.array([-open_half[0] + 1, y - size[1] / 2 - 0.1])
            hi_xy = np.array([open_half[0] - 1, y + size[1] / 2 + 0.1])
        corner = _place(rng, lo_xy, hi_xy, size, taken)
        if corner is not None:
            _car(b, rng, ground, corner + size / 2, along_x)
    for _ in range(int(rng.integers(2, 4 + int(open_half.prod() / 80)))):
        corner = _place(rng, -open_half + 0.5, open_half - 0.5, np.full(2, 1.0), taken)
        if corner is not None:
            _street_object(b, rng, ground, corner + 0.5, meshes, primitives)
    reach = open_half + setback - 0.5  # cameras stand in the street or the yard, heads 1-4 m above the ground
    region = [[*-reach, 1.0], [*reach, 4.0]]
    return b.scene("street", region, ground, elevation=(-30.0, 20.0))


def random_scene(kind: str, rng: np.random.Generator, meshes: Sequence[str | Path] = (),
                 primitives: Sequence[str] = DEFAULT_PRIMITIVES) -> Scene:
    """:func:`random_rooms` or :func:`random_street` by name (see :data:`KINDS`)."""
    makers = {"rooms": random_rooms, "street": random_street}
    if kind not in makers:
        raise ValueError(f"unknown scene kind {kind!r}; choose from {', '.join(KINDS)}")
    return makers[kind](rng, meshes, primitives)


# --- cameras and samplings -----------------------------------------------------------------------

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
        p = p[~_in_boxes(p, scene.solids, margin) & ~_in_boxes(p, scene.obstacles, margin)]
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
        A :class:`~o3dvis.training.data.prepare.Sample`; the inside cameras come first.
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
