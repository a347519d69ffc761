"""Shared parts of bench_normals.py and bench_reconstruction.py.

Meshes and their surface samples, the visibility method named on the command
line, and Open3D's normal estimation + orientation run in a subprocess with a
time limit (it can take minutes on one mesh or abort in qhull), so a slow or
crashing mesh is reported instead of stopping the run.

Run as a script only as that subprocess:
``python3 mesh_bench.py open3d-normals POINTS.npy OUT.npz KNN``.
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import open3d as o3d  # noqa: E402

from o3dvis.training.data.prepare import MESH_SUFFIXES  # noqa: E402
from o3dvis.training.data.sample import sample_surface  # noqa: E402

DEFAULT_MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes" / "val"  # ../shared beside the project


def data_parser(doc: str, limit: int, noise: str) -> argparse.ArgumentParser:
    """The parser of a benchmark that reads prepared (labelled) data rather than meshes.

    Args:
        doc: the benchmark's docstring (its help text).
        limit, noise: defaults of ``--limit`` and ``--noise``.
    """
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, help="folder of prepared .npz files")
    parser.add_argument("--limit", type=int, default=limit, help=f"files, evenly spread (default {limit})")
    parser.add_argument("--points", default="2048,8192,32768,81920", help="comma-separated cloud sizes")
    parser.add_argument("--noise", default=noise, help=f"comma-separated noise levels (default {noise})")
    parser.add_argument("--views", type=int, default=8, help="viewpoints per file (default 8)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--out", type=Path, help="also write the report to this Markdown file")
    return parser


def data_settings(args: argparse.Namespace):
    """The prepared files of the data flags, and each (points, noise) setting with its clouds.

    Sets the torch threads from ``--threads``. Returns ``(files, settings)``: ``settings`` yields
    ``(points, noise, clouds)``, ``clouds`` an iterator of ``o3dvis.evaluation.evaluate.EvalCloud``
    (subsampled, noised, ``--views`` views), one per file.
    """
    import torch

    from o3dvis.evaluation.evaluate import eval_cloud
    from o3dvis.training.data.sample import list_samples, load_sample

    torch.set_num_threads(args.threads)
    files = list_samples(args.data, args.limit)
    settings = ((n, noise, (eval_cloud(load_sample(path), n, noise, 0, args.views) for path in files))
                for n in (int(p) for p in args.points.split(","))
                for noise in (float(x) for x in args.noise.split(",")))
    return files, settings


def add_common_flags(parser: argparse.ArgumentParser, points: str) -> None:
    """Flags both benchmarks share."""
    parser.add_argument("--meshes", type=Path, default=DEFAULT_MESHES, help=f"mesh folder (default {DEFAULT_MESHES})")
    parser.add_argument("--limit", type=int, default=None,
                        help="this many meshes, spread evenly over the sorted folder (default: all)")
    parser.add_argument("--points", default=points, help=f"comma-separated cloud sizes (default {points})")
    parser.add_argument("--method", choices=("gt", "hpr", "neural"), default="neural",
                        help="visibility method of o3dvis: ground truth ray-cast on the mesh, Open3D HPR, "
                             "or the network (default)")
    parser.add_argument("--checkpoint", default=None, help="network checkpoint for --method neural "
                                                           "(default: the shipped weights)")
    parser.add_argument("--hpr-k", type=float, default=2.0, help="HPR radius = diagonal * 10**K (default 2)")
    parser.add_argument("--views", type=int, default=26, help="cameras for the o3dvis normals (default 26)")
    parser.add_argument("--refine-views", type=int, default=0,
                        help="more cameras for points the first leave uncovered (default 0)")
    parser.add_argument("--knn", type=int, default=30,
                        help="neighbours of Open3D's estimate_normals and orient_normals_consistent_tangent_plane "
                             "(default 30)")
    parser.add_argument("--timeout", type=float, default=120.0,
                        help="seconds Open3D's normals may take per mesh and size (default 120)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    parser.add_argument("--out", type=Path, default=None, help="write the Markdown table here too")


def mesh_subset(folder: Path, limit: int | None) -> list[Path]:
    """The meshes of ``folder``, sorted; ``limit`` of them evenly spread over the list."""
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not paths:
        raise SystemExit(f"no meshes in {folder}")
    if limit is not None and limit < len(paths):
        paths = [paths[i] for i in np.linspace(0, len(paths) - 1, limit).round().astype(int)]
    return paths


def load_mesh(path: Path) -> o3d.geometry.TriangleMesh:
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise ValueError(f"{path.name}: no triangles")
    return mesh


def sample(mesh: o3d.geometry.TriangleMesh, count: int, name: str, seed: int
           ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points uniform on the surface and their face normals, seeded by the mesh name."""
    key = int.from_bytes(hashlib.sha256(f"{seed}:{name}:{count}".encode()).digest()[:8], "little")
    return sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.triangles), count,
                          np.random.default_rng(key))


