"""A procedural scene's structure: one triangle mesh, its solid and obstacle boxes, where cameras stand.

A :class:`Scene` is one triangle mesh and what the samplers must know about it:
its solid boxes (wall, floor and ceiling slabs, buildings, car bodies; a surface
point strictly inside one is buried and never sampled, and no camera stands in
one), the bounding boxes of its other objects (no camera stands in them either),
and where cameras stand (a range of x, y and of heights above the floor or the
ground). A :class:`SceneBuilder` collects the parts of a scene; :func:`box_scene`
makes one of given boxes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

__all__ = ["Scene", "HeightField", "SceneBuilder", "box_scene", "in_boxes"]

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
        out = in_boxes(points, self.solids, -_BURIED) | (points[:, 2] <= self.underside + _BURIED)
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


def in_boxes(points: np.ndarray, boxes: np.ndarray, pad: float, chunk: int = 1 << 20) -> np.ndarray:
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


class SceneBuilder:
    """Collects the parts of a scene (triangle soups, solid boxes, obstacle boxes) into a :class:`Scene`."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.triangles: list[np.ndarray] = []
        self.count = 0
        self.solids: list[np.ndarray] = []
        self.obstacles: list[np.ndarray] = []

    def add(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        """A surface that neither buries points nor keeps cameras out (the ground)."""
        self.vertices.append(np.asarray(vertices, dtype=np.float64))
        self.triangles.append(np.asarray(triangles, dtype=np.int64) + self.count)
        self.count += len(vertices)

    def box(self, lo, hi, solid: bool = True) -> None:
        """An axis-aligned box from corner ``lo`` to ``hi``: solid (buries points), else an obstacle."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        self.add(lo + _BOX_CORNERS * (hi - lo), _BOX_TRIANGLES)
        (self.solids if solid else self.obstacles).append(np.stack([lo, hi]))

    def thing(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        """An object that is not a box: its bounding box keeps cameras out."""
        self.add(vertices, triangles)
        self.obstacles.append(np.stack([vertices.min(axis=0), vertices.max(axis=0)]))

    def scene(self, kind: str, region, ground: HeightField | None = None, underside: float = -np.inf,
              elevation: tuple[float, float] = (-90.0, 90.0)) -> Scene:
        """The scene of every part added; the other arguments are :class:`Scene`'s."""
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
    b = SceneBuilder()
    for lo, hi in solids:
        b.box(lo, hi)
    for mesh in objects:
        b.thing(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    return b.scene(kind, region)
