"""Training loop: CPU or CUDA, several GPUs with DDP under ``torchrun``, resumable.

A run directory holds ``last.safetensors`` + ``last_state.pt`` (weights,
optimizer, schedule, step; loaded with ``weights_only=True``), ``best.safetensors``
(best validation accuracy so far) and ``log.jsonl``. Checkpoints are written to a
temporary file and renamed, and ``last_state.pt`` alone is what a resume reads, so
a run killed at any moment resumes from its last complete checkpoint; log records
past that checkpoint are dropped then (the resumed run writes them again).
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..nn.network import NetworkConfig, VisibilityNetwork
from ..nn.octree import normalize_points
from .data.dataset import Augmentation, Batch, VisibilityDataset, collate
from .data.sample import load_sample

__all__ = ["TrainConfig", "train", "batch_loss", "validate"]


@dataclass
class TrainConfig:
    """Everything a training run depends on (saved in the run directory)."""

    data: list[str]
    out: str
    val: str | None = None
    steps: int = 10_000
    batch_size: int = 4
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup: int = 200
    val_every: int = 500
    log_every: int = 50
    val_points: int = 8192
    val_views: int = 4
    workers: int = 0
    seed: int = 0
    device: str = "cpu"
    network: dict = field(default_factory=dict)
    augmentation: dict = field(default_factory=dict)
    init: str | None = None
    time_limit: float | None = None  # seconds of this call, then a checkpoint and a stop (a resume goes on)
    # weight of dense orientation supervision: a linear head of training's own (not saved with the
    # network) reads each point's U-Net feature and is scored by 1 - its cosine to the point's
    # oriented normal, so that the features a network without normals learns carry orientation
    orientation_weight: float = 0.0


def warm_start(net: VisibilityNetwork, state: dict[str, torch.Tensor]) -> None:
    """Copies a state dict into ``net`` where shapes differ by added input channels.

    Used to start a normals model from a default one, or a model with more view
    cues from an earlier one: weights over the added inputs start at zero, so
    ``net`` first computes what the source computed from the shared inputs.
    A calibration or a fusion in ``state`` that ``net`` lacks is dropped (training
    changes the margins they were fitted to; ``o3dvis calibrate`` and ``o3dvis fuse``
    fit them anew).
    """
    from ..nn.conv import _GatherMatmul
    from ..nn.network import _FITTED

    target = net.state_dict()
    linear = {f"{name}.weight": m for name, m in net.named_modules() if isinstance(m, _GatherMatmul)}
    for name, value in state.items():
        if name.startswith(tuple(_FITTED.values())) and name not in target:
            continue
        dst = target[name]
        with torch.no_grad():
            if dst.shape == value.shape:
                dst.copy_(value)
                continue
            dst.zero_()
            if name in linear:  # (taps * in, out): the input channels are interleaved with taps
                taps = dst.shape[0] // linear[name].in_channels
                dst, value = dst.view(taps, -1, dst.shape[1]), value.view(taps, -1, value.shape[1])
            dst[tuple(slice(0, s) for s in value.shape)].copy_(value)


def batch_loss(net: torch.nn.Module, batch: Batch, use_normals: bool,
               orientation_weight: float = 0.0) -> tuple[torch.Tensor, float]:
    """Cross-entropy averaged per view of each cloud, then over them, and the pooled accuracy;
    plus ``orientation_weight`` times the orientation head's mean ``1 - cos`` to the batch's
    normals where ``net`` (an :class:`_Encoder`) has that head.

    Each (cloud, view) weighs the same whatever its number of points, so that
    2k-point clouds still count when the batch also holds 80k-point ones.
    """
    module = net.module if hasattr(net, "module") else net
    normals = batch.normals if use_normals else None
    features, orientation = net(batch.points, batch.batch, normals, len(batch.sizes))
    losses, correct, total = [], 0, 0
    for i, sl in enumerate(batch.slices()):
        surfels = module.surfels(batch.points[sl])  # once per cloud, for all its views
        for cam, label in zip(batch.cameras[i], batch.labels[i]):
            logits = module.predict(features[sl], batch.points[sl], cam,
                                    normals=normals[sl] if use_normals else None, surfels=surfels)
            target = label.long()
            losses.append(F.cross_entropy(logits, target))
            correct += int((logits.argmax(dim=1) == target).sum())
            total += len(target)
    loss = torch.stack(losses).mean()
    if orientation is not None:
        loss = loss + orientation_weight * (1 - F.cosine_similarity(orientation, batch.normals, dim=1)).mean()
    return loss, correct / total


@torch.no_grad()
def validate(net: VisibilityNetwork, files: list[Path], num_points: int = 8192, views: int = 4,
             seed: int = 0) -> float:
    """Accuracy pooled over ``views`` views of each file at ``num_points`` points (fixed subsets)."""
    was_training = net.training
    net.eval()
    device = next(net.parameters()).device
    correct = total = 0
    for f in files:
        s = load_sample(f)
        rng = np.random.default_rng([seed, len(s.points)])
        idx = rng.choice(len(s.points), size=min(num_points, len(s.points)), replace=False)
        pts, center, scale = normalize_points(torch.from_numpy(s.points[idx]).double())
        pts = pts.float().to(device)
        normals = torch.from_numpy(s.normals[idx]).to(device) if net.config.use_normals else None
        features, surfels = net.encode(pts, normals=normals), net.surfels(pts)
        for v in range(min(views, len(s.cameras))):
            cam = ((torch.from_numpy(s.cameras[v]).double() - center) / scale).float().to(device)
            pred = net.predict(features, pts, cam, normals=normals, surfels=surfels).argmax(dim=1).cpu().numpy()
            correct += int((pred == s.visibility[v, idx]).sum())
            total += len(idx)
    net.train(was_training)
    return correct / max(total, 1)


class _Encoder(torch.nn.Module):
    """Wraps ``encode`` as ``forward`` so DDP sees the U-Net's parameters used, with the optional
    orientation head (see ``TrainConfig.orientation_weight``): ``forward`` returns the per-point
    features and the head's (N, 3) answer, or None without it."""

    def __init__(self, net: VisibilityNetwork, orientation: bool = False):
        super().__init__()
        self.net = net
        width = net.predictor.project_feature.out_features  # the per-point features the predictor reads
        self.orientation = torch.nn.Linear(width, 3) if orientation else None

    def forward(self, points, batch, normals, batch_size):
        features = self.net.encode(points, batch, normals, batch_size)
        return features, None if self.orientation is None else self.orientation(features)

    def predict(self, *args, **kwargs):
        return self.net.predict(*args, **kwargs)

    def surfels(self, points):
        return self.net.surfels(points)


