"""Furnished buildings: rooms with slab walls, doors, windows, sometimes a corridor, and furniture."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..shapes import DEFAULT_PRIMITIVES
from .objects import fit_extent, place_footprint, random_object
from .scene import Scene, SceneBuilder

__all__ = ["random_rooms"]


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


def _furnish(b: SceneBuilder, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, floor: float,
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
            corner = place_footprint(rng, lo, hi, extent[:2], taken)
            if corner is not None and extent[2] < height - 0.3:
                base = np.array([*corner, floor])
                for part_lo, part_hi in parts:
                    b.box(base + part_lo, base + part_hi)
            continue
        vertices, triangles = random_object(rng, meshes, primitives, mesh_share=0.6)
        limit = np.array([*(0.8 * (hi - lo)), height - 0.5])
        vertices = fit_extent(vertices, rng.uniform(0.4, 2.0), limit)
        extent = vertices.max(axis=0)
        corner = place_footprint(rng, lo, hi, extent[:2], taken)
        if corner is not None:
            b.thing(vertices + np.array([*corner, floor]), triangles)


def _wall(b: SceneBuilder, axis: int, at: float, s0: float, s1: float, thickness: float, z0: float, z1: float,
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
    b = SceneBuilder()
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
