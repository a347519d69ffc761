"""``o3dvis visible``: write the points of a cloud that a camera sees."""

from __future__ import annotations

import argparse
import sys

from ._common import add_precision_flag, add_vector, check_output, stages

__all__ = ["register", "run"]


def register(subparsers) -> None:
    """Adds the ``visible`` subcommand."""
    parser = subparsers.add_parser(
        "visible", help="keep the points of a cloud that a camera sees",
        description="Writes the points of INPUT visible from a camera position (or an orthographic "
                    "direction), with their colours and normals.",
        epilog="example:\n  o3dvis visible scan.ply --camera -2 0 5 -o scan_visible.ply",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("input", help="point cloud file readable by Open3D (.ply, .pcd, .xyz, ...)")
    view = parser.add_mutually_exclusive_group(required=True)
    add_vector(view, "--camera", "camera position")
    add_vector(view, "--direction", "viewing direction of an orthographic camera")
    parser.add_argument("-o", "--output", required=True, help="output point cloud file")
    parser.add_argument("--model", default=None,
                        help="shipped model name or .safetensors checkpoint (default: the shipped default)")
    parser.add_argument("--threshold", type=float, default=0.5,
                        help="a point is visible when its probability exceeds this (default 0.5)")
    parser.add_argument("--device", default=None, help="torch device, e.g. cuda (default: cpu)")
    parser.add_argument("--no-normals", action="store_true",
                        help="ignore the normals of the input cloud")
    parser.add_argument("--quality", choices=("fast", "balanced", "best"), default="fast",
                        help="fast (default): one pass; balanced: two passes over a cloud without normals where "
                             "they pay; best: those and four turned copies of the cloud")
    add_precision_flag(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Reads the cloud, selects the visible points, writes them.

    Args:
        args: the parsed command line.

    Returns:
        0 when the visible points were written, 1 when no point is visible.
    """
    check_output(args.output, "-o", "point cloud")
    import open3d as o3d

    from ..dropins import select_visible
    from ..io import read_point_cloud
    from ..neural import NeuralVisibility

    model = args.model
    if args.precision != "auto":
        model = NeuralVisibility.pretrained(model or "default", device=args.device, precision=args.precision)
    with stages(3, "visible") as bar:
        pcd = read_point_cloud(args.input)
        bar.update()
        visible = select_visible(pcd, args.camera, direction=args.direction, threshold=args.threshold,
                                 model=model, device=args.device,
                                 normals=False if args.no_normals else None, quality=args.quality)
        bar.update()
        if not visible.has_points():
            print(f"no point of {args.input} is visible; nothing written", file=sys.stderr)
            return 1
        if not o3d.io.write_point_cloud(args.output, visible):
            raise RuntimeError(f"could not write {args.output}")
        bar.update()
    print(f"{len(visible.points)} of {len(pcd.points)} points visible -> {args.output}")
    return 0
