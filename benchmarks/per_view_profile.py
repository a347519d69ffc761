"""Where one view's time goes: the C kernels of o3dvis.nn.native against the torch ops they replace.

On the bench's procedural cloud and first camera, with the shipped default, each piece of a
view is timed alone (best of ``--repeats``), over chunks of the field's chunk size:

* projection: ``VisibilityNetwork.view`` (projection, depth buffers);
* inputs + products: ``VisibilityNetwork.view_margin`` over all chunks;
* products: ``VisibilityPredictor.margin_from_inputs`` alone on prepared inputs, where the
  path runs it (with float32 products the torch path multiplies by ``F.linear`` instead, and
  its inputs row is then only roughly the difference);
* inputs: the difference of the two;
* query: ``VisibilityField.query`` of the one view, as a user calls it.

Three paths, in one run: the torch ops (the kernels switched off, ``native.usable`` false, the
path of ``O3DVIS_NATIVE=0``); the C inputs kernel with torch's products (``native.has_view_margin``
false, the path of bfloat16 products asked for on a CPU without AVX512-BF16); and the fused C
kernel, inputs and products in one pass (``o3dvis_view_margin_bf16`` or ``_f32``, the default),
whose two pieces are not timed apart. Timings move with the host's load: compare columns of one run.

    python3 benchmarks/per_view_profile.py                      # 200 k points, one thread
    python3 benchmarks/per_view_profile.py --threads 2 --out benchmarks/results/per_view_profile.md
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import open3d as o3d
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import o3dvis  # noqa: E402
from o3dvis.cameras import as_views  # noqa: E402
from o3dvis.nn import native  # noqa: E402
from o3dvis.nn.cues import num_cues  # noqa: E402
from o3dvis.training.speed import bench_cloud  # noqa: E402


def _best_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return 1e3 * best


def profile(field: o3dvis.VisibilityField, camera, repeats: int, fused: bool) -> dict[str, float]:
    """Milliseconds of each piece of one view of ``field`` from ``camera`` (see the module)."""
    network, points, features = field.network, field.points_n, field.features
    cameras, _ = field._normalised(as_views(camera))
    n, step = field.num_points, field.chunk_size
    chunks = [slice(a, min(n, a + step)) for a in range(0, n, step)]
    with torch.inference_mode():
        view = network.view(points, cameras[0])
        times = {
            "projection": _best_ms(lambda: network.view(points, cameras[0]), repeats),
            "inputs + products": _best_ms(
                lambda: [network.view_margin([view], c, features, None, field.matmul_dtype) for c in chunks],
                repeats),
        }
        if not fused:
            inputs = network.predictor.embedding.dim + num_cues(network.config.cue_scales)
            x = features.new_zeros(1, inputs, step, dtype=field.matmul_dtype)  # zeros: no NaN to slow a product
            if view.native:  # real inputs where the kernels can write them
                for c in chunks:
                    view.inputs(c, features, network.predictor.embedding.num_frequencies, x[0, :, :c.stop - c.start])
            times["products"] = _best_ms(
                lambda: [network.predictor.margin_from_inputs(x[:, :, :c.stop - c.start]) for c in chunks], repeats)
            times["inputs"] = times["inputs + products"] - times["products"]
    times["query"] = _best_ms(lambda: field.query(camera), repeats)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=200_000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--precision", default="auto", help="of the per-view products (default: auto)")
    parser.add_argument("--out", type=Path, help="also write the table here")
    args = parser.parse_args()
    if not native.available():
        sys.exit("the C kernels are not built here (no compiler, or O3DVIS_NATIVE=0): nothing to compare")
    torch.set_num_threads(args.threads)
    cloud = bench_cloud(args.points, 1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points))
    vis = o3dvis.NeuralVisibility.pretrained(precision=args.precision)
    field = vis.encode(pcd)
    fused = native.has_view_margin(field.matmul_dtype)
    # each path: the switch of o3dvis.nn.native turned off for it, if any
    paths = {"torch ops": ("usable", lambda *tensors: False),
             "C inputs, torch products": ("has_view_margin", lambda dtype: False)}
    if fused:
        paths["C, fused"] = None
    columns = {}
    for name, switch in paths.items():
        saved = switch and getattr(native, switch[0])
        if switch:
            setattr(native, *switch)
        try:
            columns[name] = profile(field, cloud.cameras[:1], args.repeats, fused=switch is None)
        finally:
            if switch:
                setattr(native, switch[0], saved)
    names = list(columns)
    lines = [f"One view of {args.points:,} points, {args.threads} thread(s), {field.matmul_dtype} products, "
             f"best of {args.repeats} (ms; ratio: the torch ops over the last path that times the piece):", "",
             "| piece | " + " | ".join(names) + " | ratio |", "|---|" + "---|" * (len(names) + 1)]
    for piece in ("projection", "inputs", "products", "inputs + products", "query"):
        cells = [f"{columns[c][piece]:.2f}" if piece in columns[c] else "(fused)" for c in names]
        last = columns[names[-1]].get(piece, columns[names[-2]].get(piece))
        lines.append(f"| {piece} | " + " | ".join(cells) + f" | {columns[names[0]][piece] / last:.2f}x |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(f"Command: `python3 benchmarks/{Path(__file__).name} --threads {args.threads}`\n\n{text}")


if __name__ == "__main__":
    main()
