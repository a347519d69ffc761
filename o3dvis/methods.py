"""Named visibility methods for the bench: baselines with their sweeps, and the network.

A visibility method is any callable ``method(points (N, 3), cameras (V, 3)) ->
(V, N) bool``. :func:`resolve_methods` turns names (``hpr``, ``hpr-exp``,
``neural``) into parameter sweeps ``{label: method}``; a method that cannot be
built here (no network code, no weights) is returned as absent with the reason,
never replaced by something else.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .baselines import SWEEPS, Method, sweep

__all__ = ["NeuralMethod", "neural_method", "resolve_methods", "METHOD_NAMES"]

METHOD_NAMES = (*SWEEPS, "neural")


class NeuralMethod:
    """The network as a visibility method: one U-Net pass per cloud, then all views.

    Args:
        visibility: an ``o3dvis.NeuralVisibility``.
        identity: text naming the weights (for caches and reports).
    """

    def __init__(self, visibility, identity: str):
        self.visibility = visibility
        self.identity = identity
        self.__name__ = f"neural({identity})"

    def encode(self, points: np.ndarray):
        """The cloud's visibility field (``field.query(cameras) -> (V, N) bool``)."""
        return self.visibility.encode(np.asarray(points, dtype=np.float64))

    def __call__(self, points: np.ndarray, cameras: np.ndarray) -> np.ndarray:
        return self.encode(points).query(np.atleast_2d(np.asarray(cameras, dtype=np.float64)))


def neural_method(checkpoint: str | Path | None = None, device: str | None = None) -> NeuralMethod:
    """The neural method from a checkpoint file or the shipped weights.

    Args:
        checkpoint: a ``.safetensors`` file saved by ``VisibilityNetwork.save``;
            None for ``NeuralVisibility.pretrained()``.
        device: torch device (default: the API's choice).

    Returns:
        A :class:`NeuralMethod`.

    Raises:
        LookupError: the neural API or the weights are not available, with the reason.
    """
    try:
        from .visibility import NeuralVisibility
    except ImportError as e:
        raise LookupError(f"o3dvis.NeuralVisibility is not available ({e})") from e
    try:
        if checkpoint is None:
            return NeuralMethod(NeuralVisibility.pretrained(device=device), "pretrained")
        from .nn import VisibilityNetwork

        path = Path(checkpoint)
        if not path.is_file():
            raise FileNotFoundError(f"checkpoint {path} not found")
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
        return NeuralMethod(NeuralVisibility(VisibilityNetwork.load(path), device=device),
                            f"{path.name}@{digest}")
    except (FileNotFoundError, ValueError, KeyError, RuntimeError) as e:
        raise LookupError(f"no network weights could be loaded: {e}") from e


def resolve_methods(names, checkpoint: str | Path | None = None,
                    sweeps: dict[str, list[float]] | None = None) -> tuple[dict[str, dict[str, Method]], dict[str, str]]:
    """Builds the named methods.

    Args:
        names: method names from :data:`METHOD_NAMES`.
        checkpoint: network checkpoint for ``neural`` (default: shipped weights).
        sweeps: parameter values overriding a baseline's default grid, by name.

    Returns:
        ``(methods, absent)``: ``methods[name] = {parameter label: method}``
        (the network has the single label ``""``), and ``absent[name]`` = why
        a method could not be built.

    Raises:
        ValueError: an unknown method name.
    """
    methods: dict[str, dict[str, Method]] = {}
    absent: dict[str, str] = {}
    for name in names:
        if name not in METHOD_NAMES:
            raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHOD_NAMES)}")
        if name == "neural":
            try:
                methods[name] = {"": neural_method(checkpoint)}
            except LookupError as e:
                absent[name] = str(e)
        else:
            methods[name] = sweep(name, (sweeps or {}).get(name))
    return methods, absent
