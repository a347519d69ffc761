"""One drop-in call with and without a competing CPU-bound process on every core.

    python3 benchmarks/bench_contention.py --points 2048,200000 --rounds 5 \\
        --out benchmarks/results/contention.md

For each size, rounds of interleaved calls on the same cloud and camera (each
round starts one way later than the one before, so that no way always follows
the same other): the
drop-in ``o3dvis.hidden_point_removal_neural`` with the thread policy of
``o3dvis.threads`` (``auto``), with one thread (``o3dvis.set_num_threads(1)``, the
library's own single-threaded time), with every core whatever the load
(``set_num_threads(cores)``, what torch's threads did before the policy), and
Open3D's ``hidden_point_removal``; first on the machine as it is, then with one
busy process per usable core (``multiprocessing``, spinning). The kept encoding of
the drop-ins is cleared before every call, so that each call encodes its cloud.
Prints the medians and the ratios against the single-threaded time and against HPR.
"""

import argparse
import json
import multiprocessing
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import o3dvis  # noqa: E402
from o3dvis import encodings  # noqa: E402
from o3dvis.threads import busy_cores, usable_cores  # noqa: E402
from o3dvis.evaluation.speed import bench_cloud  # noqa: E402


def _spin(stop) -> None:
    while not stop.is_set():
        for _ in range(100_000):
            pass


class Competitors:
    """``count`` processes, each spinning on a core, for the duration of the block."""

    def __init__(self, count: int):
        self.count = count

    def __enter__(self) -> "Competitors":
        context = multiprocessing.get_context("fork")
        self.stop = context.Event()
        self.workers = [context.Process(target=_spin, args=(self.stop,), daemon=True) for _ in range(self.count)]
        for worker in self.workers:
            worker.start()
        time.sleep(1.0)  # spinning, and seen by the load averages
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        for worker in self.workers:
            worker.join(5)
            if worker.is_alive():
                worker.terminate()


def _call(pcd, camera, threads) -> float:
    o3dvis.set_num_threads(threads)
    encodings.clear()
    start = time.perf_counter()
    o3dvis.hidden_point_removal_neural(pcd, camera)
    return time.perf_counter() - start


def _hpr(pcd, camera, radius) -> float:
    start = time.perf_counter()
    pcd.hidden_point_removal(camera, radius)
    return time.perf_counter() - start


def measure(points: int, rounds: int, cores: int) -> dict[str, float]:
    """Median seconds of each way of answering one view of a ``points``-point cloud."""
    cloud = bench_cloud(points, 1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points))
    camera, radius = cloud.cameras[0], 100.0 * float(np.linalg.norm(np.ptp(cloud.points, axis=0)))
    ways = {"auto": lambda: _call(pcd, camera, None), "1 thread": lambda: _call(pcd, camera, 1),
            f"{cores} threads": lambda: _call(pcd, camera, cores), "Open3D HPR": lambda: _hpr(pcd, camera, radius)}
    for way in ways.values():  # warm: weights, kernels, allocator
        way()
    times: dict[str, list[float]] = {name: [] for name in ways}
    names = list(ways)
    for r in range(rounds):  # interleaved, each round starting one way later: load and order hit all alike
        for name in names[r % len(names):] + names[:r % len(names)]:
            times[name].append(ways[name]())
    o3dvis.set_num_threads(None)
    return {name: statistics.median(t) for name, t in times.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", default="2048,200000")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    cores = usable_cores()
    rows = []
    for load in ("as it is", f"{cores} busy processes"):
        with Competitors(cores if load != "as it is" else 0):
            busy = busy_cores()
            for n in (int(p) for p in args.points.split(",")):
                medians = measure(n, args.rounds, cores)
                single = medians["1 thread"]
                rows.append({"load": load, "busy_cores_seen": busy, "points": n, "median_s": medians,
                             "vs_single": {k: v / single for k, v in medians.items() if k != "Open3D HPR"},
                             "speedup_vs_hpr": {k: medians["Open3D HPR"] / v for k, v in medians.items()
                                                if k != "Open3D HPR"}})
                print(json.dumps(rows[-1]), flush=True)
    lines = [f"One drop-in call, {cores} usable cores, median of {args.rounds} interleaved rounds; "
             "time / the library's single-threaded time, and speed-up over Open3D HPR (> 1: faster).", "",
             "| load | points | way | median (ms) | time / 1 thread | speed-up vs HPR |", "|---|---|---|---|---|---|"]
    for r in rows:
        for name, seconds in r["median_s"].items():
            ratio = f"{r['vs_single'][name]:.2f}" if name in r["vs_single"] else ""
            speedup = f"{r['speedup_vs_hpr'][name]:.2f}x" if name in r["speedup_vs_hpr"] else ""
            lines.append(f"| {r['load']} | {r['points']:,} | {name} | {1e3 * seconds:.1f} | {ratio} | {speedup} |")
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out:
        args.out.write_text(table)
        args.out.with_suffix(".json").write_text(json.dumps({"cores": cores, "rounds": args.rounds, "rows": rows},
                                                            indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
