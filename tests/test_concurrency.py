"""Concurrency: forked DataLoader workers, threads sharing one model, repeated calls.

Open3D's HPR has died inside DataLoader workers (Open3D #7233); o3dvis must work there, give
the same answers as in the main process, be callable from several threads on one model, and
give the same bits for the same call twice.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis.nn import native
from o3dvis.threads import usable_cores
from o3dvis.training.data import random_shape

CLOUDS = 6
two_cores = pytest.mark.skipif(usable_cores() < 2, reason="needs two usable cores")
POINTS = 1200


def _cloud(i: int) -> o3d.geometry.PointCloud:
    mesh = random_shape(np.random.default_rng(i), parts=2)
    o3d.utility.random.seed(i)
    return mesh.sample_points_uniformly(POINTS)


def _camera(pcd: o3d.geometry.PointCloud, i: int) -> np.ndarray:
    points = np.asarray(pcd.points)
    lo, hi = points.min(axis=0), points.max(axis=0)
    direction = np.random.default_rng(100 + i).normal(size=3)
    return (lo + hi) / 2 + np.linalg.norm(hi - lo) * direction / np.linalg.norm(direction)


@pytest.fixture(scope="module")
def scenes():
    clouds = [_cloud(i) for i in range(CLOUDS)]
    return clouds, [_camera(c, i) for i, c in enumerate(clouds)]


class VisibleDataset(torch.utils.data.Dataset):
    """Each item runs the drop-in, select_visible and Open3D's HPR (through the baseline) on one cloud."""

    def __init__(self, clouds, cameras, model):
        self.clouds, self.cameras, self.model = clouds, cameras, model

    def __len__(self) -> int:
        return len(self.clouds)

    def __getitem__(self, i: int):
        pcd, camera = self.clouds[i], self.cameras[i]
        _, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, model=self.model)
        selected = np.asarray(o3dvis.select_visible(pcd, camera, model=self.model).points)
        points = np.asarray(pcd.points)
        hpr = o3dvis.hidden_point_removal_mask(points, camera, 100 * np.linalg.norm(np.ptp(points, axis=0)))[0]
        return torch.tensor(pt_map), torch.from_numpy(selected), torch.from_numpy(hpr)


def _load(dataset, workers: int) -> list:
    loader = torch.utils.data.DataLoader(dataset, batch_size=None, num_workers=workers,
                                         multiprocessing_context="fork" if workers else None,
                                         timeout=120 if workers else 0)
    return list(loader)


@pytest.mark.parametrize("model", ["shared", "default"])
def test_forked_dataloader_workers_give_the_main_process_answers(vis, scenes, model):
    """The model loaded before the fork (shared) or inside each worker (model=None)."""
    dataset = VisibleDataset(*scenes, vis if model == "shared" else None)
    main = _load(dataset, 0)
    forked = _load(dataset, 2)
    assert len(forked) == CLOUDS
    for (pt_map, selected, hpr), (pt_map2, selected2, hpr2), pcd in zip(main, forked, scenes[0]):
        assert 0 < len(pt_map) < POINTS
        torch.testing.assert_close(pt_map2, pt_map, rtol=0, atol=0)
        torch.testing.assert_close(selected2, selected, rtol=0, atol=0)
        np.testing.assert_array_equal(selected.numpy(), np.asarray(pcd.points)[pt_map.numpy()])
        torch.testing.assert_close(hpr2, hpr, rtol=0, atol=0)
        assert 0 < hpr.float().mean() < 1


def test_threads_sharing_one_model_give_the_sequential_answers(vis, scenes):
    clouds, cameras = scenes
    fields = [vis.encode(c) for c in clouds]
    calls = []
    for i, (pcd, camera, field) in enumerate(zip(clouds, cameras, fields)):
        others = np.stack([_camera(pcd, 10 + i + k) for k in range(3)])
        calls += [lambda pcd=pcd, camera=camera: o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)[1],
                  lambda pcd=pcd, camera=camera: np.asarray(o3dvis.select_visible(pcd, camera, model=vis).points),
                  lambda field=field, others=others: field.query(others),
                  lambda pcd=pcd, others=others: vis.encode(pcd).probabilities(others).numpy(),
                  lambda pcd=pcd, camera=camera: o3dvis.hidden_point_removal_neural(pcd, camera)[1]]
    sequential = [call() for call in calls]
    with ThreadPoolExecutor(max_workers=4) as pool:
        concurrent = list(pool.map(lambda call: call(), calls * 2))
    for expected, got in zip(sequential * 2, concurrent):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(expected))


def test_the_same_call_twice_gives_the_same_bits(vis, scenes):
    clouds, cameras = scenes
    pcd, camera = clouds[0], cameras[0]
    first = o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)[1]
    assert first == o3dvis.hidden_point_removal_neural(pcd, camera, model=vis)[1]
    fresh = o3dvis.NeuralVisibility.pretrained()  # a second load of the shipped weights
    assert first == o3dvis.hidden_point_removal_neural(pcd, camera, model=fresh)[1]
    cameras_all = np.stack(cameras)
    a = vis.encode(pcd).probabilities(cameras_all)
    b = vis.encode(o3d.geometry.PointCloud(pcd)).probabilities(cameras_all.copy())
    assert torch.equal(a, b)
    np.testing.assert_array_equal(vis.encode(pcd).query(cameras_all), a.numpy() > 0.5)


