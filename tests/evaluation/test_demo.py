"""``o3dvis demo``: the shipped sample, the scores it prints and the pictures it writes."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis.cli import main
from o3dvis.groundtruth import visibility_from_mesh
from o3dvis.evaluation.demo import (FALSE_NEGATIVE, FALSE_POSITIVE, IMAGES, default_camera, demo_sample,
                                    error_colors, observer_location, run_demo)


def test_sample_is_fixed_and_camera_outside():
    (a, mesh_a), (b, mesh_b) = demo_sample(500), demo_sample(500)
    np.testing.assert_array_equal(np.asarray(a.points), np.asarray(b.points))
    np.testing.assert_array_equal(np.asarray(mesh_a.vertices), np.asarray(mesh_b.vertices))
    assert not np.array_equal(np.asarray(demo_sample(500, seed=1)[0].points), np.asarray(a.points))
    points = np.asarray(a.points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    camera = default_camera(points)
    assert np.linalg.norm(camera - (lo + hi) / 2) == pytest.approx(np.linalg.norm(hi - lo))
    assert ((camera < lo) | (camera > hi)).any()
    observer = observer_location(points, camera, 90.0)
    centre = (lo + hi) / 2
    assert np.dot(observer - centre, camera - centre) == pytest.approx(
        (camera - centre)[2] ** 2, abs=1e-9)  # a quarter turn about z keeps only the z part
    with pytest.raises(ValueError):
        demo_sample(2)


def test_error_colors():
    predicted = np.array([True, True, False, False])
    truth = np.array([True, False, True, False])
    colors = error_colors(predicted, truth, np.full(4, 0.5))
    np.testing.assert_array_equal(colors[1], FALSE_POSITIVE)
    np.testing.assert_array_equal(colors[2], FALSE_NEGATIVE)
    assert colors[0, 0] == colors[3, 0] < 0.5 and np.ptp(colors[0]) < 0.1  # correct points: grey


def test_run_demo_scores_and_pictures(tmp_path):
    result = run_demo(tmp_path, 3000, hpr_k=[2.0, 3.0], width=160, height=120, progress=False)
    pcd, mesh = demo_sample(3000)
    truth = visibility_from_mesh(mesh, np.asarray(pcd.points), result.camera)[0]
    np.testing.assert_array_equal(result.truth, truth)
    neural, hpr = result.methods
    for m in result.methods:
        assert m.counts.accuracy == pytest.approx(np.mean(m.mask == truth))
        assert m.counts.fp == np.count_nonzero(m.mask & ~truth) and m.seconds > 0
    assert hpr.name in ("Open3D HPR (k=2)", "Open3D HPR (k=3)")
    assert set(result.images) == {*IMAGES, "demo"}
    for name, path in result.images.items():
        image = np.asarray(o3d.io.read_image(str(path)))
        assert image.ndim == 3 and image.shape[2] in (3, 4)
        if name != "demo":
            assert image.shape[:2] == (120, 160) and (image < 250).any()  # something was drawn
    errors = np.asarray(o3d.io.read_image(str(result.images["errors_hpr"])))
    red = (errors[..., 0] > 200) & (errors[..., 1] < 40) & (errors[..., 2] < 40)
    blue = (errors[..., 2] > 200) & (errors[..., 0] < 40)
    assert red.any() == (hpr.counts.fp > 0) or hpr.counts.fp < 20  # a few may hide from the observer
    assert blue.any() or hpr.counts.fn < 20


def test_cli(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--points", "2000", "--hpr-k", "2"]) == 0
    text = capsys.readouterr().out
    assert "accuracy" in text and "Open3D HPR (k=2)" in text and str(tmp_path / "demo.png") in text
    assert main(["demo", "--out", str(tmp_path), "--points", "2000", "--camera=0,0,nan"]) == 2
    assert "NaN" in capsys.readouterr().err


def test_without_matplotlib_the_demo_prints_its_numbers_and_names_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(__import__("sys").modules, "matplotlib.figure", None)  # as if not installed
    assert main(["demo", "--out", str(tmp_path / "out"), "--points", "500", "--hpr-k", "2"]) == 0
    text = capsys.readouterr().out
    assert "accuracy" in text and "Open3D HPR (k=2)" in text and "pip install 'o3dvis[demo]'" in text
    assert sorted(p.stem for p in (tmp_path / "out").iterdir()) == sorted(IMAGES)  # all but demo.png
    assert str(tmp_path / "out" / "demo.png") not in text
