"""The benchmark's named visibility methods: ``hpr``, ``hpr-exp``, ``neural``, ``neural-normals``,
``neural-estimate``, ``neural-balanced``, ``neural-best``.

``neural`` is one pass without normals (``quality="fast"``); ``neural-normals`` gives the normals
model the cloud's normals; ``neural-estimate`` estimates oriented normals in a
first pass where that is more accurate and answers with the normals model
(``NeuralVisibility.encode(normals="estimate")``); ``neural-balanced`` and ``neural-best`` answer a
cloud without normals at those qualities (``NeuralVisibility.encode(quality=...)``).

:func:`resolve_methods` turns names into parameter sweeps ``{label: method}`` (a
network method with ``needs_normals = True`` also takes ``normals=``;
``neural-x8`` and ``neural-normals-x8`` average the network over 8 rotations of
each cloud, see ``NeuralVisibility(num_rotations=...)``, and a ``-float32`` or
``-bfloat16`` ending fixes the dtype of its per-view matrix products, see
``NeuralVisibility(precision=...)``); a method that cannot be built here (no
network code, no weights) is returned as absent with the reason, never replaced
by something else.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from ..baselines import SWEEPS, Method, sweep

__all__ = ["NeuralMethod", "neural_method", "resolve_methods", "METHOD_NAMES"]

METHOD_NAMES = (*SWEEPS, "neural", "neural-normals", "neural-estimate", "neural-balanced", "neural-best")
_QUALITY_OF = {"neural-balanced": "balanced", "neural-best": "best"}
_NETWORK_VARIANT = re.compile(r"(neural(?:-normals|-estimate|-balanced|-best)?)(?:-x([1-9][0-9]*))?"
                              r"(?:-(float32|bfloat16))?")


class NeuralMethod:
    """The network as a visibility method: one U-Net pass per cloud (and rotation), then all views.

    Args:
        visibility: an ``o3dvis.NeuralVisibility``.
        identity: text naming the weights (for reports).
        use_normals: feed the cloud's normals to the network; the method is
            then called ``method(points, cameras, normals=normals)``.
        estimate: otherwise, ``encode(normals="estimate")``: normals estimated
            in a first pass (see ``NeuralVisibility.encode``).
        quality: otherwise, the cloud without normals at this quality (``"fast"``: one pass).
    """

    def __init__(self, visibility, identity: str, use_normals: bool = False, estimate: bool = False,
                 quality: str = "fast"):
        self.visibility = visibility
        self.identity = identity
        self.needs_normals = use_normals
        self.estimate = estimate
        self.quality = quality
        turns, precision = len(visibility.rotations), visibility.precision
        mode = (", normals" if use_normals else ", estimated normals" if estimate
                else f", {quality}" if quality != "fast" else "")
        self.__name__ = (f"neural({identity}{mode}"
                         f"{f', {turns} rotations' if turns > 1 else ''}"
                         f"{f', {precision}' if precision != 'auto' else ''})")

    def encode(self, points: np.ndarray, normals: np.ndarray | None = None):
        """The cloud's visibility field (``field.query(cameras) -> (V, N) bool``)."""
        if self.needs_normals and normals is None:
            raise ValueError(f"{self.__name__} needs the cloud's normals")
        return self.visibility.encode(np.asarray(points, dtype=np.float64),
                                      normals=np.asarray(normals, dtype=np.float64) if self.needs_normals
                                      else "estimate" if self.estimate else None, quality=self.quality)

    def __call__(self, points: np.ndarray, cameras: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        return self.encode(points, normals).query(np.atleast_2d(np.asarray(cameras, dtype=np.float64)))


def neural_method(checkpoint: str | Path | None = None, device: str | None = None,
                  use_normals: bool = False, num_rotations: int = 1, precision: str = "auto",
                  estimate: bool = False, quality: str = "fast") -> NeuralMethod:
    """The neural method from a checkpoint file or the shipped weights.

    Args:
        checkpoint: a ``.safetensors`` file saved by ``VisibilityNetwork.save``;
            None for ``NeuralVisibility.pretrained()``. With ``estimate``, a model that
            takes normals answers the second pass after the shipped default's first.
        device: torch device (default: the API's choice).
        use_normals: give the network the cloud's normals (a model that takes them is needed).
        num_rotations, precision: see ``NeuralVisibility``.
        estimate, quality: see :class:`NeuralMethod`.

    Returns:
        A :class:`NeuralMethod`.

    Raises:
        LookupError: the neural API or the weights are not available, with the reason.
    """
    try:
        from ..neural import NeuralVisibility
    except ImportError as e:
        raise LookupError(f"o3dvis.NeuralVisibility is not available ({e})") from e
    try:
        if checkpoint is None:
            visibility = NeuralVisibility.pretrained(device=device, num_rotations=num_rotations,
                                                     precision=precision)
            identity = "pretrained"
        else:
            from ..nn import VisibilityNetwork

            path = Path(checkpoint)
            if not path.is_file():
                raise FileNotFoundError(f"checkpoint {path} not found")
            digest = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
            network = VisibilityNetwork.load(path)
            if network.config.use_normals and estimate:  # a normals model's second pass, after the shipped first
                shipped = NeuralVisibility.pretrained(device=device, use_normals=False)
                visibility = NeuralVisibility(shipped.network, network, device=device, num_rotations=num_rotations,
                                              precision=precision, scene_network=shipped.scene_network,
                                              small_network=shipped.small_network)
            else:
                visibility = NeuralVisibility(network, device=device, num_rotations=num_rotations,
                                              precision=precision)
            identity = f"{path.name}@{digest}"
    except (FileNotFoundError, ValueError, KeyError, RuntimeError) as e:
        raise LookupError(f"no network weights could be loaded: {e}") from e
    needs = visibility.network.config.use_normals
    if use_normals and not (needs or visibility.normals_network is not None):
        raise LookupError(f"the weights ({identity}) take no normals")
    if needs and not use_normals:
        raise LookupError(f"the weights ({identity}) need normals: use the method neural-normals")
    if estimate and not use_normals and visibility.normals_network is None:
        raise LookupError(f"the weights ({identity}) come with no normals model to estimate normals for")
    return NeuralMethod(visibility, identity, use_normals, estimate, quality)


def resolve_methods(names, checkpoint: str | Path | None = None,
                    sweeps: dict[str, list[float]] | None = None) -> tuple[dict[str, dict[str, Method]], dict[str, str]]:
    """Builds the named methods.

    Args:
        names: method names from :data:`METHOD_NAMES`, or a network's name with
            ``-x<K>`` appended (its mean over ``K`` rotations of each cloud) and/or
            ``-float32`` / ``-bfloat16`` (the dtype of its per-view matrix products).
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
        variant = _NETWORK_VARIANT.fullmatch(name)
        base, turns, precision = ((variant[1], int(variant[2] or 1), variant[3] or "auto") if variant
                                  else (name, 1, "auto"))
        if base not in METHOD_NAMES:
            raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHOD_NAMES)} "
                             f"(a neural one may end in -x<rotations> and -float32 or -bfloat16, "
                             f"e.g. neural-x8, neural-float32)")
        if base.startswith("neural"):
            try:
                methods[name] = {"": neural_method(checkpoint, use_normals=base == "neural-normals",
                                                   num_rotations=turns, precision=precision,
                                                   estimate=base == "neural-estimate",
                                                   quality=_QUALITY_OF.get(base, "fast"))}
            except LookupError as e:
                absent[name] = str(e)
        else:
            methods[name] = sweep(name, (sweeps or {}).get(name))
    return methods, absent
