"""The one noise model of the project, shared by training augmentation and evaluation."""

from __future__ import annotations

import numpy as np

__all__ = ["add_noise"]


def add_noise(points: np.ndarray, level: float, scale: float, rng: np.random.Generator) -> np.ndarray:
    """Moves each point in a random direction by a distance uniform in [0, level * scale]."""
    if level < 0:
        raise ValueError(f"noise level must be >= 0, got {level}")
    direction = rng.normal(size=points.shape)
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
    return points + direction * (level * scale * rng.random((len(points), 1)))
