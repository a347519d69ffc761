"""Fitting a trained network's per-cloud calibration (:mod:`o3dvis.nn.calibration`).

Training clouds are drawn as training draws them (random size, views,
rotation and noise); the network's margins on a random subset of each cloud's
(point, view) pairs, with the cloud's calibration terms, are what
:func:`~o3dvis.nn.calibration.fit_calibration` fits.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ..models import load_model
from ..nn.calibration import NUM_TERMS, calibration_loss, calibration_terms, fit_calibration
from ..nn.network import NetworkConfig, VisibilityNetwork
from .data.dataset import Augmentation, VisibilityDataset
from .data.sample import list_samples
from .publish import portable_path

__all__ = ["calibrate"]


def calibrate(checkpoint: str | Path, data: list[str | Path], out: str | Path, clouds: int = 2000,
              keep: int = 20000, seed: int = 1, augmentation: Augmentation | None = None,
              progress: bool = True) -> dict:
    """Fits the calibration of ``checkpoint`` and writes the calibrated network to ``out``.

    Args:
        checkpoint: a network written by ``o3dvis train`` (a calibration it has is refitted).
        data: folders of prepared ``.npz`` training files.
        out: the safetensors file to write.
        clouds: training clouds to draw.
        keep: (point, view) pairs kept per cloud.
        seed: seed of the draw.
        augmentation: how clouds are drawn (default: as the shipped models were
            trained, 2 048 - 81 920 points, noise on half of them).
        progress: show a progress bar.

    Returns:
        ``u``, ``w``, the number of clouds and samples, the data folders and
        the checkpoint (as paths relative to the current directory, see
        :func:`o3dvis.publish.portable_path`), and the cross-entropy before and after.
    """
    from tqdm import tqdm

    from ..neural import NeuralVisibility

    if clouds < 1 or keep < 1:
        raise ValueError(f"clouds and keep must be positive, got {clouds} and {keep}")
    net = load_model(Path(checkpoint)).without("calibrated")
    files = [f for d in data for f in list_samples(d)]
    if not files:
        raise ValueError(f"no prepared .npz files in {[str(d) for d in data]}")
    draw = VisibilityDataset(files, augmentation or Augmentation(max_points=81920), seed=seed, length=clouds)
    vis = NeuralVisibility(net, precision="float32")  # the margins the calibration maps, unrounded
    rng = np.random.default_rng(seed)
    terms, cloud, margins, labels = [], [], [], []
    for k in tqdm(range(clouds), disable=not progress, desc="calibrate", unit="cloud"):
        points, normals, cameras, label = draw[k]
        field = vis.encode(points.double(), normals=normals if net.config.use_normals else False)
        p = field.probabilities(cameras.double()).double().clamp(1e-7, 1 - 1e-7).reshape(-1)
        rows = torch.from_numpy(rng.choice(len(p), min(len(p), keep), replace=False))
        margins.append(torch.log(p[rows]) - torch.log1p(-p[rows]))
        labels.append(label.reshape(-1)[rows].double())
        terms.append(calibration_terms(net.cloud_noise(points)[0], len(points)))
        cloud.append(torch.full((len(rows),), k))
    terms, cloud, margins, labels = torch.stack(terms), torch.cat(cloud), torch.cat(margins), torch.cat(labels)
    u, w = fit_calibration(terms, cloud, margins, labels)
    identity = torch.zeros(NUM_TERMS, dtype=torch.float64)
    calibrated = VisibilityNetwork(NetworkConfig.from_dict({**asdict(net.config), "calibrated": True}))
    calibrated.load_state_dict({**net.state_dict(), "calibration.u": u, "calibration.w": w})
    summary = {"u": u.tolist(), "w": w.tolist(), "clouds": clouds, "samples": len(margins), "seed": seed,
               "data": [portable_path(d, Path.cwd()) for d in data],
               "checkpoint": portable_path(checkpoint, Path.cwd()),
               "cross_entropy_before": calibration_loss(identity, identity, terms, cloud, margins, labels).item(),
               "cross_entropy_after": calibration_loss(u, w, terms, cloud, margins, labels).item()}
    calibrated.save(out, {"calibration": summary})
    return summary
