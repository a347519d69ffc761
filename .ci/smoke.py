"""Checks an installed o3dvis from outside the source tree, with no C compiler on PATH: the package
and its C libraries come from the install, a wheel tagged for every CPython 3.10+ on manylinux
that carries the licence and the typing marker, the widest variant this CPU runs is active, and it
answers right (a sphere's visible points against ray casting and against the torch path; the
demo through the console script)."""

import importlib.metadata
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d
import torch

import o3dvis
from o3dvis import clib
from o3dvis.apps import delaunay
from o3dvis.nn import native

package = Path(o3dvis.__file__).resolve().parent
assert package.is_relative_to(Path(sys.prefix).resolve()), f"o3dvis imported from {package}, not {sys.prefix}"
assert not any(shutil.which(cc) for cc in ("cc", "gcc", "clang")), "a C compiler is on PATH"
assert native.available() and delaunay.available(), "the C libraries are not active"
assert native.variant() == clib.runnable_variants()[-1], native.variant()
for library, folder in ((native._library.LIBRARY, "nn"), (delaunay._LIBRARY, "apps")):
    assert Path(library._name).resolve().parent == package / folder, library._name
distribution = importlib.metadata.distribution("o3dvis")
tags = [line.partition(": ")[2] for line in distribution.read_text("WHEEL").splitlines() if line.startswith("Tag: ")]
assert tags and all(tag.startswith("cp310-abi3-manylinux") for tag in tags), tags
files = {file.name for file in distribution.files}
assert {"LICENSE", "py.typed"} <= files, sorted(files)

mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60)
o3d.utility.random.seed(0)
pcd = mesh.sample_points_uniformly(20_000)
camera = np.array([0.5, -1.0, 3.0])
truth = o3dvis.visibility_from_mesh(mesh, np.asarray(pcd.points), camera)[0]
_, indices = o3dvis.hidden_point_removal_neural(pcd, camera)
mask = np.zeros(len(truth), bool)
mask[indices] = True
accuracy = (mask == truth).mean()
native.usable = lambda *tensors: False  # the torch path, for comparison
_, torch_indices = o3dvis.hidden_point_removal_neural(pcd, camera)
agreement = len(set(indices) ^ set(torch_indices)) / len(truth)
assert accuracy > 0.98, accuracy
assert agreement < 0.001, agreement

with tempfile.TemporaryDirectory() as out:
    demo = subprocess.run(["o3dvis", "demo", "--out", out, "--points", "5000"], capture_output=True, text=True)
    assert demo.returncode == 0 and (Path(out) / "demo.png").is_file(), demo.stderr
print(f"wheel smoke test: o3dvis {o3dvis.__version__} ({', '.join(tags)}) from {package} on Python "
      f"{platform.python_version()}, torch {torch.__version__}, Open3D {o3d.__version__}, numpy {np.__version__}; "
      f"C kernels {native.variant()}, Delaunay {delaunay._LIBRARY.variant}; sphere of {len(truth)} points "
      f"from {camera.tolist()}: {mask.sum()} visible, ray casting {truth.sum()}, accuracy {100 * accuracy:.2f} %, "
      f"{100 * agreement:.3f} % of points answered otherwise by the torch path; demo ran")
