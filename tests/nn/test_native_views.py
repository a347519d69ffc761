"""The per-view kernels (projection, margins, threads) against the torch ops, and how the package
loads its C libraries."""

import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis import clib
from o3dvis.nn import native
from o3dvis.nn.cues import point_surfels

from .conftest import _CAMERA, _points, _views, needs_kernels


@needs_kernels
def test_projection_rejects_what_the_kernel_cannot_take():
    points = _points(500)
    with torch.inference_mode():
        with pytest.raises(ValueError, match="need points"):
            native.project(torch.empty(0, 3), _CAMERA, None, [4])
        with pytest.raises(ValueError, match="camera must be"):
            native.project(points, _CAMERA.double(), None, [4])


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("config", [{}, {"use_normals": True}, {"num_frequencies": 2, "hidden": (24, 40, 17)},
                                    {"footprints": True}])
@pytest.mark.parametrize("rows", [slice(None), slice(1000, 4321), "indices", "five"])
def test_view_margin_equals_the_torch_one(config, rows, dtype, variant):
    """One pass of C for a view's margins against the torch reference on the same view: the
    embedding times the features and the cues (a few float32 ulps apart), then the products in
    ``dtype``, summed in another order (inputs and hidden widths that fit no register padded
    with zero weights)."""
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    if not native.has_view_margin(dtype):
        pytest.skip(f"no fused {dtype} kernel in the {variant} variant")
    torch.manual_seed(0)
    network = VisibilityNetwork(NetworkConfig(channels=(8, 8), **config)).eval()
    points = _points()
    normals = torch.nn.functional.normalize(points, dim=1) if config.get("use_normals") else None
    if rows == "indices":
        rows = torch.randperm(len(points), generator=torch.Generator().manual_seed(1))[:2500]
    elif rows == "five":  # less than a register of points, one of them twice
        rows = torch.tensor([3, 1, 4, 1, 5])
    surfels = point_surfels(points) if config.get("footprints") else None
    fast, _ = _views(points, camera=_CAMERA, surfels=surfels)
    predictor = network.predictor
    projected = torch.randn(predictor.embedding.dim, len(points)).T  # channels first, as encode() stores it
    n = len(points[rows])
    with torch.inference_mode():
        margin = network.view_margin([fast], rows, projected, normals, dtype)[0]
        dirs, cues = network.view_inputs(fast, rows, normals)  # torch ops on the view's depth buffers
        expected = predictor.margin(projected[rows], dirs, cues, dtype)
    assert margin.shape == (n,) and margin.dtype == torch.float32
    scale = expected.abs().max()
    if dtype == torch.float32:
        torch.testing.assert_close(margin, expected, atol=1e-5 * scale, rtol=1e-5)
    else:  # both round each layer's output to bfloat16; a sum in another order may round the other way
        assert (margin == expected).float().mean() > 0.95
        torch.testing.assert_close(margin, expected, atol=0.02 * scale, rtol=0)
    assert ((margin > 0) == (expected > 0)).float().mean() > 0.998


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.parametrize("rows", [slice(None), slice(700, 3100), "indices"])
def test_view_margin_reads_features_stored_per_leaf(rows, dtype):
    """Features stored per leaf (as encode_leaves keeps them), carried to each point in the
    kernel: the margins of the same features carried to every point first."""
    from o3dvis.nn.features import LeafFeatures
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    if not native.has_view_margin(dtype):
        pytest.skip(f"no fused {dtype} kernel here")
    g = torch.Generator().manual_seed(2)
    network = VisibilityNetwork(NetworkConfig(channels=(8, 8))).eval()
    points = _points()
    if rows == "indices":
        rows = torch.randperm(len(points), generator=g)[:1500]
    leaf = torch.randint(0, 600, (len(points),), generator=g).sort().values
    stored = LeafFeatures(torch.randn(27, 600, generator=g), leaf, torch.randn(27, 3, generator=g), points)
    fast, _ = _views(points, camera=_CAMERA)
    with torch.inference_mode():
        from_leaves = network.view_margin([fast], rows, stored, None, dtype)[0]
        carried = network.view_margin([fast], rows, stored.rows(), None, dtype)[0]
    scale = carried.abs().max()
    torch.testing.assert_close(from_leaves, carried, atol=(1e-5 if dtype == torch.float32 else 0.02) * scale, rtol=0)
    assert ((from_leaves > 0) == (carried > 0)).float().mean() > 0.998
    torch.testing.assert_close(stored.rows(rows), stored.rows()[rows])
    with pytest.raises(IndexError, match="leaf must lie"):
        LeafFeatures(stored.leaves, leaf + 1, stored.point_weight, points)
    with pytest.raises(ValueError, match="point_weight"):
        LeafFeatures(stored.leaves, leaf, stored.point_weight[:, :2], points)
    mlp = network.predictor.packed_mlp(torch.float32)
    with torch.inference_mode(), pytest.raises(ValueError, match="leaves must be a contiguous"):
        fast.margin(slice(None), LeafFeatures(stored.leaves.double(), leaf, stored.point_weight, points), 4, None,
                    mlp, torch.empty(len(points)))


