"""What the subcommands share: argument types and flags, the visibility method, writing images,
progress (clouds are read by :func:`o3dvis.io.read_point_cloud`).

Nothing heavy is imported here at module level: ``o3dvis --help`` builds every parser.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

__all__ = ["VECTOR_OPTIONS", "OUTPUTS", "add_vector", "add_precision_flag", "add_method_flags", "split_vectors",
           "visibility_method", "write_image", "check_output", "check_folder", "stages", "positive_ints", "floats"]

# the options that take a point or a direction, X Y Z
VECTOR_OPTIONS = ("--camera", "--direction", "--light")
# the choices of o3dvis.nn.predictor.PRECISIONS (a test checks they agree), kept here so that the
# parser imports no torch
_PRECISIONS = ("auto", "float32", "bfloat16")


def split_vectors(argv: list[str]) -> list[str]:
    """``argv`` with the older comma form of a vector option (``--camera=-2,0,5`` or
    ``--camera -2,0,5``) written as three arguments (``--camera -2 0 5``)."""
    out, after_option = [], False
    for arg in argv:
        option, equals, value = arg.partition("=")
        if equals and option in VECTOR_OPTIONS and "," in value:
            out += [option, *value.split(",")]
        elif after_option and "," in arg:
            out += arg.split(",")
        else:
            out.append(arg)
        after_option = arg in VECTOR_OPTIONS
    return out


def add_vector(parser: argparse.ArgumentParser | argparse._MutuallyExclusiveGroup, option: str, help: str,
               **kwargs) -> None:
    """Adds ``option`` (one of :data:`VECTOR_OPTIONS`), three numbers X Y Z."""
    if option not in VECTOR_OPTIONS:
        raise ValueError(f"{option} is not one of {VECTOR_OPTIONS}")
    parser.add_argument(option, type=float, nargs=3, metavar=("X", "Y", "Z"), help=help, **kwargs)


def add_precision_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--precision", choices=_PRECISIONS, default="auto",
                        help="dtype of the network's per-view matrix products (default auto: bfloat16 on "
                             "CPUs with native bfloat16 dot products, else float32)")


def add_method_flags(parser: argparse.ArgumentParser, choices: tuple[str, ...] = ("neural", "hpr", "gt")) -> None:
    """Adds ``--method`` and what the methods take (see :func:`visibility_method`)."""
    parser.add_argument("--method", choices=choices, default="neural",
                        help="visibility method: the neural network (default), Open3D's HPR, or "
                             "ground truth ray-cast against --mesh")
    parser.add_argument("--model", default=None,
                        help="shipped model name or .safetensors checkpoint (default: the shipped default)")
    parser.add_argument("--device", default=None, help="torch device, e.g. cuda (default: cpu)")
    add_precision_flag(parser)
    if "hpr" in choices:
        parser.add_argument("--hpr-k", type=float, default=2.0,
                            help="HPR radius = bbox diagonal * 10**K (default 2)")
    if "gt" in choices:
        parser.add_argument("--mesh", default=None,
                            help="mesh the points were sampled from (for --method gt)")


def visibility_method(args: argparse.Namespace):
    """The visibility method the flags of :func:`add_method_flags` name."""
    if args.method == "neural":
        from ..neural import NeuralVisibility

        return NeuralVisibility.pretrained(args.model or "default", device=args.device, precision=args.precision)
    if args.method == "hpr":
        from ..baselines import hpr_method

        return hpr_method(args.hpr_k)
    import open3d as o3d

    from ..methods import ground_truth_method

    if args.mesh is None:
        raise ValueError("--method gt needs --mesh, the mesh the points lie on")
    mesh = o3d.io.read_triangle_mesh(args.mesh)
    if len(mesh.triangles) == 0:
        raise ValueError(f"no triangles could be read from {args.mesh}")
    return ground_truth_method(mesh)


OUTPUTS = {
    "point cloud": (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts"),
    "mesh": (".ply", ".obj", ".off", ".stl", ".gltf", ".glb"),
    "image": (".png", ".jpg", ".jpeg"),
    "array": (".npy",),
}
"""The extensions Open3D (numpy for an array) writes each kind of output to."""


def check_output(path: str | Path | None, option: str, kind: str | None = None,
                 suffixes: tuple[str, ...] | None = None) -> None:
    """Refuses, before any work, an output file that could not be written: an extension that
    does not name a format of its kind, a folder that does not exist or takes no files, a folder
    in the file's place (None: no output asked for).

    Args:
        path: the file the command will write.
        option: the option that names it, for the message.
        kind: a key of :data:`OUTPUTS`, or what ``suffixes`` are extensions of; None: any extension.
        suffixes: the extensions allowed, instead of ``kind``'s in :data:`OUTPUTS`.

    Raises:
        ValueError: an extension of no such format.
        FileNotFoundError, PermissionError, IsADirectoryError: a folder that cannot take the file.
    """
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{option} {path} is a folder; give a file name")
    allowed = suffixes if suffixes is not None else OUTPUTS[kind] if kind is not None else None
    if allowed is not None and path.suffix.lower() not in allowed:
        raise ValueError(f"{option} {path}: the extension {path.suffix or '(none)'} names no {kind or 'known'} "
                         f"format; use {', '.join(allowed)}")
    folder = path.parent
    if not folder.is_dir():
        raise FileNotFoundError(f"{option} {path}: no folder {folder} to write it in; create it first")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"{option} {path}: the folder {folder} is not writable")


def check_folder(path: str | Path, option: str) -> None:
    """Refuses, before any work, an output folder that could not be made or written to: a file in
    its place, or a nearest existing folder above it that is not writable.

    Raises:
        NotADirectoryError, PermissionError: as described.
    """
    path = Path(path).absolute()
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        raise NotADirectoryError(f"{option} {path}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"{option} {path}: the folder {existing} is not writable")


def write_image(path: str, image) -> None:
    import open3d as o3d

    if not o3d.io.write_image(path, image):
        raise RuntimeError(f"could not write {path} (use .png or .jpg)")


def stages(total: int, desc: str):
    """A progress bar over a command's ``total`` stages, erased when it closes (also on an error)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", leave=False)


def positive_ints(text: str) -> list[int]:
    """Comma-separated positive integers."""
    try:
        values = [int(float(t)) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def floats(text: str) -> list[float]:
    """Comma-separated numbers."""
    try:
        return [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
