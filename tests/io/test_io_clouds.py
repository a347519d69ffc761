"""Point cloud files read through ``o3dvis.io.read_point_cloud`` (``o3dvis.io.clouds``): what Open3D
wrote is read back as Open3D reads it, and binary PCD doubles as their doubles."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from conftest import SPHERE, as_cloud


@pytest.mark.parametrize("normals", ["F 8", "F 4", None])
def test_a_binary_pcd_of_doubles_is_read_as_its_doubles(tmp_path, normals):
    """Open3D reads binary 8-byte floats as zeros: the reader decodes the points' and normals' own."""
    from o3dvis.io import read_point_cloud

    rng = np.random.default_rng(4)
    points, unit = rng.normal(size=(200, 3)), SPHERE[rng.integers(0, len(SPHERE), 200)]
    names, sizes, columns = "x y z", "8 8 8", [points]
    if normals is not None:
        size = normals.split()[1]
        names, sizes = names + " normal_x normal_y normal_z", f"{sizes} {size} {size} {size}"
    layout = [("xyz", "<f8", (3,))] + ([("n", f"<f{normals.split()[1]}", (3,))] if normals else [])
    table = np.zeros(len(points), layout)
    table["xyz"] = points
    if normals:
        table["n"] = unit
    count = len(names.split())
    header = (f"VERSION 0.7\nFIELDS {names}\nSIZE {sizes}\nTYPE {' '.join(['F'] * count)}\n"
              f"COUNT {' '.join(['1'] * count)}\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
              f"POINTS {len(points)}\nDATA binary\n")
    path = tmp_path / "doubles.pcd"
    path.write_bytes(header.encode() + table.tobytes())
    read = read_point_cloud(path)
    np.testing.assert_array_equal(np.asarray(read.points), points)
    assert read.has_normals() == (normals is not None)
    if normals:
        np.testing.assert_array_equal(np.asarray(read.normals), table["n"].astype(np.float64))


@pytest.mark.parametrize("suffix, options", [(".ply", {}), (".ply", {"write_ascii": True}), (".pcd", {}),
                                             (".pcd", {"write_ascii": True}), (".pcd", {"compressed": True}),
                                             (".xyz", {}), (".xyzn", {}), (".xyzrgb", {}), (".pts", {})])
def test_the_reader_gives_what_open3d_wrote(tmp_path, suffix, options):
    from o3dvis.io import read_point_cloud

    rng = np.random.default_rng(3)
    pcd = as_cloud(rng.normal(size=(500, 3)))
    pcd.normals = o3d.utility.Vector3dVector(SPHERE[rng.integers(0, len(SPHERE), 500)])
    pcd.colors = o3d.utility.Vector3dVector(rng.random((500, 3)))
    path = tmp_path / f"cloud{suffix}"
    assert o3d.io.write_point_cloud(str(path), pcd, **options)
    read = read_point_cloud(path)
    expected = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(read.points), np.asarray(expected.points))
    np.testing.assert_allclose(np.asarray(read.points), np.asarray(pcd.points), atol=1e-5, rtol=1e-5)  # ASCII PLY: 6 digits
    assert read.has_normals() == expected.has_normals() and read.has_colors() == expected.has_colors()
