"""Two passes inside the library against the composition of two public functions.

``estimate``: ``NeuralVisibility.encode(normals="estimate")`` (also ``quality="balanced"``);
``composed``: ``o3dvis.estimate_normals_neural(pcd)`` (26 views, triangulated), then the drop-in's
encoding of the cloud with those normals (the ``normals`` model). Prints the accuracy of both
(and of any ``o3dvis eval`` method named with ``--methods``, e.g. ``neural-best``) on the labelled
samples of ``--data``, as ``o3dvis eval`` scores them, then their time on one procedural cloud per
size of ``--time-points`` with Open3D's HPR of one view in the same run.

    python3 benchmarks/bench_two_pass.py --data data/val --points 2048,8192,32768,81920 --noise 0,0.01,0.02 \\
        --out benchmarks/results/two_pass_composed.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import open3d as o3d  # noqa: E402

from o3dvis.apps.normals import estimate_normals_neural  # noqa: E402
from o3dvis.evaluation.evaluate import evaluate, markdown_table, summarize  # noqa: E402
from o3dvis.evaluation.methods import neural_method, resolve_methods  # noqa: E402
from o3dvis.evaluation.speed import bench_cloud  # noqa: E402
from o3dvis.neural import NeuralVisibility  # noqa: E402
from o3dvis.training.data.sample import list_samples  # noqa: E402


def composed(vis: NeuralVisibility):
    """``(points, cameras) -> (V, N)``: normals from ``estimate_normals_neural``, then the drop-in's encode."""
    def method(points: np.ndarray, cameras: np.ndarray) -> np.ndarray:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        estimate_normals_neural(pcd, model=vis)
        return vis.encode(pcd).query(cameras)
    method.__name__ = "composed"
    return method


def _best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="data/val")
    parser.add_argument("--points", default="2048,8192,32768,81920")
    parser.add_argument("--noise", default="0,0.01,0.02")
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--methods", default="", help="o3dvis eval methods scored beside, e.g. neural-best")
    parser.add_argument("--time-points", default="8192,32768,200000", help="sizes timed (empty: none)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="write the JSON here and the Markdown next to it")
    args = parser.parse_args()

    vis = NeuralVisibility.pretrained()
    methods = {"estimate": {"": neural_method(estimate=True)}, "composed": {"": composed(vis)}}
    extra, absent = resolve_methods([m for m in args.methods.split(",") if m])
    methods.update(extra)
    densities = [int(p) for p in args.points.split(",")]
    noises = [float(z) for z in args.noise.split(",")]
    files = list_samples(args.data)
    rows = summarize(evaluate(files, args.data, methods, densities, noises, views=args.views), methods,
                     densities, noises)
    table = markdown_table(rows, absent)
    timing = ["| points | Open3D HPR, 1 view | estimate | composed |", "|---|---|---|---|"]
    for count in [int(p) for p in args.time_points.split(",") if p]:
        cloud = bench_cloud(count, 1)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points))
        hpr = _best_of(lambda: pcd.hidden_point_removal(cloud.cameras[0], 100 * np.linalg.norm(np.ptp(cloud.points, 0))),
                       args.repeats)
        two = _best_of(lambda: vis.encode(cloud.points, normals="estimate").query(cloud.cameras[:1]), args.repeats)
        both = _best_of(lambda: composed(vis)(cloud.points, cloud.cameras[:1]), args.repeats)
        timing.append(f"| {count:,} | {1e3 * hpr:.0f} ms | {1e3 * two:.0f} ms ({two / hpr:.2f} x HPR) | "
                      f"{1e3 * both:.0f} ms ({both / hpr:.2f} x HPR) |")
    text = table + "\n\nTime of one view, encodes included (best of {}):\n\n".format(args.repeats) + "\n".join(timing)
    print(text)
    if args.out:
        Path(args.out).write_text(json.dumps({"rows": rows, "timing": timing}, indent=1))
        Path(args.out).with_suffix(".md").write_text(text + "\n\nMade by `python3 benchmarks/bench_two_pass.py "
                                                     + " ".join(sys.argv[1:]) + "`.\n")


if __name__ == "__main__":
    main()
