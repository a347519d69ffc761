"""How much accuracy a per-leaf predictor would lose, whatever its network: the leaf-oracle bound.

Running the per-view MLP once per finest octree leaf instead of once per point
(issue 7's idea) gives every point of a leaf the same label. Even a perfect
predictor then errs on the points whose true label differs from their leaf's
representative (its first point). This prints that error and the points per
leaf, from the ray-cast labels of prepared validation files:

    python3 benchmarks/per_leaf_bound.py --data data/val --every 5 --points 32768,81920 --depths 7,8
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis.training.data.prepare import load_sample
from o3dvis.training.evaluate import list_samples, subsample_indices
from o3dvis.nn import Octree, normalize_points


def leaf_oracle(points: np.ndarray, labels: np.ndarray, depth: int) -> tuple[float, float]:
    """(share of labels that differ from their leaf's first point, points per leaf)."""
    p = normalize_points(torch.from_numpy(points).double())[0].float()
    leaf = Octree(p, torch.zeros(len(p), dtype=torch.long), depth, 2).point_leaf.numpy()
    first = np.full(leaf.max() + 1, -1)
    first[leaf[::-1]] = np.arange(len(p))[::-1]  # the last write wins: each leaf's first point
    return float((labels != labels[:, first[leaf]]).mean()), len(p) / (leaf.max() + 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="folder of prepared .npz files")
    parser.add_argument("--every", type=int, default=1, help="use every k-th file")
    parser.add_argument("--points", default="32768,81920")
    parser.add_argument("--depths", default="7,8")
    args = parser.parse_args()
    samples = [load_sample(f) for f in list_samples(args.data)[::args.every]]
    print(f"{len(samples)} files\n\n| points | leaf depth | points per leaf | oracle error % |\n|---|---|---|---|")
    for n in map(int, args.points.split(",")):
        for depth in map(int, args.depths.split(",")):
            results = []
            for s in samples:
                idx = subsample_indices(len(s.points), n, 0, s.name)
                results.append(leaf_oracle(s.points[idx], s.visibility[:, idx], depth))
            error, per_leaf = np.mean(results, axis=0)
            print(f"| {n:,} | {depth} | {per_leaf:.2f} | {100 * error:.2f} |")


if __name__ == "__main__":
    main()
