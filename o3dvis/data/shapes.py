"""Procedural training shapes: random unions of primitives under random transforms.

Tori, thin plates, open cups and bowls, nested and interpenetrating parts give
self-occlusion that the real meshes alone would not cover, so training never
depends on one mesh set.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import open3d as o3d

__all__ = ["random_shape", "PRIMITIVES", "write_shapes"]

Mesh = o3d.geometry.TriangleMesh


def _open_cylinder(rng: np.random.Generator) -> Mesh:
    """A cup: cylinder wall with a bottom, open at the top (both sides are surface)."""
    r, h = rng.uniform(0.3, 1.0), rng.uniform(0.5, 2.0)
    mesh = o3d.geometry.TriangleMesh.create_cylinder(r, h, resolution=32, split=4)
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    keep = ~(v[t][:, :, 2] > h / 2 - 1e-9).all(axis=1)
    mesh.triangles = o3d.utility.Vector3iVector(t[keep])
    mesh.remove_unreferenced_vertices()
    return mesh


def _bowl(rng: np.random.Generator) -> Mesh:
    """A hemispherical shell, possibly shallower."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(rng.uniform(0.5, 1.0), resolution=24)
    v, t = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    cut = rng.uniform(-0.3, 0.5) * np.abs(v[:, 2]).max()
    mesh.triangles = o3d.utility.Vector3iVector(t[(v[t][:, :, 2] < cut).all(axis=1)])
    mesh.remove_unreferenced_vertices()
    return mesh


PRIMITIVES: dict[str, Callable[[np.random.Generator], Mesh]] = {
    "box": lambda rng: Mesh.create_box(*rng.uniform(0.2, 1.5, 3)),
    "plate": lambda rng: Mesh.create_box(*rng.uniform(0.8, 2.0, 2), rng.uniform(0.01, 0.06)),
    "sphere": lambda rng: Mesh.create_sphere(rng.uniform(0.2, 1.0), resolution=24),
    "cylinder": lambda rng: Mesh.create_cylinder(rng.uniform(0.1, 0.6), rng.uniform(0.3, 2.0), 24),
    "cone": lambda rng: Mesh.create_cone(rng.uniform(0.2, 0.8), rng.uniform(0.3, 1.5), 24),
    "torus": lambda rng: Mesh.create_torus(rng.uniform(0.5, 1.0), rng.uniform(0.05, 0.35), 32, 16),
    "cup": _open_cylinder,
    "bowl": _bowl,
}


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return o3d.geometry.get_rotation_matrix_from_quaternion(q / np.linalg.norm(q))


def random_shape(rng: np.random.Generator, parts: int | None = None) -> Mesh:
    """A union of 1-6 random primitives, each scaled, rotated and placed at random.

    Args:
        rng: numpy random generator (the shape is a function of its state).
        parts: number of primitives (default: random in 1..6).

    Returns:
        A triangle mesh centred near the origin.
    """
    parts = int(rng.integers(1, 7)) if parts is None else parts
    names = list(PRIMITIVES)
    mesh = Mesh()
    for _ in range(parts):
        part = PRIMITIVES[names[rng.integers(len(names))]](rng)
        part.translate(-part.get_center())
        part.scale(rng.uniform(0.5, 1.5), center=np.zeros(3))
        part.rotate(_random_rotation(rng), center=np.zeros(3))
        part.translate(rng.normal(scale=0.6, size=3))
        mesh += part
    return mesh.translate(-mesh.get_axis_aligned_bounding_box().get_center())


def write_shapes(out_dir: str, count: int, seed: int = 0) -> list[str]:
    """Writes ``count`` random shapes as ``procedural__NNNNN.ply`` into ``out_dir``."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        mesh = random_shape(np.random.default_rng([seed, i]))
        path = out / f"procedural__{i:05d}.ply"
        o3d.io.write_triangle_mesh(str(path), mesh)
        paths.append(str(path))
    return paths
