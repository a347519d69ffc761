"""Fitting a trained network's fusion with the surfel z-buffer (:mod:`o3dvis.nn.fusion`).

Scene clouds are drawn from prepared training files (random size and noise,
the cameras inside each scene); the frozen network's margins and the z-buffer's
answers of a random subset of each cloud's (point, camera) pairs are what the
fusion MLP is fitted on, by cross-entropy.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from ..models import load_model
from ..nn.cues import point_surfels
from ..nn.fusion import ZBufferFusion, fusion_inputs, zbuffer_inputs
from ..nn.network import NetworkConfig, VisibilityNetwork
from ..nn.zbuffer import surfel_zbuffer
from .data.sample import list_samples, load_sample
from .publish import portable_path

if TYPE_CHECKING:
    from ..evaluation.evaluate import EvalCloud
    from ..neural import NeuralVisibility

__all__ = ["fuse", "fit_fusion"]


def fit_fusion(margins: torch.Tensor, zbuffers: torch.Tensor, noise: torch.Tensor, labels: torch.Tensor,
               steps: int = 3000, batch_size: int = 65536, seed: int = 0,
               hidden: int = 32) -> tuple[ZBufferFusion, float, float]:
    """A :class:`ZBufferFusion` of ``hidden`` units fitted to pairs' margins (M,), z-buffer answers
    (M, 4), their clouds' noise cues (M, 2) and labels (M,) (1: visible) by Adam on the
    cross-entropy, with a cosine-decayed learning rate.

    Returns:
        The fusion, and the cross-entropy of the margins alone and of the fused ones.
    """
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    fusion = ZBufferFusion(hidden)
    margins, inputs, noise = margins.float(), zbuffer_inputs(zbuffers.float()), noise.float()
    x = fusion_inputs(margins, inputs, noise)
    fusion.mean.copy_(x.mean(dim=0))
    fusion.std.copy_(x.std(dim=0).clamp_min(1e-3))
    labels = labels.float()
    opt = torch.optim.Adam(fusion.mlp.parameters(), lr=1e-2)
    schedule = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.5 * (1 + math.cos(math.pi * s / steps)))
    loss = nn.functional.binary_cross_entropy_with_logits
    with torch.enable_grad():
        for _ in range(steps):
            pick = torch.randint(len(labels), (min(batch_size, len(labels)),), generator=generator)
            opt.zero_grad()
            loss(fusion(margins[pick], inputs[pick], noise[pick]), labels[pick]).backward()
            opt.step()
            schedule.step()
    with torch.no_grad():
        before = loss(margins.clamp(-15, 15), labels).item()
        after = loss(fusion(margins, inputs, noise), labels).item()
    return fusion, before, after


def _cloud_pairs(vis: NeuralVisibility, cloud: EvalCloud, rng: np.random.Generator, keep: int
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """What the fusion is fitted on, for ``keep`` random (camera, point) pairs of one cloud.

    Args:
        vis: the frozen network.
        cloud: a cloud with its labels.
        rng: draws the pairs.
        keep: pairs kept (all, when the cloud has fewer).

    Returns:
        The pairs' margins (M,), z-buffer answers (M, 4), the cloud's noise cues (M, 2) and the
        labels (M,).
    """
    field = vis.encode(cloud.points)
    p = field.probabilities(cloud.cameras).double().clamp(1e-7, 1 - 1e-7)
    margin = torch.log(p) - torch.log1p(-p)
    cameras = field.frame.to_unit(torch.as_tensor(cloud.cameras)).to(field.points.dtype)
    with torch.inference_mode():  # as the fused network's field computes them (C kernels, where built)
        surfels = point_surfels(field.points, areas=True)
        answers = torch.stack([surfel_zbuffer(field.points, surfels, c) for c in cameras])
        cues = (field.noise if field.noise is not None  # the field's own, when its network reads them
                else VisibilityNetwork.cloud_noise(field.points, ordered=True)[0]).float()
    if field.rank is not None:
        answers = answers[:, field.rank]
    rows = torch.from_numpy(rng.choice(margin.numel(), min(margin.numel(), keep), replace=False))
    return (margin.reshape(-1)[rows].float(), answers.reshape(-1, answers.shape[-1])[rows],
            cues.expand(len(rows), -1), torch.from_numpy(cloud.labels).reshape(-1)[rows])


def fuse(checkpoint: str | Path, data: list[str | Path], out: str | Path, clouds: int = 400, keep: int = 20000,
         seed: int = 1, min_points: int = 8192, max_points: int = 65536, noise: float = 0.02,
         noise_prob: float = 0.5, steps: int = 3000, hidden: int = 32, progress: bool = True) -> dict:
    """Fits the fusion of ``checkpoint`` on scenes and writes the fused network to ``out``.

    Args:
        checkpoint: a network written by ``o3dvis train`` (a fusion it has is refitted).
        data: folders of prepared scene ``.npz`` files (``o3dvis prepare --scenes``); only their
            cameras inside the scene's bounding box are used.
        out: the safetensors file to write.
        clouds: clouds to draw.
        keep: (point, camera) pairs kept per cloud.
        seed: seed of the draw and of the fit.
        min_points, max_points: range of a cloud's size (log-uniform; all of a file's points at most).
        noise: largest noise level, a fraction of the median camera distance (as ``o3dvis eval --scenes``).
        noise_prob: share of clouds that get noise.
        steps: Adam steps of the fit.
        hidden: width of the fusion's hidden layer (at most 128, what the C kernel takes).
        progress: show a progress bar.

    Returns:
        The number of clouds and samples, the data folders and checkpoint (as paths relative
        to the current directory), and the cross-entropy before and after.
    """
    from tqdm import tqdm

    from ..evaluation.evaluate import eval_cloud, inside_cameras
    from ..neural import NeuralVisibility

    if clouds < 1 or keep < 1 or not 1 <= min_points <= max_points:
        raise ValueError(f"clouds and keep must be positive and 1 <= min_points <= max_points, got {clouds}, "
                         f"{keep}, {min_points}, {max_points}")
    NetworkConfig(fusion=True, fusion_hidden=hidden)  # the width checked before the draw
    net = load_model(Path(checkpoint)).without("fusion")
    files = [f for d in data for f in list_samples(d)]
    if not files:
        raise ValueError(f"no prepared .npz files in {[str(d) for d in data]}")
    vis = NeuralVisibility(net, precision="float32")  # the margins the fusion maps, unrounded
    rng = np.random.default_rng(seed)
    margins, zbuffers, cloud_cues, labels = [], [], [], []
    bar = tqdm(total=clouds, disable=not progress, desc="fuse", unit="cloud")
    tries = 0
    while len(margins) < clouds:
        tries += 1
        if tries > 20 * clouds:
            raise ValueError("too few scene files with cameras inside their bounding box")
        sample = load_sample(files[rng.integers(len(files))])
        if not inside_cameras(sample).any():
            continue
        size = int(round(math.exp(rng.uniform(math.log(min_points), math.log(max_points)))))
        level = float(rng.uniform(0, noise)) if rng.random() < noise_prob else 0.0
        cloud = eval_cloud(sample, size, level, seed=int(rng.integers(1 << 31)), inside=True)
        for kept, rows in zip((margins, zbuffers, cloud_cues, labels), _cloud_pairs(vis, cloud, rng, keep)):
            kept.append(rows)
        bar.update()
    bar.close()
    fusion, before, after = fit_fusion(torch.cat(margins), torch.cat(zbuffers), torch.cat(cloud_cues),
                                       torch.cat(labels), steps, seed=seed, hidden=hidden)
    fused = VisibilityNetwork(NetworkConfig.from_dict({**asdict(net.config), "fusion": True,
                                                       "fusion_hidden": hidden}))
    fused.load_state_dict({**net.state_dict(), **{f"fusion.{k}": v for k, v in fusion.state_dict().items()}})
    summary = {"clouds": clouds, "samples": sum(len(m) for m in margins), "seed": seed,
               "data": [portable_path(d, Path.cwd()) for d in data],
               "checkpoint": portable_path(checkpoint, Path.cwd()),
               "cross_entropy_before": before, "cross_entropy_after": after}
    fused.save(out, {"fusion": summary})
    return summary
