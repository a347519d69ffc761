"""How good must normals be for the normals model to help: true, PCA, and partly flipped normals.

The points-only default trails tuned HPR on clean clouds while the normals model
beats it. Could the default estimate normals itself (a head of its U-Net) and
feed them to the predictor? This bounds that idea from above with the shipped
normals model and four kinds of normals on the validation clouds (16 views):

* ``true``: the mesh normals of the sampled points;
* ``PCA``: Open3D's ``estimate_normals`` over each point's ``k`` nearest neighbours,
  oriented by the true normal (an oracle orientation no network has);
* ``PCA, f flipped``: the same with a random share ``f`` of them reversed;
* ``o3dvis``: ``estimate_normals_neural``'s normals (26 views of the points-only
  default, triangulated), which a points-only pipeline can have: default ->
  normals -> normals model. The default's own accuracy is the first column.

    python3 benchmarks/normals_input_probe.py --data data/val --points 2048,8192
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis import NeuralVisibility
from o3dvis.apps.normals import multiview_normals
from o3dvis.training.data.prepare import load_sample
from o3dvis.training.evaluate import Counts, eval_cloud, list_samples


def pca_normals(points: np.ndarray, k: int) -> np.ndarray:
    """Unoriented unit normals from the ``k`` nearest points (Open3D's PCA), (N, 3)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    return np.asarray(pcd.normals)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="folder of prepared .npz files")
    parser.add_argument("--points", default="2048,8192")
    parser.add_argument("--views", type=int, default=16)
    parser.add_argument("--k", type=int, default=10, help="neighbours of the PCA normals")
    parser.add_argument("--flip", type=float, default=0.1, help="share of PCA normals reversed")
    parser.add_argument("--noise", type=float, default=0.0, help="noise level, share of the bbox diagonal")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model, default = NeuralVisibility.pretrained("normals"), NeuralVisibility.pretrained("default")
    files = list_samples(args.data)
    kinds = ["true", "PCA", f"PCA, {100 * args.flip:g} % flipped", "o3dvis"]
    print(f"{len(files)} files, {args.views} views, {100 * args.noise:g} % noise, normals model, PCA with "
          f"k = {args.k}\n\n| points | default (no normals): accuracy % | "
          + " | ".join(f"{kind} normals: accuracy %" for kind in kinds) + " |\n"
          "|---|" + "---|" * (len(kinds) + 1))
    for n in map(int, args.points.split(",")):
        rng = np.random.default_rng(0)
        counts = [Counts() for _ in range(len(kinds) + 1)]
        for f in files:
            cloud = eval_cloud(load_sample(f), n, args.noise, 0, args.views)
            field = default.encode(cloud.points)  # the U-Net once, for both uses of the default
            counts[0] += Counts.of(field.query(cloud.cameras), cloud.labels)
            pca = pca_normals(cloud.points, args.k)
            pca *= np.where((pca * cloud.normals).sum(axis=1, keepdims=True) < 0, -1, 1)
            flipped = pca * np.where(rng.random((len(pca), 1)) < args.flip, -1, 1)
            estimated = multiview_normals(cloud.points, field)
            for i, normals in enumerate((cloud.normals, pca, flipped, estimated), start=1):
                counts[i] += Counts.of(model.encode(cloud.points, normals=normals).query(cloud.cameras),
                                       cloud.labels)
        print(f"| {n:,} | " + " | ".join(f"{100 * c.accuracy:.1f}" for c in counts) + " |", flush=True)


if __name__ == "__main__":
    main()
