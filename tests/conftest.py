"""What several test modules share: the shipped model and a small random one, Open3D's HPR example
cloud and cameras around it, shapes for the applications and the rooms, the data of the bad-input tests.

Open3D is imported inside the helpers that need it: tests/test_gpu_machine.py runs where it is not
installed.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from o3dvis.geometry import fibonacci_sphere  # noqa: E402


# ---------------------------------------------------------------- models

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


SMALL = dict(depth=5, full_depth=2, channels=(8, 16), feature_channels=8, num_frequencies=2, hidden=(16,))
"""A small network's configuration: the API's semantics at a fraction of the shipped model's cost."""


@pytest.fixture(scope="module")
def network():
    """A network of the ``SMALL`` configuration and random weights, in eval mode."""
    import torch

    from o3dvis.nn import NetworkConfig, VisibilityNetwork

    torch.manual_seed(0)
    return VisibilityNetwork(NetworkConfig(**SMALL)).eval()


@pytest.fixture(scope="module")
def small_vis(network):
    """``network`` as a model; a module whose tests take it as ``vis`` overrides ``vis`` with it."""
    import o3dvis

    return o3dvis.NeuralVisibility(network)


# ---------------------------------------------------------------- Open3D's HPR example and cameras

@pytest.fixture(scope="module")
def pcd():
    """Open3D's HPR example on a procedural shape: 3 000 Poisson-disk samples."""
    import open3d as o3d

    from o3dvis.training.data import random_shape

    mesh = random_shape(np.random.default_rng(3), parts=3)
    o3d.utility.random.seed(1)
    cloud = mesh.sample_points_poisson_disk(3000)
    cloud.colors = o3d.utility.Vector3dVector(np.random.default_rng(0).random((3000, 3)))
    return cloud


@pytest.fixture(scope="module")
def points(pcd) -> np.ndarray:
    """The points of ``pcd``."""
    return np.asarray(pcd.points).copy()


def _camera(points: np.ndarray, direction=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A camera outside the cloud at one bounding-box diagonal from its centre."""
    center = (points.min(0) + points.max(0)) / 2
    diag = np.linalg.norm(points.max(0) - points.min(0))
    return center + diag * np.asarray(direction) / np.linalg.norm(direction)


def _median_threshold(vis, cloud, camera) -> float:
    """A threshold that splits the points into visible and hidden halves."""
    return float(vis.encode(cloud).probabilities(camera).median())


def _look_at(eye, target) -> np.ndarray:
    """The extrinsic of a camera at ``eye`` looking at ``target`` (Open3D's: x right, y down, z ahead)."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0] if abs(forward[1]) < 0.9 else [1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    extrinsic = np.eye(4)
    extrinsic[:3, :3], extrinsic[:3, 3] = rotation, -rotation @ eye
    return extrinsic


def _pinhole(eye, target, width=-1, height=-1, focal=50.0):
    """Open3D pinhole camera parameters of a camera at ``eye`` looking at ``target``."""
    import open3d as o3d

    params = o3d.camera.PinholeCameraParameters()
    params.extrinsic = _look_at(np.asarray(eye, float), np.asarray(target, float))
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, focal, focal,
                                                         (width - 1) / 2, (height - 1) / 2)
    return params


# ---------------------------------------------------------------- shapes

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


def _sample(mesh, count: int, seed: int = 0):
    """Points uniform on a mesh, their face normals, and the ground-truth method of the mesh."""
    from o3dvis.apps import ground_truth_method
    from o3dvis.training.data.sample import sample_surface

    points, normals = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.triangles), count,
                                     np.random.default_rng(seed))
    return points, normals, ground_truth_method(mesh)


def _cloud(points, colors=None):
    """A legacy Open3D cloud of the points, with their colours where given."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(colors)
    return pcd


@pytest.fixture(scope="module")
def sphere():
    """4 000 points of the unit sphere's mesh, their normals and its ground-truth method (``_sample``)."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60)
    return _sample(mesh, 4000)


def _box(size, center):
    """The mesh of a box of ``size`` centred on ``center``."""
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(*size)
    return box.translate(np.asarray(center, float) - np.asarray(size, float) / 2)


def _sphere(count: int, seed: int = 0) -> np.ndarray:
    """``count`` random points on the unit sphere."""
    points = np.random.default_rng(seed).normal(size=(count, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def _sphere_with_bump(n=3000, seed=0):
    """``n`` random points on the unit sphere, 30 % further out where x > 0.7 (a float32 tensor)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    p = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    return p * (1 + 0.3 * (p[:, :1] > 0.7))


# ---------------------------------------------------------------- plane triangulations

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


# ---------------------------------------------------------------- bad input and files

SPHERE = fibonacci_sphere(160)


def as_cloud(points):
    """A float64 (N, 3) array as a legacy PointCloud, a float32 one as a tensor PointCloud, else as is."""
    import open3d as o3d

    if isinstance(points, np.ndarray) and points.ndim == 2 and points.shape[1] == 3:
        if points.dtype == np.float64:
            return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        if points.dtype == np.float32:
            return o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    return points


def lzf_literal(data: bytes) -> bytes:
    """``data`` LZF-compressed as runs of literal bytes only, after the two sizes a compressed PCD puts
    before its data (any LZF reader decompresses it)."""
    runs = b"".join(bytes([len(data[i:i + 32]) - 1]) + data[i:i + 32] for i in range(0, len(data), 32))
    return np.array([len(runs), len(data)], dtype="<u4").tobytes() + runs
