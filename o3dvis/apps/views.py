"""Best and worst views: gradient descent on the soft visibility over camera positions."""

from __future__ import annotations

import numpy as np
import torch

from ..cameras import fibonacci_sphere
from ..clouds import cloud_points
from ..geometry import bounds
from ..methods import accepts_method_keyword, resolve_soft_method

__all__ = ["best_view"]


@accepts_method_keyword
def best_view(pcd, maximize: bool = True, steps: int = 300, model=None, *, starts: int = 8,
              lr: float = 0.05, distance: float | None = None,
              progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The camera position that sees the most (or the fewest) points.

    The camera lives on the sphere of radius ``distance`` around the
    bounding-box centre, parameterised by an unconstrained 3-vector normalised
    to a direction. Adam maximises (or minimises) the mean visibility
    probability over the points, from ``starts`` directions spread on a
    Fibonacci lattice at once; the best position met on any start wins.

    Args:
        pcd: ``o3d.geometry.PointCloud`` (legacy or tensor) or (N, 3) points.
        maximize: True for the best view, False for the worst.
        steps: optimisation steps.
        model: the visibility source (default: the pretrained network): as in
            :func:`o3dvis.methods.resolve_soft_method`, a network, or a callable
            mapping a (V, 3) camera tensor to (V, N) differentiable probabilities.
        starts: number of starting directions.
        lr: Adam learning rate (a step of ``lr`` moves the camera by about
            ``lr`` radians at first), decayed with a cosine schedule.
        distance: sphere radius (default: the bounding-box diagonal, the
            distance the network is trained at).
        progress: show a progress bar.

    Returns:
        The camera position (3,) and the loss curve (steps,) of the winning
        start: minus the visible fraction when maximising, the fraction otherwise.
    """
    from tqdm import trange

    if steps < 1 or starts < 1:
        raise ValueError(f"steps and starts must be at least 1, got {steps} and {starts}")
    points = cloud_points(pcd)
    soft = resolve_soft_method(model, points)
    lo, hi = bounds(points)
    radius = float(np.linalg.norm(hi - lo)) if distance is None else float(distance)
    if not radius > 0:
        raise ValueError("the camera distance must be positive (the points span no volume)")
    # float64: a float32 camera far from the origin (georeferenced clouds) is off by its ulp
    center = torch.tensor((lo + hi) / 2, dtype=torch.float64)
    direction = torch.tensor(fibonacci_sphere(starts), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([direction], lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    sign = -1.0 if maximize else 1.0
    curves = torch.empty(steps, starts)
    best_loss, best_camera = float("inf"), None
    for step in trange(steps, disable=not progress, desc="best view" if maximize else "worst view"):
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
