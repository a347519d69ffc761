"""Visibility sources: what the ``model=`` argument of the applications becomes.

A visibility method is any callable ``method(points (N, 3), cameras (V, 3)) ->
(V, N) bool``. Applications (normals, reconstruction, shadows, renders, best
views) take the source of visibility as ``model=``, the keyword the Open3D
drop-ins take too: ``None`` for the shipped neural network, a model name or
checkpoint path, an ``o3dvis.NeuralVisibility`` or ``VisibilityNetwork``, a
``VisibilityField`` already encoded for the same points, or any visibility
method (:func:`ground_truth_method`, the HPR methods of :mod:`o3dvis.baselines`);
:func:`resolve_method` checks and adapts it. The benchmark's registry of named
methods is :mod:`o3dvis.evaluation.methods`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from .baselines import Method

__all__ = ["resolve_method", "resolve_soft_method", "ground_truth_method"]


def _neural(model):
    """``model`` as a NeuralVisibility or VisibilityField when it names or is a network (None: the
    pretrained one, loaded once per process; a name or path: that model; the benchmark's
    :class:`~o3dvis.evaluation.methods.NeuralMethod` gives its NeuralVisibility), else None."""
    from .field import VisibilityField
    from .models import torch_device
    from .neural import NeuralVisibility
    from .nn.network import VisibilityNetwork
    from .pretrained import resolve_model

    if model is None or isinstance(model, (str, Path, VisibilityNetwork)):
        return resolve_model(model, torch_device(None))
    inner = getattr(model, "visibility", None)
    if isinstance(inner, NeuralVisibility):
        return inner
    return model if isinstance(model, (NeuralVisibility, VisibilityField)) else None


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


def resolve_method(model) -> Method:
    """A checked callable ``(points, cameras, indices=None) -> (V, N) bool`` for ``model``.

    With ``indices``, the answer is for those points only, (V, len(indices));
    the neural network then predicts only them (every point still occludes),
    and it encodes a cloud once for all calls with the same ``points`` array.

    Args:
        model: None (the pretrained neural network), a model name or checkpoint
            path (as ``NeuralVisibility.pretrained`` takes), an ``o3dvis.NeuralVisibility``
            or ``VisibilityNetwork``, an ``o3dvis.VisibilityField`` of the same points,
            or a callable ``(points, cameras) -> (V, N)`` such as :func:`ground_truth_method`
            or ``o3dvis.baselines.hpr_method(k)``; one with a true attribute
            ``takes_indices`` (such as what this returns) is passed ``indices=``.

    Returns:
        The callable; it raises ``ValueError`` when the method's answer has the wrong shape.

    Raises:
        TypeError: ``model`` is none of these.
        ValueError, FileNotFoundError: a model name or path that names no model.
    """
    neural = _neural(model)
    if neural is not None:
        encoded: dict = {}

        def run(points, cameras, indices):
            if encoded.get("points") is not points:
                encoded.update(points=points, field=_field(neural, points))
            return encoded["field"].query(cameras, indices=indices)
    elif getattr(model, "takes_indices", False):
        def run(points, cameras, indices):
            return model(points, cameras, indices=indices)
    elif callable(model):
        def run(points, cameras, indices):
            result = _shape_checked(model(points, cameras), cameras, len(points))
            return result if indices is None else result[:, indices]
    else:
        raise TypeError("model must be None, a model name or path, a NeuralVisibility, a VisibilityNetwork, "
                        "a VisibilityField or a callable (points, cameras) -> (V, N) bool; got "
                        f"{type(model).__name__}")

    def checked(points: np.ndarray, cameras: np.ndarray, indices: np.ndarray | None = None) -> np.ndarray:
        cameras = np.atleast_2d(np.asarray(cameras, dtype=np.float64))
        count = len(points) if indices is None else len(indices)
        return _shape_checked(run(points, cameras, indices), cameras, count).astype(bool, copy=False)

    checked.takes_indices = True
    return checked


def resolve_soft_method(model, points: np.ndarray) -> Callable:
    """A differentiable ``cameras (V, 3) tensor -> (V, N) probabilities`` for ``points``.

    Args:
        model: None (the pretrained network), a model name or checkpoint path, a
            ``NeuralVisibility`` or ``VisibilityNetwork`` (encoded here), a
            ``VisibilityField`` of these points, or a callable mapping a torch
            camera tensor to probabilities.
        points: (N, 3) points.

    Raises:
        TypeError: ``model`` is none of these.
    """
    neural = _neural(model)
    if neural is not None:
        return _field(neural, points).probabilities
    if callable(model):
        return model
    raise TypeError("model must be None, a model name or path, a NeuralVisibility, a VisibilityNetwork, "
                    "a VisibilityField or a callable mapping a camera tensor to visibility probabilities; "
                    f"got {type(model).__name__}")


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
