"""One view of the torch core on a GPU, eager and replayed from a CUDA graph, and their answers.

The per-view step (projection, depth buffers, predictor) is launch-bound on a GPU; captured once
in a CUDA graph with a static camera tensor, it is replayed for any camera copied into that
tensor. Shipped default, Fibonacci sphere, 200 k and 1 M points, median of 20:

    python3 benchmarks/bench_gpu_graph.py cuda

Prints, per size, the eager and the replayed time and how the replay's answer for a new camera
compares with the eager one. Runs on a machine with PyTorch alone (no Open3D).
"""
import statistics, sys, time
from pathlib import Path
import torch
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from o3dvis.geometry import fibonacci_sphere
from o3dvis.nn import VisibilityNetwork, morton_order, normalize_points
dev = torch.device(sys.argv[1] if len(sys.argv) > 1 else "cuda")
if dev.type != "cuda" or not torch.cuda.is_available():
    sys.exit(f"CUDA graphs need a CUDA device, got {dev} (CUDA available: {torch.cuda.is_available()})")
net = VisibilityNetwork.load(Path(__file__).resolve().parents[1] / "o3dvis/weights/default.safetensors", dev).eval()
for n in (200000, 1000000):
    p = normalize_points(torch.from_numpy(fibonacci_sphere(n)).to(dev))[0].float(); p = p[morton_order(p)]
    cam = torch.tensor([0.0, 0.0, 3.0], device=dev)
    with torch.no_grad():
        f = net.encode(p, noise=net.cloud_noise(p, ordered=True))
        step = lambda: net.view_margin([net.view(p, cam)], slice(None), f, None, torch.float32)
        def timed(fn, k=20):
            fn(); ts = []
            for _ in range(k):
                torch.cuda.synchronize(); t = time.perf_counter(); fn(); torch.cuda.synchronize(); ts.append(time.perf_counter() - t)
            return 1e3 * statistics.median(ts)
        eager = timed(step)
        s = torch.cuda.Stream(); s.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(s):
            for _ in range(3): step()
        torch.cuda.current_stream().wait_stream(s)
        g = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(g):
                out = step()
        except Exception as e:
            print(n, f"eager {eager:.2f} ms; capture failed: {type(e).__name__}: {str(e)[:300]}"); continue
        replay = timed(g.replay)
        cam.copy_(torch.tensor([2.0, 1.0, -1.5], device=dev)); g.replay(); ref = step()
        agree = ((out > 0) == (ref > 0)).float().mean().item()
        print(n, f"eager {eager:.2f} ms, graph replay {replay:.3f} ms, labels agree with eager for a new camera {agree:.5f}, max diff {(out - ref).abs().max().item():.2e}")
