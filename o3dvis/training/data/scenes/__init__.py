"""Procedural scenes for cameras inside the cloud: furnished rooms and streets, in metres.

* :mod:`.scene`: the :class:`Scene` (one mesh, its solid and obstacle boxes, where
  cameras stand), its builder and :func:`box_scene`.
* :func:`random_rooms` (:mod:`.rooms`): a building of one to six rooms 3-8 m wide,
  with slab walls that have thickness, interior walls with door gaps, windows,
  sometimes a corridor, no ceiling now and then, and furniture: meshes from a folder
  and procedural shapes scaled to furniture size, tables, cabinets and sofas.
* :func:`random_street` (:mod:`.streets`): a street 30-100 m long, or an open yard,
  between blocks of buildings, on uneven ground (a height field), with cars, trees,
  poles and clutter.
* :mod:`.sampling`: :func:`free_positions` (random camera or sensor positions
  inside, away from every surface and outside every object), :func:`sample_uniform`
  (area-weighted on the surfaces), :func:`sample_lidar` (the hits of rays cast from
  a few sensor positions: density falls with range, surfaces no sensor saw have no
  points) and :func:`scene_sample` (a labelled :class:`~o3dvis.training.data.sample.Sample`
  of a scene: points, normals, cameras inside and outside, ray-cast visibility).
* :func:`drive_log` (:mod:`.drives`): a driving log over a street network with side streets, a
  LiDAR map accumulated from sweeps along the trajectory, pinhole frames, and
  :func:`frame_truth`, what each frame sees by ray casting.
* :func:`random_scene`: a scene of one of the :data:`KINDS`.

Everything is a function of the random generator passed in.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..shapes import DEFAULT_PRIMITIVES
from .drives import DriveLog, drive_log, frame_truth, frame_view
from .rooms import random_rooms
from .sampling import SAMPLINGS, free_positions, sample_lidar, sample_uniform, scene_sample
from .scene import HeightField, Scene, box_scene
from .streets import random_street

__all__ = ["Scene", "HeightField", "SAMPLINGS", "KINDS", "box_scene", "random_rooms", "random_street",
           "random_scene", "free_positions", "sample_uniform", "sample_lidar", "scene_sample",
           "DriveLog", "drive_log", "frame_view", "frame_truth"]

KINDS = ("rooms", "street")
"""The scene generators of :func:`random_scene`."""


def random_scene(kind: str, rng: np.random.Generator, meshes: Sequence[str | Path] = (),
                 primitives: Sequence[str] = DEFAULT_PRIMITIVES) -> Scene:
    """:func:`random_rooms` or :func:`random_street` by name (see :data:`KINDS`)."""
    makers = {"rooms": random_rooms, "street": random_street}
    if kind not in makers:
        raise ValueError(f"unknown scene kind {kind!r}; choose from {', '.join(KINDS)}")
    return makers[kind](rng, meshes, primitives)
