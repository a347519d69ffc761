"""What runs on a GPU machine that has PyTorch but no Open3D: the torch core on CUDA gives the CPU's
answers (skipped without a CUDA device), and the core and training import and run without Open3D.

Nothing here imports Open3D, so this file also runs where it is not installed.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import box_surface

ROOT = Path(__file__).resolve().parents[1]
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def _dumbbell(count: int) -> np.ndarray:
    """Two overlapping spheres: an object with hidden points from every side."""
    from o3dvis.geometry import fibonacci_sphere

    half = fibonacci_sphere(count // 2)
    return np.concatenate([half, 0.8 * fibonacci_sphere(count - count // 2) + [1.2, 0.0, 0.0]])


def _labels_agree(cpu: np.ndarray, gpu: np.ndarray) -> float:
    return float((cpu == gpu).mean())


@cuda
@pytest.mark.parametrize("normals", [False, "estimate"])
def test_cuda_gives_the_cpu_answers_for_an_object(normals):
    from o3dvis import NeuralVisibility

    points = _dumbbell(20_000)
    cameras = np.array([[0.6, 0.0, 4.0], [-4.0, 1.0, 0.5], [0.6, -4.0, -1.0]])
    cpu = NeuralVisibility.pretrained(precision="float32").encode(points, normals=normals)
    gpu = NeuralVisibility.pretrained(device="cuda").encode(torch.from_numpy(points).cuda(), normals=normals)
    assert gpu.device.type == "cuda"  # float32 products there, as on the CPU here ("auto" may pick bfloat16)
    assert (cpu.normals is None) == (gpu.normals is None) == (normals is False)
    probabilities = gpu.probabilities(cameras)
    assert probabilities.device.type == "cuda"
    torch.testing.assert_close(probabilities.cpu().float(), cpu.probabilities(cameras).float(), atol=2e-3, rtol=0)
    assert _labels_agree(cpu.query(cameras), gpu.query(cameras)) > 0.999


@cuda
def test_cuda_gives_the_cpu_answers_inside_a_room():
    from o3dvis import NeuralVisibility

    points = box_surface([0, 0, 0], [4, 3, 2.5], 20_000, np.random.default_rng(0))
    camera = np.array([[1.0, 1.5, 1.2]])
    cpu = NeuralVisibility.pretrained(precision="float32").encode(points).query(camera)
    gpu = NeuralVisibility.pretrained(device="cuda").encode(points).query(camera)
    assert cpu.mean() > 0.05
    assert _labels_agree(cpu, gpu) > 0.999


def test_the_torch_core_and_training_run_without_open3d(tmp_path):
    """With Open3D unimportable, arrays are encoded and queried in one and two passes, and the
    training data set draws clouds with estimated normals."""
    from o3dvis.training.data.sample import Sample, save_sample

    points = _dumbbell(4000)
    cameras = np.array([[0.6, 0.0, 4.0], [-4.0, 0.0, 0.0]])
    visibility = np.ones((2, len(points)), dtype=bool)
    save_sample(Sample(points.astype(np.float32), points.astype(np.float32), cameras.astype(np.float32),
                       visibility, "a"), tmp_path / "a.npz")
    script = f"""
import sys
sys.modules["open3d"] = None  # import open3d raises ImportError
import numpy as np
from o3dvis import NeuralVisibility
from o3dvis.training.data.dataset import Augmentation, VisibilityDataset

points = np.load({str(tmp_path / "a.npz")!r})["points"].astype(np.float64)
vis = NeuralVisibility.pretrained()
assert vis.encode(points).query([[0.6, 0.0, 4.0]]).shape == (1, len(points))
assert vis.encode(points, normals="estimate").normals is not None
data = VisibilityDataset([{str(tmp_path / "a.npz")!r}], Augmentation(min_points=3000, max_points=3000,
                         noise_prob=0.0, estimated_normals=1.0))
assert data[0][1].shape == (3000, 3)
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith("ok")
