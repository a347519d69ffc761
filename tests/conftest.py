import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MPLBACKEND", "Agg")

import pytest  # noqa: E402


@pytest.fixture
def torch_ops(monkeypatch):
    """Queries run their per-view steps as torch ops, not the C kernels of o3dvis.nn.native."""
    from o3dvis.nn import native

    monkeypatch.setattr(native, "usable", lambda *tensors: False)
