"""Oriented normals: o3dvis against Open3D's estimate_normals + orient_normals_consistent_tangent_plane.

For each mesh and cloud size, points are sampled uniformly on the surface with
their face normals, and four pipelines estimate oriented normals:

* ``Open3D``: ``estimate_normals(KNN(k))`` + ``orient_normals_consistent_tangent_plane(k)``
  (in a subprocess with a time limit);
* ``o3dvis``: ``estimate_normals_neural`` (triangles of the surface seen from
  ``--views`` cameras, oriented towards them);
* ``o3dvis KNN``: ``estimate_normals_neural(search_param=KNN(k))``, planes fitted to
  the ``--covisible-knn`` nearest neighbours weighted by co-visibility, no triangulation;
* ``PCA + o3dvis``: Open3D's ``estimate_normals(KNN(k))`` oriented by ``orient_normals_neural``.

Scores: *oriented* = share of points whose normal points to the same side as
the reference; *angle* = mean unsigned angle to the true normal (degrees).
The reference side is the outward normal on closed meshes (every edge shared
by two triangles; winding made consistent, sign from the signed volume, which
must agree on every connected part: a part inside out, as in one val mug,
would otherwise count the side every camera sees as wrong).
Elsewhere mesh winding is arbitrary, so the reference is the side that
ray-cast visibility from 100 random cameras sees: points seen from both sides
(open sheets) or from no camera are not scored for orientation (the table
says which share is scored).

    nice -n 10 python3 benchmarks/bench_normals.py --method gt --limit 10 --points 20000,100000 \\
        --out benchmarks/results/normals_gt.md
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import open3d as o3d

from mesh_bench import (Timed, add_common_flags, command_line, emit_report, load_mesh, markdown,
                        mesh_subset, method_label, open3d_normals, sample, visibility_method)
from o3dvis.apps.normals import estimate_normals_neural, orient_normals_neural
from o3dvis.groundtruth import sample_viewpoints, visibility_from_mesh

PIPELINES = ("Open3D", "o3dvis", "o3dvis KNN", "PCA + o3dvis")
REFERENCE_VIEWS = 100


def outward_mesh(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh | None:
    """A copy wound consistently with normals pointing out, or None where "out" is not defined.

    Closed means every edge has exactly two triangles; self-intersections are allowed.
    Each connected part is wound on its own, so a mesh of several parts has an
    outside only when one winding gives every part a positive volume; otherwise
    (a part inside out, or a cavity modelled as a separate shell) None.
    """
    if not (mesh.is_edge_manifold(allow_boundary_edges=False) and mesh.is_orientable()):
        return None
    out = o3d.geometry.TriangleMesh(mesh)
    if not out.orient_triangles():
        return None
    v, t = np.asarray(out.vertices), np.asarray(out.triangles)
    volume = np.einsum("ij,ij->i", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]]))
    part_volume = np.bincount(np.asarray(out.cluster_connected_triangles()[0]), volume)
    if (part_volume > 0).all():
        return out
    if (part_volume < 0).all():
        out.triangles = o3d.utility.Vector3iVector(t[:, [0, 2, 1]])
        return out
    return None


def visibility_reference(mesh, points, normals) -> tuple[np.ndarray, np.ndarray]:
    """Normals flipped to the side 100 random cameras see, and which points that decides.

    The cameras are random (seeded), not the Fibonacci lattices o3dvis uses.
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    cameras = sample_viewpoints(REFERENCE_VIEWS, (lo + hi) / 2, float(np.linalg.norm(hi - lo)),
                                np.random.default_rng(REFERENCE_VIEWS))
    visible = visibility_from_mesh(mesh, points, cameras)
    side = np.sign(np.einsum("vnk,nk->vn", cameras[:, None, :] - points[None], normals))
    front, back = (visible & (side > 0)).any(axis=0), (visible & (side < 0)).any(axis=0)
    return np.where(back[:, None] & ~front[:, None], -normals, normals), front ^ back


def scores(estimate: np.ndarray, reference: np.ndarray, scored: np.ndarray) -> tuple[float, float]:
    cos = np.einsum("ij,ij->i", estimate, reference) / np.maximum(np.linalg.norm(estimate, axis=1), 1e-300)
    oriented = 100 * float((cos[scored] > 0).mean())
    angle = float(np.degrees(np.arccos(np.clip(np.abs(cos), 0, 1))).mean())
    return oriented, angle


