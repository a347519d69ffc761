"""Clouds that carry their own normals: oriented, from ``estimate_normals()``, flipped at random, facing a sensor.

For each mesh, cloud size and noise level, points are sampled uniformly on the surface with their
face normals, turned to the side that ray-cast cameras see (oriented normals, as a mesh's outward
normals), and moved by the project's noise (each point up to ``noise`` x the diagonal). The cloud
then carries one of four kinds of normals and is answered for 4 random cameras at the
bounding-box diagonal, scored against ray casting (accuracy, %):

* as given: ``encode(pcd, normals=True)``, the normals model reading the normals as they are;
* default: ``encode(pcd)``, which estimates normals anew where the cloud's look unoriented;
* without normals: ``encode(pcd, normals=False)``, the same on every row.

The ``checked`` column is the share of clouds whose normals the default ignored, with a warning.

    nice -n 10 python3 benchmarks/bench_cloud_normals.py --points 2048,8192,32768,81920 --noise 0,0.01 \\
        --out benchmarks/results/cloud_normals.md
"""

from __future__ import annotations

import argparse
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

from mesh_bench import DEFAULT_MESHES, command_line, emit_report, load_mesh, markdown, mesh_subset, sample
from o3dvis.groundtruth import orient_normals, sample_viewpoints, visibility_from_mesh
from o3dvis.neural import NeuralVisibility
from o3dvis.training.data.perturb import add_noise

KINDS = ("oriented", "estimate_normals()", "random signs", "facing a sensor")
REFERENCE_VIEWS = 32


def normals_of(kind: str, points: np.ndarray, oriented: np.ndarray, sensor: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
    """The normals a cloud of ``kind`` carries."""
    if kind == "oriented":
        return oriented
    if kind == "estimate_normals()":
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pcd.estimate_normals()
        return np.asarray(pcd.normals)
    if kind == "random signs":
        return oriented * rng.choice([-1.0, 1.0], size=(len(points), 1))
    return np.where(np.einsum("ij,ij->i", sensor - points, oriented)[:, None] < 0, -oriented, oriented)


def score(vis: NeuralVisibility, mesh_path: Path, count: int, noise: float, seed: int) -> dict:
    """Accuracies (and whether the default re-estimated) of one mesh's cloud for every kind."""
    mesh = load_mesh(mesh_path)
    points, normals = sample(mesh, count, mesh_path.name, seed)
    rng = np.random.default_rng(seed)
    lo, hi = points.min(axis=0), points.max(axis=0)
    center, diagonal = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    reference = sample_viewpoints(REFERENCE_VIEWS, center, diagonal, rng)
    oriented = orient_normals(points, normals, reference, visibility_from_mesh(mesh, points, reference))
    cameras = sample_viewpoints(4, center, diagonal, rng)
    truth = visibility_from_mesh(mesh, points, cameras)
    noisy = add_noise(points, noise, diagonal, rng)
    sensor = center + diagonal * np.array([0.3, 0.4, 0.87])
    row = {"without normals": float((vis.encode(noisy, normals=False).query(cameras) == truth).mean())}
    for kind in KINDS:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(noisy))
        pcd.normals = o3d.utility.Vector3dVector(normals_of(kind, noisy, oriented, sensor, rng))
        row[kind, "as given"] = float((vis.encode(pcd, normals=True).query(cameras) == truth).mean())
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            field = vis.encode(pcd)
        row[kind, "default"] = float((field.query(cameras) == truth).mean())
        row[kind, "checked"] = float(any("unoriented" in str(w.message) for w in caught))
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", type=Path, default=DEFAULT_MESHES, help=f"mesh folder (default {DEFAULT_MESHES})")
    parser.add_argument("--limit", type=int, default=None, help="this many meshes, evenly spread (default: all)")
    parser.add_argument("--points", default="2048,8192,32768,81920", help="comma-separated cloud sizes")
    parser.add_argument("--noise", default="0,0.01", help="comma-separated noise levels (fractions of the diagonal)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    parser.add_argument("--out", type=Path, default=None, help="write the Markdown report here too")
    args = parser.parse_args()
    torch.set_num_threads(1)
    vis = NeuralVisibility.pretrained()
    paths = mesh_subset(args.meshes, args.limit)
    sizes = [int(p) for p in args.points.split(",")]
    header = ["normals", "noise", *[f"{n // 1024} k" if n >= 1024 else str(n) for n in sizes]]
    table: dict = defaultdict(dict)
    for noise in (float(x) for x in args.noise.split(",")):
        for count in sizes:
            rows = [score(vis, path, count, noise, args.seed) for path in paths]
            for key in rows[0]:
                table[key, noise][count] = 100 * float(np.mean([r[key] for r in rows]))
    lines = []
    for noise in sorted({noise for _, noise in table}):
        lines.append(["without normals", f"{noise:g}", *[f"{table['without normals', noise][n]:.1f}" for n in sizes]])
        for kind in KINDS:
            for how in ("as given", "default", "checked"):
                values = table[(kind, how), noise]
                cells = [f"{values[n]:.0f} %" if how == "checked" else f"{values[n]:.1f}" for n in sizes]
                lines.append([f"{kind}, {how}", f"{noise:g}", *cells])
    report = "\n".join([command_line(), "", f"{len(paths)} meshes of {args.meshes.name}; accuracy (%) for 4 "
                        "cameras; `checked`: clouds whose normals the default ignored.", "",
                        markdown(header, lines)])
    return emit_report(report, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
