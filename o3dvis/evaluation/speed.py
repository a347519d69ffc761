"""Timing of visibility methods against Open3D's Hidden Point Removal, in the same run.

The reference is Open3D's own ``PointCloud.hidden_point_removal`` called once
per view (radius = 100 x bounding-box diagonal), on a procedural shape's
surface sample, with cameras on the sphere of radius = diagonal around the
centre. A method exposing ``encode(points) -> field`` with
``field.query(cameras)`` (the network) is timed in its two stages.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np

from ..baselines import Method
from ..geometry import diagonal
from ..groundtruth import sample_viewpoints
from ..training.data.sample import sample_surface
from ..training.data.shapes import random_shape
from .evaluate import EvalCloud, run_method

__all__ = ["bench_cloud", "PeakMemory", "open3d_hpr_seconds", "time_method", "benchmark", "markdown_table"]

REFERENCE = "Open3D HPR"


def bench_cloud(num_points: int, num_views: int, seed: int = 0) -> EvalCloud:
    """A procedural shape's surface sample and cameras at one diagonal from its centre.

    Returns:
        ``EvalCloud(points (num_points, 3), cameras (num_views, 3), labels=None, normals)``.
    """
    rng = np.random.default_rng(seed)
    mesh = random_shape(rng, parts=4)
    points, normals = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.triangles), num_points, rng)
    lo, hi = points.min(axis=0), points.max(axis=0)
    cameras = sample_viewpoints(num_views, (lo + hi) / 2, float(np.linalg.norm(hi - lo)), rng)
    return EvalCloud(points, cameras, None, normals)


def _seconds(fn: Callable[[], object], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


class PeakMemory:
    """Peak resident memory above the level at entry, sampled every millisecond by a thread.

    ``peak_mib`` is None where ``/proc/self/statm`` does not exist (not Linux).
    """

    def __init__(self, interval: float = 1e-3):
        self.interval, self.peak_mib = interval, None
        self._stop = threading.Event()

    @staticmethod
    def _rss() -> int | None:
        try:
            with open("/proc/self/statm") as f:
                return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, IndexError):
            return None

    def _watch(self) -> None:
        while not self._stop.wait(self.interval):
            self._peak = max(self._peak, self._rss() or 0)

    def __enter__(self) -> "PeakMemory":
        self._start = self._rss()
        self._peak = self._start or 0
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        if self._start is not None:
            self.peak_mib = (max(self._peak, self._rss() or 0) - self._start) / 2**20


def open3d_hpr_seconds(points: np.ndarray, cameras: np.ndarray, repeats: int = 1) -> float:
    """Seconds Open3D's HPR takes for all views (best of ``repeats``), cloud creation included."""
    import open3d as o3d

    radius = 100.0 * diagonal(points)

    def run() -> None:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        for camera in cameras:
            pcd.hidden_point_removal(camera, radius)

    return _seconds(run, repeats)


@contextlib.contextmanager
def _octree_seconds() -> Iterator[list[float]]:
    """Yields a list whose one entry sums the seconds the block spends building octrees
    (:meth:`~o3dvis.nn.network.VisibilityNetwork.octree`, on any network): the part of an encoding
    timed within that very encoding, from the keys it computed already, so that it never exceeds it."""
    from ..nn.network import VisibilityNetwork

    spent, lock, build = [0.0], threading.Lock(), VisibilityNetwork.octree

    def timed(self, *args, **kwargs):
        start = time.perf_counter()
        try:
            return build(self, *args, **kwargs)
        finally:
            with lock:
                spent[0] += time.perf_counter() - start

    VisibilityNetwork.octree = timed
    try:
        yield spent
    finally:
        VisibilityNetwork.octree = build