def run_o3dvis(points, method, args, pca_knn=None, search_param=None
               ) -> tuple[np.ndarray | None, float, float, str]:
    """o3dvis normals (triangulated, or fitted to the co-visible neighbours ``search_param`` finds),
    or PCA normals oriented by o3dvis: normals, seconds, of which visibility, status."""
    timed = Timed(method)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    start = time.perf_counter()
    try:
        if pca_knn is None:
            estimate_normals_neural(pcd, search_param, args.views, timed, refine_views=args.refine_views)
        else:
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(pca_knn))
            orient_normals_neural(pcd, args.views, timed, refine_views=args.refine_views)
    except Exception as e:  # reported in the table, never stops the run
        return None, float("nan"), timed.seconds, f"error: {type(e).__name__}: {str(e)[:60]}"
    return np.asarray(pcd.normals), time.perf_counter() - start, timed.seconds, "ok"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_flags(parser, "20000,100000")
    parser.add_argument("--covisible-knn", type=int, default=16,
                        help="neighbours of the o3dvis KNN pipeline (default 16)")
    args = parser.parse_args()
    sizes = [int(s) for s in args.points.split(",")]
    covisible = o3d.geometry.KDTreeSearchParamKNN(args.covisible_knn)
    shared_method = None if args.method == "gt" else visibility_method(args, None)
    records = []
    for path in mesh_subset(args.meshes, args.limit):
        mesh = load_mesh(path)
        outward = outward_mesh(mesh)
        method = shared_method or visibility_method(args, mesh)
        for n in sizes:
            points, normals = sample(outward or mesh, n, path.name, args.seed)
            if outward is not None:
                reference, scored, kind = normals, np.ones(n, bool), "outward"
            else:
                reference, scored = visibility_reference(mesh, points, normals)
                kind = f"visible side ({100 * scored.mean():.0f} %)"
            row = {"mesh": path.stem, "n": n, "reference": kind}
            est, seconds, status = open3d_normals(points, args.knn, args.timeout)
            result = {"Open3D": (est, seconds, None, status),
                      "o3dvis": run_o3dvis(points, method, args),
                      "o3dvis KNN": run_o3dvis(points, method, args, search_param=covisible),
                      "PCA + o3dvis": run_o3dvis(points, method, args, args.knn)}
            for name, (est, seconds, vis_seconds, status) in result.items():
                ok = status == "ok"
                oriented, angle = scores(est, reference, scored) if ok else (float("nan"), float("nan"))
                row[name] = dict(status=status, oriented=oriented, angle=angle, seconds=seconds,
                                 vis=vis_seconds)
            records.append(row)
            print(" | ".join(_row(row)), flush=True)
    return emit_report(_report(records, sizes, args), args.out)


def _cell(r: dict) -> list[str]:
    if r["status"] != "ok":
        return [r["status"] if r["status"] != "timeout" else "timeout", "", ""]
    time_text = f"{r['seconds']:.2f}" + (f" ({r['vis']:.2f})" if r["vis"] is not None else "")
    return [f"{r['oriented']:.2f}", f"{r['angle']:.2f}", time_text]


def _row(row: dict) -> list[str]:
    return [row["mesh"], str(row["n"]), row["reference"]] + sum((_cell(row[p]) for p in PIPELINES), [])


def _report(records: list[dict], sizes: list[int], args) -> str:
    header = ["mesh", "points", "reference"] + sum(
        ([f"{p} oriented %", f"{p} angle °", f"{p} s" + (" (visibility s)" if p != "Open3D" else "")]
         for p in PIPELINES), [])
    parts = [command_line(), "",
             f"Normals benchmark: {len(records)} runs, o3dvis with {method_label(args)}; "
             f"Open3D with k = {args.knn}, limit {args.timeout:g} s per run.",
             "", markdown(header, [_row(r) for r in records]), "", "Summary:", ""]
    summary = []
    for n in sizes:
        rows = [r for r in records if r["n"] == n]
        finished = [r for r in rows if r["Open3D"]["status"] == "ok"]
        groups = [("", rows)] + ([(f" (the {len(finished)} meshes Open3D finished)", finished)]
                                 if 0 < len(finished) < len(rows) else [])
        for suffix, group in groups:
            summary += [_summary_row(n, p + suffix, [r[p] for r in group]) for p in PIPELINES]
        for p in ("o3dvis", "o3dvis KNN"):
            for suffix, group in groups:
                both = [(r["Open3D"], r[p]) for r in group if r[p]["status"] == "ok"
                        and r["Open3D"]["status"] in ("ok", "timeout")]
                if both:
                    ratio = np.median([a["seconds"] / b["seconds"] for a, b in both])
                    summary.append([str(n), f"Open3D s / {p} s (median per mesh){suffix}"] + [""] * 7
                                   + [f"{ratio:.2f}x", ""])
    parts.append(markdown(["points", "pipeline", "ok", "timeouts", "errors", "mean oriented %",
                           "min oriented %", "meshes ≥ 99 %", "mean angle °", "median s", "total s"],
                          summary))
    parts.append("")
    parts.append("Timeouts count at the limit in the speed ratio. Times are wall-clock on a shared "
                 "machine; '(visibility s)' is the part spent in the visibility method.")
    return "\n".join(parts)


def _summary_row(n: int, label: str, results: list[dict]) -> list[str]:
    ok = [r for r in results if r["status"] == "ok"]
    timeouts = sum(r["status"] == "timeout" for r in results)
    counts = [str(n), label, f"{len(ok)}/{len(results)}", str(timeouts), str(len(results) - len(ok) - timeouts)]
    if not ok:
        return counts + [""] * 6
    oriented = np.array([r["oriented"] for r in ok])
    return counts + [f"{oriented.mean():.2f}", f"{oriented.min():.2f}", f"{(oriented >= 99).sum()}/{len(ok)}",
                     f"{np.mean([r['angle'] for r in ok]):.2f}", f"{np.median([r['seconds'] for r in ok]):.2f}",
                     f"{np.sum([r['seconds'] for r in ok]):.1f}"]


if __name__ == "__main__":
    raise SystemExit(main())
