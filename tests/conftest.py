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


@pytest.fixture(scope="module")
def vis():
    """The shipped model, loaded once per test module, with one intra-op thread (two OpenMP threads
    on two busy cores are many times slower than one)."""
    import torch

    import o3dvis

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield o3dvis.NeuralVisibility.pretrained()
    torch.set_num_threads(threads)
