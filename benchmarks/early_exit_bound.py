"""What an early exit for points far behind the coarsest depth buffer would skip, and cost.

For each view, a point whose depth lies at least T pixel footprints behind the
nearest point in its pixel of the coarsest depth buffer could be answered
"hidden" without its cues and MLP. This counts, on prepared data, the share of
points such a rule would skip and the accuracy it would change (errors after
minus errors of the network on those points), for several T.

    python3 benchmarks/early_exit_bound.py --data data/val --limit 16 \\
        --out benchmarks/results/early_exit_bound.md
"""

from __future__ import annotations

import numpy as np
import torch

from mesh_bench import command_line, data_parser, data_settings, emit_report, markdown
from o3dvis.cameras import as_views
from o3dvis.neural import NeuralVisibility


def main() -> int:
    parser = data_parser(__doc__, 16, "0,0.02")
    parser.add_argument("--behind", default="5,10,20", help="values of T, in pixel footprints")
    args = parser.parse_args()
    vis = NeuralVisibility.pretrained("default", use_normals=False)
    net, behind = vis.network, [float(t) for t in args.behind.split(",")]
    rows = []
    files, settings = data_settings(args)
    for n, noise, clouds in settings:
        skipped, change, total = np.zeros(len(behind)), np.zeros(len(behind)), 0
        for cloud in clouds:
            field = vis.encode(cloud.points)
            said = field.query(cloud.cameras)
            cameras = field._normalised(as_views(cloud.cameras, None))[0]
            with torch.inference_mode():
                for v, camera in enumerate(cameras):
                    # the centre pixel's cue of the coarsest scale: asinh(residual in footprints),
                    # of the field's rows, put back in the cloud's order
                    cues = net.view(field.points_n, camera).cues(field.rank)
                    residual = torch.sinh(cues[:, -5]).numpy()
                    truth, network = cloud.labels[v], said[v]
                    for i, t in enumerate(behind):
                        skip = residual >= t
                        skipped[i] += skip.sum()
                        change[i] += truth[skip].sum() - (network[skip] != truth[skip]).sum()
            total += cloud.labels.size
        rows.append([f"{n:,}", f"{100 * noise:g} %"] + sum(
            ([f"{100 * s / total:.1f}", f"{-100 * c / total:+.3f}"] for s, c in zip(skipped, change)), []))
        print(" | ".join(rows[-1]), flush=True)
    header = ["points", "noise"] + sum(([f"T={t:g}: skipped %", f"T={t:g}: accuracy change (points)"]
                                        for t in behind), [])
    report = "\n".join([command_line(), "",
                        f"Early exit at T pixel footprints behind the coarsest depth buffer: "
                        f"{len(files)} files of {args.data}, {args.views} views each.", "",
                        markdown(header, rows)])
    return emit_report(report, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
