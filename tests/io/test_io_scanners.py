"""LAS, LAZ and E57 maps read through o3dvis.io.read_point_cloud: small files written here with
laspy and pye57, read back exactly; cut, wrong or empty files refused with a ValueError naming the
file; a missing extra named in an ImportError."""

import re
import struct
import sys

import numpy as np
import pytest

from o3dvis.io import SUFFIXES, read_point_cloud

laspy = pytest.importorskip("laspy")
pye57 = pytest.importorskip("pye57")

_LAS_OFFSETS_AT = 155  # bytes into a LAS header where its x, y, z offsets (float64) start


def _write_las(path, count=200, point_format=3, rgb_max=65535, seed=0):
    """A LAS or LAZ file of ``count`` points on a grid of 1/8 (exact in binary), with colours up to
    ``rgb_max`` and intensities where the format has them; returns (points, colours 16-bit, intensity)."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(point_format=point_format, version="1.2")
    header.scales, header.offsets = [0.125] * 3, [1000.0, -20.0, 5.0]
    las = laspy.LasData(header)
    points = rng.integers(-4000, 4000, (count, 3)) * 0.125 + header.offsets
    las.x, las.y, las.z = points.T
    intensity = rng.integers(0, 4000, count)
    las.intensity = intensity
    colours = rng.integers(0, rgb_max + 1, (count, 3))
    if point_format in (2, 3):
        las.red, las.green, las.blue = colours.T
    las.write(path)
    return points, colours, intensity


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_las_map_is_read_exactly_with_its_16_bit_colours(tmp_path, suffix):
    path = tmp_path / f"map{suffix}"
    points, colours, _ = _write_las(path)
    pcd = read_point_cloud(path)
    assert np.asarray(pcd.points).dtype == np.float64
    np.testing.assert_array_equal(np.asarray(pcd.points), points)
    np.testing.assert_array_equal(np.asarray(pcd.colors), colours / 65535.0)


def test_8_bit_colours_in_a_las_file_are_scaled_by_255(tmp_path):
    path = tmp_path / "map.las"
    _, colours, _ = _write_las(path, rgb_max=255)
    np.testing.assert_array_equal(np.asarray(read_point_cloud(path).colors), colours / 255.0)


def test_a_las_map_without_colours_has_its_intensity_as_grey(tmp_path):
    path = tmp_path / "map.las"
    points, _, intensity = _write_las(path, point_format=1)
    pcd = read_point_cloud(path)
    np.testing.assert_array_equal(np.asarray(pcd.points), points)
    np.testing.assert_array_equal(np.asarray(pcd.colors), np.repeat(intensity[:, None] / intensity.max(), 3, axis=1))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@pytest.mark.parametrize("cut", ["a whole point", "inside a point", "inside the header"])
def test_a_las_file_cut_short_is_refused(tmp_path, suffix, cut):
    """laspy itself reads an uncompressed file cut at a whole point as the points before the cut."""
    path = tmp_path / f"map{suffix}"
    _write_las(path)
    content = path.read_bytes()
    size = {"a whole point": len(content) - 34 * 5, "inside a point": len(content) - 50, "inside the header": 150}[cut]
    path.write_bytes(content[:size])
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: .*truncated"):
        read_point_cloud(path)


def test_a_file_that_is_not_a_las_one_is_refused(tmp_path):
    path = tmp_path / "map.las"
    path.write_bytes(b"PLYF this is no LAS header, just some bytes " * 20)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: not a LAS file"):
        read_point_cloud(path)


def test_a_las_header_with_a_nan_offset_is_refused(tmp_path):
    path = tmp_path / "map.las"
    _write_las(path)
    content = bytearray(path.read_bytes())
    content[_LAS_OFFSETS_AT:_LAS_OFFSETS_AT + 8] = struct.pack("<d", float("nan"))
    path.write_bytes(bytes(content))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: bad scale factors .* or offsets"):
        read_point_cloud(path)


def test_a_las_file_without_points_is_refused(tmp_path):
    path = tmp_path / "map.las"
    _write_las(path, count=0)
    with pytest.raises(ValueError, match=rf"^no points could be read from {re.escape(str(path))}$"):
        read_point_cloud(path)


def _write_e57(path, scans):
    """An E57 file of scans given as (local points (N, 3) in float32 values, rotation (w, x, y, z), translation,
    extra fields)."""
    with pye57.E57(str(path), mode="w") as e57:
        for local, rotation, translation, extra in scans:
            data = {name: local[:, axis] for axis, name in enumerate(("cartesianX", "cartesianY", "cartesianZ"))}
            e57.write_scan_raw({**data, **extra}, rotation=np.asarray(rotation), translation=np.asarray(translation))


def _local(rng, count):
    return rng.uniform(-5, 5, (count, 3)).astype(np.float32).astype(np.float64)


def test_e57_scans_are_moved_by_their_poses_and_merged(tmp_path):
    from pyquaternion import Quaternion  # pye57's dependency, an independent conversion

    rng = np.random.default_rng(1)
    scans = []
    for k in range(2):
        local = _local(rng, 300 + k)
        colours = {name: rng.integers(0, 256, len(local)).astype(np.uint8)
                   for name in ("colorRed", "colorGreen", "colorBlue")}
        rotation = np.array([np.cos(0.4 * (k + 1)), 0.0, np.sin(0.4 * (k + 1)), 0.0])
        scans.append((local, rotation, np.array([10.0 * k, 2.0, -3.0]), colours))
    path = tmp_path / "map.e57"
    _write_e57(path, scans)
    pcd = read_point_cloud(path)
    expected = np.concatenate([local @ Quaternion(q).rotation_matrix.T + t for local, q, t, _ in scans])
    np.testing.assert_allclose(np.asarray(pcd.points), expected, rtol=0, atol=1e-12)
    rgb = np.concatenate([np.stack([extra[name] for name in ("colorRed", "colorGreen", "colorBlue")], axis=1)
                          for *_, extra in scans])
    np.testing.assert_array_equal(np.asarray(pcd.colors), rgb / 255.0)


def test_an_e57_scan_without_colours_has_its_intensity_as_grey(tmp_path):
    rng = np.random.default_rng(2)
    local = _local(rng, 100)
    intensity = np.linspace(0.25, 0.75, len(local))
    path = tmp_path / "map.e57"
    _write_e57(path, [(local, [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], {"intensity": intensity})])
    pcd = read_point_cloud(path)
    np.testing.assert_array_equal(np.asarray(pcd.points), local)
    grey = np.asarray(pcd.colors)
    np.testing.assert_allclose(grey[:, 0], (intensity - 0.25) / 0.5, atol=1e-6)  # limits: the file's extremes
    assert (grey == grey[:, :1]).all()


def test_e57_points_marked_invalid_are_left_out(tmp_path):
    local = _local(np.random.default_rng(5), 40)
    state = np.tile(np.array([0, 2, 0, 1], dtype=np.int8), 10)  # 1: a direction only, 2: no point
    path = tmp_path / "map.e57"
    _write_e57(path, [(local, [1.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0], {"cartesianInvalidState": state})])
    np.testing.assert_array_equal(np.asarray(read_point_cloud(path).points), local[state == 0] + [1.0, 2.0, 3.0])


def test_an_e57_pose_that_is_no_rotation_is_refused(tmp_path):
    path = tmp_path / "map.e57"
    _write_e57(path, [(_local(np.random.default_rng(3), 50), [2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], {})])
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: scan 0's pose rotation .* not a unit quaternion"):
        read_point_cloud(path)


@pytest.mark.parametrize("damage", ["cut", "not an E57 file"])
def test_a_damaged_e57_file_is_refused(tmp_path, damage):
    path = tmp_path / "map.e57"
    _write_e57(path, [(_local(np.random.default_rng(4), 500), [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], {})])
    content = path.read_bytes()
    path.write_bytes(content[:len(content) // 2] if damage == "cut" else b"ASTM-E57 or not " * 100)
    message = rf"^{re.escape(str(path))}: not an E57 file, or a truncated or corrupted one \(\w"
    with pytest.raises(ValueError, match=message):
        read_point_cloud(path)
    assert path.is_file()  # pye57 removes a file it fails to open for writing; one read stays


@pytest.mark.parametrize("suffix, module, extra", [(".las", "laspy", "las"), (".laz", "laspy", "las"),
                                                   (".e57", "pye57", "e57")])
def test_a_missing_extra_is_named(tmp_path, monkeypatch, suffix, module, extra):
    path = tmp_path / f"map{suffix}"
    path.write_bytes(b"\0" * 400)
    monkeypatch.setitem(sys.modules, module, None)  # an import of it raises ImportError
    with pytest.raises(ImportError, match=rf'needs {module}; install it with: pip install "o3dvis\[{extra}\]"'):
        read_point_cloud(path)


def test_a_laz_file_without_a_decompressor_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "map.laz"
    _write_las(path)
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    with pytest.raises(ImportError, match=r'needs lazrs; install it with: pip install "o3dvis\[las\]"'):
        read_point_cloud(path)


def test_the_scanner_formats_are_among_the_suffixes_read():
    assert {".las", ".laz", ".e57"} <= set(SUFFIXES)
