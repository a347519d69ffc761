"""``o3dvis eval`` (accuracy tables), ``o3dvis eval-drives`` (accuracy on driving logs) and ``o3dvis bench``
(timing against Open3D HPR)."""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

from ._common import check_output, floats, positive_ints

__all__ = ["register", "run_eval", "run_drives", "run_bench"]

_EVAL_EXAMPLE = """example:
  o3dvis eval --data data/val --points 2048,8192,32768,81920 --noise 0,0.01,0.02 \\
      --methods hpr,hpr-exp --views 16 --out benchmarks/results/val.json --cache ~/.cache/o3dvis-eval

Baselines are scored at every value of their sweep (--hpr-k, --gamma, --splat) and the
best value per density and noise level over the whole set is reported with it.
A method that cannot run here (no network weights) is reported absent.

Scenes (from `o3dvis prepare --scenes`), cameras inside the cloud only:
  o3dvis eval --scenes --data data/val_scenes --points 16384 --noise 0,0.01 --views 6 \\
      --methods hpr,zbuffer,neural --out benchmarks/results/val_scenes.json

With --scenes, noise is relative to the median camera-to-point distance, each
sampling is its own table, baselines are tuned per column for accuracy and for
balanced accuracy, and a network that refuses cameras inside is reported absent."""

_DRIVES_EXAMPLE = """example (the table of benchmarks/results/drives.md):
  o3dvis eval-drives --lengths 100,300,1000 --noise 0,0.01 --frames 6 --seeds 0 \\
      --out benchmarks/results/drives.json

Each seed and length is a procedural log (a street network, LiDAR sweeps every 5 m
accumulated into one map, a forward 640 x 480 frame of 90 degrees every 5 m); a frame's
points are the map's within --range of its camera and inside its image, labelled by ray
casting. Noise moves each map point by up to that fraction of its range from its sweep.
o3dvis variants: o3dvis-whole (the whole map encoded once), o3dvis-crop60 (a 60 m crop
encoded), o3dvis-x4 (4 rotations), o3dvis-object (no scene model)."""

_BENCH_EXAMPLE = """example:
  o3dvis bench --points 2048,8192,32768 --views 1,26 --methods hpr,hpr-exp,neural

Open3D's hidden_point_removal runs on the same cloud and cameras in the same
run; speed-up = its time / the method's time."""


def _names(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


_SCENE_HPR_K = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)  # inside a room the best radius is far smaller than outside


