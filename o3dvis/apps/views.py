"""Best and worst views: the camera on a sphere around a cloud that sees the most (or fewest) points.

The default search scores a Fibonacci lattice of candidate views from one encoding of the cloud,
then refines the best few by a compass search: batches of views on shrinking cones around each,
without gradients, so that a view costs a query. ``search="gradient"`` runs Adam on the soft
visibility instead, through the network's gradient with respect to the camera; a differentiable
view costs many queries, so it is the slower of the two.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ..cameras import fibonacci_sphere
from ..clouds import cloud_points
from ..geometry import bounds, box_diagonal
from ..methods import resolve_soft_method

__all__ = ["best_view", "SEARCHES"]

SEARCHES = ("candidates", "gradient")
"""The searches :func:`best_view` runs: a scored lattice refined by compass search, or Adam."""

_DEFAULTS = {"candidates": (10, 4), "gradient": (300, 8)}  # steps, starts of each search
_PROPOSALS = 8  # views on the cone around each refined view, per step
_BATCH_VALUES = 1 << 22  # probabilities per call of the model (views x points)
_PROGRESS_DELAY = 2.0  # seconds before a progress bar shows: a quick call prints nothing


def best_view(pcd, maximize: bool = True, steps: int | None = None, model=None, *, starts: int | None = None,
              candidates: int = 200, search: str = "candidates", lr: float = 0.05,
              distance: float | None = None, progress: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The camera position that sees the most (or the fewest) points.

    The camera lives on the sphere of radius ``distance`` around the bounding-box centre, and a
    view's score is the mean visibility probability over the points (a soft count). The cloud
    is encoded once. The default search scores ``candidates`` directions spread on a Fibonacci
    lattice, then refines the ``starts`` best by ``steps`` rounds of a compass search: each round
    scores views on a cone around each, moves to the best, and halves the cone's angle where
    nothing was better (from the lattice's spacing down). ``search="gradient"`` runs Adam on
    an unconstrained 3-vector normalised to a direction from ``starts`` lattice directions at
    once; a gradient step costs many queries, so it is much slower for a view about as good.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor) or (N, 3) points.
        maximize: True for the best view, False for the worst.
        steps: rounds of the compass search (default 10), or Adam steps with
            ``search="gradient"`` (default 300).
        model: the visibility source (default: the pretrained network): as in
            :func:`o3dvis.methods.resolve_soft_method`, a network, or a callable
            mapping a (V, 3) camera tensor to (V, N) probabilities (differentiable
            for ``search="gradient"``).
        starts: views refined (default 4), or starting directions with
            ``search="gradient"`` (default 8).
        candidates: lattice directions scored first (``"candidates"`` search only).
        search: ``"candidates"`` (default) or ``"gradient"``, see above.
        lr: Adam learning rate of the gradient search (a step of ``lr`` moves the
            camera by about ``lr`` radians at first), decayed with a cosine schedule.
        distance: sphere radius (default: the bounding-box diagonal, the
            distance the network is trained at).
        progress: show a progress bar where the call lasts more than a couple of seconds.

    Returns:
        The camera position (3,) and the loss curve: minus the visible fraction when
        maximising, the fraction otherwise; of the best view after the lattice and after
        each round, (steps + 1,), or of the winning start at each Adam step, (steps,).

    Raises:
        ValueError: steps, starts or candidates below 1, an unknown search, a distance
            that is not positive.
    """
    if search not in SEARCHES:
        raise ValueError(f"search must be one of {', '.join(SEARCHES)}; got {search!r}")
    default_steps, default_starts = _DEFAULTS[search]
    steps = default_steps if steps is None else steps
    starts = default_starts if starts is None else starts
    if steps < 1 or starts < 1 or candidates < 1:
        raise ValueError(f"steps, starts and candidates must be at least 1, got {steps}, {starts} and {candidates}")
    points = cloud_points(pcd)
    soft = resolve_soft_method(model, points)
    lo, hi = bounds(points)
    radius = box_diagonal(lo, hi) if distance is None else float(distance)
    if not radius > 0:
        raise ValueError("the camera distance must be positive (the points span no volume)")
    # float64: a float32 camera far from the origin (georeferenced clouds) is off by its ulp
    center = torch.tensor((lo + hi) / 2, dtype=torch.float64)
    sign = -1.0 if maximize else 1.0
    desc = "best view" if maximize else "worst view"
    if search == "gradient":
        return _gradient_search(soft, center, radius, sign, steps, starts, lr, desc if progress else None)
    return _compass_search(soft, center, radius, sign, len(points), steps, min(starts, candidates), candidates,
                           desc if progress else None)


