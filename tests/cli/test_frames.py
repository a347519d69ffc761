"""``o3dvis frames``: one file per frame, written whole or not at all, a stopped run resumed."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from o3dvis.apps import map_frames
from o3dvis.apps.map_frames import Frame, FrameMap
from o3dvis.apps.pinhole import look_at
from o3dvis.cli import main
from conftest import box_surface

_ROOT = Path(__file__).resolve().parents[2]
_W, _H = 160, 120


def _trajectory(extrinsics) -> o3d.camera.PinholeCameraTrajectory:
    intrinsic = o3d.camera.PinholeCameraIntrinsic(_W, _H, 80.0, 80.0, 79.5, 59.5)
    cameras = []
    for extrinsic in extrinsics:
        camera = o3d.camera.PinholeCameraParameters()
        camera.intrinsic, camera.extrinsic = intrinsic, extrinsic
        cameras.append(camera)
    trajectory = o3d.camera.PinholeCameraTrajectory()
    trajectory.parameters = cameras
    return trajectory


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """A corridor map (.ply) and a trajectory walking along it (.json): (map, poses, trajectory)."""
    folder = tmp_path_factory.mktemp("log")
    points = box_surface([0, 0, 0], [40, 6, 3], 8_000, np.random.default_rng(3))
    o3d.io.write_point_cloud(str(folder / "map.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    trajectory = _trajectory([look_at(np.array([x, 3.0, 1.5]), np.array([x + 10, 2.0, 1.0])) for x in range(2, 30, 4)])
    assert o3d.io.write_pinhole_camera_trajectory(str(folder / "poses.json"), trajectory)
    return folder / "map.ply", folder / "poses.json", trajectory


def _expected(log, images: bool = False) -> list[Frame]:
    ply, _, trajectory = log
    pcd = o3d.io.read_point_cloud(str(ply))
    return list(FrameMap(pcd, max_range=10.0).frames(trajectory, images=images, progress=False))


def _frames_of(out: Path) -> list[Path]:
    """The frames' files in ``out``, not the temporary ones (named .NAME.PID.tmp.npz)."""
    return sorted(p for p in out.glob("*.npz") if not p.name.startswith("."))


def test_each_frame_is_a_file_of_its_visible_points(log, tmp_path, capsys):
    ply, poses, trajectory = log
    out = tmp_path / "frames"
    assert main(["frames", str(ply), str(poses), "-o", str(out), "--max-range", "10", "--depth-png"]) == 0
    expected = _expected(log, images=True)
    files = _frames_of(out)
    assert [f.name for f in files] == [f"{i:06d}.npz" for i in range(len(trajectory.parameters))]
    for path, frame in zip(files, expected):
        written = Frame.load(path)
        assert written.depth_image is None and len(written)
        for name in ("indices", "pixels", "depths"):
            np.testing.assert_array_equal(getattr(written, name), getattr(frame, name))
        png = np.asarray(o3d.io.read_image(str(path.with_suffix(".png"))))
        assert png.dtype == np.uint16 and png.shape == (_H, _W)
        np.testing.assert_array_equal(png, np.rint(frame.depth_image.astype(np.float64) * 1000).astype(np.uint16))
    assert "7 frames written" in capsys.readouterr().out
    assert (out / "names.txt").read_text().split("\n") == [str(i) for i in range(7)] + [""]  # the poses' names
    assert main(["frames", str(ply), str(poses), "-o", str(out), "--max-range", "10", "--depth-png"]) == 0
    assert "all 7 frames are written" in capsys.readouterr().out


def test_a_stopped_run_keeps_its_frames_and_the_next_answers_only_the_rest(log, tmp_path, monkeypatch):
    """The rest answered from the crops the whole trajectory gives them (the corridor is encoded in crops)."""
    ply, poses, trajectory = log
    centres = FrameMap(o3d.io.read_point_cloud(str(ply)), max_range=10.0).tile_centres(
        map_frames.pinhole_frames(trajectory))
    assert len({tuple(c) for c in centres}) > 1
    out = tmp_path / "frames"
    argv = ["frames", str(ply), str(poses), "-o", str(out), "--max-range", "10"]
    monkeypatch.setenv("O3DVIS_NUM_THREADS", "1")  # one frame at a time
    answered = []
    answer = FrameMap._answer

    def stopping(self, view, *args):
        if len(answered) == 2:  # within the first crop: the rest, alone, would be cropped otherwise
            raise KeyboardInterrupt
        answered.append(view)
        return answer(self, view, *args)

    monkeypatch.setattr(FrameMap, "_answer", stopping)
    assert main(argv) == 130
    assert [f.name for f in _frames_of(out)] == ["000000.npz", "000001.npz"]
    monkeypatch.setattr(FrameMap, "_answer", lambda self, view, *a: answered.append(view) or answer(self, view, *a))
    answered.clear()
    assert main(argv) == 0 and len(answered) == len(trajectory.parameters) - 2
    for path, expected in zip(_frames_of(out), _expected(log)):
        np.testing.assert_array_equal(Frame.load(path).indices, expected.indices)