@needs_kernels
def test_kernels_share_their_blocks_among_threads_with_the_same_answers(variant, monkeypatch):
    """The convolutions, up-samplings and view margins give each row the same sums on any number
    of threads (the caller's and the crew's, which may be more than the cores), and refuse a count
    out of range; a forked child, which has none of the parent's helpers, still gets its answers."""
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork
    from o3dvis.threads import torch_threads

    g = torch.Generator().manual_seed(8)
    x, index = torch.randn(2000, 32, generator=g), torch.randint(0, 2001, (1500, 27), generator=g)
    weight, shift = torch.randn(27 * 32, 48, generator=g) / 27, torch.randn(48, generator=g)
    rows = torch.sort(torch.randperm(8 * 2000, generator=g)[:5000]).values
    up_weight = torch.randn(32, 8 * 48, generator=g) / 32
    packed = native.pack_conv(weight, 27) if native.has_gather_conv() else None

    def answers(threads: int) -> list[np.ndarray]:  # numpy: no torch op of OpenMP's in a forked child
        out = [native.upsample(x, rows, up_weight, shift, True, threads=threads)]
        if packed is not None:
            out.append(native.gather_conv(x, index, packed, 27, 48, shift, relu=True, threads=threads))
        return [a.numpy() for a in out]

    one = answers(1)
    for threads in (2, 3, 7):
        assert all(np.array_equal(a, b) for a, b in zip(answers(threads), one))
    for bad in (0, native.MAX_THREADS + 1, True, 2.0):
        with pytest.raises(ValueError, match="threads must be"):
            native.upsample(x, rows, up_weight, shift, True, threads=bad)
    network = VisibilityNetwork(NetworkConfig(channels=(8, 8))).eval()
    points = _points()
    fast, _ = _views(points, camera=_CAMERA)
    projected = torch.randn(network.predictor.embedding.dim, len(points), generator=g).T
    monkeypatch.setattr(native.threads, "usable_cores", lambda: 8)  # the threads torch is given, whatever the cores
    with torch_threads(3):  # by default, torch's count for calls of work enough, one for the others
        assert native.kernel_threads() == native.kernel_threads(work=native.SHARED_WORK) == 3
        assert native.kernel_threads(work=native.SHARED_WORK - 1) == 1 and native.kernel_threads(2, work=1) == 2
    for dtype in (torch.float32, torch.bfloat16):
        if native.has_view_margin(dtype):
            margins = []
            for threads in (1, 3):
                with torch.inference_mode(), torch_threads(threads):
                    margins.append(network.view_margin([fast], slice(None), projected, None, dtype))
            assert torch.equal(*margins)
    if hasattr(os, "fork"):
        pid = os.fork()
        if pid == 0:  # the child: exit 0 only if the kernels answer alike within the alarm
            import signal

            signal.alarm(20)
            os._exit(0 if all(np.array_equal(a, b) for a, b in zip(answers(2), one)) else 1)
        _, status = os.waitpid(pid, 0)
        assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


