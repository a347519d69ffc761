"""The CPU thread policy (o3dvis.threads): never more threads than cores, one for small work or
when other processes keep the cores busy, overridable by a call or the environment."""

from __future__ import annotations

import multiprocessing
import threading
import time

import numpy as np
import pytest
import torch

import o3dvis
from o3dvis import threads
from o3dvis.nn import native
from o3dvis.evaluation.speed import bench_cloud


@pytest.fixture(autouse=True)
def automatic(monkeypatch):
    """Each test starts (and the others go on) with the automatic policy and torch's count kept."""
    monkeypatch.delenv(threads.ENV_VAR, raising=False)
    before = torch.get_num_threads()
    o3dvis.set_num_threads(None)
    yield
    o3dvis.set_num_threads(None)
    torch.set_num_threads(before)


def _spin(stop) -> None:
    while not stop.is_set():
        pass


def test_a_fixed_count_is_used_up_to_the_cores(monkeypatch):
    monkeypatch.setattr(threads, "usable_cores", lambda: 3)
    o3dvis.set_num_threads(2)
    assert o3dvis.get_num_threads() == 2 and threads.plan_threads(1, 10**9) == 2  # fixed: size ignored
    o3dvis.set_num_threads(8)
    assert threads.plan_threads(10**9, 1) == 3
    o3dvis.set_num_threads("auto")
    assert o3dvis.get_num_threads() is None
    monkeypatch.setenv(threads.ENV_VAR, "1")
    assert o3dvis.get_num_threads() == 1 and threads.plan_threads(10**9, 1) == 1
    o3dvis.set_num_threads(2)  # a call wins over the environment
    assert threads.plan_threads(10**9, 1) == 2
    monkeypatch.setattr(threads, "_forked", True)  # in a forked child: at most its own torch count
    torch.set_num_threads(1)
    assert threads.plan_threads(10**9, 1) == 1


@pytest.mark.parametrize("bad", [0, -1, 1.5, "two", True, "2.0", "²"])
def test_bad_counts_raise(bad, monkeypatch):
    with pytest.raises(ValueError, match="positive int"):
        o3dvis.set_num_threads(bad)
    monkeypatch.setenv(threads.ENV_VAR, str(bad))
    with pytest.raises(ValueError, match=threads.ENV_VAR):
        threads.plan_threads(10**9, 1)


def test_automatic_count_takes_small_work_torch_count_cores_and_load(monkeypatch):
    monkeypatch.setattr(threads, "usable_cores", lambda: 4)
    monkeypatch.setattr(threads, "busy_cores", lambda: 0)
    monkeypatch.setattr(threads, "cpu_pressure", lambda: None)
    torch.set_num_threads(8)
    assert threads.plan_threads(100, 1000) == 1
    assert threads.plan_threads(1000, 1000) == 4
    torch.set_num_threads(3)
    assert threads.plan_threads(1000, 1000) == 3
    torch.set_num_threads(8)
    monkeypatch.setattr(threads, "busy_cores", lambda: 3)
    assert threads.plan_threads(1000, 1000) == 1
    monkeypatch.setattr(threads, "busy_cores", lambda: 4)
    assert threads.plan_threads(1000, 1000) == 1
    monkeypatch.setattr(threads, "busy_cores", lambda: 0)
    monkeypatch.setattr(threads, "cpu_pressure", lambda: threads.MAX_PRESSURE + 0.01)
    assert threads.plan_threads(1000, 1000) == 1
    monkeypatch.setattr(threads, "cpu_pressure", lambda: threads.MAX_PRESSURE)
    assert threads.plan_threads(1000, 1000) == 4


def test_load_readings_are_used_again_for_a_short_while(monkeypatch):
    """busy_cores, cpu_pressure and usable_cores read /proc and /sys once per _READING_AGE seconds,
    each on its own."""
    reads = []
    monkeypatch.setattr(threads, "_busy_cores", lambda: reads.append("busy") or len(reads))
    monkeypatch.setattr(threads, "_cpu_pressure", lambda: reads.append("pressure") or 0.5)
    monkeypatch.setattr(threads, "_usable_cores", lambda: reads.append("cores") or 2)
    monkeypatch.setattr(threads, "_readings", {})
    monkeypatch.setattr(threads, "_READING_AGE", 60.0)
    assert [threads.busy_cores() for _ in range(3)] == [1, 1, 1] and threads.cpu_pressure() == 0.5
    assert [threads.usable_cores() for _ in range(3)] == [2, 2, 2]
    assert reads == ["busy", "pressure", "cores"]
    monkeypatch.setattr(threads, "_READING_AGE", 0.0)  # every call reads anew
    assert threads.busy_cores() == 4 and threads.busy_cores() == 5 and reads[3:] == ["busy", "busy"]