def _add_method_args(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument("--methods", type=_names, default=_names(default),
                   help=f"comma-separated: hpr, hpr-exp, zbuffer, neural, neural-normals, neural-estimate "
                        f"(normals estimated in a first pass where that is more accurate), neural-balanced, "
                        f"neural-best (those qualities; neural is fast); a neural one "
                        f"with -x<K> appended averages K rotations of each cloud, e.g. neural-x8 "
                        f"(default: {default})")
    p.add_argument("--model", "--checkpoint", dest="checkpoint", default=None, metavar="MODEL",
                   help="shipped model name or .safetensors checkpoint for 'neural' (a model that "
                        "takes normals: for 'neural-normals', and for 'neural-estimate' after the "
                        "shipped default's first pass; default: the shipped default; --checkpoint "
                        "is the older name)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default: 2)")


def register(subparsers) -> None:
    """Adds the ``eval`` and ``bench`` subcommands."""
    fmt = argparse.RawDescriptionHelpFormatter
    p = subparsers.add_parser("eval", help="accuracy of visibility methods on labelled data",
                              description="Accuracy, FN/FP rates and per-category accuracy of visibility "
                                          "methods against ray-cast labels, per density and noise level.",
                              epilog=_EVAL_EXAMPLE, formatter_class=fmt)
    p.add_argument("--data", type=Path, required=True, help="folder of .npz samples from `o3dvis prepare`")
    p.add_argument("--points", type=positive_ints, default=[2048, 8192, 32768, 81920],
                   help="densities (default: 2048,8192,32768,81920)")
    p.add_argument("--noise", type=floats, default=[0.0],
                   help="noise levels as fractions of the bounding-box diagonal (default: 0)")
    _add_method_args(p, "hpr,hpr-exp,neural")
    p.add_argument("--views", type=int, default=None, help="first K viewpoints of each file (default: all)")
    p.add_argument("--limit", type=int, default=None, help="first M files only")
    p.add_argument("--hpr-k", type=floats, default=None,
                   help="HPR sweep: radius = diagonal * 10^k (default: the sweep of o3dvis.baselines.SWEEPS)")
    p.add_argument("--gamma", type=floats, default=None,
                   help="hpr-exp sweep of the kernel exponent, < 0 (default: the sweep of o3dvis.baselines.SWEEPS)")
    p.add_argument("--splat", type=floats, default=None,
                   help="zbuffer sweep of the disc radius, in point spacings (default: the sweep of "
                        "o3dvis.baselines.SWEEPS)")
    p.add_argument("--scenes", action="store_true",
                   help="score the cameras inside the cloud only, per sampling, with balanced accuracy; "
                        f"the HPR sweep defaults to k = {','.join(f'{k:g}' for k in _SCENE_HPR_K)}")
    p.add_argument("--seed", type=int, default=0, help="seed of subsampling and noise (default: 0)")
    p.add_argument("-o", "--out", type=Path, default=None, help="write JSON here and the Markdown next to it (.md)")
    p.add_argument("--cache", type=Path, default=None,
                   help="folder of per-file baseline results; a rerun resumes from it "
                        "(empty it after changing a baseline)")
    p.set_defaults(func=run_eval)

    _register_drives(subparsers, fmt)

    p = subparsers.add_parser("bench", help="timing against Open3D's hidden_point_removal",
                              description="Times visibility methods and Open3D HPR on the same procedural "
                                          "clouds and cameras.",
                              epilog=_BENCH_EXAMPLE, formatter_class=fmt)
    p.add_argument("--points", type=positive_ints, default=[2048, 8192, 32768, 81920, 200_000, 1_000_000],
                   help="cloud sizes (default: 2048,8192,32768,81920,200000,1000000)")
    p.add_argument("--views", type=positive_ints, default=[1, 26], help="numbers of views (default: 1,26)")
    _add_method_args(p, "hpr,hpr-exp,neural")
    p.add_argument("--repeats", type=int, default=1, help="best of this many runs (default: 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the cloud and cameras (default: 0)")
    p.add_argument("-o", "--out", type=Path, default=None, help="write JSON here and the Markdown next to it (.md)")
    p.set_defaults(func=run_bench)


def _register_drives(subparsers, fmt) -> None:
    p = subparsers.add_parser("eval-drives", help="accuracy of visibility methods on procedural driving logs",
                              description="Accuracy and balanced accuracy of visibility methods on the pinhole "
                                          "frames of procedural driving logs, against ray casting, per log "
                                          "length and noise level, and as logs grow.",
                              epilog=_DRIVES_EXAMPLE, formatter_class=fmt)
    p.add_argument("--lengths", type=floats, default=[100.0, 300.0, 1000.0],
                   help="log lengths in metres (default: 100,300,1000)")
    p.add_argument("--noise", type=floats, default=[0.0, 0.01],
                   help="noise levels, fractions of each point's range from its sweep (default: 0,0.01)")
    p.add_argument("--methods", type=_names, default=None,
                   help="comma-separated: o3dvis (and its variants), hpr, zbuffer, pixel-zbuffer, everything "
                        "(default: all five)")
    p.add_argument("--model", "--checkpoint", dest="checkpoint", default=None, metavar="MODEL",
                   help="shipped model name or .safetensors checkpoint for o3dvis (default: the shipped models)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default: 2)")
    p.add_argument("--seeds", type=floats, default=[0], help="one log of each length per seed (default: 0)")
    p.add_argument("--frames", type=int, default=6, help="frames evaluated along each log (default: 6)")
    p.add_argument("--range", dest="max_range", type=float, default=None,
                   help="a frame's range in metres (default: 40)")
    p.add_argument("--points-per-metre", type=float, default=3400.0,
                   help="map points per metre of log (default: 3400, 400 k points over 120 m)")
    p.add_argument("--heading", type=float, default=0.0,
                   help="turn of the map about z, degrees (default: 0, the main road along x)")
    p.add_argument("--hpr-k", type=floats, default=None, help="HPR sweep: radius = diagonal * 10^k")
    p.add_argument("--splat", type=floats, default=None, help="zbuffer sweep of the disc radius, in point spacings")
    p.add_argument("-o", "--out", type=Path, default=None, help="write JSON here and the Markdown next to it (.md)")
    p.set_defaults(func=run_drives)


def _write(out: Path | None, report: dict, markdown: str) -> None:
    print(markdown)
    if out is not None:
        out.write_text(json.dumps(report, indent=1) + "\n")
        out.with_suffix(".md").write_text(markdown)
        print(f"wrote {out} and {out.with_suffix('.md')}", file=sys.stderr)


def _checkpoint(model: str | None) -> Path | None:
    """The file ``--model`` names: None for the shipped default, a shipped model's file, or a path."""
    if model is None or model == "default":
        return None
    from ..models import WEIGHTS_DIR, available_models, read_model_card

    if not Path(model).is_file() and model in available_models():
        return WEIGHTS_DIR / read_model_card()["models"][model]["file"]
    return Path(model)


def _methods(args, sweeps: dict):
    import torch

    from ..evaluation.methods import resolve_methods

    torch.set_num_threads(max(1, args.threads))
    methods, absent = resolve_methods(args.methods, _checkpoint(args.checkpoint), sweeps)
    for name, reason in absent.items():
        print(f"{name}: absent ({reason})", file=sys.stderr)
    return methods, absent


def run_eval(args) -> int:
    """``o3dvis eval``: prints the Markdown tables; ``--out`` also writes JSON."""
    from ..evaluation.evaluate import category_of, evaluate, markdown_table, scene_table, summarize
    from ..training.data.sample import list_samples

    if args.views is not None and args.views < 1:
        raise ValueError("--views must be >= 1")
    check_output(args.out, "--out")
    hpr_k = args.hpr_k or (list(_SCENE_HPR_K) if args.scenes else None)
    methods, absent = _methods(args, {"hpr": hpr_k, "hpr-exp": args.gamma, "zbuffer": args.splat})
    files = list_samples(args.data, args.limit)
    if args.scenes:
        for path in files:  # the first file with a camera inside
            if not _drop_refusing(methods, absent, path, min(args.points), args.views):
                break
    if not methods:
        print("no method can run", file=sys.stderr)
        return 1
    per_file = evaluate(files, args.data, methods, args.points, args.noise, args.seed, args.views,
                        args.cache, cached=[m for m in methods if not m.startswith("neural")],
                        inside=args.scenes)
    categories = dict(sorted(Counter(category_of(f, args.data) for f in files).items()))
    settings = {"data": str(args.data), "files": len(files), "points": args.points, "noise": args.noise,
                "views": args.views, "seed": args.seed, "scenes": args.scenes,
                "sweeps": {m: list(s) for m, s in methods.items()}}
    if args.scenes:
        groups: dict[str, dict] = {}
        for name, entry in per_file.items():
            groups.setdefault(entry["category"].split("-")[-1], {})[name] = entry
        rows = {g: summarize(group, methods, args.points, args.noise) for g, group in sorted(groups.items())}
        markdown = scene_table(rows, absent)
    else:
        rows = summarize(per_file, methods, args.points, args.noise)
        markdown = markdown_table(rows, absent, categories)
    report = {"settings": settings, "categories": categories, "absent": absent, "results": rows}
    _write(args.out, report, markdown)
    return 0


def _drop_refusing(methods: dict, absent: dict, path: Path, points: int, views: int | None) -> bool:
    """Moves to ``absent`` the methods that refuse a camera inside the file's cloud.

    Returns:
        True when the file has no camera inside (nothing was tried).
    """
    from ..evaluation.evaluate import eval_cloud, run_method
    from ..training.data.sample import load_sample

    cloud = eval_cloud(load_sample(path), points, 0.0, views=views, inside=True)
    if not len(cloud.cameras):
        return True
    first = cloud._replace(cameras=cloud.cameras[:1], labels=cloud.labels[:1])
    for name in [n for n in methods if n.startswith("neural")]:
        try:
            run_method(next(iter(methods[name].values())), first)
        except ValueError as e:
            absent[name] = f"refuses a camera inside the cloud: {str(e).splitlines()[0]}"
            del methods[name]
            print(f"{name}: absent ({absent[name]})", file=sys.stderr)
    return False


def _drives_command(args, seeds: list[int], max_range: float) -> str:
    """The ``o3dvis eval-drives`` command line that repeats this run (every setting spelled out)."""
    def joined(values) -> str:
        return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values)

    command = (f"o3dvis eval-drives --lengths {joined(args.lengths)} --noise {joined(args.noise)} "
               f"--frames {args.frames} --seeds {joined(seeds)} --range {max_range:g} "
               f"--points-per-metre {args.points_per_metre:g} --heading {args.heading:g}")
    for flag, value in (("--methods", args.methods), ("--hpr-k", args.hpr_k), ("--splat", args.splat),
                        ("--model", args.checkpoint and [args.checkpoint])):
        command += f" {flag} {joined(value)}" if value else ""
    return command


