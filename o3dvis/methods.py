"""Named visibility methods for the bench: baselines with their sweeps, and the network.

A visibility method is any callable ``method(points (N, 3), cameras (V, 3)) ->
(V, N) bool``; one with ``needs_normals = True`` also takes ``normals=``.
:func:`resolve_methods` turns names (``hpr``, ``hpr-exp``, ``neural``,
``neural-normals``) into parameter sweeps ``{label: method}``; a method that cannot be
built here (no network code, no weights) is returned as absent with the reason,
never replaced by something else.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .baselines import SWEEPS, Method, sweep

__all__ = ["NeuralMethod", "neural_method", "resolve_methods", "METHOD_NAMES"]

METHOD_NAMES = (*SWEEPS, "neural", "neural-normals")


class NeuralMethod:
    """The network as a visibility method: one U-Net pass per cloud, then all views.

    Args:
        visibility: an ``o3dvis.NeuralVisibility``.
        identity: text naming the weights (for reports).
        use_normals: feed the cloud's normals to the network; the method is
            then called ``method(points, cameras, normals=normals)``.
    """

    def __init__(self, visibility, identity: str, use_normals: bool = False):
        self.visibility = visibility
        self.identity = identity
        self.needs_normals = use_normals
        self.__name__ = f"neural({identity}{', normals' if use_normals else ''})"

    def encode(self, points: np.ndarray, normals: np.ndarray | None = None):
        """The cloud's visibility field (``field.query(cameras) -> (V, N) bool``)."""
        if self.needs_normals and normals is None:
            raise ValueError(f"{self.__name__} needs the cloud's normals")
        return self.visibility.encode(np.asarray(points, dtype=np.float64),
                                      normals=np.asarray(normals, dtype=np.float64) if self.needs_normals else False)

    def build_octree(self, points: np.ndarray):
        """The octree that encoding builds for ``points`` (timed alone by the bench)."""
        import torch

        from .nn import normalize_points

        points = torch.as_tensor(points, dtype=torch.float64, device=self.visibility.device)
        return self.visibility.network.octree(normalize_points(points)[0].float())

    def __call__(self, points: np.ndarray, cameras: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        return self.encode(points, normals).query(np.atleast_2d(np.asarray(cameras, dtype=np.float64)))


def neural_method(checkpoint: str | Path | None = None, device: str | None = None,
                  use_normals: bool = False) -> NeuralMethod:
    """The neural method from a checkpoint file or the shipped weights.

    Args:
        checkpoint: a ``.safetensors`` file saved by ``VisibilityNetwork.save``;
            None for ``NeuralVisibility.pretrained()``.
        device: torch device (default: the API's choice).
        use_normals: give the network the cloud's normals (a model that takes them is needed).

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
            visibility, identity = NeuralVisibility.pretrained(device=device), "pretrained"
        else:
            from .nn import VisibilityNetwork

            path = Path(checkpoint)
            if not path.is_file():
                raise FileNotFoundError(f"checkpoint {path} not found")
            digest = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
            visibility = NeuralVisibility(VisibilityNetwork.load(path), device=device)
            identity = f"{path.name}@{digest}"
    except (FileNotFoundError, ValueError, KeyError, RuntimeError) as e:
        raise LookupError(f"no network weights could be loaded: {e}") from e
    needs = visibility.network.config.use_normals
    if use_normals and not (needs or visibility.normals_network is not None):
        raise LookupError(f"the weights ({identity}) take no normals")
    if needs and not use_normals:
        raise LookupError(f"the weights ({identity}) need normals: use the method neural-normals")
    return NeuralMethod(visibility, identity, use_normals)


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
        if name.startswith("neural"):
            try:
                methods[name] = {"": neural_method(checkpoint, use_normals=name == "neural-normals")}
            except LookupError as e:
                absent[name] = str(e)
        else:
            methods[name] = sweep(name, (sweeps or {}).get(name))
    return methods, absent
