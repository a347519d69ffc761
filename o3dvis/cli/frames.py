"""``o3dvis frames``: what each camera of a trajectory sees of a map, one file per frame.

Each frame's file is written under a temporary name and renamed when complete, so a run that
is stopped (Ctrl-C, a kill, a lost machine) leaves whole files only, and a run started again
answers only the frames whose files are missing.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ._common import add_precision_flag, check_folder

__all__ = ["register", "run"]

_TEMPORARY = ".tmp"  # the files being written: .NAME.PID.tmp.SUFFIX


def _positive_int(text: str) -> int:
    value = int(text) if text.strip().isdecimal() else 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


_DESCRIPTION = """For each pinhole camera of POSES, writes the points of MAP it sees: their indices in MAP, pixel
coordinates (u, v) and depths, in OUT/NNNNNN.npz (arrays indices, pixels, depths), and with --depth-png
its 16-bit depth image, OUT/NNNNNN.png (NNNNNN: the camera's index); OUT/names.txt holds a name per
camera, in their order (a COLMAP model's image names, else the indices). Each file appears whole or not
at all; a run started again skips the frames already written."""
_EXAMPLES = """examples:
  o3dvis frames map.ply trajectory.json -o frames --max-range 40
  o3dvis frames map.ply trajectory.json -o frames --max-range 40 --ray auto --workers 32"""


def register(subparsers) -> None:
    """Adds the ``frames`` subcommand."""
    parser = subparsers.add_parser("frames", help="the points of a map each camera of a trajectory sees",
                                   description=_DESCRIPTION, epilog=_EXAMPLES,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("map", help="the map: a point cloud file readable by Open3D (.ply, .pcd, .xyz, ...)")
    parser.add_argument("poses", help="the cameras: an Open3D trajectory (.json, or .log with Open3D's default "
                                      "intrinsic) or a COLMAP model (its folder)")
    parser.add_argument("-o", "--output", required=True, metavar="OUT", help="folder of the frames' files")
    parser.add_argument("--max-range", type=_positive_float, default=None, metavar="M",
                        help="a frame sees only the points within M of its camera (default: all in its image)")
    parser.add_argument("--depth-png", action="store_true",
                        help="also write each frame's depth image, 16-bit PNG in units of 1/--depth-scale, "
                             "0 where no point shows (or deeper than 16 bits hold)")
    parser.add_argument("--depth-scale", type=_positive_float, default=1000.0,
                        metavar="S", help="depth image units per map unit (default 1000: mm of a map in metres)")
    parser.add_argument("--threshold", type=float, default=0.5,
                        help="a point is visible when its probability exceeds this (default 0.5)")
    parser.add_argument("--ray", default=None, metavar="ADDRESS",
                        help="answer the frames on a Ray cluster: 'auto' joins the one this machine runs, "
                             "'local' starts one here, else the address of its head (needs o3dvis[ray])")
    parser.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                        help="Ray actors, one CPU each (default: the cluster's CPUs); with --ray only")
    parser.add_argument("--batch-size", type=_positive_int, default=8,
                        help="consecutive frames a Ray actor answers at a time (default 8)")
    parser.add_argument("--model", default=None,
                        help="shipped model name or .safetensors checkpoint (default: the shipped default)")
    parser.add_argument("--device", default=None, help="torch device, e.g. cuda (default: cpu)")
    add_precision_flag(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Reads the map and the poses, answers the frames not written yet, writes each as it comes.

    Returns:
        0 once every frame's file is in the folder.
    """
    check_folder(args.output, "-o")
    if args.workers is not None and args.ray is None:
        raise ValueError("--workers sets the Ray actors: give --ray too")
    if not 0 <= args.threshold <= 1:
        raise ValueError(f"--threshold must be in [0, 1], got {args.threshold}")
    from tqdm import tqdm

    from ..apps.map_frames import pinhole_frames
    from ..io import read_point_cloud, read_poses

    pcd = read_point_cloud(args.map)
    poses = read_poses(args.poses)
    views = pinhole_frames(poses.trajectory)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    _remove_unfinished(out)
    _atomically(out / "names.txt", lambda path: path.write_text("".join(f"{name}\n" for name in poses.names)))
    digits = max(6, len(str(len(views) - 1)))
    stems = [f"{i:0{digits}d}" for i in range(len(views))]
    todo = [i for i, stem in enumerate(stems) if not _written(out, stem, args.depth_png)]
    if not todo:
        print(f"all {len(views)} frames are written in {out}")
        return 0
    with tqdm(total=len(views), initial=len(views) - len(todo), unit="frame", desc="frames", leave=False) as bar:
        for i, frame in _answers(args, pcd, views, todo):
            _write(out, stems[i], frame, args.depth_png, args.depth_scale)
            bar.update()
    before = f", {len(views) - len(todo)} were there" if len(todo) < len(views) else ""
    print(f"{len(todo)} frames written to {out}{before}")
    return 0


def _answers(args: argparse.Namespace, pcd, views: list, todo: list[int]):
    """``(index, Frame)`` of the frames ``todo``, in this process or on Ray, each answered from the crop
    of the map the whole trajectory gives it."""
    model = args.model
    if args.precision != "auto" or args.device is not None:
        from ..neural import NeuralVisibility

        model = NeuralVisibility.pretrained(model or "default", device=args.device, precision=args.precision)
    if args.ray is not None:
        from ..cluster import frames_on_ray

        yield from frames_on_ray(pcd, views, max_range=args.max_range, threshold=args.threshold,
                                 images=args.depth_png, model=model, workers=args.workers, batch_size=args.batch_size,
                                 indices=todo, address=None if args.ray == "local" else args.ray)
        return
    from ..apps.map_frames import FrameMap

    answers = FrameMap(pcd, max_range=args.max_range, model=model, device=args.device).frames(
        views, threshold=args.threshold, images=args.depth_png, progress=False, indices=todo)
    yield from zip(todo, answers)


def _written(out: Path, name: str, depth_png: bool) -> bool:
    """Whether the frame ``name`` is written: its arrays, and its depth image where asked for."""
    return (out / f"{name}.npz").is_file() and (not depth_png or (out / f"{name}.png").is_file())


def _write(out: Path, name: str, frame, depth_png: bool, depth_scale: float) -> None:
    """Writes a frame's files, each under a temporary name renamed when complete; its arrays last,
    which mark it written."""
    import dataclasses

    if depth_png:
        _atomically(out / f"{name}.png", lambda path: _write_depth_png(path, frame.depth_image, depth_scale))
    arrays = dataclasses.replace(frame, depth_image=None, index_image=None)
    _atomically(out / f"{name}.npz", lambda path: arrays.save(path))


def _atomically(path: Path, write) -> None:
    """``write(temporary path)``, then the temporary file renamed to ``path`` (within one folder,
    so that ``path`` is the whole file or none)."""
    temporary = path.with_name(f".{path.stem}.{os.getpid()}{_TEMPORARY}{path.suffix}")
    try:
        write(temporary)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def _write_depth_png(path: Path, depth, scale: float) -> None:
    """A float depth image as a 16-bit PNG of ``depth * scale``, 0 beyond what 16 bits hold."""
    import numpy as np
    import open3d as o3d

    scaled = np.rint(depth.astype(np.float64) * scale)
    scaled[scaled > np.iinfo(np.uint16).max] = 0
    if not o3d.io.write_image(str(path), o3d.geometry.Image(scaled.astype(np.uint16))):
        raise OSError(f"could not write {path}")


def _remove_unfinished(out: Path) -> None:
    """Removes the temporary files of runs of this machine that are gone (stopped while writing)."""
    for path in out.glob(f".*{_TEMPORARY}.*"):
        pid = path.name.split(".")[-3]
        if pid.isdecimal() and not _running(int(pid)):
            path.unlink(missing_ok=True)


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's
        return True
    return True
