"""Mesh folder -> labelled samples: points, oriented normals, viewpoints, visibility bits.

One compressed ``.npz`` per mesh (or per procedural scene and sampling, see
:func:`prepare_scenes`), written atomically, so an interrupted run resumes by
skipping finished files. Work is spread over processes; a broken mesh is
reported and skipped.
"""

from __future__ import annotations

import hashlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from .sample import Sample, sample_surface, save_sample

__all__ = ["MESH_SUFFIXES", "label_mesh", "prepare", "prepare_scenes", "label_scene"]

MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl")


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

    from ...groundtruth import orient_normals, sample_viewpoints, visibility_from_mesh

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
    normals = orient_normals(points, normals, cameras, visibility)
    return Sample(points.astype(np.float32), normals.astype(np.float32),
                  cameras.astype(np.float32), visibility, path.stem)


def _job(args: tuple) -> tuple[str, str | None]:
    path, out, num_points, num_views, seed = args
    try:
        save_sample(label_mesh(path, num_points, num_views, seed), Path(out))
        return str(path), None
    except Exception as e:  # a broken mesh must not stop the run
        return str(path), f"{type(e).__name__}: {e}"


def _mesh_files(mesh_dir: str | Path) -> list[Path]:
    mesh_dir = Path(mesh_dir)
    if not mesh_dir.is_dir():
        raise ValueError(f"{mesh_dir} is not a folder")
    return sorted(p for p in mesh_dir.rglob("*") if p.suffix.lower() in MESH_SUFFIXES)


def _run(job, jobs: list[tuple], skipped: int, workers: int, progress: bool, unit: str) -> dict:
    """Runs ``job`` over ``jobs`` in processes; returns counts ``done``, ``skipped``, ``failed`` (list)."""
    from tqdm import tqdm

    failed = []
    with ProcessPoolExecutor(max(1, workers)) as pool:
        for path, err in tqdm(pool.map(job, jobs), total=len(jobs), disable=not progress,
                              desc="prepare", unit=unit):
            if err:
                failed.append((path, err))
                tqdm.write(f"skipped {path}: {err}")
    return {"done": len(jobs) - len(failed), "skipped": skipped, "failed": failed}


def prepare(mesh_dir: str | Path, out_dir: str | Path, num_points: int = 100_000,
            num_views: int = 16, workers: int = 1, seed: int = 0, progress: bool = True) -> dict:
    """Labels every mesh below ``mesh_dir`` into ``out_dir`` (resumable, parallel).

    Output names keep the subfolder as a prefix (``sub__name.npz``) so that
    categories survive. Returns counts: ``done``, ``skipped``, ``failed`` (list).
    """
    mesh_dir, out_dir = Path(mesh_dir), Path(out_dir)
    meshes = _mesh_files(mesh_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs, skipped = [], 0
    for p in meshes:
        rel = p.relative_to(mesh_dir).with_suffix("")
        out = out_dir / ("__".join(rel.parts) + ".npz")
        if out.exists():
            skipped += 1
        else:
            jobs.append((str(p), str(out), num_points, num_views, seed))
    return _run(_job, jobs, skipped, workers, progress, "mesh")


def label_scene(index: int, meshes: list[str], num_points: int = 100_000, num_views: int = 16,
                seed: int = 0, kinds: tuple[str, ...] = ("rooms", "street"),
                samplings: tuple[str, ...] = ("uniform", "lidar"),
                max_range: float | None = None) -> list[Sample]:
    """Procedural scene ``index`` (see :mod:`o3dvis.training.data.scenes`) labelled once per sampling.

    The scene's kind is ``kinds[index % len(kinds)]``; its geometry depends on
    ``(seed, index)`` only, each sampling's points and cameras on ``(seed,
    index, sampling)``. A quarter of the ``num_views`` cameras (rounded down)
    stand outside, the rest inside. Samples are named ``{kind}-{sampling}__{index:05d}``,
    so that the evaluation's categories are kind and sampling.

    Args:
        index: scene number.
        meshes: mesh files to draw furniture and objects from (may be empty).
        num_points, num_views: points and cameras per sample.
        seed: base seed.
        kinds, samplings: see ``o3dvis.training.data.scenes.KINDS`` and ``SAMPLINGS``.
        max_range: LiDAR-like range limit in metres (default: none).
    """
    from .scenes import SAMPLINGS, random_scene, scene_sample  # Open3D: loaded when scenes are labelled

    unknown = sorted(set(samplings) - set(SAMPLINGS))
    if unknown or not samplings:
        raise ValueError(f"unknown samplings {unknown}; choose from {', '.join(SAMPLINGS)}")
    if not kinds:
        raise ValueError("no scene kinds given")
    kind = kinds[index % len(kinds)]
    scene = random_scene(kind, np.random.default_rng([seed, index]), meshes)
    outside = num_views // 4
    return [scene_sample(scene, sampling, num_points, num_views - outside, outside,
                         np.random.default_rng([seed, index, 1 + SAMPLINGS.index(sampling)]),
                         max_range=max_range, name=f"{kind}-{sampling}__{index:05d}")
            for sampling in samplings]


def _scene_job(args: tuple) -> tuple[str, str | None]:
    index, out_dir, meshes, num_points, num_views, seed, kinds, samplings, max_range = args
    try:
        for sample in label_scene(index, meshes, num_points, num_views, seed, kinds, samplings, max_range):
            save_sample(sample, Path(out_dir) / f"{sample.name}.npz")
        return f"scene {index}", None
    except Exception as e:  # one failed scene must not stop the run
        return f"scene {index}", f"{type(e).__name__}: {e}"


def prepare_scenes(out_dir: str | Path, count: int, mesh_dir: str | Path | None = None,
                   num_points: int = 100_000, num_views: int = 16, workers: int = 1, seed: int = 0,
                   kinds: tuple[str, ...] = ("rooms", "street"),
                   samplings: tuple[str, ...] = ("uniform", "lidar"),
                   max_range: float | None = None, progress: bool = True) -> dict:
    """Writes ``count`` labelled procedural scenes, each once per sampling (resumable, parallel).

    See :func:`label_scene` for what scene ``i`` is. A scene is skipped when
    all its files exist.

    Args:
        out_dir: folder for the ``.npz`` files (created).
        count: number of scenes.
        mesh_dir: folder of meshes for furniture and objects (None: procedural shapes only).
        num_points, num_views, workers, seed, kinds, samplings, max_range: as in :func:`label_scene`.
        progress: show a progress bar.

    Returns:
        Counts of scenes: ``done``, ``skipped``, ``failed`` (list of (scene, error)).
    """
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    meshes = [str(p) for p in _mesh_files(mesh_dir)] if mesh_dir is not None else []
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    jobs, skipped = [], 0
    for index in range(count):
        names = [f"{kinds[index % len(kinds)]}-{s}__{index:05d}.npz" for s in samplings] if kinds else []
        if names and all((out_dir / n).exists() for n in names):
            skipped += 1
        else:
            jobs.append((index, str(out_dir), meshes, num_points, num_views, seed, tuple(kinds),
                         tuple(samplings), max_range))
    return _run(_scene_job, jobs, skipped, workers, progress, "scene")
