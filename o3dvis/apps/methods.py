"""The visibility method an application runs on: neural (default), HPR, ground truth, any callable.

A visibility method maps points (N, 3) and cameras (V, 3) to a (V, N) bool
array. Applications accept one as ``method=``: ``None`` for the shipped neural
network, an ``o3dvis.NeuralVisibility``, a ``VisibilityField`` already encoded
for the same points, or any such callable (:func:`ground_truth_method`, the
HPR methods of :mod:`o3dvis.baselines`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["VisibilityMethod", "resolve_method", "resolve_soft_method", "ground_truth_method"]

VisibilityMethod = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _neural(method):
    """``method`` as a NeuralVisibility or VisibilityField when it is one (None: the pretrained
    network; an ``o3dvis.methods.NeuralMethod`` gives its NeuralVisibility), else None."""
    from ..visibility import NeuralVisibility, VisibilityField

    if method is None:
        return NeuralVisibility.pretrained()
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


def resolve_method(method) -> VisibilityMethod:
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


def ground_truth_method(mesh) -> VisibilityMethod:
    """Exact visibility by ray casting against ``mesh`` (points must lie on its surface).

    Args:
        mesh: ``o3d.geometry.TriangleMesh`` (legacy or tensor) or ``(vertices, triangles)``.

    Returns:
        A visibility method.
    """
    from ..data.groundtruth import as_legacy_mesh, visibility_from_mesh

    mesh = as_legacy_mesh(mesh)
    return lambda points, cameras: visibility_from_mesh(mesh, points, cameras)
