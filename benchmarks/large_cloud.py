"""Time and peak memory of neural visibility on a 10 M-point cloud, and its accuracy.

The cloud is a Fibonacci sphere of unit radius seen from ``(0.3, -0.2, 3)``: a point ``p``
is visible exactly when ``p . c > 1``, so the accuracy printed is against the exact answer.
Peak memory is the process's maximum resident set (``ru_maxrss``), which includes the ~0.5 GB
of torch and Open3D themselves (printed as the baseline before the cloud exists).

    nice -n 10 python3 benchmarks/large_cloud.py                  # 10 M points, CPU
    python3 benchmarks/large_cloud.py --points 1000000 --device cuda --threads 4
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import o3dvis  # noqa: E402
from o3dvis.apps import fibonacci_sphere  # noqa: E402
from o3dvis.nn.predictor import PRECISIONS  # noqa: E402

CAMERA = np.array([0.3, -0.2, 3.0])


def _rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=10_000_000)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--model", default="default", help="shipped model name or .safetensors path")
    parser.add_argument("--precision", default="auto", choices=PRECISIONS,
                        help="dtype of the per-view matrix products (default: auto)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    vis = o3dvis.NeuralVisibility.pretrained(args.model, args.device, precision=args.precision)
    baseline = _rss_gib()
    points = fibonacci_sphere(args.points)
    truth = points @ CAMERA > 1.0
    t0 = time.perf_counter()
    field = vis.encode(points)
    t1 = time.perf_counter()
    mask = field.query(CAMERA)[0]
    t2 = time.perf_counter()
    record = {"points": args.points, "device": args.device, "threads": torch.get_num_threads(),
              "matmul_dtype": str(field.matmul_dtype).removeprefix("torch."),
              "encode_s": round(t1 - t0, 2), "query_s": round(t2 - t1, 2), "total_s": round(t2 - t0, 2),
              "baseline_rss_gib": round(baseline, 2), "peak_rss_gib": round(_rss_gib(), 2),
              "accuracy": round(float((mask == truth).mean()), 5),
              "visible_fraction": round(float(mask.mean()), 5), "true_fraction": round(float(truth.mean()), 5)}
    if torch.device(args.device).type == "cuda":
        record["peak_cuda_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    print(json.dumps(record))


if __name__ == "__main__":
    main()
