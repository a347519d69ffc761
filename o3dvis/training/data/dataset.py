"""Training samples: random subsets of labelled clouds with random views, rotation and noise."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ...geometry import diagonal, random_rotation
from ...nn.octree import normalize_points
from .perturb import add_noise
from .sample import Sample, load_sample

__all__ = ["Augmentation", "VisibilityDataset", "Batch", "collate"]


@dataclass
class Augmentation:
    """How a training cloud is drawn from a labelled sample.

    Args:
        min_points, max_points: range of the subsample size (log-uniform).
        views: viewpoints drawn per cloud.
        noise: largest noise level, a fraction of the bounding-box diagonal (see ``add_noise``).
        noise_prob: share of clouds that get noise.
        rotate: apply a uniform random rotation.
        estimated_normals: share of clouds whose normals are those that
            ``normals="estimate"`` computes (the shipped default's first pass,
            :func:`o3dvis.two_pass.first_pass_normals`), with their flips and angle
            errors, instead of the exact ones (which a cloud keeps where two passes
            would not be taken): for a normals model that answers on estimated normals.
    """

    min_points: int = 2048
    max_points: int = 16384
    views: int = 4
    noise: float = 0.02
    noise_prob: float = 0.5
    rotate: bool = True
    estimated_normals: float = 0.0


@dataclass
class Batch:
    """Clouds concatenated for the U-Net, and per-cloud views (all normalised)."""

    points: Tensor
    normals: Tensor
    batch: Tensor
    cameras: list[Tensor]
    labels: list[Tensor]
    sizes: list[int]

    def slices(self) -> list[slice]:
        """The rows of each cloud in ``points``, ``normals`` and ``batch``."""
        ends = np.cumsum(self.sizes).tolist()
        return [slice(end - size, end) for end, size in zip(ends, self.sizes)]

    def to(self, device: torch.device | str) -> "Batch":
        return Batch(self.points.to(device), self.normals.to(device), self.batch.to(device),
                     [c.to(device) for c in self.cameras], [v.to(device) for v in self.labels],
                     self.sizes)


class VisibilityDataset(torch.utils.data.Dataset):
    """Prepared ``.npz`` samples drawn as augmented training clouds.

    Each item is a tuple ``(points, normals, cameras, labels)`` in normalised
    coordinates: (n, 3), (n, 3), (views, 3), (views, n) bool. Item ``k`` draws
    its file and augmentation from the seed ``(seed, k)``, so a run is
    reproducible and resumes exactly by starting from the next item.

    Args:
        files: prepared ``.npz`` files.
        augmentation: how clouds are drawn.
        seed: base seed.
        length: number of items (e.g. steps x batch size); default one per file.
        cache: keep loaded samples in memory.
    """

    def __init__(self, files: list[str | Path], augmentation: Augmentation | None = None,
                 seed: int = 0, length: int | None = None, cache: bool = True):
        if not files:
            raise ValueError("no training files")
        self.files = [Path(f) for f in files]
        self.aug = augmentation or Augmentation()
        self.seed = seed
        self.length = len(self.files) if length is None else length
        self._cache: dict[int, Sample] | None = {} if cache else None

    def __len__(self) -> int:
        return self.length

    def sample(self, index: int) -> Sample:
        if self._cache is None:
            return load_sample(self.files[index])
        if index not in self._cache:
            self._cache[index] = load_sample(self.files[index])
        return self._cache[index]

    def __getitem__(self, item: int):
        rng = np.random.default_rng([self.seed, item])
        s, a = self.sample(int(rng.integers(len(self.files)))), self.aug
        n = int(np.exp(rng.uniform(np.log(a.min_points), np.log(a.max_points + 1))))
        n = min(n, len(s.points))
        idx = rng.choice(len(s.points), size=n, replace=False)
        views = rng.choice(len(s.cameras), size=min(a.views, len(s.cameras)), replace=False)
        points, normals, cameras = s.points[idx].astype(np.float64), s.normals[idx], s.cameras[views]
        labels = s.visibility[views][:, idx]
        if a.rotate:
            rot = random_rotation(rng)
            points, normals, cameras = points @ rot.T, normals @ rot.T, cameras @ rot.T
        if a.noise > 0 and rng.random() < a.noise_prob:
            points = add_noise(points, rng.uniform(0, a.noise), diagonal(points), rng)
        if a.estimated_normals > 0 and rng.random() < a.estimated_normals:
            from ...neural import NeuralVisibility  # the runtime's, imported where it is asked for
            from ...two_pass import first_pass_normals

            estimated = first_pass_normals(NeuralVisibility.pretrained().encode(points, normals=False), points)
            normals = normals if estimated is None else estimated  # None: two passes would not be taken
        pts, center, scale = normalize_points(torch.from_numpy(points))
        cams = (torch.from_numpy(cameras.astype(np.float64)) - center) / scale
        return (pts.float(), torch.from_numpy(np.ascontiguousarray(normals)).float(), cams.float(),
                torch.from_numpy(labels))


def collate(items) -> Batch:
    points, normals, cameras, labels = zip(*items)
    sizes = [len(p) for p in points]
    batch = torch.cat([torch.full((n,), i, dtype=torch.long) for i, n in enumerate(sizes)])
    return Batch(torch.cat(points), torch.cat(normals), batch, list(cameras), list(labels), sizes)
