"""The drop-ins' memory of the last cloud they encoded, for callers that loop over cameras.

Open3D users call ``hidden_point_removal`` once per camera with the same cloud; the
drop-ins (:mod:`o3dvis.dropins`) then run the U-Net once and each further camera
costs a query only. An encoding is reused when the same cloud object is asked
again, with the same model, unchanged (its settings, rotations and networks, none put in anew or
taken out, and the weights of the networks the encoding came from, changed in place or put in anew
by no one, an optimiser included; see :mod:`o3dvis.nn.state` for changes made through ``.data``),
the same ``normals`` choice and ``quality``,
and its points (and normals) still equal, value for value, to those encoded: a
cloud changed in place, or a new cloud at the address of a freed one, is encoded
anew. With a scene network, a camera inside the cloud's bounding box and one
outside it are answered by different networks: which side the camera is on is
part of what is kept. A crop (``max_range``) is encoded on every call. One
encoding is kept (of at most :data:`MAX_POINTS` points), with a copy of its
points; :func:`clear` frees it.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from .clouds import cloud_arrays

if TYPE_CHECKING:  # type hints only: o3dvis.neural and o3dvis.field stay unloaded until used
    from .cameras import Views
    from .field import VisibilityField
    from .neural import NeuralVisibility
    from .nn.network import VisibilityNetwork

__all__ = ["MAX_POINTS", "encode", "clear"]

MAX_POINTS = 1 << 20
"""Larger clouds are not kept: their encoding would hold hundreds of MB after the call."""


class _Entry(NamedTuple):
    cloud: int  # id() of the cloud object
    model: "NeuralVisibility"  # held, so that no other model takes its id
    settings: tuple
    inside: bool  # with a scene network, whether the camera it was made for is inside the cloud's box
    networks: list["VisibilityNetwork"]  # those of the model that the encoding depends on
    weights: list[list]  # their weights then (VisibilityNetwork.weights_state)
    points: Tensor  # copies of what was encoded
    normals: Tensor | None
    field: "VisibilityField"


_last: _Entry | None = None
_lock = threading.Lock()


def _settings(model: "NeuralVisibility", normals, quality: str) -> tuple:
    """What an encoding depends on besides the cloud and the networks' weights: the normals choice
    and quality, the networks the model holds now (compared by identity: which of them a cloud is
    routed to follows from them) and its rotations, value for value."""
    held = (model.network, model.normals_network, model.scene_network, model.small_network)
    rotations = tuple(model.rotations.flatten().tolist())
    return normals, quality, str(model.device), model.precision, model.chunk_size, held, rotations


def _inside(model: "NeuralVisibility", field: "VisibilityField", views: "Views") -> bool:
    """Whether a scene network answers ``views`` from inside the bounding box of ``field``'s cloud
    (its frame has the box): with one, the encoding made for a camera inside is the scene model's."""
    return (model.scene_network is not None and views.positions is not None
            and bool(field.frame.contains(views.positions).all()))


def _same(a: Tensor | None, b: Tensor | None) -> bool:
    return (a is None) == (b is None) and (a is None or (a.shape == b.shape and bool(torch.equal(a, b))))


def _holds(entry: _Entry | None, model: "NeuralVisibility", pcd, settings: tuple, points: Tensor,
           normals: Tensor | None, views: "Views") -> bool:
    """Whether ``entry`` is the encoding of this cloud, as it is now, by ``model`` as it is now, for
    ``views`` on the same side of the cloud's bounding box."""
    return (entry is not None and entry.cloud == id(pcd) and entry.model is model and entry.settings == settings
            and all(net.weights_unchanged(weights) for net, weights in zip(entry.networks, entry.weights))
            and _same(entry.points, points) and _same(entry.normals, normals)
            and entry.inside == _inside(model, entry.field, views))


def encode(model: "NeuralVisibility", pcd, normals, views: "Views", quality: str = "fast") -> "VisibilityField":
    """The field the drop-ins query for one view: the one kept from the last call when it holds.

    Args:
        model: the network to encode with.
        pcd: a cloud, as :meth:`NeuralVisibility.encode` takes it.
        normals: None, True, False or ``"estimate"`` are kept with the encoding; explicit
            normals (an array) are encoded every time.
        views: the view to come (:class:`~o3dvis.cameras.Views`): with a scene network, a
            camera inside the cloud's bounding box gets the scene model's field.
        quality: as :meth:`NeuralVisibility.encode` takes it, kept with the encoding.

    Returns:
        The cloud's :class:`VisibilityField` (the kept one is shared: do not change it).

    Raises:
        As :meth:`NeuralVisibility.encode`.
    """
    global _last
    if normals is not None and not isinstance(normals, (bool, str)):
        return model.encode(pcd, normals, views=views, quality=quality)
    cloud = cloud_arrays(pcd)
    settings = _settings(model, normals, quality)
    with _lock:
        last = _last
    if _holds(last, model, pcd, settings, *cloud, views):
        return last.field
    field = model.encode(cloud, normals, views=views, quality=quality)
    if len(cloud.points) <= MAX_POINTS:
        networks = list(field.encoders)
        entry = _Entry(id(pcd), model, settings, _inside(model, field, views), networks,
                       [net.weights_state() for net in networks], cloud.points.clone(),
                       None if cloud.normals is None else cloud.normals.clone(), field)
        with _lock:
            _last = entry
    return field


def clear() -> None:
    """Forgets the kept encoding (and frees its memory)."""
    global _last
    with _lock:
        _last = None
