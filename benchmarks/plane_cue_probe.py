"""How much one view cue alone tells: the accuracy of a single threshold on it.

For every point and view of the validation clouds, each depth-buffer cue of
``o3dvis.nn.view_cues(..., planes=True)`` is scored on its own: the best
threshold on it over all files and views together (one number per cue and
density, no tuning per file), and the mean over files of each file's own best
threshold. The residual to the own pixel's nearest point is what the shipped
cues give at each scale; the plane residual is the ``plane_cues`` option's.
The rows of the thin-walled files show where the two differ most:

    python3 benchmarks/plane_cue_probe.py --data data/val --points 2048,8192
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis.training.data.prepare import load_sample
from o3dvis.training.evaluate import eval_cloud, list_samples
from o3dvis.nn import view_cues
from o3dvis.nn.cues import DEFAULT_SCALES

THIN = ("lgmcts__shapenet_bowl", "semrob__chair_341a", "semrob__cup_", "semrob__rifle_", "semrob__bathtub_")


def best_threshold(score: np.ndarray, hidden: np.ndarray) -> float:
    """Accuracy of the best rule ``hidden = score > t``."""
    h = hidden[np.argsort(score, kind="stable")]
    correct = np.concatenate([[0], np.cumsum(~h)]) + np.concatenate([np.cumsum(h[::-1])[::-1], [0]])
    return correct.max() / len(h)


def cloud_cues(sample, num_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(V * n, 5 * S) own-pixel and plane cues of all views, (V * n,) hidden labels."""
    cloud = eval_cloud(sample, num_points, 0.0)
    points = torch.from_numpy(cloud.points).float()
    scales = len(DEFAULT_SCALES)
    rows = []
    for camera in cloud.cameras:
        _, cues = view_cues(points, torch.from_numpy(camera).float(), planes=True)
        rows.append(torch.cat([cues[:, 4:9 * scales:9], cues[:, 9 * scales:]], dim=1).numpy())
    return np.concatenate(rows), ~cloud.labels.reshape(-1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="folder of prepared .npz files")
    parser.add_argument("--points", default="2048,8192")
    parser.add_argument("--limit", type=int, help="first files only")
    args = parser.parse_args()
    files = list_samples(args.data, args.limit)
    names = [f"own pixel, scale {s}" for s in DEFAULT_SCALES] + [f"plane, scale {s}" for s in DEFAULT_SCALES]
    print(f"{len(files)} files of {args.data}, clean clouds, all views of each; accuracy % of one "
          "threshold on one cue (hidden when above it)\n")
    print("| points | cue | one threshold for all files | best threshold per file, mean | "
          "per file, the five thin-walled files |\n|---|---|---|---|---|")
    for n in map(int, args.points.split(",")):
        per_file, thin, pooled_x, pooled_y = [], [], [], []
        for path in files:
            sample = load_sample(path)
            x, hidden = cloud_cues(sample, n)
            accuracy = [best_threshold(x[:, k], hidden) for k in range(x.shape[1])]
            per_file.append(accuracy)
            if sample.name.startswith(THIN):
                thin.append(accuracy)
            pooled_x.append(x)
            pooled_y.append(hidden)
        x, hidden = np.concatenate(pooled_x), np.concatenate(pooled_y)
        for k, name in enumerate(names):
            pooled = best_threshold(x[:, k], hidden)
            thin_mean = f"{100 * np.mean([a[k] for a in thin]):.1f}" if thin else "—"
            print(f"| {n:,} | {name} | {100 * pooled:.1f} | {100 * np.mean([a[k] for a in per_file]):.1f} "
                  f"| {thin_mean} |")


if __name__ == "__main__":
    main()
