"""Procedural training shapes: random unions of primitives under random transforms.

Tori, thin plates, open cups and bowls, nested and interpenetrating parts give
self-occlusion that the real meshes alone would not cover, so training never
depends on one mesh set. The thick-walled cups, tubs and bowls (opt-in by name)
put two opposite-facing surfaces closer than the point spacing, as in the
walls of real cups, bowls and bathtubs. Enclosures (opt-in) put a random shape
inside a closed shell, or one with a hole cut in it: whole surfaces that no
viewpoint sees, as in the inner parts of CAD assemblies.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import open3d as o3d

__all__ = ["random_shape", "random_enclosure", "PRIMITIVES", "DEFAULT_PRIMITIVES", "write_shapes"]

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


def _lathe(profile: np.ndarray, resolution: int) -> Mesh:
    """Revolves a closed ``(radius, height)`` polyline from the axis to the axis about z."""
    angles = np.linspace(0, 2 * np.pi, resolution, endpoint=False)
    r, z = profile[:, :1], profile[:, 1:]
    rings = np.stack([r * np.cos(angles), r * np.sin(angles), np.broadcast_to(z, r.shape[:1] + angles.shape)],
                     axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(len(profile) - 1), np.arange(resolution), indexing="ij")
    a, b = i * resolution + j, i * resolution + (j + 1) % resolution
    c, d = a + resolution, b + resolution
    tris = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    mesh = Mesh(o3d.utility.Vector3dVector(rings), o3d.utility.Vector3iVector(tris))
    mesh.merge_close_vertices(1e-9)  # the rings of radius 0 collapse to one pole each
    return mesh.remove_degenerate_triangles()


def _thick_cup(rng: np.random.Generator) -> Mesh:
    """A cup (or, with 4-6 sides, a tub) whose wall and bottom are 2-12 % of its radius thick."""
    r, h = rng.uniform(0.3, 1.0), rng.uniform(0.4, 2.0)
    t = r * rng.uniform(0.02, 0.12)
    profile = np.array([[0, 0], [r, 0], [r, h], [r - t, h], [r - t, t], [0, t]])
    return _lathe(profile, int(rng.choice([4, 6, 32])))


def _thick_bowl(rng: np.random.Generator) -> Mesh:
    """A spherical bowl with a wall 2-12 % of its radius thick and a flat rim."""
    r = rng.uniform(0.5, 1.0)
    t = r * rng.uniform(0.02, 0.12)
    theta = np.linspace(-np.pi / 2, rng.uniform(-0.35, 0.5), 12)
    arc = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    return _lathe(np.concatenate([r * arc, (r - t) * arc[::-1]]), 32)


PRIMITIVES: dict[str, Callable[[np.random.Generator], Mesh]] = {
    "box": lambda rng: Mesh.create_box(*rng.uniform(0.2, 1.5, 3)),
    "plate": lambda rng: Mesh.create_box(*rng.uniform(0.8, 2.0, 2), rng.uniform(0.01, 0.06)),
    "sphere": lambda rng: Mesh.create_sphere(rng.uniform(0.2, 1.0), resolution=24),
    "cylinder": lambda rng: Mesh.create_cylinder(rng.uniform(0.1, 0.6), rng.uniform(0.3, 2.0), 24),
    "cone": lambda rng: Mesh.create_cone(rng.uniform(0.2, 0.8), rng.uniform(0.3, 1.5), 24),
    "torus": lambda rng: Mesh.create_torus(rng.uniform(0.5, 1.0), rng.uniform(0.05, 0.35), 32, 16),
    "cup": _open_cylinder,
    "bowl": _bowl,
    "thick_cup": _thick_cup,
    "thick_bowl": _thick_bowl,
}

DEFAULT_PRIMITIVES = ("box", "plate", "sphere", "cylinder", "cone", "torus", "cup", "bowl")
"""The parts :func:`random_shape` draws from unless told (the shipped sample and benchmarks use them)."""


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return o3d.geometry.get_rotation_matrix_from_quaternion(q / np.linalg.norm(q))


def random_shape(rng: np.random.Generator, parts: int | None = None,
                 primitives: Sequence[str] = DEFAULT_PRIMITIVES) -> Mesh:
    """A union of 1-6 random primitives, each scaled, rotated and placed at random.

    Args:
        rng: numpy random generator (the shape is a function of its state).
        parts: number of primitives (default: random in 1..6).
        primitives: names in :data:`PRIMITIVES` to draw the parts from, uniformly.

    Returns:
        A triangle mesh centred near the origin.
    """
    unknown = sorted(set(primitives) - set(PRIMITIVES))
    if unknown or not primitives:
        what = f"unknown primitives {unknown}" if unknown else "no primitives given"
        raise ValueError(f"{what}; choose from {sorted(PRIMITIVES)}")
    parts = int(rng.integers(1, 7)) if parts is None else parts
    mesh = Mesh()
    for _ in range(parts):
        part = PRIMITIVES[primitives[rng.integers(len(primitives))]](rng)
        part.translate(-part.get_center())
        part.scale(rng.uniform(0.5, 1.5), center=np.zeros(3))
        part.rotate(_random_rotation(rng), center=np.zeros(3))
        part.translate(rng.normal(scale=0.6, size=3))
        mesh += part
    return mesh.translate(-mesh.get_axis_aligned_bounding_box().get_center())


def _shell(rng: np.random.Generator) -> tuple[Mesh, float]:
    """A closed sphere, ellipsoid or box about the origin, finely triangulated, and its inradius."""
    axes = rng.uniform(0.6, 1.4, 3) if rng.random() < 0.7 else np.ones(3)
    if rng.random() < 0.5:
        mesh = Mesh.create_sphere(1.0, resolution=32)
    else:
        mesh = Mesh.create_box(2.0, 2.0, 2.0).translate((-1.0, -1.0, -1.0)).subdivide_midpoint(4)
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * axes)
    return mesh, float(axes.min())


def random_enclosure(rng: np.random.Generator, primitives: Sequence[str] = DEFAULT_PRIMITIVES,
                     hole: bool | None = None) -> Mesh:
    """A random shape (2-5 parts) inside a shell, which half of the time has a hole cut in it.

    The shell is a sphere, ellipsoid or box; the shape is scaled to 50-90 % of
    the shell's inradius, so that it lies wholly inside. The hole removes the
    shell's triangles beyond a random plane, 30-80 % of the way to its edge.

    Args:
        rng: numpy random generator (the mesh is a function of its state).
        primitives: names in :data:`PRIMITIVES` to draw the inner parts from.
        hole: cut a hole in the shell (None: at random).

    Returns:
        A triangle mesh centred near the origin, randomly rotated.
    """
    inner = random_shape(rng, int(rng.integers(2, 6)), primitives)
    shell, inradius = _shell(rng)
    v = np.asarray(inner.vertices)
    inner.scale(rng.uniform(0.5, 0.9) * inradius / np.linalg.norm(v, axis=1).max(), center=np.zeros(3))
    if (rng.random() < 0.5) if hole is None else hole:
        axis = rng.normal(size=3)
        v, t = np.asarray(shell.vertices), np.asarray(shell.triangles)
        height = v @ (axis / np.linalg.norm(axis))
        cut = rng.uniform(0.3, 0.8) * height.max()
        shell.triangles = o3d.utility.Vector3iVector(t[~(height[t] > cut).all(axis=1)])
        shell.remove_unreferenced_vertices()
    mesh = shell + inner
    return mesh.rotate(_random_rotation(rng), center=np.zeros(3))


def write_shapes(out_dir: str, count: int, seed: int = 0,
                 primitives: Sequence[str] = DEFAULT_PRIMITIVES, enclosed: bool = False) -> list[str]:
    """Writes ``count`` random shapes as ``procedural__NNNNN.ply`` into ``out_dir``.

    With ``enclosed``, each is a :func:`random_enclosure` of the primitives.
    """
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        rng = np.random.default_rng([seed, i])
        mesh = random_enclosure(rng, primitives) if enclosed else random_shape(rng, primitives=primitives)
        path = out / f"procedural__{i:05d}.ply"
        o3d.io.write_triangle_mesh(str(path), mesh)
        paths.append(str(path))
    return paths
