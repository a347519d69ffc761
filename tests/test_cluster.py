"""Camera frames of a map on a local Ray instance with two workers: the single process's answers."""

import signal
import sys

import numpy as np
import pytest

from o3dvis.apps.map_frames import FrameMap
from o3dvis.apps.pinhole import look_at
from conftest import box_surface

_K = np.array([[80.0, 0, 79.5], [0, 80.0, 59.5], [0, 0, 1]])  # 160 x 120
_W, _H = 160, 120


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    pytest.importorskip("ray.data")
    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
    yield ray
    ray.shutdown()


def test_frames_on_ray_are_the_single_process_frames(ray_instance):
    from o3dvis.cluster import frames_on_ray

    points = box_surface([0, 0, 0], [60, 6, 3], 6_000, np.random.default_rng(2))  # a corridor, in crops of 12
    extrinsics = np.stack([look_at(np.array([x, 3.0, 1.5]), np.array([x + 10, 2.5, 1.0])) for x in range(4, 34, 3)])
    expected = list(FrameMap(points, max_range=8.0).frames(extrinsics, intrinsic=_K, width=_W, height=_H,
                                                             images=True, progress=False))
    chosen = [7, 2, 0, 5, 9, 4]  # answered with the crops the whole trajectory gives them
    answered = dict(frames_on_ray(points, extrinsics, intrinsic=_K, width=_W, height=_H, max_range=8.0,
                                  images=True, workers=2, batch_size=2, indices=chosen))
    assert sorted(answered) == sorted(chosen)
    for i in chosen:
        assert len(expected[i]), i
        for name in ("indices", "pixels", "depths", "depth_image", "index_image"):
            np.testing.assert_array_equal(getattr(answered[i], name), getattr(expected[i], name),
                                          err_msg=f"frame {i}: {name}")


def test_a_worker_killed_mid_run_costs_no_frame(ray_instance):
    import psutil

    from o3dvis.cluster import frames_on_ray

    points = box_surface([0, 0, 0], [60, 6, 3], 6_000, np.random.default_rng(2))
    extrinsics = np.stack([look_at(np.array([x, 3.0, 1.5]), np.array([x + 10, 2.5, 1.0]))
                           for x in np.arange(4, 34, 1.0)])
    expected = list(FrameMap(points, max_range=8.0).frames(extrinsics, intrinsic=_K, width=_W, height=_H,
                                                             progress=False))
    answers = frames_on_ray(points, extrinsics, intrinsic=_K, width=_W, height=_H, max_range=8.0, workers=2,
                            batch_size=1)
    answered = dict([next(answers)])
    actors = [process for process in psutil.process_iter(["cmdline"])
              if any("FrameWorker" in part for part in process.info["cmdline"] or [])]
    assert actors, "no actor process found"
    actors[0].send_signal(signal.SIGKILL)  # Ray Data restarts the actor and answers its frames again
    answered.update(answers)
    assert sorted(answered) == list(range(len(extrinsics)))
    for i, frame in answered.items():
        for name in ("indices", "pixels", "depths"):
            np.testing.assert_array_equal(getattr(frame, name), getattr(expected[i], name),
                                          err_msg=f"frame {i}: {name}")


def test_a_missing_ray_names_the_extra(monkeypatch):
    from o3dvis.cluster import frames_on_ray

    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(ImportError, match=r'pip install "o3dvis\[ray\]"'):
        frames_on_ray(np.zeros((3, 3)), np.eye(4), intrinsic=_K, width=_W, height=_H)


def test_bad_cluster_arguments_are_refused_before_ray_starts(monkeypatch):
    pytest.importorskip("ray")
    from o3dvis.cluster import frames_on_ray

    points = np.random.default_rng(0).random((50, 3))
    for kwargs, error in (({"workers": 0}, "workers"), ({"batch_size": 1.5}, "batch_size"),
                          ({"indices": [3]}, r"\[0, 1\)")):
        with pytest.raises(ValueError, match=error):
            frames_on_ray(points, np.eye(4), intrinsic=_K, width=_W, height=_H, **kwargs)

