"""The shipped models, loaded once per process and shared, and the ``model=`` argument."""

from __future__ import annotations

import threading
from pathlib import Path

import torch

from . import models
from .models import available_models, torch_device
from .neural import NeuralVisibility
from .nn.network import VisibilityNetwork

__all__ = ["shared_pretrained", "resolve_model"]

_CACHE: dict[tuple[str, str, str], NeuralVisibility] = {}
_CACHE_LOCK = threading.Lock()


def shared_pretrained(name: str = "default", device: str | torch.device | None = None) -> NeuralVisibility:
    """The shipped model ``name`` on ``device``, loaded once per process and shared by every caller.

    What the functions of o3dvis use when given no model: loading the weights and
    checking their sha256 can take longer than the visibility of a small cloud,
    so it is done once. Thread-safe; the instance is shared, so do not move or change it
    (:meth:`NeuralVisibility.pretrained` gives a private one).

    Args:
        name: a model name of the model card (not a file path).
        device: torch device (default: CPU).

    Returns:
        The shared :class:`NeuralVisibility`, the same object on every call with
        the same name, device and weights folder.

    Raises:
        ValueError: ``name`` is not in the model card (the message lists the available ones).
    """
    key = _cache_key(name, device)
    with _CACHE_LOCK:
        if key not in _CACHE:  # the model card is read only here: a hit costs no file access
            names = available_models()
            if name not in names:
                raise ValueError(f"unknown model {name!r}; available: {', '.join(names) or 'none'}")
            _CACHE[key] = NeuralVisibility.pretrained(name, device)
        return _CACHE[key]


def _cache_key(name: str, device: str | torch.device | None) -> tuple[str, str, str]:
    return str(models.WEIGHTS_DIR), name, str(torch_device(device))


def resolve_model(model, device: torch.device) -> NeuralVisibility:
    """A :class:`NeuralVisibility` from the ``model=`` argument of the functions below."""
    if isinstance(model, NeuralVisibility):
        return model.to(device)
    if isinstance(model, VisibilityNetwork):
        return NeuralVisibility(model, device=device)
    if model is None or isinstance(model, (str, Path)):
        name = "default" if model is None else model
        if isinstance(name, str) and (_cache_key(name, device) in _CACHE or name in available_models()):
            return shared_pretrained(name, device)
        return NeuralVisibility.pretrained(name, device)
    raise TypeError("model must be None, a model name or path, a NeuralVisibility or a "
                    f"VisibilityNetwork, got {type(model).__name__}")