@needs_kernels
def test_view_margin_rejects_what_the_kernel_cannot_take():
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    network = VisibilityNetwork(NetworkConfig(channels=(8, 8))).eval()
    points = _points(500)
    fast, _ = _views(points, camera=_CAMERA)
    projected = torch.randn(27, 500).T
    mlp = network.predictor.packed_mlp(torch.float32)
    with torch.inference_mode():
        with pytest.raises(ValueError, match="does not match the view's inputs"):  # inputs for 2 frequencies
            fast.margin(slice(None), torch.randn(15, 500).T, 2, None, mlp, torch.empty(500))
        with pytest.raises(ValueError, match=r"out must be a contiguous \(500,\)"):
            fast.margin(slice(None), projected, 4, None, mlp, torch.empty(499))
        with pytest.raises(ValueError, match="step 1"):
            fast.margin(slice(0, 500, 2), projected, 4, None, mlp, torch.empty(250))
        with pytest.raises(ValueError, match="stored channels first"):  # no hidden copy of all N per chunk
            fast.margin(slice(None), projected.contiguous(), 4, None, mlp, torch.empty(500))
        with pytest.raises(ValueError, match="float32 on the CPU"):
            fast.margin(slice(None), projected.double(), 4, None, mlp, torch.empty(500))
        with pytest.raises(IndexError, match=r"rows must lie in \[0, 500\)"):
            fast.margin(torch.tensor([0, 500]), projected, 4, None, mlp, torch.empty(2))
        with pytest.raises(ValueError, match="normals must be"):
            fast.margin(slice(None), projected, 4, torch.empty(499, 3), mlp, torch.empty(500))
        view = (fast.dirs, projected, 4, fast.buffers, fast.corners, fast.sides, fast.depth, fast.rpix, True)
        for empty in (1e4, float("nan")):  # beyond the kernels' asinh
            with pytest.raises(ValueError, match="empty must be a residual"):
                native.view_margin(slice(None), *view, empty, None, mlp, torch.empty(500))
        wide = native.pack_mlp([(torch.randn(144, 63), torch.randn(144)), (torch.randn(1, 144), torch.randn(1))],
                               torch.float32)
        with pytest.raises(ValueError, match="wider than 128"):
            fast.margin(slice(None), projected, 4, None, wide, torch.empty(500))
    with pytest.raises(ValueError, match="one output"):
        native.pack_mlp([(torch.randn(2, 63), torch.randn(2))], torch.float32)
    with pytest.raises(ValueError, match="float32 or bfloat16"):
        native.pack_mlp([(torch.randn(1, 63), torch.randn(1))], torch.float64)


def test_packed_mlp_follows_the_weights():
    """Packed once per dtype, again after an optimiser step changes the weights in place."""
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    predictor = VisibilityNetwork(NetworkConfig(channels=(8, 8))).predictor
    packed = predictor.packed_mlp(torch.bfloat16)
    assert predictor.packed_mlp(torch.bfloat16) is packed
    assert packed.sizes.tolist() == [64, 32, 32, 1]  # 63 inputs padded to 64, two hidden layers of 32
    assert predictor.packed_mlp(torch.float32).sizes.tolist() == [63, 32, 32, 4]  # the margin and 3 of padding
    with torch.no_grad():
        predictor.mlp[0].weight.add_(1.0)
    assert predictor.packed_mlp(torch.bfloat16) is not packed


def _cloud(normals: bool) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_points(40_000).double().numpy()))
    if normals:
        pcd.estimate_normals()
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        pcd.normals = o3d.utility.Vector3dVector(-np.asarray(pcd.normals))
    return pcd


@needs_kernels
@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
@pytest.mark.parametrize("normals", [False, True])
def test_answers_equal_those_of_the_torch_ops(precision, normals, variant, monkeypatch):
    """The shipped models, both input paths: the same answers but for points on a pixel border."""
    pcd = _cloud(normals)
    cameras = np.array([[3.0, 0.5, 0.2], [-0.4, 2.5, 1.0], [0.3, -0.2, -3.0]])
    vis = o3dvis.NeuralVisibility.pretrained(precision=precision)
    fast = vis.encode(pcd)
    assert (fast.normals is not None) == normals
    probs = fast.probabilities(cameras)
    monkeypatch.setattr(native, "usable", lambda *tensors: False)
    slow = vis.encode(pcd).probabilities(cameras)
    assert ((probs > 0.5) == (slow > 0.5)).float().mean() > 0.999
    assert (probs - slow).abs().mean() < 1e-4


@needs_kernels
@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_without_a_fused_kernel_the_torch_products_answer_alike(precision, monkeypatch):
    """The path of a CPU without bfloat16 dot products asked for bfloat16 products: the view
    built by C, the inputs and products by torch; the same answers as the fused kernel."""
    pcd = _cloud(False)
    cameras = np.array([[3.0, 0.5, 0.2], [-0.4, 2.5, 1.0]])
    vis = o3dvis.NeuralVisibility.pretrained(precision=precision)
    field = vis.encode(pcd)
    if not native.has_view_margin(field.matmul_dtype):
        pytest.skip("no fused kernel here for these products")
    fused = field.probabilities(cameras)
    monkeypatch.setattr(native, "has_view_margin", lambda dtype: False)
    unfused = field.probabilities(cameras)
    assert ((fused > 0.5) == (unfused > 0.5)).float().mean() > 0.999
    assert (fused - unfused).abs().max() < 1e-2


