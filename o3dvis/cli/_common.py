"""What the subcommands share: argument types and flags, the visibility method, writing images,
progress (clouds are read by :func:`o3dvis.io.read_point_cloud`).

Nothing heavy is imported here at module level: ``o3dvis --help`` builds every parser.
"""

from __future__ import annotations

import argparse

__all__ = ["VECTOR_OPTIONS", "add_vector", "add_precision_flag", "add_method_flags", "split_vectors",
           "visibility_method", "write_image", "stages", "positive_ints", "floats"]

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
