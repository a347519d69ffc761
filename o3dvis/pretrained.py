"""The shipped models and checkpoints given by path, loaded once per process and shared, and the
``model=`` argument."""

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
_FILES: dict[tuple[str, str], tuple[tuple, NeuralVisibility]] = {}  # (path, device): (files' stats, model)


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
        return _shared_file(name, device)
    raise TypeError("model must be None, a model name or path, a NeuralVisibility or a "
                    f"VisibilityNetwork, got {type(model).__name__}")


def _stats(path: Path) -> tuple:
    """What tells a file written anew: its inode, size and times (None for a missing file)."""
    try:
        stat = path.stat()
    except OSError:
        return (None,)
    return stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns


def _shared_file(path: str | Path, device: torch.device) -> NeuralVisibility:
    """The model of the checkpoint at ``path`` on ``device``, loaded (and its sha256 checked) once per
    process and shared while neither the file nor the model card next to it (which may list its
    sha256) is written anew, so that the drop-ins' kept encoding (:mod:`o3dvis.encodings`) holds
    across calls.

    Raises:
        As :meth:`NeuralVisibility.pretrained`.
    """
    resolved = Path(path).resolve()
    if not resolved.is_file():
        return NeuralVisibility.pretrained(path, device)  # its error names what is missing
    key = str(resolved), str(torch_device(device))
    stats = _stats(resolved) + _stats(resolved.parent / models.CARD_NAME)
    with _CACHE_LOCK:
        kept = _FILES.get(key)
        if kept is None or kept[0] != stats:
            _FILES[key] = stats, NeuralVisibility.pretrained(path, device)
        return _FILES[key][1]