def _python(code: str, cwd: Path | None = None, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-W", "always", "-c", code], capture_output=True, text=True,
                          env={**os.environ, **env}, cwd=cwd, timeout=300)


_QUERY = ("import numpy as np, open3d as o3d, o3dvis\n"
          "from o3dvis.nn import native\n"
          "from o3dvis.apps import delaunay\n"
          "pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).normal(size=(3000, 3))))\n"
          "_, idx = o3dvis.hidden_point_removal_neural(pcd, [0, 0, 10])\n"
          "o3dvis.reconstruct_view_dependent(pcd, [0, 0, 10])\n")


@needs_kernels
def test_only_what_the_package_built_is_loaded_and_nothing_compiles(tmp_path):
    """No compiler and no cache at run time: with no C compiler to be found and an empty home, the
    kernels are the package's own files, and nothing is written."""
    code = _QUERY + ("package = __import__('pathlib').Path(o3dvis.__file__).parent\n"
                     "maps = open('/proc/self/maps').read().split()\n"
                     "ours = {p for p in maps if '_kernels' in p or '_delaunay' in p or 'o3dvis' in p}\n"
                     "print(native.available(), delaunay.available(), "
                     "all(__import__('pathlib').Path(p).parent.parent == package for p in ours), len(ours))")
    home = tmp_path / "home"
    home.mkdir()
    run = _python(code, CC="/nonexistent/cc", PATH=str(tmp_path), HOME=str(home), XDG_CACHE_HOME=str(home / "cache"),
                  O3DVIS_NATIVE="1")
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["True", "True", "True", "2"], run.stdout
    assert "RuntimeWarning" not in run.stderr
    assert not list(home.iterdir())


def test_with_the_c_code_turned_off_queries_run_the_fallbacks_with_one_warning():
    run = _python(_QUERY + "print(native.available(), delaunay.available(), 0 < len(idx) < 3000)", O3DVIS_NATIVE="0")
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "False", "True"]
    assert run.stderr.count("RuntimeWarning") == 1, run.stderr
    assert "torch ops" in run.stderr and "Qhull" in run.stderr and "O3DVIS_NATIVE=0" in run.stderr


def test_a_package_built_without_a_compiler_runs_the_fallbacks_with_one_warning(tmp_path):
    """What an install with no C compiler leaves: the package without its libraries."""
    package = Path(o3dvis.__file__).parent
    shutil.copytree(package, tmp_path / "o3dvis", ignore=shutil.ignore_patterns("*.so", "*.pyd", "__pycache__"))
    run = _python(_QUERY + "print(native.available(), delaunay.available(), 0 < len(idx) < 3000)",
                  cwd=tmp_path, PYTHONPATH=str(tmp_path), O3DVIS_NATIVE="1")
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "False", "True"]
    assert run.stderr.count("RuntimeWarning") == 1 and "not built" in run.stderr, run.stderr


def test_a_variant_this_cpu_cannot_run_is_never_loaded(monkeypatch):
    monkeypatch.setattr(clib, "cpu_flags", lambda: frozenset())
    monkeypatch.setattr(clib, "_warned", threading.Lock())
    assert clib.runnable_variants() == ["base"]
    with pytest.warns(RuntimeWarning, match="cannot run the avx2 variant"):
        assert clib.load("o3dvis.nn._kernels", native._library.SIGNATURES, "avx2") is None
    if native.available():
        assert clib.load("o3dvis.nn._kernels", native._library.SIGNATURES).variant == "base"


def test_the_build_goes_on_without_a_compiler(tmp_path):
    """The libraries are optional extensions: with no C compiler the install succeeds without them."""
    root = Path(__file__).resolve().parents[2]
    run = subprocess.run([sys.executable, "setup.py", "-q", "build_ext", "--build-lib", str(tmp_path / "lib"),
                          "--build-temp", str(tmp_path / "tmp")], cwd=root, capture_output=True, text=True,
                         env={**os.environ, "CC": "/nonexistent/cc"}, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "o3dvis.nn._kernels_base" in run.stderr and not list(tmp_path.rglob("*.so"))