def run_drives(args) -> int:
    """``o3dvis eval-drives``: prints the Markdown tables; ``--out`` also writes JSON."""
    import torch

    from ..evaluation.drives import (FRAME_RANGE, METHOD_NAMES, drive_methods, drives_table, evaluate_drives,
                                     summarize_drives)

    check_output(args.out, "--out")
    if args.frames < 1 or any(s < 0 or s != int(s) for s in args.seeds):
        raise ValueError("--frames must be >= 1 and --seeds integers >= 0")
    torch.set_num_threads(max(1, args.threads))
    methods, absent = drive_methods(args.methods or METHOD_NAMES, _checkpoint(args.checkpoint), args.hpr_k,
                                    args.splat)
    for name, reason in absent.items():
        print(f"{name}: absent ({reason})", file=sys.stderr)
    if not methods:
        print("no method can run", file=sys.stderr)
        return 1
    seeds, max_range = [int(s) for s in args.seeds], FRAME_RANGE if args.max_range is None else args.max_range
    options = {"points_per_metre": args.points_per_metre, "heading": args.heading}
    per_frame = evaluate_drives(args.lengths, args.noise, methods, seeds, args.frames, max_range, options)
    summary = summarize_drives(per_frame, methods, args.noise)
    settings = {"lengths": args.lengths, "noise": args.noise, "seeds": seeds, "frames": args.frames,
                "max_range": max_range, "log": options, "sweeps": {m: list(s) for m, s in methods.items()},
                "command": _drives_command(args, seeds, max_range)}
    report = {"settings": settings, "absent": absent, "results": summary, "frames": per_frame}
    _write(args.out, report, drives_table(summary, settings, absent))
    return 0


