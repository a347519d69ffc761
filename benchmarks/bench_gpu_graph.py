"""One view of the torch core on a GPU, eager and replayed from a CUDA graph, and their answers.

The per-view step (projection, depth buffers, predictor) is launch-bound on a GPU; captured once
in a CUDA graph with a static camera tensor, it is replayed for any camera copied into that
tensor. Shipped default, Fibonacci sphere (as ``bench_gpu.py`` builds it), 200 k and 1 M points,
median of 20:

    python3 benchmarks/bench_gpu_graph.py cuda

Prints, per size, the eager and the replayed time and how the replay's answer for a new camera
compares with the eager one. Runs on a machine with PyTorch alone (no Open3D).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1])]

from bench_gpu import WEIGHTS, sphere, timed  # noqa: E402
from o3dvis.nn import VisibilityNetwork  # noqa: E402


def main() -> int:
    device = torch.device(sys.argv[1] if len(sys.argv) > 1 else "cuda")
    if device.type != "cuda" or not torch.cuda.is_available():
        sys.exit(f"CUDA graphs need a CUDA device, got {device} (CUDA available: {torch.cuda.is_available()})")
    net = VisibilityNetwork.load(WEIGHTS, device).eval()
    for n in (200000, 1000000):
        points = sphere(n, device)
        camera = torch.tensor([0.0, 0.0, 3.0], device=device)
        with torch.no_grad():
            features = net.encode(points, noise=net.cloud_noise(points, ordered=True))

            def step() -> torch.Tensor:
                return net.view_margin([net.view(points, camera)], slice(None), features, None, torch.float32)

            eager = timed(step, device, 20)
            side = torch.cuda.Stream()  # warm-up on a side stream, as capture asks
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                for _ in range(3):
                    step()
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            try:
                with torch.cuda.graph(graph):
                    out = step()
            except RuntimeError as e:
                print(n, f"eager {eager:.2f} ms; capture failed: {str(e)[:300]}")
                continue
            replay = timed(graph.replay, device, 20)
            camera.copy_(torch.tensor([2.0, 1.0, -1.5], device=device))
            graph.replay()
            ref = step()
            agree = ((out > 0) == (ref > 0)).float().mean().item()
            print(n, f"eager {eager:.2f} ms, graph replay {replay:.3f} ms, labels agree with eager for a new "
                     f"camera {agree:.5f}, max diff {(out - ref).abs().max().item():.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
