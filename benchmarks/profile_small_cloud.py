"""Where one drop-in call on a small cloud spends its time, in CPU time of one thread.

    python3 benchmarks/profile_small_cloud.py --points 2048,8192 --out benchmarks/results/small_cloud_profile.md

CPU time of the calling thread (``time.thread_time``), best of ``--repeats``, on one torch thread:
on a shared machine it counts only the time this thread ran, which wall-clock time does not. The
stages: the whole ``encode`` (normalisation, Morton order, flat-hull test, noise cues, octree, U-Net,
projection), the network's ``encode`` alone, the octree with its neighbour tables, the U-Net on a
built octree, one ``query``; and the multiply-adds of the U-Net's matrix products. The network is
the one that encodes a cloud of that size, its stages timed with the products in the dtype that
``encode`` gives them (bfloat16 on a CPU with native bfloat16 dot products).
"""

import argparse
import sys
import time
import timeit
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis.nn import native  # noqa: E402
from o3dvis.nn.conv import products_in  # noqa: E402
from o3dvis.nn.octree import morton_order, normalize_points  # noqa: E402
from o3dvis.nn.predictor import resolve_precision  # noqa: E402
from o3dvis.pretrained import shared_pretrained  # noqa: E402
from o3dvis.evaluation.speed import bench_cloud  # noqa: E402


def _cpu_ms(fn, repeats: int) -> float:
    return 1e3 * min(timeit.repeat(fn, timer=time.thread_time, number=1, repeat=repeats))


def _unet_mflop(network, octree, signal) -> float:
    """Multiply-adds x 2 of the U-Net's matrix products on ``octree``, counted by a hook on ``@``
    (with the layers as torch ops: the convolutions' products are the fused kernel's, the
    up-samplings' cover all eight octants of every parent)."""
    flops, matmul, available = [0], torch.Tensor.__matmul__, native.available

    def counted(a, b):
        flops[0] += 2 * a.shape[0] * a.shape[1] * b.shape[-1]
        return matmul(a, b)

    torch.Tensor.__matmul__, native.available = counted, lambda: False
    try:
        network.unet(signal, octree)
    finally:
        torch.Tensor.__matmul__, native.available = matmul, available
    return flops[0] / 1e6


def profile(points: int, repeats: int) -> dict:
    vis = shared_pretrained()
    cloud = bench_cloud(points, 1)
    network = vis.encode(cloud.points).network  # the small model under 4 000 points
    normalised = normalize_points(torch.from_numpy(cloud.points).float())[0]
    normalised = normalised[morton_order(normalised)]

    def octree():
        tree = network.octree(normalised)
        for level in range(network.config.depth - len(network.config.channels), network.config.depth):
            tree.neighbours(level)
        return tree

    with torch.no_grad(), products_in(resolve_precision(vis.precision, vis.device)):
        tree = octree()
        noise = network.cloud_noise(normalised, ordered=True) if network.config.noise_cues else None
        signal = network._signal(normalised, torch.zeros(points, dtype=torch.long), tree, None, noise)
        field = vis.encode(cloud.points)
        return {"points": points,
                "encode_ms": _cpu_ms(lambda: vis.encode(cloud.points), repeats),
                "network_encode_ms": _cpu_ms(lambda: network.encode(normalised, noise=noise), repeats),
                "octree_and_neighbours_ms": _cpu_ms(octree, repeats),
                "unet_ms": _cpu_ms(lambda: network.unet(signal, tree), repeats),
                "query_ms": _cpu_ms(lambda: field.query(cloud.cameras[0]), repeats),
                "unet_mflop": _unet_mflop(network, tree, signal),
                "nodes_per_level": [tree.num_nodes(level) for level in range(tree.depth + 1)]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", default="2048,8192")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [profile(int(n), args.repeats) for n in args.points.split(",")]
    lines = [f"CPU time of one thread (best of {args.repeats}), one torch thread; "
             f"`python3 benchmarks/profile_small_cloud.py --points {args.points}`.", "",
             "| points | encode (ms) | network encode (ms) | octree + neighbours (ms) | U-Net (ms) | "
             "query (ms) | U-Net MFLOP | octree nodes per level |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['points']:,} | {r['encode_ms']:.1f} | {r['network_encode_ms']:.1f} | "
                     f"{r['octree_and_neighbours_ms']:.1f} | {r['unet_ms']:.1f} | {r['query_ms']:.2f} | "
                     f"{r['unet_mflop']:.0f} | {r['nodes_per_level']} |")
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out:
        args.out.write_text(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
