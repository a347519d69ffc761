"""The Open3D drop-ins (``o3dvis.dropins``) on a small random network: Open3D's semantics and
signature for ``hidden_point_removal_neural``, every camera form of one view, ``select_visible``,
``register``, and their refusals."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

import o3dvis

from conftest import _camera, _median_threshold, _pinhole


@pytest.fixture(scope="module")
def vis(small_vis):
    """The small random network's model here, not the shipped one."""
    return small_vis


def test_hpr_legacy_semantics(vis, pcd, points):
    camera = _camera(points)
    threshold = _median_threshold(vis, pcd, camera)
    mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, 500.0, threshold=threshold, model=vis,
                                                      triangulate=True)
    assert isinstance(mesh, o3d.geometry.TriangleMesh)
    assert isinstance(pt_map, list) and all(isinstance(i, int) for i in pt_map)
    assert 0 < len(pt_map) < len(points)
    assert min(pt_map) >= 0 and max(pt_map) < len(points) and len(set(pt_map)) == len(pt_map)
    # Open3D's own test: the mesh vertices are the selected points.
    np.testing.assert_array_equal(np.asarray(mesh.vertices), points[pt_map])
    expected = vis.encode(points).query(camera, threshold=threshold)[0]
    np.testing.assert_array_equal(np.flatnonzero(expected), pt_map)
    triangles = np.asarray(mesh.triangles)
    assert len(triangles) > 0 and triangles.min() >= 0 and triangles.max() < len(pt_map)
    v = np.asarray(mesh.vertices)
    normals = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])
    assert (np.einsum("ij,ij->i", normals, camera - v[triangles[:, 0]]) >= 0).all()


@pytest.mark.parametrize("dtype", [o3d.core.float64, o3d.core.float32])
def test_hpr_tensor_semantics(vis, pcd, points, dtype):
    camera = _camera(points)
    threshold = _median_threshold(vis, pcd, camera)
    tpcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(points, dtype=dtype))
    mesh, pt_map = o3dvis.hidden_point_removal_neural(tpcd, o3d.core.Tensor(camera), 500.0,
                                                      threshold=threshold, model=vis)
    assert isinstance(mesh, o3d.t.geometry.TriangleMesh)
    assert isinstance(pt_map, o3d.core.Tensor) and pt_map.dtype == o3d.core.int64
    index = pt_map.numpy()
    assert index.ndim == 1 and 0 < len(index) < len(points)
    assert index.min() >= 0 and index.max() < len(points)
    np.testing.assert_array_equal(mesh.vertex.positions.numpy(), tpcd.point.positions.numpy()[index])
    assert mesh.vertex.positions.dtype == dtype
    if dtype == o3d.core.float64:
        _, legacy_map = o3dvis.hidden_point_removal_neural(pcd, camera, threshold=threshold, model=vis)
        np.testing.assert_array_equal(index, legacy_map)


def test_radius_is_unused_and_triangles_optional(vis, pcd, points):
    camera = _camera(points)
    maps = [o3dvis.hidden_point_removal_neural(pcd, camera, r, model=vis)[1] for r in (None, 1e-9, 1e5)]
    assert maps[0] == maps[1] == maps[2]
    mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)
    assert pt_map == maps[0] and len(mesh.triangles) == 0
    np.testing.assert_array_equal(np.asarray(mesh.vertices), points[pt_map])


def test_the_drop_in_takes_every_camera_form_of_one_view(vis, pcd, points):
    field = vis.encode(points)
    eye = _camera(points)
    params = _pinhole(eye, points.mean(0), width=40, height=30, focal=60.0)
    threshold = _median_threshold(vis, points, eye)

    def pt_map(camera=None, **kwargs):
        return o3dvis.hidden_point_removal_neural(pcd, camera, threshold=threshold, model=vis, **kwargs)[1]

    culled = np.flatnonzero(field.query(params, threshold=threshold)[0])
    assert pt_map(params) == pt_map([params]) == culled.tolist()
    assert pt_map(params, frustum=False) == pt_map(eye) == pt_map(eye[None])
    assert 0 < len(culled) < len(pt_map(eye))
    selected = o3dvis.select_visible(pcd, params, threshold=threshold, model=vis)
    np.testing.assert_array_equal(np.asarray(selected.points), points[culled])
    direction = np.array([0.2, -0.3, -1.0])
    expected = np.flatnonzero(field.query(direction=direction, threshold=threshold)[0])
    mesh, ortho = o3dvis.hidden_point_removal_neural(pcd, direction=direction, threshold=threshold, model=vis,
                                                     triangulate=True)
    assert ortho == expected.tolist()
    v, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert len(triangles) > 0
    normals = np.cross(v[triangles[:, 1]] - v[triangles[:, 0]], v[triangles[:, 2]] - v[triangles[:, 0]])
    assert (normals @ -direction >= 0).all()  # facing the orthographic camera
    for batch in ([eye, -eye], [params, params]):
        with pytest.raises(ValueError, match=r"got 2: .*query\(cameras\)"):
            pt_map(batch)
    with pytest.raises(ValueError, match="exactly one"):
        pt_map(eye, direction=direction)


