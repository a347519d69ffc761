"""matplotlib, an optional dependency (the ``demo`` extra): only the demo's figure and the
loss plot of ``o3dvis best-view --plot`` draw with it."""

from __future__ import annotations

__all__ = ["figure_class"]


def figure_class(purpose: str) -> type:
    """matplotlib's ``Figure``, which draws and saves with no display and leaves pyplot's
    backend alone.

    Args:
        purpose: what needs it, for the error.

    Raises:
        ImportError: where matplotlib is not installed, naming the extra that installs it.
    """
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise ImportError(f"{purpose} needs matplotlib; install it with: pip install 'o3dvis[demo]'") from None
    return Figure
