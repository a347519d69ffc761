"""Shadows (``o3dvis.apps.shadows``) of a cube on a floor under a light above it, on ray-cast
ground-truth visibility; and the ``model=`` keyword the applications take."""

from __future__ import annotations

import numpy as np
import pytest

from o3dvis.apps import make_view, points_in_shadow, render_with_shadows, shadow_map

from conftest import _box, _cloud, _sample


@pytest.fixture(scope="module")
def box_on_floor():
    """A unit cube standing on a thin 4 x 4 floor plate, both centred on the z axis."""
    mesh = _box((1, 1, 1), (0, 0, 0.5)) + _box((4, 4, 0.02), (0, 0, -0.01))
    return _sample(mesh, 12000, seed=1)


LIGHT = np.array([0.0, 0.0, 5.0])


def _floor_in_shadow(points: np.ndarray) -> np.ndarray:
    """Floor points a light at (0, 0, 5) cannot see past the cube top (z = 1, |x|, |y| <= 0.5)."""
    return np.abs(points[:, :2]).max(axis=1) * 4 / 5 < 0.5


def test_points_in_shadow_under_a_light_above_a_box(box_on_floor):
    points, _, method = box_on_floor
    shadow = points_in_shadow(_cloud(points), LIGHT, method)
    floor_top = np.abs(points[:, 2]) < 1e-6
    cube_bottom = (np.abs(points[:, 2]) < 1e-6) & (np.abs(points[:, :2]).max(axis=1) < 0.5)
    cube_top = np.abs(points[:, 2] - 1) < 1e-6
    floor_bottom = np.abs(points[:, 2] + 0.02) < 1e-6
    assert shadow[cube_bottom].all() and shadow[floor_bottom].all()
    assert not shadow[cube_top].any()
    expected = _floor_in_shadow(points[floor_top])
    assert expected.sum() > 50 and (~expected).sum() > 1000
    assert (shadow[floor_top] == expected).mean() > 0.995  # points on the shadow's rim may differ


def test_shadow_map_holds_the_depths_of_the_cube_top_and_the_floor(box_on_floor):
    points, _, method = box_on_floor
    image = np.asarray(shadow_map(_cloud(points), LIGHT, 128, method))
    assert image.shape == (128, 128) and image.dtype == np.float32
    assert abs(image[64, 64] - 4.0) < 1e-3  # the light looks straight down at the cube top
    values = image[image > 0]
    near_expected = np.minimum(np.abs(values - 4.0), np.abs(values - 5.0)) < 1e-3
    assert near_expected.mean() > 0.99
    assert (np.abs(values - 5.0) < 1e-3).sum() > (np.abs(values - 4.0) < 1e-3).sum()


def test_render_with_shadows_darkens_the_shadow(box_on_floor):
    points, _, method = box_on_floor
    camera = np.array([3.0, 0.5, 2.5])
    image = np.asarray(render_with_shadows(_cloud(points), LIGHT, camera, 200, 150, method,
                                           ambient=0.25))
    view = make_view(points, camera, 200, 150)
    uv, _ = view.project(np.array([[0.56, 0.0, 0.0], [1.6, 0.0, 0.0]]))
    (c1, r1), (c2, r2) = np.rint(uv).astype(int)
    assert image[r1, c1].mean() == pytest.approx(0.25 * 0.8 * 255, abs=2)  # shadowed floor
    assert image[r2, c2].mean() == pytest.approx(0.8 * 255, abs=2)  # lit floor


def test_model_keyword_takes_names_and_visibility_methods(box_on_floor):
    """``model=`` of the applications takes what the drop-ins take (a shipped model's name) and
    any visibility method; ``method=`` is no keyword of theirs."""
    points, _, method = box_on_floor
    pcd = _cloud(points)
    by_name = points_in_shadow(pcd, LIGHT, model="default")
    np.testing.assert_array_equal(by_name, points_in_shadow(pcd, LIGHT))
    assert not np.array_equal(points_in_shadow(pcd, LIGHT, model=method), np.zeros(len(points), bool))
    with pytest.raises(TypeError, match="method"):
        points_in_shadow(pcd, LIGHT, method=method)