def test_workers_only_gives_torch_one_thread_and_plans_as_before(monkeypatch):
    """Inside workers_only the caller's torch ops run on one thread while the library's workers are
    planned with torch's count from before (nested blocks too), and the two-pass encode's
    orientation step runs inside it; torch's count is back after."""
    monkeypatch.setattr(threads, "usable_cores", lambda: 4)
    monkeypatch.setattr(threads, "busy_cores", lambda: 0)
    monkeypatch.setattr(threads, "cpu_pressure", lambda: None)
    torch.set_num_threads(3)
    with threads.workers_only():
        assert torch.get_num_threads() == 1 and threads.plan_threads(1000, 1000) == 3
        with threads.workers_only():
            assert torch.get_num_threads() == 1 and threads.plan_threads(1000, 1000) == 3
        assert torch.get_num_threads() == 1 and threads.plan_threads(1000, 1000) == 3
    assert torch.get_num_threads() == 3 and threads.plan_threads(1000, 1000) == 3
    seen = []
    first_pass = o3dvis.two_pass.estimated_normals

    def spy(*args, **kwargs):
        seen.append((torch.get_num_threads(), threads.plan_threads(10 ** 6, 1)))
        return first_pass(*args, **kwargs)

    monkeypatch.setattr(o3dvis.two_pass, "estimated_normals", spy)
    o3dvis.NeuralVisibility.pretrained().encode(bench_cloud(3_000, 1).points, normals="estimate")
    assert seen == [(1, 3)] and torch.get_num_threads() == 3


def test_busy_processes_on_every_core_are_seen():
    cores = threads.usable_cores()
    context = multiprocessing.get_context("fork")
    stop = context.Event()
    workers = [context.Process(target=_spin, args=(stop,), daemon=True) for _ in range(cores)]
    for w in workers:
        w.start()
    try:
        # windows of 20 samples, up to 6 s: the forked spinners take a moment to be scheduled, and one
        # window can fall while this process's own threads hold the cores
        windows, plans = [], []
        deadline = time.monotonic() + 6.0
        while time.monotonic() < deadline:
            time.sleep(0.25)
            windows.append([threads.busy_cores() for _ in range(20)])
            plans.append(threads.plan_threads(10**9, 1))
            if np.median(windows[-1]) >= cores - 0.5 and plans[-1] == 1:
                break
        assert max(max(w) for w in windows) <= cores
        assert np.median(windows[-1]) >= cores - 0.5, windows
        assert plans[-1] == 1, plans
        pressure = threads.cpu_pressure()
        assert pressure is None or 0 <= pressure <= 1
    finally:
        stop.set()
        for w in workers:
            w.join(5)
            if w.is_alive():
                w.terminate()


def test_own_busy_threads_are_counted_as_own():
    """Threads of this process busy in torch (the interpreter lock released) are this process's
    running tasks, which :func:`busy_cores` leaves out of the other processes' load."""
    stop = threading.Event()
    matrix = torch.rand(256, 256)

    def work():
        while not stop.is_set():
            matrix @ matrix

    mine = [threading.Thread(target=work, daemon=True) for _ in range(2)]
    for t in mine:
        t.start()
    try:
        assert max(threads._own_running() for _ in range(20)) >= 3
    finally:
        stop.set()
        for t in mine:
            t.join()


