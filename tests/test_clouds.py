"""Clouds in every form the API takes, brought to one checked form (o3dvis.clouds)."""

import numpy as np
import open3d as o3d
import pytest
import torch

from o3dvis.clouds import Cloud, cloud_arrays, cloud_points, unit_normals

POINTS = np.random.default_rng(0).normal(size=(50, 3))


def test_every_form_gives_the_same_float64_points_and_normals():
    legacy = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(POINTS))
    legacy.normals = o3d.utility.Vector3dVector(-POINTS)
    tensor = o3d.t.geometry.PointCloud.from_legacy(legacy)
    for cloud in (legacy, tensor):
        points, normals = cloud_arrays(cloud)
        assert points.dtype == torch.float64 and torch.allclose(points, torch.from_numpy(POINTS), atol=1e-6)
        assert torch.allclose(normals, -torch.from_numpy(POINTS), atol=1e-6)
    for array in (POINTS, torch.from_numpy(POINTS), POINTS.astype(np.float32)):
        points, normals = cloud_arrays(array)
        assert normals is None and points.shape == (50, 3)
    np.testing.assert_array_equal(cloud_points(legacy), POINTS)


def test_a_cloud_is_taken_as_it_is_and_crops_its_normals_with_its_points():
    cloud = cloud_arrays(POINTS)
    assert cloud_arrays(cloud) is cloud
    with_normals = Cloud(cloud.points, torch.from_numpy(-POINTS))
    crop = with_normals.crop(torch.tensor([3, 7]))
    assert torch.equal(crop.points, cloud.points[[3, 7]]) and torch.equal(crop.normals, -cloud.points[[3, 7]])
    assert Cloud(cloud.points, None).crop(torch.tensor([1])).normals is None


@pytest.mark.parametrize("bad, error", [(np.zeros((0, 3)), ValueError), (np.zeros((4, 2)), ValueError),
                                        (np.full((3, 3), np.nan), ValueError), ("points", TypeError)])
def test_bad_clouds_are_refused(bad, error):
    with pytest.raises(error):
        cloud_arrays(bad)


def test_unit_normals_are_checked_and_scaled():
    normals = unit_normals(2 * POINTS, len(POINTS))
    np.testing.assert_allclose(normals.norm(dim=1).numpy(), 1.0)
    with pytest.raises(ValueError, match="shape"):
        unit_normals(POINTS[:10], len(POINTS))
    with pytest.raises(ValueError, match="zero length"):
        unit_normals(np.zeros_like(POINTS), len(POINTS))
