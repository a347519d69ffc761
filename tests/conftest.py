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


def _signed_areas(xy: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The signed area of each triangle (positive: counter-clockwise)."""
    a, b, c = (xy[triangles[:, i]] for i in range(3))
    return ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]) / 2


def _check_triangulation(xy: np.ndarray, triangles: np.ndarray) -> None:
    """Counter-clockwise, no overlap or gap (the areas sum to the hull's), every distinct point a
    corner, and no point strictly inside a triangle's circumcircle (exact: integer coordinates)."""
    from scipy.spatial import ConvexHull

    distinct = np.unique(xy, axis=0)
    areas = _signed_areas(xy, triangles)
    assert (areas > 0).all()
    assert areas.sum() == pytest.approx(ConvexHull(distinct).volume, rel=1e-12)
    assert len(np.unique(xy[np.unique(triangles)], axis=0)) == len(distinct)
    p = xy.astype(np.int64)
    d = p[None, :, :] - p[triangles][:, :, None, :]  # (T, 3, N, 2): each corner minus each point
    lift = (d ** 2).sum(-1)
    cross = lambda i, j: d[:, i, :, 0] * d[:, j, :, 1] - d[:, j, :, 0] * d[:, i, :, 1]  # noqa: E731
    in_circle = lift[:, 0] * cross(1, 2) - lift[:, 1] * cross(0, 2) + lift[:, 2] * cross(0, 1)
    assert (in_circle <= 0).all()


def lzf_literal(data: bytes) -> bytes:
    """``data`` LZF-compressed as runs of literal bytes only, after the two sizes a compressed PCD puts
    before its data (any LZF reader decompresses it)."""
    runs = b"".join(bytes([len(data[i:i + 32]) - 1]) + data[i:i + 32] for i in range(0, len(data), 32))
    return np.array([len(runs), len(data)], dtype="<u4").tobytes() + runs