def test_encode_and_query_run_on_the_planned_threads_and_restore_torch(monkeypatch):
    """With one usable core, nothing runs on two threads (torch's, o3dvis's or the C kernels'); with a
    fixed count of two, the encode's ops and convolutions split over two, and a query's view is one
    pass of C whose blocks two threads share where the kernels answer, else its chunks go side by
    side; the caller's torch count is back after each, and the answers are the same."""
    if threads.usable_cores() < 2:
        pytest.skip("needs two usable cores")
    vis = o3dvis.NeuralVisibility.pretrained(precision="float32")
    cloud = bench_cloud(20_000, 3)
    seen, ran_on, kernel = [], [], []
    encode, margin, view_margin = vis.network.encode_leaves, vis.network.view_margin, native.view_margin

    def spy_encode(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return encode(*args, **kwargs)

    def spy_margin(*args, **kwargs):
        ran_on.append(threading.current_thread())
        return margin(*args, **kwargs)

    def spy_kernel(*args, **kwargs):
        kernel.append(native.kernel_threads(kwargs.get("threads")))
        return view_margin(*args, **kwargs)

    def spy():
        monkeypatch.setattr(vis.network, "encode_leaves", spy_encode)
        monkeypatch.setattr(vis.network, "view_margin", spy_margin)
        monkeypatch.setattr(native, "view_margin", spy_kernel)

    spy()
    torch.set_num_threads(2)
    monkeypatch.setattr(threads, "usable_cores", lambda: 1)
    field = vis.encode(cloud.points)
    field.chunk_size = 4096
    one = field.probabilities(cloud.cameras)
    assert seen == [1] and set(ran_on) == {threading.current_thread()} and set(kernel) <= {1}
    assert torch.get_num_threads() == 2
    monkeypatch.undo()
    spy()
    seen.clear(), ran_on.clear(), kernel.clear()
    torch.set_num_threads(1)
    o3dvis.set_num_threads(2)
    field = vis.encode(cloud.points)
    field.chunk_size = 4096
    two = field.probabilities(cloud.cameras[0])
    assert seen == [2]
    if native.available():  # one pass of C for the view, its blocks on two threads
        assert ran_on == [threading.current_thread()] and kernel == [2]
    else:  # the torch ops' chunks side by side
        assert threading.current_thread() not in ran_on and len(ran_on) == 5
    assert torch.get_num_threads() == 1
    torch.testing.assert_close(two, one[:1], atol=1e-5, rtol=0)


@pytest.mark.parametrize("points", [3_000, 20_000])
def test_answers_do_not_depend_on_the_thread_count(points):
    """The shipped models at their default precision (bfloat16 products where the CPU has them) give
    one cloud the same probabilities, to the bit, on one thread and on two: the load of the machine,
    which sets the automatic count, does not change an answer (the small model, then the default)."""
    vis = o3dvis.NeuralVisibility.pretrained()
    cloud = bench_cloud(points, 4)
    shrunk = cloud.points.copy()
    shrunk[: points // 2] *= 0.5  # half the cloud towards the origin: the small model's answers
    answers = []  # for 3 000 of these points differed by up to 0.008 when products split by thread
    for count in (1, 2):
        o3dvis.set_num_threads(count)
        answers.append(vis.encode(shrunk).probabilities(cloud.cameras[:4]))
    assert torch.equal(answers[0], answers[1])


def test_worker_threads_are_kept_between_calls_and_nested_calls_stay_on_their_worker():
    """threaded_map's threads serve the next call too; an item that maps again runs its items on
    its own worker (no threads beyond those planned); the caller's torch count is kept."""
    torch.set_num_threads(2)
    ran_on = {t for _ in range(10) for t in threads.threaded_map(lambda _: threading.current_thread(), range(8), 2)}
    assert threading.current_thread() not in ran_on and all(t.is_alive() for t in ran_on)  # kept, idle
    assert len(ran_on) <= threads._worker_pool()._max_workers

    def inner(k):
        here = threading.get_ident()
        return k, {threading.get_ident() for _ in threads.threaded_map(lambda _: None, range(3), 2)} | {here}

    for k, ran_on in threads.threaded_map(inner, range(4), 2):
        assert len(ran_on) == 1 and threading.get_ident() not in ran_on
    assert list(threads.threaded_map(lambda x: x * x, range(5), 3)) == [0, 1, 4, 9, 16]
    assert torch.get_num_threads() == 2


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork here")
def test_worker_threads_are_made_anew_in_a_forked_child():
    """A child forked after the threads were made has none of them: its calls make their own
    (a kept pool of the parent's threads would wait for them forever)."""
    import os
    import signal

    list(threads.threaded_map(lambda x: x, range(4), 2))
    pid = os.fork()
    if pid == 0:  # the child: exit 0 only if the map answers within the alarm
        signal.alarm(20)
        ok = list(threads.threaded_map(lambda x: x + 1, range(6), 2)) == [1, 2, 3, 4, 5, 6]
        os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


_FORKED_WORKER = """
import multiprocessing, os, sys
import numpy as np, open3d as o3d, torch
import o3dvis

def answer(points):
    return o3dvis.hidden_point_removal_neural(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)),
                                              [0.0, 0.0, 3.0])[1]

def worker(points, queue):  # as a DataLoader worker: one torch thread of its own, then a call
    torch.set_num_threads(1)
    queue.put(answer(points))

if __name__ == "__main__":
    if sys.argv[1] == "call":
        o3dvis.set_num_threads(2)
    points = np.random.default_rng(0).normal(size=(60_000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    parent = answer(points)  # an OpenMP team of two threads has run here
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=worker, args=(points, queue), daemon=True)  # one that hangs ends with us
    child.start()
    print(queue.get(timeout=60) == parent)
"""


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork here")
@pytest.mark.skipif(threads.usable_cores() < 2, reason="one core: no OpenMP team in the parent")
@pytest.mark.parametrize("fixed_by", ["call", "environment"])
def test_a_fixed_count_never_overrides_a_forked_workers_own(fixed_by):
    """A child forked after the parent ran a call on a fixed two threads, that sets one torch thread
    (as a DataLoader worker does), answers on that one, as the parent did: torch's OpenMP (GNU
    libgomp) keeps none of the parent's team in the child, and a team of two there waits for ever."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "PYTHONPATH": str(Path(o3dvis.__file__).parent.parent)}
    env.pop(threads.ENV_VAR, None)
    if fixed_by == "environment":
        env[threads.ENV_VAR] = "2"
    run = subprocess.run([sys.executable, "-c", _FORKED_WORKER, fixed_by], capture_output=True, text=True,
                         timeout=240, env=env)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == "True"
