"""Encode and per-view time of the torch core on a GPU (or any torch device), at 200 k and 1 M points.

Runs on a machine with PyTorch alone (no Open3D): it loads the shipped default's weights with
``VisibilityNetwork.load`` and times the two stages the library runs for every cloud and view,
with the device synchronised around each:

    python3 benchmarks/bench_gpu.py --device cuda --points 200000,1000000

Encode = Morton order, octree, noise cues and the U-Net (``VisibilityNetwork.encode``); one view
= its projection and depth buffers and the predictor on every point
(``VisibilityNetwork.view`` + ``view_margin``), in float32 and in bfloat16 products. Then the same
through the public API, as a user calls it with a numpy cloud (``NeuralVisibility.pretrained``
on the device): ``encode``, ``query`` of one camera and of 26, and the two-pass
``encode(normals="estimate")`` (its orientation runs on the CPU). Points are a Fibonacci sphere
seen from outside (cameras at 3 radii). Medians of ``--repeats`` after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis.geometry import fibonacci_sphere  # noqa: E402
from o3dvis.neural import NeuralVisibility  # noqa: E402
from o3dvis.nn import VisibilityNetwork, morton_order, normalize_points  # noqa: E402
from o3dvis.nn.conv import products_in  # noqa: E402

WEIGHTS = Path(__file__).resolve().parents[1] / "o3dvis" / "weights" / "default.safetensors"


def sphere(count: int, device: torch.device) -> torch.Tensor:
    """``count`` points of a Fibonacci sphere, normalised and Morton-ordered on ``device``."""
    normalised, _, _ = normalize_points(torch.from_numpy(fibonacci_sphere(count)).to(device))
    normalised = normalised.float()
    return normalised[morton_order(normalised)]


def timed(fn, device: torch.device, repeats: int) -> float:
    """Median wall time of ``fn`` in ms, the device synchronised before and after each call."""
    fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--points", default="200000,1000000")
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    device = torch.device(args.device)
    net = VisibilityNetwork.load(WEIGHTS, device).eval()
    camera = torch.tensor([0.0, 0.0, 3.0], device=device)
    vis = NeuralVisibility.pretrained(device=device)
    cameras = 3 * fibonacci_sphere(26)
    rows = []
    with torch.no_grad():
        for n in (int(p) for p in args.points.split(",")):
            points = sphere(n, device)

            def encode(dtype: torch.dtype = torch.float32) -> torch.Tensor:
                with products_in(dtype):
                    return net.encode(points, noise=net.cloud_noise(points, ordered=True))

            features = encode()
            record = {"points": n, "device": str(device),
                      "name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"}
            for name, dtype in (("float32", torch.float32), ("bfloat16", torch.bfloat16)):
                record[f"encode_ms_{name}"] = round(timed(lambda: encode(dtype), device, args.repeats), 2)
                record[f"view_ms_{name}"] = round(timed(
                    lambda: net.view_margin([net.view(points, camera)], slice(None), features, None, dtype),
                    device, args.repeats), 2)
            cloud = fibonacci_sphere(n)
            field = vis.encode(cloud)
            record["api_encode_ms"] = round(timed(lambda: vis.encode(cloud), device, args.repeats), 2)
            record["api_view_ms"] = round(timed(lambda: field.query(cameras[:1]), device, args.repeats), 2)
            record["api_26_views_ms"] = round(timed(lambda: field.query(cameras), device, args.repeats), 2)
            record["api_two_pass_encode_ms"] = round(
                timed(lambda: vis.encode(cloud, normals="estimate"), device, args.repeats), 2)
            if device.type == "cuda":
                record["peak_gib"] = round(torch.cuda.max_memory_allocated(device) / 2**30, 2)
            rows.append(record)
            print(json.dumps(record), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
