"""Accuracy of a network against its decision threshold, per density and noise level.

The network says "visible" when its probability exceeds a threshold (0.5 by
default). This sweep shows where another threshold would score higher, on
prepared data (run it on training data, so that nothing is tuned on val):
a network trained on clean and noisy clouds alike cannot tell them apart, and
a single threshold then trades one against the other (clean clouds want
about 0.6, dense noisy ones 0.1-0.3).

    python3 benchmarks/threshold_sweep.py --data data/train --limit 30 \\
        --out benchmarks/results/threshold_train.md
"""

from __future__ import annotations

import numpy as np

from mesh_bench import command_line, data_parser, data_settings, emit_report, markdown
from o3dvis.neural import NeuralVisibility


def main() -> int:
    parser = data_parser(__doc__, 30, "0,0.01,0.02")
    parser.add_argument("--model", default="default", help="shipped model name or .safetensors path")
    parser.add_argument("--thresholds", default="0.1,0.2,0.3,0.4,0.5,0.6,0.7")
    args = parser.parse_args()
    vis = NeuralVisibility.pretrained(args.model, use_normals=False)
    thresholds = np.array([float(t) for t in args.thresholds.split(",")])
    rows = []
    files, settings = data_settings(args)
    for n, noise, clouds in settings:
        correct, total = np.zeros(len(thresholds)), 0
        for cloud in clouds:
            probs = vis.encode(cloud.points).probabilities(cloud.cameras).numpy()
            correct += [((probs > t) == cloud.labels).sum() for t in thresholds]
            total += cloud.labels.size
        accuracy = 100 * correct / total
        best = int(accuracy.argmax())
        rows.append([f"{n:,}", f"{100 * noise:g} %"] + [f"{a:.2f}" for a in accuracy]
                    + [f"{thresholds[best]:g} ({accuracy[best] - accuracy[thresholds == 0.5].max():+.2f})"
                       if (thresholds == 0.5).any() else f"{thresholds[best]:g}"])
        print(" | ".join(rows[-1]), flush=True)
    report = "\n".join([command_line(), "",
                        f"Accuracy (%) of `{args.model}` by decision threshold: {len(files)} files of "
                        f"{args.data}, {args.views} views each.", "",
                        markdown(["points", "noise"] + [f"{t:g}" for t in thresholds]
                                 + ["best (vs 0.5)"], rows)])
    return emit_report(report, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
