"""Procedural driving logs (a street network, a LiDAR map, pinhole frames, ray-cast ground truth) and the
evaluation of visibility methods on their frames."""

from __future__ import annotations

import json

import numpy as np
import pytest

from o3dvis.evaluation.drives import (drive_methods, drives_table, evaluate_drives, o3dvis_frame,
                                      summarize_drives)
from o3dvis.training.data.scenes import drive_log, frame_truth, frame_view

SPARSE = 400.0  # map points per metre: a 30 m log of some 12 k points


@pytest.fixture(scope="module")
def log():
    return drive_log(30, seed=1, points_per_metre=SPARSE)


def test_a_log_is_a_function_of_its_seed(log):
    again, other = drive_log(30, seed=1, points_per_metre=SPARSE), drive_log(30, seed=2, points_per_metre=SPARSE)
    np.testing.assert_array_equal(again.points, log.points)
    np.testing.assert_array_equal(again.frames[3].extrinsic, log.frames[3].extrinsic)
    assert other.points.shape == log.points.shape and not np.array_equal(other.points, log.points)
    assert len(log.points) == 7 * round(5 * SPARSE) and len(log.frames) == 7 and len(log.sweeps) == 7
    assert log.points.dtype == np.float32 and log.poses.shape == (31, 4, 4)


def test_a_longer_log_extends_a_shorter_one(log):
    longer = drive_log(60, seed=1, points_per_metre=SPARSE)
    n = len(log.points)
    assert len(longer.points) > n
    np.testing.assert_array_equal(longer.points[:n], log.points)
    np.testing.assert_array_equal(longer.noisy(0.01, 1)[:n], log.noisy(0.01, 1))
    for short, long in zip(log.frames, longer.frames):
        np.testing.assert_array_equal(short.extrinsic, long.extrinsic)


def test_frames_look_forward_along_the_trajectory(log):
    for index, frame in enumerate(log.frames[:-1]):
        view = frame_view(frame)
        assert (view.width, view.height) == (640, 480)
        assert view.intrinsic[0, 0] == pytest.approx(320.0)  # 90 degrees across
        assert abs(np.asarray(frame.extrinsic)[2, 2]) < 1e-9  # level
        ahead = log.poses[round(log.frame_distance[index]) + 1, :3, 3]  # where the vehicle is a metre on
        assert view.project(ahead[None])[1][0] == pytest.approx(1.0, abs=0.05)


def test_noise_grows_with_range_and_is_bounded(log):
    assert log.noisy(0.0) is log.points
    noisy = log.noisy(0.01, seed=4)
    moved = np.linalg.norm(noisy - log.points, axis=1)
    reach = np.linalg.norm(log.points - log.sweeps[log.sweep_of], axis=1)
    assert (moved <= 0.01 * reach + 1e-4).all() and moved.mean() > 0.002 * reach.mean()
    np.testing.assert_array_equal(noisy, log.noisy(0.01, seed=4))


def test_a_frames_points_are_within_range_and_inside_its_image(log):
    indices, visible = frame_truth(log, 2, max_range=25.0)
    view = frame_view(log.frames[2])
    uv, depth = view.project(log.points[indices].astype(np.float64))
    assert len(indices) > 1000 and np.all(np.diff(indices) > 0)
    assert (depth > 0).all() and (uv >= -0.5).all() and (uv[:, 0] < 639.5).all() and (uv[:, 1] < 479.5).all()
    assert (np.linalg.norm(log.points[indices] - view.location, axis=1) <= 25.0 + 1e-3).all()
    # every point of the map in range and in the image is the frame's
    uv_all, depth_all = view.project(log.points.astype(np.float64))
    inside = (depth_all > 0) & (np.abs(uv_all[:, 0] - 319.5) < 320) & (np.abs(uv_all[:, 1] - 239.5) < 240) \
        & (np.linalg.norm(log.points - view.location, axis=1) <= 25.0)
    assert abs(int(inside.sum()) - len(indices)) <= 2  # ties at the image's edge and the range's
    assert 0.5 < visible.mean() < 0.98


def _segment_crosses(start: np.ndarray, ends: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) bool: the segment from ``start`` to each of ``ends`` passes through the box's interior."""
    d = ends - start
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - start) / d, (hi - start) / d
    enter, leave = np.nanmax(np.minimum(a, b), axis=1), np.nanmin(np.maximum(a, b), axis=1)
    return (enter < leave) & (leave > 0) & (enter < 1)


