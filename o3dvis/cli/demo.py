"""``o3dvis demo``: neural visibility against Open3D's HPR on the shipped sample, as PNGs."""

from __future__ import annotations

import argparse

from ._common import add_vector, check_folder, floats

__all__ = ["register", "run"]

_EXAMPLE = """example:
  o3dvis demo --out demo --points 20000

The sample is a fixed procedural shape (two tori, a bowl, a cup and a plate
wound through each other) built at run time; ground truth is ray-cast on it."""


def register(subparsers) -> None:
    """Adds the ``demo`` subcommand."""
    p = subparsers.add_parser(
        "demo", help="compare neural visibility with Open3D's HPR on the shipped sample",
        description="Runs the shipped network and Open3D's hidden_point_removal on the shipped "
                    "sample, prints their accuracy against ray-cast ground truth and their times, "
                    "and writes pictures: input, neural, HPR, ground truth, and errors (false "
                    "positives red, false negatives blue).",
        epilog=_EXAMPLE, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--out", default="o3dvis-demo", help="folder for the PNGs (default: o3dvis-demo)")
    p.add_argument("--points", type=int, default=20_000, help="points on the sample (default: 20000)")
    add_vector(p, "--camera", "camera position (default: one bounding-box diagonal from the centre)")
    p.add_argument("--model", default=None,
                   help="shipped model name or .safetensors checkpoint (default: the shipped default)")
    p.add_argument("--device", default=None, help="torch device, e.g. cuda (default: cpu)")
    p.add_argument("--hpr-k", type=floats, default=None,
                   help="HPR radius = bbox diagonal * 10**K; with several values, the most accurate "
                        "is shown (default: the sweep of o3dvis eval)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Runs the demo and prints the table and where the pictures are.

    Args:
        args: the parsed command line.

    Returns:
        0.
    """
    from ..evaluation.demo import IMAGES, run_demo

    check_folder(args.out, "--out")
    result = run_demo(args.out, args.points, args.camera, model=args.model, device=args.device,
                      hpr_k=args.hpr_k)
    camera = ", ".join(f"{x:.3g}" for x in result.camera)
    print(f"{result.num_points:,} points on the shipped sample, camera at ({camera}); "
          f"{int(result.truth.sum()):,} points visible (ray-cast ground truth)\n")
    print(result.table())
    for m in result.methods:
        print(f"  {m.name}: {m.detail}")
    print("\npictures (seen from beside the camera):")
    captions = {**IMAGES, "demo": "all of the above in one figure"}
    for name, path in result.images.items():
        print(f"  {path}  {captions[name]}")
    if result.figure_missing:
        print(f"  {result.figure_missing}")
    return 0
