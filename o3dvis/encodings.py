"""The drop-ins' memory of the last cloud they encoded, for callers that loop over cameras.

Open3D users call ``hidden_point_removal`` once per camera with the same cloud; the
drop-ins (:mod:`o3dvis.dropins`) then run the U-Net once and each further camera
costs a query only. An encoding is reused when the same cloud object is asked
again, with the same model, unchanged (its settings, and the weights of the networks the encoding
came from, changed in place or put in anew by no one, an optimiser included), the same ``normals`` choice,
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
import weakref
from typing import TYPE_CHECKING, NamedTuple

import torch
from torch import Tensor

from .clouds import cloud_arrays
from .field import inside_box
from .nn.octree import bounding_box

if TYPE_CHECKING:  # type hints only: o3dvis.neural and o3dvis.field stay unloaded until used
    from .field import VisibilityField
    from .neural import NeuralVisibility

__all__ = ["MAX_POINTS", "encode", "clear"]

MAX_POINTS = 1 << 20
"""Larger clouds are not kept: their encoding would hold hundreds of MB after the call."""


class _Entry(NamedTuple):
    cloud: int  # id() of the cloud object
    model: "NeuralVisibility"  # held, so that no other model takes its id
    settings: tuple
    networks: list[torch.nn.Module]  # those of the model that the encoding depends on
    tensors: list[tuple[Tensor, int, int]]  # each tensor of those networks, its version and address then
    points: Tensor  # copies of what was encoded
    normals: Tensor | None
    field: "VisibilityField"


_last: _Entry | None = None
_lock = threading.Lock()


def _settings(model: "NeuralVisibility", normals, points: Tensor, camera: Tensor | None) -> tuple:
    """What an encoding depends on besides the cloud and the networks' weights: with a scene
    network, whether the camera is inside the cloud's bounding box too."""
    inside = (model.scene_network is not None and camera is not None
              and bool(inside_box(camera.detach().to(points)[None], bounding_box(points))[0]))
    return normals, str(model.device), model.precision, model.chunk_size, len(model.rotations), inside


def _networks(model: "NeuralVisibility", field: "VisibilityField", normals, count: int) -> list[torch.nn.Module]:
    """The networks of ``model`` that an encoding of ``count`` points depends on: the one that
    encoded it, the scene network that answers its cameras inside the box, and with estimated
    normals the first pass's."""
    networks = [field.network, model.scene_network, model._points_network(count) if normals == "estimate" else None]
    return [net for i, net in enumerate(networks) if net is not None and all(net is not n for n in networks[:i])]


def _tensors(networks: list[torch.nn.Module]) -> list[tuple[Tensor, int, int]]:
    """Each parameter and buffer of ``networks``, with its version (bumped by every in-place change,
    an optimiser's step included) and its storage's address."""
    return [(t, t._version, t.data_ptr()) for net in networks for table in _tables(net)
            for t in table.values() if t is not None]


_TREES: "weakref.WeakKeyDictionary[torch.nn.Module, tuple[list, list]]" = weakref.WeakKeyDictionary()


def _tables(net: torch.nn.Module) -> list[dict]:
    """The parameter and buffer tables of every module of ``net``: kept per network with its tree of
    modules, and walked anew when a module has been put in or taken out (walking a network's
    modules took a fifth of a small cloud's drop-in call)."""
    kept = _TREES.get(net)
    if kept is None or any(tuple(children.values()) != before for children, before in kept[0]):
        modules = list(net.modules())
        kept = ([(m._modules, tuple(m._modules.values())) for m in modules],
                [table for m in modules for table in (m._parameters, m._buffers)])
        _TREES[net] = kept
    return kept[1]


def _same(a: Tensor | None, b: Tensor | None) -> bool:
    return (a is None) == (b is None) and (a is None or (a.shape == b.shape and bool(torch.equal(a, b))))


def _holds(entry: _Entry | None, model: "NeuralVisibility", pcd, settings: tuple, points: Tensor,
           normals: Tensor | None) -> bool:
    """Whether ``entry`` is the encoding of this cloud, as it is now, by ``model`` as it is now."""
    return (entry is not None and entry.cloud == id(pcd) and entry.model is model and entry.settings == settings
            and _same_tensors(entry.tensors, _tensors(entry.networks))
            and _same(entry.points, points) and _same(entry.normals, normals))


def _same_tensors(kept: list[tuple[Tensor, int, int]], now: list[tuple[Tensor, int, int]]) -> bool:
    """Whether the networks hold the same tensors as when ``kept`` was taken, unchanged since."""
    return len(kept) == len(now) and all(a is b and version == now_version and address == now_address
                                         for (a, version, address), (b, now_version, now_address) in zip(kept, now))


def encode(model: "NeuralVisibility", pcd, normals=None, camera: Tensor | None = None) -> "VisibilityField":
    """The field the drop-ins query for one view: the one kept from the last call when it holds.

    Args:
        model: the network to encode with.
        pcd: a cloud, as :meth:`NeuralVisibility.encode` takes it.
        normals: None, True or False are kept with the encoding; explicit normals
            (an array) are encoded every time.
        camera: the (3,) camera of the view to come, or None (a direction): with
            a scene network, a camera inside the cloud's bounding box gets the
            scene model's field.

    Returns:
        The cloud's :class:`VisibilityField` (the kept one is shared: do not change it).

    Raises:
        As :meth:`NeuralVisibility.encode`.
    """
    global _last
    if normals is not None and not isinstance(normals, bool):
        return model._encode(pcd, normals, camera)
    points, cloud_normals = cloud_arrays(pcd)
    settings = _settings(model, normals, points, camera)
    with _lock:
        last = _last
    if _holds(last, model, pcd, settings, points, cloud_normals):
        return last.field
    field = model._encode(pcd, normals, camera, (points, cloud_normals))
    if len(points) <= MAX_POINTS:
        networks = _networks(model, field, normals, len(points))
        entry = _Entry(id(pcd), model, settings, networks, _tensors(networks), points.clone(),
                       None if cloud_normals is None else cloud_normals.clone(), field)
        with _lock:
            _last = entry
    return field


def clear() -> None:
    """Forgets the kept encoding (and frees its memory)."""
    global _last
    with _lock:
        _last = None
