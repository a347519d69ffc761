import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402


def box_surface(lo, hi, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points uniform on the six faces of the box [lo, hi] (rooms for the tests of
    cameras inside a cloud)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    areas = np.repeat([size[1] * size[2], size[0] * size[2], size[0] * size[1]], 2)
    face = rng.choice(6, size=count, p=areas / areas.sum())
    points = lo + rng.random((count, 3)) * size
    axis = face // 2
    points[np.arange(count), axis] = np.where(face % 2 == 0, lo[axis], hi[axis])
    return points


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


def lzf_literal(data: bytes) -> bytes:
    """``data`` LZF-compressed as runs of literal bytes only, after the two sizes a compressed PCD puts
    before its data (any LZF reader decompresses it)."""
    runs = b"".join(bytes([len(data[i:i + 32]) - 1]) + data[i:i + 32] for i in range(0, len(data), 32))
    return np.array([len(runs), len(data)], dtype="<u4").tobytes() + runs
