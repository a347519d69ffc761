"""Open3D where it is installed.

Clouds and cameras arrive as Open3D's types, but the torch core under them, and training, also run
where Open3D is not installed (a GPU machine that trains, given arrays): the modules that take
Open3D's types ask through here instead of importing it.
"""

from __future__ import annotations

import functools
import importlib
from types import ModuleType

__all__ = ["open3d_or_none", "require_open3d", "is_open3d"]


@functools.cache
def open3d_or_none() -> ModuleType | None:
    """The ``open3d`` module, or None where it is not installed."""
    try:
        return importlib.import_module("open3d")
    except ImportError:
        return None


def require_open3d(purpose: str) -> ModuleType:
    """The ``open3d`` module.

    Args:
        purpose: what needs it, for the error.

    Raises:
        ImportError: where Open3D is not installed.
    """
    o3d = open3d_or_none()
    if o3d is None:
        raise ImportError(f"{purpose} needs Open3D; install it with: pip install open3d")
    return o3d


def is_open3d(value, *names: str) -> bool:
    """Whether ``value`` is an instance of one of Open3D's types, named by their paths in the module
    (``"geometry.PointCloud"``, ``"core.Tensor"``); False where Open3D is not installed.
    """
    o3d = open3d_or_none()
    if o3d is None:
        return False
    return isinstance(value, tuple(functools.reduce(getattr, name.split("."), o3d) for name in names))