@two_cores
def test_views_answered_side_by_side_on_the_threads_as_one_at_a_time(scenes, monkeypatch):
    """A cloud of more than one chunk is answered a view per worker thread (each on one torch
    thread) when o3dvis runs on several: the same answers as one view at a time on the caller's
    thread; the caller keeps its thread count; a worker's error reaches the caller; gradients stay
    on the caller's thread."""
    pcd = scenes[0][0]
    views = np.stack([_camera(pcd, 20 + k) for k in range(5)])
    field = o3dvis.NeuralVisibility.pretrained(precision="float32").encode(pcd)
    field.chunk_size = 500  # below the cloud's 1 200 points: one view per batch, in chunks
    ran_on = []
    answer = o3dvis.VisibilityField._frame_probabilities

    def spy(self, *args, **kwargs):
        ran_on.append(threading.current_thread())
        return answer(self, *args, **kwargs)

    monkeypatch.setattr(o3dvis.VisibilityField, "_frame_probabilities", spy)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        o3dvis.set_num_threads(2)
        side_by_side = field.probabilities(views)
        assert len(ran_on) == 5 and threading.current_thread() not in ran_on
        assert all(t.name.startswith("o3dvis-views") for t in ran_on)
        assert torch.get_num_threads() == 2
        ran_on.clear()
        o3dvis.set_num_threads(1)
        one_at_a_time = field.probabilities(views)
        assert ran_on == [threading.current_thread()] * 5
        torch.testing.assert_close(side_by_side, one_at_a_time, atol=1e-6, rtol=0)
        np.testing.assert_array_equal(field.query(views), one_at_a_time.numpy() > 0.5)

        o3dvis.set_num_threads(2)
        ran_on.clear()
        cameras = torch.tensor(views, requires_grad=True)
        field.probabilities(cameras).sum().backward()
        assert ran_on == [threading.current_thread()] * 5 and torch.isfinite(cameras.grad).all()

        calls = []

        def fail(self, features, points, normals, cameras, directions, orthographic, batch, rows, n,
                 workers=1):
            calls.append(batch.start)
            if batch.start == 0:
                raise RuntimeError("a worker failed")
            time.sleep(0.05)

        monkeypatch.setattr(o3dvis.VisibilityField, "_frame_probabilities", fail)
        many = np.stack([_camera(pcd, 40 + k) for k in range(40)])
        with pytest.raises(RuntimeError, match="a worker failed"):
            field.query(many)
        assert len(calls) < 10  # the views not yet started when the first failed were dropped
        assert torch.get_num_threads() == 2
    finally:
        o3dvis.set_num_threads(None)
        torch.set_num_threads(threads)


@two_cores
def test_one_view_shared_out_among_threads_answers_as_on_one(scenes, monkeypatch):
    """A single view of a cloud of several chunks, when o3dvis runs on several threads, is one pass
    of C whose blocks the kernels' threads share where the kernels run, else its chunks answered
    on the worker threads: the same answers as on the caller's thread alone, for a first query
    (made to read the features from the leaves, whatever their points a leaf) and a later one
    (from the points)."""
    import o3dvis.field

    monkeypatch.setattr(o3dvis.field, "_LEAF_READ_POINTS", 0)
    pcd = scenes[0][0]
    view = _camera(pcd, 7)
    vis = o3dvis.NeuralVisibility.pretrained(precision="float32", use_small=False)  # the network spied on
    ran_on, kernel = [], []
    margin, view_margin = vis.network.view_margin, native.view_margin

    def spy(*args, **kwargs):
        ran_on.append(threading.current_thread())
        return margin(*args, **kwargs)

    def spy_kernel(*args, **kwargs):
        kernel.append(native.kernel_threads(kwargs.get("threads")))
        return view_margin(*args, **kwargs)

    monkeypatch.setattr(vis.network, "view_margin", spy)
    monkeypatch.setattr(native, "view_margin", spy_kernel)
    in_c = native.available() and native.has_view_margin(torch.float32)
    threads = torch.get_num_threads()
    try:
        for query in ("first", "later"):
            fields = [vis.encode(pcd) for _ in range(2)]
            for field in fields:
                field.chunk_size = 300  # four chunks of the 1 200 points
                if query == "later":
                    field.probabilities(view)
            ran_on.clear(), kernel.clear()
            torch.set_num_threads(2)
            o3dvis.set_num_threads(2)
            side_by_side = fields[0].probabilities(view)
            if in_c:
                assert ran_on == [threading.current_thread()] and kernel == [2]
            else:
                assert len(ran_on) == 4 and all(t.name.startswith("o3dvis-views") for t in ran_on)
            assert torch.get_num_threads() == 2
            ran_on.clear(), kernel.clear()
            o3dvis.set_num_threads(1)
            alone = fields[1].probabilities(view)
            assert ran_on == [threading.current_thread()] * (1 if in_c else 4) and set(kernel) <= {1}
            torch.testing.assert_close(side_by_side, alone, atol=0, rtol=0)
    finally:
        o3dvis.set_num_threads(None)
        torch.set_num_threads(threads)