@pytest.mark.parametrize("radius", [-1.0, 0, float("nan"), float("inf")])
def test_the_drop_in_refuses_the_radius_open3d_refuses(vis, pcd, points, radius):
    camera = _camera(points)
    with pytest.raises(RuntimeError):
        pcd.hidden_point_removal(camera, radius)
    with pytest.raises(o3dvis.dropins.RadiusError, match="radius must be larger than zero") as error:
        o3dvis.hidden_point_removal_neural(pcd, camera, radius, model=vis)
    assert isinstance(error.value, RuntimeError) and isinstance(error.value, ValueError)


def test_the_drop_in_refuses_a_radius_that_is_not_a_number(vis, pcd, points):
    for bad in ("1", True, [1.0]):
        with pytest.raises(TypeError, match="radius must be a number"):
            o3dvis.hidden_point_removal_neural(pcd, _camera(points), bad, model=vis)


def test_hpr_docstring_documents_radius_as_unused():
    doc = o3dvis.hidden_point_removal_neural.__doc__
    assert "radius: unused" in doc and "points[pt_map]" in doc


def test_other_bad_arguments(vis, pcd, points):
    field = vis.encode(points)
    camera = _camera(points)
    with pytest.raises(ValueError, match="threshold"):
        field.query(camera, threshold=1.5)
    with pytest.raises(TypeError, match="threshold"):
        field.query(camera, threshold="high")
    with pytest.raises(ValueError, match="give one camera, got 2"):
        o3dvis.hidden_point_removal_neural(pcd, [camera, camera], model=vis)
    with pytest.raises(TypeError, match="PointCloud"):
        o3dvis.hidden_point_removal_neural(points, camera, model=vis)
    with pytest.raises(ValueError, match="one camera"):
        o3dvis.select_visible(pcd, [camera, -camera], model=vis)
    with pytest.raises(TypeError, match="model must be"):
        o3dvis.select_visible(pcd, camera, model=3)
    params = o3d.camera.PinholeCameraParameters()
    params.extrinsic = np.diag([2.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="rigid"):
        field.query(params)
    with pytest.raises(TypeError, match="VisibilityNetwork"):
        o3dvis.NeuralVisibility("default")


def test_select_visible_keeps_colours_and_normals(vis, pcd, points):
    cloud = o3d.geometry.PointCloud(pcd)
    cloud.estimate_normals()
    camera = _camera(points)
    threshold = _median_threshold(vis, points, camera)
    out = o3dvis.select_visible(cloud, camera, threshold=threshold, model=vis)
    index = np.flatnonzero(vis.encode(points).query(camera, threshold=threshold)[0])
    assert 0 < len(index) < len(points)
    np.testing.assert_array_equal(np.asarray(out.points), points[index])
    np.testing.assert_array_equal(np.asarray(out.colors), np.asarray(cloud.colors)[index])
    np.testing.assert_array_equal(np.asarray(out.normals), np.asarray(cloud.normals)[index])
    tcloud = o3d.t.geometry.PointCloud.from_legacy(cloud, o3d.core.float64)
    tout = o3dvis.select_visible(tcloud, camera, threshold=threshold, model=vis)
    assert isinstance(tout, o3d.t.geometry.PointCloud)
    np.testing.assert_array_equal(tout.point.positions.numpy(), points[index])
    np.testing.assert_array_equal(tout.point.colors.numpy(), np.asarray(cloud.colors)[index])
    np.testing.assert_array_equal(tout.point.normals.numpy(), np.asarray(cloud.normals)[index])
    arrays = o3dvis.select_visible(points, camera, threshold=threshold, model=vis)
    np.testing.assert_array_equal(np.asarray(arrays.points), points[index])


def test_register_attaches_the_method(vis, pcd, points):
    o3dvis.register()
    camera = _camera(points)
    mesh, pt_map = pcd.hidden_point_removal_neural(camera, 100.0, model=vis)
    assert pt_map == o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)[1]
    tpcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    _, tmap = tpcd.hidden_point_removal_neural(o3d.core.Tensor(camera), 100.0, model=vis)
    assert tmap.numpy().tolist() == pt_map