def test_a_write_stopped_midway_leaves_no_part_of_a_file(log, tmp_path, monkeypatch):
    ply, poses, _ = log
    out = tmp_path / "frames"
    out.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale, alive = out / f".000004.{int(dead.stdout)}.tmp.npz", out / f".000005.{os.getpid()}.tmp.npz"
    stale.write_bytes(b"PK\x03\x04 a killed run's part")
    alive.write_bytes(b"PK\x03\x04 a running writer's part")
    save = Frame.save

    def cut_short(self, file):
        Path(file).write_bytes(b"PK\x03\x04 half")
        raise KeyboardInterrupt

    monkeypatch.setattr(Frame, "save", cut_short)
    assert main(["frames", str(ply), str(poses), "-o", str(out), "--max-range", "10"]) == 130
    assert _frames_of(out) == [] and not stale.exists() and alive.exists()
    assert sorted(p.name for p in out.iterdir()) == [alive.name, "names.txt"]
    monkeypatch.setattr(Frame, "save", save)
    assert main(["frames", str(ply), str(poses), "-o", str(out), "--max-range", "10"]) == 0
    assert len(_frames_of(out)) == 7


def test_a_killed_run_loses_nothing_it_wrote(log, tmp_path):
    ply, _, trajectory = log
    poses = tmp_path / "long.json"  # the trajectory six times over: long enough to be killed midway
    assert o3d.io.write_pinhole_camera_trajectory(str(poses), _trajectory(
        [p.extrinsic for p in trajectory.parameters] * 6))
    out = tmp_path / "frames"
    env = {**os.environ, "PYTHONPATH": str(_ROOT)}
    child = subprocess.Popen([sys.executable, "-m", "o3dvis", "frames", str(ply), str(poses), "-o", str(out),
                              "--max-range", "10"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not (out.is_dir() and _frames_of(out)) and child.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    child.send_signal(signal.SIGKILL)
    assert child.wait() == -signal.SIGKILL  # killed while it ran
    kept = _frames_of(out)
    assert 0 < len(kept) < 42 and all(len(Frame.load(path)) for path in kept)  # each whole
    assert main(["frames", str(ply), str(poses), "-o", str(out), "--max-range", "10"]) == 0
    expected = _expected(log)
    files = _frames_of(out)
    assert len(files) == 42 and not [p for p in out.iterdir() if p.name.startswith(".")]
    for i, path in enumerate(files):
        np.testing.assert_array_equal(Frame.load(path).indices, expected[i % 7].indices, err_msg=path.name)


def test_a_pose_that_is_not_a_rotation_is_refused_before_any_frame(log, tmp_path, capsys):
    ply, _, trajectory = log
    extrinsics = [p.extrinsic for p in trajectory.parameters]
    extrinsics[2] = extrinsics[2] @ np.diag([1.0, 1.0, 3.0, 1.0])
    poses = tmp_path / "bad.json"
    assert o3d.io.write_pinhole_camera_trajectory(str(poses), _trajectory(extrinsics))
    out = tmp_path / "frames"
    assert main(["frames", str(ply), str(poses), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("o3dvis frames: error: ") and "camera 2" in err and "rigid" in err
    assert len(err.splitlines()) == 1
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("argv, error", [
    (["--workers", "2"], "--workers sets the Ray actors"),
    (["--threshold", "2"], "--threshold"),
])
def test_bad_options_are_refused(log, tmp_path, capsys, argv, error):
    ply, poses, _ = log
    assert main(["frames", str(ply), str(poses), "-o", str(tmp_path / "f"), *argv]) == 2
    assert error in capsys.readouterr().err


def test_a_poses_file_of_another_kind_is_refused(log, tmp_path, capsys):
    ply, _, _ = log
    (tmp_path / "poses.txt").write_text("0 0 0\n")
    assert main(["frames", str(ply), str(tmp_path / "poses.txt"), "-o", str(tmp_path / "f")]) == 2
    assert ".json or .log" in capsys.readouterr().err


def test_ray_gets_the_frames_left_and_the_options(log, tmp_path, monkeypatch):
    """--ray hands the frames not yet written and the options to o3dvis.cluster.frames_on_ray (which
    tests/test_cluster.py runs on Ray), and writes what it answers."""
    from o3dvis import cluster

    ply, poses, trajectory = log
    out = tmp_path / "frames"
    expected = _expected(log, images=True)
    out.mkdir()
    expected[1].save(out / "000001.npz")
    calls = []

    def on_ray(pcd, views, **kwargs):
        calls.append(kwargs)
        return iter([(i, expected[i]) for i in kwargs["indices"]])

    monkeypatch.setattr(cluster, "frames_on_ray", on_ray)
    argv = ["frames", str(ply), str(poses), "-o", str(out), "--max-range", "10", "--workers", "3",
            "--batch-size", "5", "--threshold", "0.4"]
    assert main([*argv, "--ray", "local"]) == 0
    assert main([*argv, "--ray", "ray://head:10001", "--depth-png"]) == 0  # the frames have no depth image yet
    first, second = calls
    assert first["indices"] == [0, 2, 3, 4, 5, 6] and first["address"] is None and not first["images"]
    assert second["indices"] == list(range(7)) and second["address"] == "ray://head:10001" and second["images"]
    assert (first["workers"], first["batch_size"], first["threshold"], first["max_range"]) == (3, 5, 0.4, 10.0)
    assert len(_frames_of(out)) == len(list(out.glob("*.png"))) == len(trajectory.parameters)
