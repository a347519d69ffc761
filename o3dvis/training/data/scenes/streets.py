"""Streets and yards: blocks of buildings on uneven ground, with cars, trees, poles and clutter."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import open3d as o3d

from ..shapes import DEFAULT_PRIMITIVES
from .objects import fit_extent, place_footprint, random_object
from .scene import HeightField, SceneBuilder, Scene

__all__ = ["random_street"]


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


def building_plots(rng: np.random.Generator, start: float, stop: float, skip: tuple[float, float] | None
         ) -> list[tuple[float, float]]:
    """Building frontages (u0, u1) along a row, with random gaps, avoiding the span ``skip``."""
    out, u = [], start + rng.uniform(0, 4)
    while u < stop - 4:
        w = min(rng.uniform(6, 25), stop - u)
        if skip is None or u + w <= skip[0] or u >= skip[1]:
            out.append((u, u + w))
        u += w + (rng.uniform(2, 6) if rng.random() < 0.4 else 0.0)
    return out


def add_car(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, centre: np.ndarray, along_x: bool) -> None:
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


def _street_object(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, xy: np.ndarray,
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
    vertices, triangles = random_object(rng, meshes, primitives, mesh_share=0.5)
    vertices = fit_extent(vertices, rng.uniform(0.5, 2.5), np.full(3, 2.5))
    extent = vertices.max(axis=0)
    corner = xy - extent[:2] / 2
    footprint = corner + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) * extent[:2]
    b.thing(vertices + np.array([*corner, ground.height(footprint).max()]), triangles)


def add_building(b: SceneBuilder, rng: np.random.Generator, ground: HeightField, lo: np.ndarray, hi: np.ndarray) -> None:
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
    b = SceneBuilder()
    b.add(*ground.mesh())
    rows = [(0, s) for s in (-1, 1)] + ([(1, s) for s in (-1, 1)] if yard else [])
    cross = None
    if not yard and rng.random() < 0.4:
        c = rng.uniform(-open_half[0] + 10, open_half[0] - 10)
        cross = (c - open_half[1], c + open_half[1])
    for axis, side in rows:
        span = open_half[axis]
        for u0, u1 in building_plots(rng, -span, span, cross):
            d = depth * rng.uniform(0.6, 1.0)
            near = open_half[1 - axis] + setback
            lo, hi = np.zeros(2), np.zeros(2)
            lo[axis], hi[axis] = u0, u1
            lo[1 - axis], hi[1 - axis] = (near, near + d) if side > 0 else (-near - d, -near)
            add_building(b, rng, ground, lo, hi)
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
        corner = place_footprint(rng, lo_xy, hi_xy, size, taken)
        if corner is not None:
            add_car(b, rng, ground, corner + size / 2, along_x)
    for _ in range(int(rng.integers(2, 4 + int(open_half.prod() / 80)))):
        corner = place_footprint(rng, -open_half + 0.5, open_half - 0.5, np.full(2, 1.0), taken)
        if corner is not None:
            _street_object(b, rng, ground, corner + 0.5, meshes, primitives)
    reach = open_half + setback - 0.5  # cameras stand in the street or the yard, heads 1-4 m above the ground
    region = [[*-reach, 1.0], [*reach, 4.0]]
    return b.scene("street", region, ground, elevation=(-30.0, 20.0))
