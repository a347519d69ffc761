"""The plane Delaunay triangulation (``o3dvis/apps/delaunay.c``) against Qhull and against its
definition, on points in general position and on the degenerate sets Qhull struggles with."""

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import Delaunay

from o3dvis.apps import delaunay
from o3dvis.apps.delaunay import delaunay_triangles

from conftest import _check_triangulation, _signed_areas

native = pytest.mark.skipif(os.environ.get("O3DVIS_NATIVE") == "0", reason="C kernels turned off (O3DVIS_NATIVE=0)")


def _set(triangles: np.ndarray) -> set[tuple[int, ...]]:
    return set(map(tuple, np.sort(triangles, axis=1).tolist()))


@native
@pytest.mark.parametrize("count", [3, 4, 10, 100, 3000])
def test_equals_qhull_on_points_in_general_position(count):
    rng = np.random.default_rng(count)
    xy = rng.integers(0, 1 << 20, size=(count, 2)) / 1024.0  # on the snapping grid: nothing moves
    assert _set(delaunay_triangles(xy)) == _set(Delaunay(xy).simplices)
    normal = np.random.default_rng(count).normal(size=(count, 2))  # any doubles: snapped to 2^-26 of the extent
    assert len(_set(delaunay_triangles(normal)) ^ _set(Delaunay(normal).simplices)) <= 4


@native
@pytest.mark.parametrize("side", [3, 10, 50, 1000])
def test_integer_points_with_ties_and_duplicates(side):
    """Lattice points (many on one line, four on one circle) and repeats: still a Delaunay
    triangulation of the distinct points."""
    rng = np.random.default_rng(side)
    for count in (5, 60, 300):
        xy = rng.integers(0, side, size=(count, 2)).astype(float)
        if len(np.unique(xy, axis=0)) >= 3 and np.linalg.matrix_rank(xy - xy[0]) == 2:
            _check_triangulation(xy, delaunay_triangles(xy))


@native
def test_a_grid_is_split_into_two_triangles_a_cell():
    xy = np.stack(np.meshgrid(np.arange(30.0), np.arange(20.0)), -1).reshape(-1, 2)
    triangles = delaunay_triangles(xy * 0.37 + 5)  # scaled and moved off the snapping grid's nodes
    assert len(triangles) == 2 * 29 * 19
    _check_triangulation(xy, triangles)


@native
def test_points_on_one_circle():
    angle = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    circle = np.c_[np.cos(angle), np.sin(angle)]
    assert len(delaunay_triangles(circle)) == 98
    assert len(delaunay_triangles(np.r_[circle, [[0.0, 0.0]]])) == 100


@pytest.mark.parametrize("xy", [np.zeros((0, 2)), np.ones((2, 2)), np.ones((5, 2)),
                                np.c_[np.arange(10.0), 2 * np.arange(10.0) + 1],
                                np.c_[np.arange(9.0), np.full(9, 0.3)] * 0.1],
                         ids=["none", "two", "one point repeated", "a line", "a horizontal line"])
def test_fewer_than_three_distinct_or_collinear_give_no_triangle(xy):
    triangles = delaunay_triangles(xy)
    assert triangles.shape == (0, 3) and triangles.dtype == np.int64


@native
def test_points_near_a_line_give_triangles_thinner_than_the_snapping_grid():
    """Doubles on a line of slope 3 are not on one line after snapping (as they are not exactly on
    one before): thin triangles, as Qhull's degenerate simplices."""
    xy = np.c_[np.arange(7.0) * 0.1, np.arange(7.0) * 0.3]
    triangles = delaunay_triangles(xy)
    assert (np.abs(_signed_areas(xy, triangles)) <= 2.0 ** -26 * 1.8 ** 2).all()


@pytest.mark.parametrize("xy, message", [(np.ones((5, 3)), "shape"), (np.ones(6), "shape"),
                                         (np.array([[0, 0], [1, 0], [0, np.nan]]), "finite"),
                                         (np.array([[0, 0], [1, 0], [0, np.inf]]), "finite")])
def test_bad_coordinates_are_refused(xy, message):
    with pytest.raises(ValueError, match=message):
        delaunay_triangles(xy)


@native
@pytest.mark.parametrize("xy", [[[-1e308, 0], [1e308, 0], [0, 1e308]], [[0, 0], [1e-310, 0], [0, 3e-310]]],
                         ids=["wider than the largest double", "narrower than its inverse"])
def test_a_span_beyond_a_doubles_range_is_refused(xy):
    with pytest.raises(ValueError, match="span"), np.errstate(over="ignore"):
        delaunay_triangles(np.array(xy))


def test_too_many_points_are_refused(monkeypatch):
    monkeypatch.setattr(delaunay, "MAX_POINTS", 10)
    with pytest.raises(ValueError, match="at most 10"):
        delaunay_triangles(np.random.default_rng(0).random((11, 2)))


def test_without_the_library_qhull_answers_with_a_warning(tmp_path):
    code = ("import numpy as np\n"
            "from o3dvis.apps.delaunay import delaunay_triangles\n"
            "xy = np.random.default_rng(3).integers(0, 1 << 20, size=(500, 2)) / 1024.0\n"
            "np.save(r'%s', delaunay_triangles(xy))\n" % (tmp_path / "t.npy"))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "O3DVIS_NATIVE": "0"})
    assert run.returncode == 0, run.stderr
    assert "RuntimeWarning" in run.stderr and "Qhull" in run.stderr
    xy = np.random.default_rng(3).integers(0, 1 << 20, size=(500, 2)) / 1024.0
    assert _set(np.load(tmp_path / "t.npy")) == _set(delaunay_triangles(xy)) == _set(Delaunay(xy).simplices)


@native
def test_the_view_surface_in_c_equals_the_numpy_steps(monkeypatch):
    """Delaunay, the 3D edge filter, the turn to the camera and the unit normals in one pass of C
    give the numpy fallback's triangles, and its normals to rounding."""
    from o3dvis.apps import triangulation

    rng = np.random.default_rng(5)
    points = rng.normal(size=(4000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)  # a sphere, seen from +z
    points = np.r_[points[points[:, 2] > 0], [[0, 0, 0.5]] * 3]  # and a repeated point off it
    camera = np.array([0.2, -0.1, 4.0])
    coords = points[:, :2] / (camera[2] - points[:, 2:3])
    max_edge = rng.uniform(0.02, 0.12, len(points))  # some triangles too long at one end only
    fast = triangulation.delaunay_surface(points, coords, max_edge, camera)
    monkeypatch.setattr(delaunay, "available", lambda: False)
    slow = triangulation.delaunay_surface(points, coords, max_edge, camera)
    assert 0 < len(fast[0]) < len(delaunay_triangles(coords))
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_allclose(fast[1], slow[1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(fast[1], axis=1), 1, atol=1e-15)
    facing = np.einsum("ij,ij->i", fast[1], camera - points[fast[0][:, 0]])
    assert (facing >= 0).all()
