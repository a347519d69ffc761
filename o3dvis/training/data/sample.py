"""A labelled sample, its file, and points drawn on a mesh's surface.

The lowest layer of the labelled data: :mod:`.prepare` labels meshes and
procedural scenes into :class:`Sample` files, :mod:`.scenes` samples their
surfaces, the data set, the evaluation and the fits read the files back. It
imports neither Open3D nor the rest of the package, so that training from
prepared files runs where Open3D is not installed.
"""

from __future__ import annotations

import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["Sample", "sample_surface", "save_sample", "load_sample", "list_samples"]


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
    """``count`` points uniform on the surface (by area) and their triangle normals.

    Raises:
        ValueError: the triangles have no area (or a non-finite one).
    """
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


def save_sample(sample: Sample, out: str | Path) -> None:
    """Writes ``sample`` to ``out`` (a compressed ``.npz``, visibility bit-packed) atomically:
    an interrupted run leaves no partial file under that name."""
    out = Path(out)
    tmp = out.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, points=sample.points, normals=sample.normals, cameras=sample.cameras,
                        visibility=np.packbits(sample.visibility, axis=1),
                        num_points=np.int64(len(sample.points)))
    os.replace(tmp, out)


def load_sample(path: str | Path) -> Sample:
    """Reads a file written by :func:`save_sample`.

    Raises:
        ValueError: the file is broken or not a sample.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as f:
            n = int(f["num_points"])
            vis = np.unpackbits(f["visibility"], axis=1, count=n).astype(bool)
            return Sample(f["points"], f["normals"], f["cameras"], vis, path.stem)
    except (OSError, KeyError, ValueError, zlib.error, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: not a readable o3dvis sample ({e})") from e


def list_samples(data_dir: str | Path, limit: int | None = None) -> list[Path]:
    """The ``.npz`` samples below ``data_dir``, sorted, at most ``limit``.

    Raises:
        FileNotFoundError: ``data_dir`` is not a folder.
        ValueError: it holds no sample.
    """
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise FileNotFoundError(f"{data_dir} is not a folder")
    files = sorted(p for p in data_dir.rglob("*.npz") if not p.name.endswith(".tmp.npz"))
    if not files:
        raise ValueError(f"no .npz samples below {data_dir} (make them with `o3dvis prepare`)")
    return files[:limit] if limit else files
