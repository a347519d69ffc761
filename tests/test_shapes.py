"""Procedural shapes: every primitive is a usable surface; the thick walls have two sides."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis.data.shapes import DEFAULT_PRIMITIVES, PRIMITIVES, random_shape, write_shapes


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