def visibility_method(args: argparse.Namespace, mesh: o3d.geometry.TriangleMesh):
    """The visibility method ``--method`` names, for clouds sampled on ``mesh``."""
    if args.method == "gt":
        from o3dvis.methods import ground_truth_method

        return ground_truth_method(mesh)
    if args.method == "hpr":
        from o3dvis.baselines import hpr_method

        return hpr_method(args.hpr_k)
    from o3dvis.neural import NeuralVisibility

    return NeuralVisibility.pretrained(args.checkpoint or "default")


def method_label(args: argparse.Namespace) -> str:
    """What ran as o3dvis: the visibility method and the cameras."""
    method = {"gt": "ground-truth visibility (ray cast on the mesh)",
              "hpr": f"Open3D HPR visibility (radius = diagonal x 10^{args.hpr_k:g})",
              "neural": f"neural visibility ({args.checkpoint or 'shipped weights'})"}[args.method]
    return f"{method}, {args.views} views + {args.refine_views} refinement views"


def emit_report(report: str, out) -> int:
    """Prints a benchmark's report and writes it to ``out`` (a Path) when given; returns 0."""
    print("\n" + report)
    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(report + "\n")
    return 0


class Timed:
    """Wraps a visibility method and adds up the seconds spent in it."""

    def __init__(self, method):
        from o3dvis.methods import resolve_method

        self.method, self.seconds = resolve_method(method), 0.0

    takes_indices = True

    def __call__(self, points, cameras, indices=None):
        start = time.perf_counter()
        try:
            return self.method(points, cameras, indices)
        finally:
            self.seconds += time.perf_counter() - start


def open3d_normals(points: np.ndarray, knn: int, timeout: float) -> tuple[np.ndarray | None, float, str]:
    """Open3D ``estimate_normals(KNN(knn))`` + ``orient_normals_consistent_tangent_plane(knn)``.

    Runs in a fresh Python process so that a time limit can stop it and a
    crash cannot take the benchmark down.

    Returns:
        ``(normals or None, seconds inside Open3D, status)``: status is ``ok``,
        ``timeout``, or the error the process ended with.
    """
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "points.npy", Path(tmp) / "normals.npz"
        np.save(src, points)
        cmd = [sys.executable, str(Path(__file__).resolve()), "open3d-normals", str(src), str(dst), str(knn)]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return None, timeout, "timeout"
        if proc.returncode != 0 or not dst.exists():
            lines = (proc.stderr or "").strip().splitlines()
            reason = lines[-1] if lines else f"exit code {proc.returncode}"
            return None, float("nan"), f"error: {reason[:80]}"
        with np.load(dst) as f:
            return f["normals"], float(f["seconds"]), "ok"


def _open3d_normals_worker(src: str, dst: str, knn: str) -> None:
    points = np.load(src)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    start = time.perf_counter()
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(int(knn)))
    pcd.orient_normals_consistent_tangent_plane(int(knn))
    seconds = time.perf_counter() - start
    np.savez(dst, normals=np.asarray(pcd.normals), seconds=seconds)


def command_line() -> str:
    """The command that produced a report, for its first line."""
    return "Command: `python3 " + " ".join(sys.argv) + "`"


def markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) != 5 or sys.argv[1] != "open3d-normals":
        raise SystemExit("usage: mesh_bench.py open3d-normals POINTS.npy OUT.npz KNN")
    _open3d_normals_worker(*sys.argv[2:])