def time_method(method: Method, cloud: EvalCloud, repeats: int = 1) -> dict:
    """Seconds a method takes for all views of ``cloud``; ``encode``/``query`` split when it has them.

    The memory is measured in one untimed run before the timed ones: the sampler's
    thread takes the interpreter lock every millisecond, which slows methods that
    run on threads of their own (3 ms of 33 per view for the network at 200 k points).

    Returns:
        ``{"seconds": total, "peak_mib": resident memory above the start (None off Linux)}``,
        plus ``"encode_s"`` and ``"query_s"`` for two-stage methods, and ``"octree_s"``
        for those that build octrees: the part of ``encode_s`` that built them, in the same run.
    """
    if not hasattr(method, "encode"):
        with PeakMemory() as memory:
            run_method(method, cloud)
        return {"seconds": _seconds(lambda: run_method(method, cloud), repeats), "peak_mib": memory.peak_mib}
    normals = (cloud.normals,) if getattr(method, "needs_normals", False) else ()
    warm = min(len(cloud.points), 2048)  # first call pays allocations and thread start-up
    method.encode(cloud.points[:warm], *(n[:warm] for n in normals)).query(cloud.cameras[:1])

    def run() -> tuple[float, float, float]:
        with _octree_seconds() as octree:
            start = time.perf_counter()
            field = method.encode(cloud.points, *normals)
            mid = time.perf_counter()
        field.query(cloud.cameras)
        return mid - start, time.perf_counter() - mid, octree[0]

    with PeakMemory() as memory:
        run()
    runs = [run() for _ in range(repeats)]
    encode_s, octree_s = min((e, o) for e, _, o in runs)  # the octree of the fastest encoding
    query_s = min(q for _, q, _ in runs)
    timing = {"seconds": encode_s + query_s, "encode_s": encode_s, "query_s": query_s,
              "peak_mib": memory.peak_mib}
    if octree_s > 0:
        timing["octree_s"] = octree_s
    return timing


def benchmark(methods: dict[str, Method], sizes: list[int], views: list[int], repeats: int = 1,
              seed: int = 0, progress: bool = True) -> list[dict]:
    """Times every method and Open3D's HPR on the same clouds.

    Args:
        methods: ``{name: method}``.
        sizes: numbers of points.
        views: numbers of views.
        repeats: rounds; each times Open3D and every method once; each one's fastest round counts.
        seed: seed of the cloud and cameras.
        progress: show a tqdm bar.

    Returns:
        One row per (size, views, method): ``points, views, method, seconds``,
        ``reference_s`` (Open3D HPR, same cloud and cameras), ``speedup``
        (reference / method), and for two-stage methods ``encode_s`` and
        ``query_per_view_s``.
    """
    from tqdm import tqdm

    rows = []
    steps = [(n, v) for n in sizes for v in views]
    for n, v in tqdm(steps, desc="bench", unit="setting", disable=not progress):
        cloud = bench_cloud(n, v, seed)
        best: dict[str, dict] = {}
        for _ in range(repeats):  # interleaved rounds: a burst of load hits every method alike
            for name, timing in [(REFERENCE, lambda: {"seconds": open3d_hpr_seconds(cloud.points, cloud.cameras)}),
                                 *((k, lambda m=m: time_method(m, cloud)) for k, m in methods.items())]:
                t = timing()
                if name not in best or t["seconds"] < best[name]["seconds"]:
                    best[name] = t
        reference = best[REFERENCE]["seconds"]
        for name, t in best.items():
            row = {"points": n, "views": v, "method": name, "seconds": t["seconds"], "reference_s": reference,
                   "speedup": reference / t["seconds"]}
            if "encode_s" in t:
                row.update(encode_s=t["encode_s"], query_per_view_s=t["query_s"] / v)
            if "octree_s" in t:
                row["octree_s"] = t["octree_s"]
            if t.get("peak_mib") is not None:
                row["peak_mib"] = t["peak_mib"]
            rows.append(row)
    return rows


def markdown_table(rows: list[dict]) -> str:
    """Markdown timing table; speed-up = Open3D HPR time / method time (> 1: faster)."""
    lines = ["| points | views | method | total (ms) | octree (ms) | encode (ms) | query per view (ms) | "
             "peak memory (MiB) | speed-up vs Open3D HPR |",
             "|---|---|---|---|---|---|---|---|---|"]

    def ms(key: str, digits: int = 1) -> str:
        return f"{1e3 * r[key]:.{digits}f}" if key in r else ""

    for r in rows:
        peak = f"{r['peak_mib']:.0f}" if "peak_mib" in r else ""
        lines.append(f"| {r['points']:,} | {r['views']} | {r['method']} | {ms('seconds')} | {ms('octree_s')} | "
                     f"{ms('encode_s')} | {ms('query_per_view_s', 2)} | {peak} | {r['speedup']:.2f}x |")
    return "\n".join(lines) + "\n"
