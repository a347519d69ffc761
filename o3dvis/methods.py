"""Visibility methods: what applications and the bench run on, and how a choice becomes one.

A visibility method is any callable ``method(points (N, 3), cameras (V, 3)) ->
(V, N) bool``. Applications accept one as ``method=``: ``None`` for the shipped
neural network, an ``o3dvis.NeuralVisibility``, a ``VisibilityField`` already
encoded for the same points, or any such callable (:func:`ground_truth_method`,
the HPR methods of :mod:`o3dvis.baselines`); :func:`resolve_method` checks and
adapts it. The bench names its methods instead: :func:`resolve_methods` turns
``hpr``, ``hpr-exp``, ``neural`` and ``neural-normals`` into parameter sweeps
``{label: method}`` (a network method with ``needs_normals = True`` also takes
``normals=``; ``neural-x8`` and ``neural-normals-x8`` average the network over
8 rotations of each cloud, see ``NeuralVisibility(num_rotations=...)``, and a
``-float32`` or ``-bfloat16`` ending fixes the dtype of its per-view matrix
products, see ``NeuralVisibility(precision=...)``); a
method that cannot be built here (no network code, no weights) is returned as
absent with the reason, never replaced by something else.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .baselines import SWEEPS, Method, sweep

__all__ = ["resolve_method", "resolve_soft_method", "ground_truth_method", "NeuralMethod",
           "neural_method", "resolve_methods", "METHOD_NAMES"]

METHOD_NAMES = (*SWEEPS, "neural", "neural-normals")
_NETWORK_VARIANT = re.compile(r"(neural(?:-normals)?)(?:-x([1-9][0-9]*))?(?:-(float32|bfloat16))?")


def _neural(method):
    """``method`` as a NeuralVisibility or VisibilityField when it is one (None: the pretrained
    network, loaded once per process; a :class:`NeuralMethod` gives its NeuralVisibility), else None."""
    from .field import VisibilityField
    from .neural import NeuralVisibility
    from .pretrained import shared_pretrained

    if method is None:
        return shared_pretrained()
    inner = getattr(method, "visibility", None)
    if isinstance(inner, NeuralVisibility):
        return inner
    return method if isinstance(method, (NeuralVisibility, VisibilityField)) else None


def _field(neural, points: np.ndarray):
    """The VisibilityField of ``points``: encoded here, or checked to hold as many points."""
    if not hasattr(neural, "encode"):
        if neural.num_points != len(points):
            raise ValueError(f"the VisibilityField holds {neural.num_points} points, the cloud "
                             f"{len(points)}: encode this cloud")
        return neural
    return neural.encode(points)


def _shape_checked(result, cameras: np.ndarray, count: int) -> np.ndarray:
    """``result`` as an array, ValueError unless it is (cameras, count)."""
    result = np.asarray(result)
    if result.shape != (len(cameras), count):
        raise ValueError(f"the visibility method returned shape {result.shape}, expected "
                         f"({len(cameras)}, {count}) for {len(cameras)} cameras and "
                         f"{count} points")
    return result


def resolve_method(method) -> Method:
    """A checked callable ``(points, cameras, indices=None) -> (V, N) bool`` for ``method``.

    With ``indices``, the answer is for those points only, (V, len(indices));
    the neural network then predicts only them (every point still occludes),
    and it encodes a cloud once for all calls with the same ``points`` array.

    Args:
        method: None (the pretrained neural network), an ``o3dvis.NeuralVisibility``,
            an ``o3dvis.VisibilityField`` of the same points, or a callable
            ``(points, cameras) -> (V, N)`` such as :func:`ground_truth_method`
            or ``o3dvis.baselines.hpr_method(k)``; one with a true attribute
            ``takes_indices`` (such as what this returns) is passed ``indices=``.

    Returns:
        The callable; it raises ``ValueError`` when the method's answer has the wrong shape.
    """
    neural = _neural(method)
    if neural is not None:
        encoded: dict = {}

        def run(points, cameras, indices):
            if encoded.get("points") is not points:
                encoded.update(points=points, field=_field(neural, points))
            return encoded["field"].query(cameras, indices=indices)
    elif getattr(method, "takes_indices", False):
        def run(points, cameras, indices):
            return method(points, cameras, indices=indices)
    elif callable(method):
        def run(points, cameras, indices):
            result = _shape_checked(method(points, cameras), cameras, len(points))
            return result if indices is None else result[:, indices]
    else:
        raise TypeError("method must be None, a NeuralVisibility, a VisibilityField or a callable "
                        f"(points, cameras) -> (V, N) bool; got {type(method).__name__}")

    def checked(points: np.ndarray, cameras: np.ndarray, indices: np.ndarray | None = None) -> np.ndarray:
        cameras = np.atleast_2d(np.asarray(cameras, dtype=np.float64))
        count = len(points) if indices is None else len(indices)
        return _shape_checked(run(points, cameras, indices), cameras, count).astype(bool, copy=False)

    checked.takes_indices = True
    return checked


def resolve_soft_method(method, points: np.ndarray) -> Callable:
    """A differentiable ``cameras (V, 3) tensor -> (V, N) probabilities`` for ``points``.

    Args:
        method: None (the pretrained network), a ``NeuralVisibility`` (encoded
            here), a ``VisibilityField`` of these points, or a callable mapping a
            torch camera tensor to probabilities.
        points: (N, 3) points.
    """
    neural = _neural(method)
    if neural is not None:
        return _field(neural, points).probabilities
    if callable(method):
        return method
    raise TypeError("method must be None, a NeuralVisibility, a VisibilityField or a callable "
                    f"mapping a camera tensor to visibility probabilities; got {type(method).__name__}")


def ground_truth_method(mesh) -> Method:
    """Exact visibility by ray casting against ``mesh`` (points must lie on its surface).

    Args:
        mesh: ``o3d.geometry.TriangleMesh`` (legacy or tensor) or ``(vertices, triangles)``.

    Returns:
        A visibility method.
    """
    from .groundtruth import as_legacy_mesh, visibility_from_mesh

    mesh = as_legacy_mesh(mesh)
    return lambda points, cameras: visibility_from_mesh(mesh, points, cameras)


class NeuralMethod:
    """The network as a visibility method: one U-Net pass per cloud (and rotation), then all views.

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
        turns, precision = len(visibility.rotations), visibility.precision
        self.__name__ = (f"neural({identity}{', normals' if use_normals else ''}"
                         f"{f', {turns} rotations' if turns > 1 else ''}"
                         f"{f', {precision}' if precision != 'auto' else ''})")

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
                  use_normals: bool = False, num_rotations: int = 1, precision: str = "auto") -> NeuralMethod:
    """The neural method from a checkpoint file or the shipped weights.

    Args:
        checkpoint: a ``.safetensors`` file saved by ``VisibilityNetwork.save``;
            None for ``NeuralVisibility.pretrained()``.
        device: torch device (default: the API's choice).
        use_normals: give the network the cloud's normals (a model that takes them is needed).
        num_rotations, precision: see ``NeuralVisibility``.

    Returns:
        A :class:`NeuralMethod`.

    Raises:
        LookupError: the neural API or the weights are not available, with the reason.
    """
    try:
        from .neural import NeuralVisibility
    except ImportError as e:
        raise LookupError(f"o3dvis.NeuralVisibility is not available ({e})") from e
    try:
        if checkpoint is None:
            visibility = NeuralVisibility.pretrained(device=device, num_rotations=num_rotations,
                                                     precision=precision)
            identity = "pretrained"
        else:
            from .nn import VisibilityNetwork

            path = Path(checkpoint)
            if not path.is_file():
                raise FileNotFoundError(f"checkpoint {path} not found")
            digest = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
            visibility = NeuralVisibility(VisibilityNetwork.load(path), device=device,
                                          num_rotations=num_rotations, precision=precision)
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
                                                   num_rotations=turns, precision=precision)}
            except LookupError as e:
                absent[name] = str(e)
        else:
            methods[name] = sweep(name, (sweeps or {}).get(name))
    return methods, absent