def _compass_search(soft: Callable, center: torch.Tensor, radius: float, sign: float, count: int, steps: int,
                    starts: int, candidates: int, desc: str | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`best_view`'s default search; ``desc``: the progress bar's title (None: no bar)."""
    from tqdm import tqdm

    per_call = max(1, _BATCH_VALUES // max(count, 1))
    total = candidates + steps * starts * _PROPOSALS
    with tqdm(total=total, desc=desc, unit="view", disable=desc is None, delay=_PROGRESS_DELAY,
              leave=False) as bar:
        def losses(directions: np.ndarray) -> np.ndarray:
            out = []
            for a in range(0, len(directions), per_call):
                cameras = center + radius * torch.from_numpy(directions[a:a + per_call])
                with torch.no_grad():
                    out.append(sign * soft(cameras).double().mean(dim=1).cpu().numpy())
                bar.update(len(cameras))
            return np.concatenate(out)

        lattice = fibonacci_sphere(candidates)
        scores = losses(lattice)
        order = np.argsort(scores, kind="stable")[:starts]
        best, best_loss = lattice[order], scores[order]
        angle = np.full(starts, np.sqrt(np.pi / candidates))  # half the lattice's spacing
        curve = [best_loss.min()]
        for step in range(steps):
            proposals = _cones(best, angle, step)
            tried = losses(proposals.reshape(-1, 3)).reshape(starts, _PROPOSALS)
            pick = tried.argmin(axis=1)
            better = tried[np.arange(starts), pick] < best_loss
            best[better] = proposals[better, pick[better]]
            best_loss[better] = tried[better, pick[better]]
            angle[~better] /= 2
            curve.append(best_loss.min())
    winner = int(best_loss.argmin())
    return (center + radius * torch.from_numpy(best[winner])).numpy(), np.asarray(curve, dtype=np.float64)


def _cones(axes: np.ndarray, angles: np.ndarray, step: int) -> np.ndarray:
    """(S, _PROPOSALS, 3) unit directions at ``angles`` (S,) from the unit ``axes`` (S, 3), evenly
    around each, turned by the golden angle at each ``step`` so that rounds do not repeat a pattern."""
    helper = np.where(np.abs(axes[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(axes, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(axes, u)
    turn = 2 * np.pi * np.arange(_PROPOSALS) / _PROPOSALS + step * np.pi * (3 - np.sqrt(5))
    ring = np.cos(turn)[None, :, None] * u[:, None] + np.sin(turn)[None, :, None] * v[:, None]
    cones = np.cos(angles)[:, None, None] * axes[:, None] + np.sin(angles)[:, None, None] * ring
    return cones / np.linalg.norm(cones, axis=2, keepdims=True)


def _gradient_search(soft: Callable, center: torch.Tensor, radius: float, sign: float, steps: int, starts: int,
                     lr: float, desc: str | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`best_view`'s ``search="gradient"``; ``desc``: the progress bar's title (None: no bar)."""
    from tqdm import trange

    direction = torch.tensor(fibonacci_sphere(starts), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([direction], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    curves = torch.empty(steps, starts)
    best_loss, best_camera = float("inf"), None
    for step in trange(steps, disable=desc is None, desc=desc, delay=_PROGRESS_DELAY, leave=False):
        cameras = center + radius * direction / direction.norm(dim=1, keepdim=True)
        loss = sign * soft(cameras).mean(dim=1)
        curves[step] = loss.detach()
        winner = int(curves[step].argmin())
        if float(curves[step, winner]) < best_loss:
            best_loss, best_camera = float(curves[step, winner]), cameras[winner].detach().clone()
        optimizer.zero_grad()
        loss.sum().backward()
        optimizer.step()
        schedule.step()
    start = int(curves.min(dim=0).values.argmin())
    return best_camera.double().numpy(), curves[:, start].numpy().astype(np.float64)
