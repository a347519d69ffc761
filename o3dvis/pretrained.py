"""The ``model=`` argument of the drop-ins and applications, made a :class:`NeuralVisibility`.

A name or path gives :meth:`NeuralVisibility.pretrained`, whose networks are loaded once per
process; the same model object is handed out while those networks stay the ones loaded, so that
the drop-ins' kept encoding (:mod:`o3dvis.encodings`) holds across calls.
"""

from __future__ import annotations

import threading
from pathlib import Path

import torch

from .models import is_shared
from .neural import NeuralVisibility
from .nn.network import VisibilityNetwork

__all__ = ["resolve_model"]

_HELD: dict[tuple, NeuralVisibility] = {}  # by the networks it holds and its device
_LOCK = threading.Lock()


def resolve_model(model, device: torch.device) -> NeuralVisibility:
    """A :class:`NeuralVisibility` from the ``model=`` argument.

    Args:
        model: None (the shipped default), a model name or checkpoint path, a
            :class:`NeuralVisibility` (moved to ``device``) or a ``VisibilityNetwork``.
        device: the torch device to answer on.

    Returns:
        The model; for None, a name or a path, the same object on every call while its files
        are unchanged (shared: do not change it).

    Raises:
        TypeError: ``model`` is none of these.
        FileNotFoundError, ValueError: as :meth:`NeuralVisibility.pretrained`.
    """
    if isinstance(model, NeuralVisibility):
        return model.to(device)
    if isinstance(model, VisibilityNetwork):
        return NeuralVisibility(model, device=device)
    if model is None or isinstance(model, (str, Path)):
        fresh = NeuralVisibility.pretrained("default" if model is None else model, device)
        key = tuple(id(net) for net in fresh.networks()), str(fresh.device)
        with _LOCK:
            held = _HELD.get(key)
            if held is None or any(a is not b for a, b in zip(held.networks(), fresh.networks())):
                for stale in [k for k, m in _HELD.items() if not all(map(is_shared, m.networks()))]:
                    del _HELD[stale]  # its networks were loaded anew: its files changed, or it did
                held = _HELD[key] = fresh
            return held
    raise TypeError("model must be None, a model name or path, a NeuralVisibility or a "
                    f"VisibilityNetwork, got {type(model).__name__}")
