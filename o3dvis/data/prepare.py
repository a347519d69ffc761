"""Mesh folder -> labelled samples: points, oriented normals, viewpoints, visibility bits.

One compressed ``.npz`` per mesh, written atomically, so an interrupted run
resumes by skipping finished files. Work is spread over processes; a broken
mesh is reported and skipped.
"""

from __future__ import annotations

import hashlib
import os
import zipfile
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["MESH_SUFFIXES", "sample_surface", "label_mesh", "prepare", "load_sample", "Sample"]

MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl")


@dataclass
class Sample:
    """A labelled point cloud: ``visibility[v, i]`` tells whether ``cameras[v]`` sees ``points[i]``."""

    points: np.ndarray
    normals: np.ndarray
    cameras: np.ndarray
    visibility: np.ndarray
    name: str


def sample_surface(vertices: np.ndarray, triangles: np.ndarray, count: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points uniform on the surface (by area) and their triangle normals."""
    tri = vertices[triangles]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    if not np.isfinite(area).all() or area.sum() <= 0:
        raise ValueError("mesh has no surface area")
    face = rng.choice(len(triangles), size=count, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    points = np.einsum("ij,ijk->ik", bary, tri[face])
    normals = cross[face] / np.maximum(area[face], 1e-300)[:, None]
    return points, normals


def _seed(name: str, seed: int) -> int:
    return int.from_bytes(hashlib.sha256(f"{seed}:{name}".encode()).digest()[:8], "little")


def label_mesh(path: str | Path, num_points: int = 100_000, num_views: int = 16,
               seed: int = 0) -> Sample:
    """Samples a mesh file and labels its points from random viewpoints (the paper's protocol).

    Viewpoints are uniform on the sphere of radius = bounding-box diagonal
    around the bounding-box centre. Normals are flipped towards the cameras
    that see them, so they come out oriented.
    """
    import open3d as o3d

    from .groundtruth import sample_viewpoints, visibility_from_mesh

    path = Path(path)
    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if len(triangles) == 0:
        raise ValueError(f"{path.name}: no triangles could be read")
    rng = np.random.default_rng(_seed(path.name, seed))
    points, normals = sample_surface(vertices, triangles, num_points, rng)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    cameras = sample_viewpoints(num_views, (lo + hi) / 2, float(np.linalg.norm(hi - lo)), rng)
    visibility = visibility_from_mesh(mesh, points, cameras)
    facing = np.einsum("vnk,nk->vn", cameras[:, None, :] - points[None], normals)
    flip = (np.where(visibility, np.sign(facing), 0).sum(axis=0)) < 0
    normals[flip] *= -1
    return Sample(points.astype(np.float32), normals.astype(np.float32),
                  cameras.astype(np.float32), visibility, path.stem)


def _save(sample: Sample, out: Path) -> None:
    tmp = out.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, points=sample.points, normals=sample.normals, cameras=sample.cameras,
                        visibility=np.packbits(sample.visibility, axis=1),
                        num_points=np.int64(len(sample.points)))
    os.replace(tmp, out)


def load_sample(path: str | Path) -> Sample:
    """Reads a file written by :func:`prepare`; raises ``ValueError`` if it is broken."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as f:
            n = int(f["num_points"])
            vis = np.unpackbits(f["visibility"], axis=1, count=n).astype(bool)
            return Sample(f["points"], f["normals"], f["cameras"], vis, path.stem)
    except (OSError, KeyError, ValueError, zlib.error, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: not a readable o3dvis sample ({e})") from e


def _job(args: tuple) -> tuple[str, str | None]:
    path, out, num_points, num_views, seed = args
    try:
        _save(label_mesh(path, num_points, num_views, seed), Path(out))
        return str(path), None
    except Exception as e:  # a broken mesh must not stop the run
        return str(path), f"{type(e).__name__}: {e}"


def prepare(mesh_dir: str | Path, out_dir: str | Path, num_points: int = 100_000,
            num_views: int = 16, workers: int = 1, seed: int = 0, progress: bool = True) -> dict:
    """Labels every mesh below ``mesh_dir`` into ``out_dir`` (resumable, parallel).

    Output names keep the subfolder as a prefix (``sub__name.npz``) so that
    categories survive. Returns counts: ``done``, ``skipped``, ``failed`` (list).
    """
    from tqdm import tqdm

    mesh_dir, out_dir = Path(mesh_dir), Path(out_dir)
    if not mesh_dir.is_dir():
        raise ValueError(f"{mesh_dir} is not a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    meshes = sorted(p for p in mesh_dir.rglob("*") if p.suffix.lower() in MESH_SUFFIXES)
    jobs, skipped = [], 0
    for p in meshes:
        rel = p.relative_to(mesh_dir).with_suffix("")
        out = out_dir / ("__".join(rel.parts) + ".npz")
        if out.exists():
            skipped += 1
        else:
            jobs.append((str(p), str(out), num_points, num_views, seed))
    failed = []
    with ProcessPoolExecutor(max(1, workers)) as pool:
        for path, err in tqdm(pool.map(_job, jobs), total=len(jobs), disable=not progress,
                              desc="prepare", unit="mesh"):
            if err:
                failed.append((path, err))
                tqdm.write(f"skipped {path}: {err}")
    return {"done": len(jobs) - len(failed), "skipped": skipped, "failed": failed}
