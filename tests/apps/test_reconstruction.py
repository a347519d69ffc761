"""Surface reconstruction (``o3dvis.apps.reconstruction``) on ray-cast ground-truth visibility: the
view-dependent mesh and Poisson on oriented normals."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis.apps import reconstruct_poisson, reconstruct_view_dependent

from conftest import _box, _cloud, _sample


def test_view_dependent_mesh_is_the_visible_cap(sphere):
    points, _, method = sphere
    camera = np.array([0.0, 0.0, 5.0])
    mesh = reconstruct_view_dependent(_cloud(points), camera, method)
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert (vertices[:, 2] > 0.2 - 0.02).all()  # the cap z > r^2 / d seen from distance d = 5
    centroids = vertices[triangles].mean(axis=1)
    mesh.compute_triangle_normals()
    facing = np.einsum("ij,ij->i", np.asarray(mesh.triangle_normals), camera - centroids)
    assert (facing > 0).all()
    cap_area = 2 * np.pi * (1 - 1 / 5)  # 2 pi r h with h = r - r^2 / d
    assert 0.9 * cap_area < mesh.get_surface_area() < 1.02 * cap_area


def test_view_dependent_mesh_does_not_bridge_depth_jumps():
    near = _box((1.0, 1.0, 0.01), (0, 0, 1.0))
    far = _box((3.0, 3.0, 0.01), (0, 0, 0.0))
    points, _, method = _sample(near + far, 6000)
    mesh = reconstruct_view_dependent(_cloud(points), [0.2, 0.1, 6.0], method)
    z = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)][:, :, 2]
    assert len(z) > 1000
    assert ((z > 0.5).all(axis=1) | (z < 0.5).all(axis=1)).all()


@pytest.mark.parametrize("search_param", [None, o3d.geometry.KDTreeSearchParamKNN(12)])
def test_poisson_on_neural_normals_recovers_the_sphere(sphere, search_param):
    points, _, method = sphere
    pcd = _cloud(points)
    mesh, densities = reconstruct_poisson(pcd, depth=6, model=method, search_param=search_param)
    radii = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert len(densities) == len(radii)
    assert np.abs(radii - 1).mean() < 0.02
    assert abs(mesh.get_surface_area() - 4 * np.pi) < 0.05 * 4 * np.pi
    assert not pcd.has_normals()  # the input is left alone
    if search_param is not None:  # the search reaches the fit: one too narrow for any plane fails
        with pytest.raises(ValueError, match="three neighbours"):
            reconstruct_poisson(pcd, depth=6, model=method,
                                search_param=o3d.geometry.KDTreeSearchParamHybrid(radius=1e-9, max_nn=5))


def test_poisson_refuses_a_depth_beyond_what_open3d_the_cloud_and_memory_allow(sphere, monkeypatch):
    """Refused before the normals are estimated: Open3D crashes at depth 30, and deep octrees exhaust memory."""
    from o3dvis.apps import reconstruction

    points, _, method = sphere
    with pytest.raises(ValueError, match="depth=30 is beyond 16"):
        reconstruct_poisson(_cloud(points), depth=30, model=method)
    with pytest.raises(ValueError, match="depth=11 is beyond 10, the deepest octree 160 points fill"):
        reconstruct_poisson(_cloud(points[:160]), depth=11, model=method)
    monkeypatch.setattr(reconstruction, "_available_memory", lambda: 2**20)
    with pytest.raises(ValueError, match=r"depth=6 needs about .* GiB for 4000 points.* memory available"):
        reconstruct_poisson(_cloud(points), depth=6, model=method)
    monkeypatch.setattr(reconstruction, "_available_memory", lambda: None)  # unknown: only the other limits
    assert len(reconstruct_poisson(_cloud(points[:160]), depth=10, model=method)[0].vertices) > 0


def test_poisson_gives_the_same_mesh_on_every_run(sphere):
    points, _, method = sphere
    pcd = _cloud(points)
    runs = [reconstruct_poisson(pcd, depth=7, model=method)[0] for _ in range(3)]
    for mesh in runs[1:]:
        assert np.array_equal(np.asarray(mesh.vertices), np.asarray(runs[0].vertices))
        assert np.array_equal(np.asarray(mesh.triangles), np.asarray(runs[0].triangles))