def test_points_behind_a_parked_car_are_hidden():
    log = drive_log(30, seed=3, points_per_metre=1500)
    height = log.scene.solids[:, 1, 2] - log.scene.solids[:, 0, 2]
    footprint = np.sort(log.scene.solids[:, 1, :2] - log.scene.solids[:, 0, :2], axis=1)
    bodies = log.scene.solids[(height < 0.85) & (footprint[:, 1] > 3.7) & (footprint[:, 1] < 4.9)]
    assert len(bodies) >= 2
    behind = 0
    for index in range(len(log.frames)):
        indices, visible = frame_truth(log, index)
        camera, points = log.camera(index), log.points[indices].astype(np.float64)
        for lo, hi in bodies[np.linalg.norm(bodies.mean(axis=1) - camera, axis=1) < 30]:
            through = _segment_crosses(camera, points, lo + 0.05, hi - 0.05)
            beyond = through & ~((points > lo - 0.05) & (points < hi + 0.05)).all(axis=1)
            assert not visible[beyond].any()
            behind += int(beyond.sum())
    assert behind > 50


def test_bad_logs_and_frames_are_refused(log):
    with pytest.raises(ValueError, match="length"):
        drive_log(0)
    with pytest.raises(ValueError, match="field of view"):
        drive_log(10, fov=180)
    with pytest.raises(ValueError, match="points must be the log's map"):
        frame_truth(log, 0, log.points[:10])
    with pytest.raises(ValueError, match="max_range"):
        frame_truth(log, 0, max_range=0)
    with pytest.raises(ValueError, match="unknown method"):
        drive_methods(["hpr", "o3dvis-crop"])


def test_pixel_zbuffer_keeps_the_nearest_point_of_each_pixel(log):
    methods, _ = drive_methods(["pixel-zbuffer"])
    frame = log.frames[0]
    view = frame_view(frame)
    forward = np.asarray(frame.extrinsic)[2, :3]
    points = view.location + np.outer([10.0, 20.0, 10.2], forward)  # the third within 2 % of the first
    answer = {label: m(points)(frame, np.arange(3), 40.0) for label, m in methods["pixel-zbuffer"].items()}
    np.testing.assert_array_equal(answer["cell=1,tol=0.05"], [True, False, True])
    np.testing.assert_array_equal(answer["cell=8,tol=0.5"], [True, False, True])


def test_o3dvis_answers_a_frame_of_the_map(log, vis):
    indices, truth = frame_truth(log, 1)
    seen = o3dvis_frame(vis, log.points, log.frames[1], 40.0)
    assert np.isin(seen, indices).all() and len(seen) > 0.5 * truth.sum()
    assert (np.isin(indices, seen) == truth).mean() > 0.8
    with pytest.raises(ValueError, match="crop"):
        o3dvis_frame(vis, log.points, log.frames[1], 40.0, crop=30.0)
    far = log.points + np.float32(1000.0)  # nothing within range of the camera
    assert len(o3dvis_frame(vis, far, log.frames[1], 40.0)) == 0


def test_evaluation_runs_end_to_end_on_tiny_logs():
    methods, absent = drive_methods(["o3dvis", "hpr", "pixel-zbuffer", "everything"], hpr_k=[3.0])
    assert not absent
    per_frame = evaluate_drives([20, 40], [0.0, 0.01], methods, frames=2, log_options={"points_per_metre": SPARSE},
                                progress=False)
    assert {(e["length"], e["distance"], e["along"], e["first"]) for e in per_frame.values()} == {
        (20.0, 0.0, True, True), (20.0, 20.0, True, True), (40.0, 0.0, True, True), (40.0, 40.0, True, False),
        (40.0, 20.0, False, True)}
    summary = summarize_drives(per_frame, methods, [0.0, 0.01])
    rows = {(r["method"], r["points"], r["noise"]): r for r in summary["along"]}
    everything = rows["everything", 20.0, 0.0]
    counts = np.sum([e["counts"]["everything"][""]["20"]["0"] for e in per_frame.values() if e["length"] == 20],
                    axis=0)
    assert everything["balanced_accuracy"] == 0.5 and everything["accuracy"] == pytest.approx(counts[0] / counts.sum())
    assert rows["o3dvis", 20.0, 0.0]["balanced_accuracy"] > 0.75
    assert rows["pixel-zbuffer", 40.0, 0.01]["balanced_param"].startswith("cell=")
    table = drives_table(summary, {"lengths": [20, 40], "seeds": [0], "frames": 2, "max_range": 40.0})
    assert "| o3dvis - tuned hpr |" in table and "from the 20 m log to the 40 m log" in table
    assert "| everything | 50.0 / " in table


def test_command_writes_the_tables(tmp_path, capsys):
    from o3dvis.cli import main

    out = tmp_path / "drives.json"
    assert main(["eval-drives", "--lengths", "20", "--noise", "0", "--frames", "1", "--methods",
                 "everything,pixel-zbuffer", "--points-per-metre", "300", "-o", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["settings"]["lengths"] == [20.0] and len(report["frames"]) == 1
    markdown = out.with_suffix(".md").read_text()
    assert "| everything | 50.0 / " in markdown
    assert ("Made by `o3dvis eval-drives --lengths 20 --noise 0 --frames 1 --seeds 0 --range 40 --points-per-metre "
            "300 --heading 0 --methods everything,pixel-zbuffer`") in markdown
    assert main(["eval-drives", "--lengths", "20", "--frames", "0"]) == 2