def run_bench(args) -> int:
    """``o3dvis bench``: prints the timing table; ``--out`` also writes JSON."""
    from ..clib import cpu_name
    from ..nn import native
    from ..threads import usable_cores
    from ..evaluation.speed import benchmark, markdown_table

    check_output(args.out, "--out")
    # one setting per baseline: Open3D's usual radius (k = 2) and a mid-grid kernel exponent
    methods, absent = _methods(args, {"hpr": [2.0], "hpr-exp": [-0.01]})
    single = {name: next(iter(sweep.values())) for name, sweep in methods.items()}
    rows = benchmark(single, args.points, args.views, args.repeats, args.seed)
    kernels, cpu, cores = native.variant(), cpu_name(), usable_cores()
    report = {"settings": {"points": args.points, "views": args.views, "repeats": args.repeats,
                           "threads": args.threads, "seed": args.seed, "c_kernels": kernels is not None,
                           "kernel_variant": kernels, "cpu": cpu, "cores": cores,
                           "methods": {n: getattr(m, "__name__", n) for n, m in single.items()}},
              "absent": absent, "results": rows}
    markdown = (markdown_table(rows) + "".join(f"\n{n}: absent ({r})" for n, r in absent.items())
                + "\nper-view steps of the neural methods on the CPU: "
                + (f"C kernels (o3dvis.nn.native, {kernels} variant)" if kernels else "torch ops (no C kernels built)")
                + f"; {cpu or 'CPU unnamed'}, {cores} cores usable\n")
    _write(args.out, report, markdown)
    return 0