def _atomic(path: Path, write) -> None:
    """Calls ``write(tmp)`` and renames ``tmp`` to ``path``: a kill leaves the old file or the new one."""
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def _truncate_log(path: Path, step: int) -> None:
    """Keeps the records of ``log.jsonl`` up to ``step`` (a record cut short by a kill goes too)."""
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line).get("step", 0) <= step:
                kept.append(line + "\n")
        except json.JSONDecodeError:
            continue
    _atomic(path, lambda tmp: tmp.write_text("".join(kept)))


def _files(dirs: list[str]) -> list[Path]:
    files = sorted(p for d in dirs for p in Path(d).glob("*.npz") if not p.name.endswith(".tmp.npz"))
    if not files:
        raise ValueError(f"no prepared .npz files in {dirs}")
    return files


def _out_of_time(limit: float | None, start: float, world: int, device: torch.device) -> bool:
    """Whether ``limit`` seconds have passed since ``start`` (on any process, when there are several)."""
    if limit is None:
        return False
    late = time.time() - start >= limit
    if world > 1:
        flag = torch.tensor([float(late)], device=device)
        torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
        late = bool(flag.item())
    return late


def _process_group(cfg: TrainConfig) -> tuple[int, int, torch.device]:
    """The number of processes, this one's rank and its device; joins the process group when there
    are several (``torchrun`` sets ``WORLD_SIZE``, ``RANK`` and ``LOCAL_RANK``)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    device = torch.device(cfg.device)
    if world > 1:
        import torch.distributed as dist

        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        if device.type == "cuda":
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(device)
    return world, rank, device


def _resume(out: Path, net: VisibilityNetwork, encoder: _Encoder, opt: torch.optim.Optimizer, sched,
            device: torch.device) -> tuple[int, float]:
    """Loads the run's last state into the network, the orientation head, the optimiser and the
    schedule; returns the step it was saved at and the best validation accuracy so far."""
    state = torch.load(out / "last_state.pt", map_location=device, weights_only=True)
    net.load_state_dict(state["model"] if "model" in state else  # a state without the weights: last.safetensors
                        VisibilityNetwork.load(out / "last.safetensors", device).state_dict())
    if encoder.orientation is not None:
        encoder.orientation.load_state_dict(state["orientation"])
    opt.load_state_dict(state["optimizer"])
    sched.load_state_dict(state["scheduler"])
    return int(state["step"]), float(state["best"])


def _save_state(out: Path, net: VisibilityNetwork, encoder: _Encoder, opt: torch.optim.Optimizer, sched,
                step: int, best: float) -> None:
    """Writes ``last.safetensors`` and ``last_state.pt`` (what :func:`_resume` reads), each atomically."""
    _atomic(out / "last.safetensors", lambda tmp: net.save(tmp, {"step": step}))
    _atomic(out / "last_state.pt", lambda tmp: torch.save(
        {"model": net.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
         "step": step, "best": best,
         **({} if encoder.orientation is None else {"orientation": encoder.orientation.state_dict()})}, tmp))


def train(cfg: TrainConfig, progress: bool = True) -> Path:
    """Runs (or resumes) a training run; returns the path of the best checkpoint."""
    from tqdm import tqdm

    world, rank, device = _process_group(cfg)
    files, val_files = _files(cfg.data), (_files([cfg.val]) if cfg.val else [])
    (out := Path(cfg.out)).mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    net = VisibilityNetwork(NetworkConfig.from_dict(cfg.network)).to(device)
    encoder = _Encoder(net, orientation=cfg.orientation_weight > 0).to(device)
    opt = torch.optim.AdamW(encoder.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)

    def lr_at(step: int) -> float:
        if step < cfg.warmup:
            return (step + 1) / cfg.warmup
        return 0.5 * (1 + math.cos(math.pi * (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_at)
    start, best = 0, -1.0
    if (out / "last_state.pt").exists():
        start, best = _resume(out, net, encoder, opt, sched, device)
        if rank == 0:
            _truncate_log(out / "log.jsonl", start)
    elif cfg.init:
        from safetensors.torch import load_file

        warm_start(net, load_file(cfg.init, device=str(device)))
    if rank == 0:
        (out / "config.json").write_text(json.dumps(asdict(cfg), indent=2))
    model = (torch.nn.parallel.DistributedDataParallel(encoder, find_unused_parameters=False) if world > 1
             else encoder)

    data = VisibilityDataset(files, Augmentation(**cfg.augmentation),
                             seed=cfg.seed * 1000 + rank, length=cfg.steps * cfg.batch_size)
    items = torch.utils.data.Subset(data, range(start * cfg.batch_size, len(data)))
    loader = torch.utils.data.DataLoader(items, batch_size=cfg.batch_size, collate_fn=collate,
                                         num_workers=cfg.workers)
    log = open(out / "log.jsonl", "a") if rank == 0 else None
    bar = tqdm(total=cfg.steps, initial=start, disable=not progress or rank != 0, desc="train")
    net.train()
    t0, run_loss, run_acc = time.time(), 0.0, 0.0
    for step, batch in enumerate(loader, start=start + 1):
        batch = batch.to(device)
        loss, acc = batch_loss(model, batch, net.config.use_normals, cfg.orientation_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(encoder.parameters(), 1.0)
        opt.step()
        sched.step()
        run_loss, run_acc = 0.98 * run_loss + 0.02 * loss.item(), 0.98 * run_acc + 0.02 * acc
        debias = 1 - 0.98 ** (step - start)  # running means start at zero
        bar.update(1)
        bar.set_postfix(loss=f"{run_loss / debias:.3f}", acc=f"{run_acc / debias:.3f}")
        out_of_time = _out_of_time(cfg.time_limit, t0, world, device)
        if rank != 0:
            if out_of_time:
                break
            continue
        if step % cfg.log_every == 0:
            log.write(json.dumps({"step": step, "loss": loss.item(), "acc": acc,
                                  "lr": sched.get_last_lr()[0], "time": time.time() - t0}) + "\n")
            log.flush()
        if step % cfg.val_every == 0 or step == cfg.steps or out_of_time:
            record = {"step": step, "time": time.time() - t0}
            if val_files:
                record["val_acc"] = validate(net, val_files, cfg.val_points, cfg.val_views)
            log.write(json.dumps(record) + "\n")  # before the checkpoint: a resume drops it if need be
            log.flush()
            if val_files and record["val_acc"] > best:
                best = record["val_acc"]
                _atomic(out / "best.safetensors", lambda tmp: net.save(tmp, {"step": step, "val_acc": best}))
            _save_state(out, net, encoder, opt, sched, step, best)
            bar.write(json.dumps(record))
        if out_of_time:
            break
    bar.close()
    if world > 1:
        torch.distributed.destroy_process_group()
    return out / ("best.safetensors" if val_files else "last.safetensors")
