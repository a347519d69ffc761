"""Poisson reconstruction on o3dvis normals against the same pipeline on Open3D's normals.

For each mesh and cloud size, points are sampled uniformly on the surface and
``TriangleMesh.create_from_point_cloud_poisson(depth)`` runs twice: on
``estimate_normals_neural`` normals (``reconstruct_poisson``; with ``--covisible-knn K``
fitted to K co-visible neighbours instead of triangulated) and on Open3D's
``estimate_normals(KNN(k))`` + ``orient_normals_consistent_tangent_plane(k)``
(in a subprocess with a time limit). Both meshes are untrimmed. Against the
source mesh (30 000 points sampled on each surface):

* Chamfer distance = mean nearest-neighbour distance both ways, summed, in % of
  the source's bounding-box diagonal (lower is better);
* F-score at 1 % of the diagonal (higher is better).

    nice -n 10 python3 benchmarks/bench_reconstruction.py --method gt --limit 10 \\
        --out benchmarks/results/poisson_gt.md
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from mesh_bench import (Timed, add_common_flags, command_line, emit_report, load_mesh, markdown,
                        mesh_subset, method_label, open3d_normals, sample, visibility_method)
from o3dvis.apps.reconstruction import reconstruct_poisson

EVAL_POINTS = 30_000
F_THRESHOLD = 0.01


def surface_distance(recon: o3d.geometry.TriangleMesh, source: np.ndarray, diagonal: float,
                     seed: int) -> tuple[float, float]:
    """Chamfer distance (% of the diagonal) and F-score (%) of ``recon`` against source samples."""
    if len(recon.triangles) == 0:
        return float("nan"), 0.0
    ours, _ = sample(recon, EVAL_POINTS, "reconstruction", seed)
    to_source = cKDTree(source).query(ours)[0] / diagonal
    to_recon = cKDTree(ours).query(source)[0] / diagonal
    precision, recall = (to_source < F_THRESHOLD).mean(), (to_recon < F_THRESHOLD).mean()
    f_score = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return 100 * float(to_source.mean() + to_recon.mean()), 100 * float(f_score)


def poisson(points: np.ndarray, normals: np.ndarray, depth: int) -> o3d.geometry.TriangleMesh:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    return o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)[0]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_flags(parser, "20000")
    parser.add_argument("--depth", type=int, default=8, help="Poisson octree depth (default 8)")
    parser.add_argument("--covisible-knn", type=int, default=None, metavar="K",
                        help="o3dvis normals fitted to K co-visible neighbours (default: triangulated)")
    args = parser.parse_args()
    search = None if args.covisible_knn is None else o3d.geometry.KDTreeSearchParamKNN(args.covisible_knn)
    sizes = [int(s) for s in args.points.split(",")]
    shared_method = None if args.method == "gt" else visibility_method(args, None)
    rows, records = [], []
    for path in mesh_subset(args.meshes, args.limit):
        mesh = load_mesh(path)
        method = Timed(shared_method or visibility_method(args, mesh))
        vertices = np.asarray(mesh.vertices)
        diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
        source, _ = sample(mesh, EVAL_POINTS, path.name + ":eval", args.seed)
        for n in sizes:
            points, _ = sample(mesh, n, path.name, args.seed)
            record = {"mesh": path.stem, "n": n}
            start, method.seconds = time.perf_counter(), 0.0
            try:
                ours = reconstruct_poisson(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)),
                                           args.depth, method, num_views=args.views,
                                           refine_views=args.refine_views, search_param=search)[0]
                record["o3dvis"] = (*surface_distance(ours, source, diagonal, args.seed),
                                    time.perf_counter() - start, "ok")
            except Exception as e:  # reported, never stops the run
                record["o3dvis"] = (float("nan"), float("nan"), float("nan"),
                                    f"error: {type(e).__name__}: {str(e)[:60]}")
            normals, seconds, status = open3d_normals(points, args.knn, args.timeout)
            if status == "ok":
                start = time.perf_counter()
                theirs = poisson(points, normals, args.depth)
                record["Open3D"] = (*surface_distance(theirs, source, diagonal, args.seed),
                                    seconds + time.perf_counter() - start, "ok")
            else:
                record["Open3D"] = (float("nan"), float("nan"), seconds, status)
            records.append(record)
            rows.append(_row(record))
            print(" | ".join(rows[-1]), flush=True)
    return emit_report(_report(records, rows, sizes, args), args.out)


def _cells(result: tuple) -> list[str]:
    chamfer, f_score, seconds, status = result
    if status != "ok":
        return [status, "", ""]
    return [f"{chamfer:.3f}", f"{f_score:.1f}", f"{seconds:.2f}"]


def _row(record: dict) -> list[str]:
    return [record["mesh"], str(record["n"])] + _cells(record["Open3D"]) + _cells(record["o3dvis"])


def _report(records: list[dict], rows: list[list[str]], sizes: list[int], args) -> str:
    header = ["mesh", "points", "Open3D normals: Chamfer %", "F-score %", "s",
              "o3dvis normals: Chamfer %", "F-score %", "s"]
    summary = []
    for n in sizes:
        for name in ("Open3D", "o3dvis"):
            ok = [r[name] for r in records if r["n"] == n and r[name][3] == "ok"]
            total = sum(r["n"] == n for r in records)
            if ok:
                chamfer, f_score, seconds = (np.array([o[i] for o in ok]) for i in range(3))
                summary.append([str(n), name, f"{len(ok)}/{total}", f"{np.nanmean(chamfer):.3f}",
                                f"{np.nanmedian(chamfer):.3f}", f"{f_score.mean():.1f}",
                                f"{np.median(seconds):.2f}"])
            else:
                summary.append([str(n), name, f"0/{total}", "", "", "", ""])
        both = [(r["Open3D"], r["o3dvis"]) for r in records if r["n"] == n
                and r["Open3D"][3] == "ok" and r["o3dvis"][3] == "ok"]
        if both:
            better = sum(b[1] > a[1] for a, b in both)
            summary.append([str(n), "o3dvis F-score higher", f"{better}/{len(both)} meshes",
                            "", "", "", ""])
    return "\n".join([
        command_line(), "",
        f"Poisson benchmark (depth {args.depth}, untrimmed): o3dvis normals with {method_label(args)}"
        f"{'' if args.covisible_knn is None else f', fitted to {args.covisible_knn} co-visible neighbours'}; "
        f"Open3D normals with k = {args.knn}, limit {args.timeout:g} s per run. "
        f"Chamfer in % of the bbox diagonal, F-score at {100 * F_THRESHOLD:g} % of it; "
        "times include normals and Poisson.", "",
        markdown(header, rows), "", "Summary:", "",
        markdown(["points", "normals", "ok", "mean Chamfer %", "median Chamfer %", "mean F-score %",
                  "median s"], summary)])


if __name__ == "__main__":
    raise SystemExit(main())
