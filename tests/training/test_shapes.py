"""Procedural shapes: every primitive is a usable surface; the thick walls have two sides;
enclosures hide their contents unless holed."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis.groundtruth import visibility_from_mesh
from o3dvis.training.data.shapes import DEFAULT_PRIMITIVES, PRIMITIVES, random_enclosure, random_shape, write_shapes


def _hits(mesh: o3d.geometry.TriangleMesh, origin, direction) -> np.ndarray:
    """Distances along one ray to every surface it crosses, nearest first."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    ray = o3d.core.Tensor([[*origin, *direction]], dtype=o3d.core.float32)
    return np.sort(scene.list_intersections(ray)["t_hit"].numpy())


@pytest.mark.parametrize("name", sorted(PRIMITIVES))
def test_every_primitive_has_surface(name):
    for seed in range(3):
        mesh = PRIMITIVES[name](np.random.default_rng(seed))
        assert len(mesh.triangles) > 0 and mesh.get_surface_area() > 0


@pytest.mark.parametrize("name", ["thick_cup", "thick_bowl"])
def test_thick_walls_are_closed_two_sided_surfaces(name):
    for seed in range(6):
        mesh = PRIMITIVES[name](np.random.default_rng(seed))
        assert mesh.is_watertight() and not mesh.is_self_intersecting()
        # The inner wall is the outer one scaled about the axis (cup) or the centre (bowl), so a ray
        # from there, off the mesh's vertices and edges, crosses both at distances in ratio (r - t) / r.
        if name == "thick_cup":
            hits = _hits(mesh, (0, 0, mesh.get_max_bound()[2] / 2), (1, 0.05, 0))
        else:
            hits = _hits(mesh, (0, 0, 0), (0.05, 0.03, -1))
        assert len(hits) == 2, hits
        assert 0.02 - 1e-6 <= (hits[1] - hits[0]) / hits[1] <= 0.12 + 1e-6


def test_primitives_are_chosen_by_name(tmp_path):
    one = random_shape(np.random.default_rng(0), parts=1, primitives=("thick_bowl",))
    assert one.is_watertight()
    files = write_shapes(str(tmp_path), 2, seed=1, primitives=("thick_cup", "plate"))
    assert all(len(o3d.io.read_triangle_mesh(f).triangles) for f in files)
    assert set(DEFAULT_PRIMITIVES) < set(PRIMITIVES)
    with pytest.raises(ValueError, match="unknown primitives"):
        random_shape(np.random.default_rng(0), primitives=("box", "teapot"))
    with pytest.raises(ValueError, match="no primitives given"):
        random_shape(np.random.default_rng(0), primitives=())



def _seen(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Distances from the origin of points sampled on the mesh, and whether any of 32 cameras sees each."""
    o3d.utility.random.seed(0)
    points = np.asarray(mesh.sample_points_uniformly(20000).points)
    cameras = np.random.default_rng(0).normal(size=(32, 3))
    cameras *= 6 / np.linalg.norm(cameras, axis=1, keepdims=True)
    return np.linalg.norm(points, axis=1), visibility_from_mesh(mesh, points, cameras).any(axis=0)


def test_enclosures_hide_their_contents_unless_holed(tmp_path):
    for seed in range(3):
        # a closed convex shell around parts within 90 % of its inradius: what no camera sees is the
        # parts, every one of them nearer the centre than any point of the shell
        radius, seen = _seen(random_enclosure(np.random.default_rng([seed, 0]), hole=False))
        shell = radius[seen].min()
        assert 0.01 < (~seen).mean() < 0.9 and radius[~seen].max() < 0.95 * shell
        # the same shell and parts (turned otherwise): through the hole, some of the parts are seen
        radius, seen = _seen(random_enclosure(np.random.default_rng([seed, 0]), hole=True))
        assert (seen & (radius < 0.95 * shell)).any()
    files = write_shapes(str(tmp_path), 2, seed=1, enclosed=True)
    assert all(len(o3d.io.read_triangle_mesh(f).triangles) for f in files)
