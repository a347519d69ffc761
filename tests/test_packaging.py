"""How the package is built: a wheel with no C library is pure Python and carries the licence and
the typing marker, a package installed without its C libraries says so at import, and an in-place
build leaves one file a library. ``.ci/wheel`` checks the native, manylinux wheel."""

import os
import shutil
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest

import o3dvis

ROOT = Path(__file__).resolve().parent.parent


def test_a_wheel_built_without_a_compiler_is_pure_python_and_carries_the_licence(tmp_path):
    """pip caches the wheels it builds: one built with no compiler must not be tagged as compiled
    code for this platform."""
    run = subprocess.run([sys.executable, "setup.py", "-q", "egg_info", "--egg-base", str(tmp_path),
                          "build", "--build-base", str(tmp_path / "build"),
                          "bdist_wheel", "--bdist-dir", str(tmp_path / "bdist"), "--dist-dir", str(tmp_path / "dist")],
                         cwd=ROOT, capture_output=True, text=True, env={**os.environ, "CC": "/nonexistent/cc"},
                         timeout=300)
    assert run.returncode == 0, run.stderr
    (wheel,) = (tmp_path / "dist").iterdir()
    assert wheel.name == f"o3dvis-{o3dvis.__version__}-py3-none-any.whl"
    names = zipfile.ZipFile(wheel).namelist()
    info = f"o3dvis-{o3dvis.__version__}.dist-info"
    tags = zipfile.ZipFile(wheel).read(f"{info}/WHEEL").decode().splitlines()
    assert "Root-Is-Purelib: true" in tags and "Tag: py3-none-any" in tags, tags
    assert not [name for name in names if name.endswith((".so", ".pyd"))]
    assert {f"{info}/licenses/LICENSE", "o3dvis/py.typed", "o3dvis/weights/default.safetensors"} <= set(names)


def test_a_package_installed_without_its_libraries_warns_at_import(tmp_path):
    """The warning comes with ``import o3dvis``, which still loads neither torch nor Open3D."""
    shutil.copytree(ROOT / "o3dvis", tmp_path / "o3dvis", ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    code = "import sys, o3dvis; print('torch' in sys.modules, 'open3d' in sys.modules)"
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "O3DVIS_NATIVE": "1"}
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "False"]
    assert run.stderr.count("RuntimeWarning") == 1, run.stderr
    assert "not built: o3dvis.nn._kernels, o3dvis.apps._delaunay" in run.stderr, run.stderr
    assert "--no-cache-dir" in run.stderr


def test_a_package_with_its_libraries_imports_without_a_warning(tmp_path):
    if not all(o3dvis.clib.built_variants(module) for module in o3dvis.clib.LIBRARIES):
        pytest.skip("this tree's C libraries are not built")
    run = subprocess.run([sys.executable, "-W", "error", "-c", "import o3dvis"], cwd=ROOT, capture_output=True,
                         text=True, env={**os.environ, "O3DVIS_NATIVE": "1"})
    assert run.returncode == 0 and not run.stderr, run.stderr


def test_an_in_place_build_removes_a_librarys_files_under_other_names(tmp_path):
    """An interpreter-specific file left from an older build would be loaded before the abi3 one."""
    for name in ("setup.py", "pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, tmp_path)
    shutil.copytree(ROOT / "o3dvis", tmp_path / "o3dvis", ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    stale = tmp_path / "o3dvis" / "nn" / "_kernels_base.cpython-311-x86_64-linux-gnu.so"
    stale.touch()
    for module in o3dvis.clib.LIBRARIES:  # built already: newer than their sources, nothing compiles
        for variant in o3dvis.clib.VARIANTS:
            library = tmp_path / "lib" / f"{module.replace('.', '/')}_{variant}.abi3.so"
            library.parent.mkdir(parents=True, exist_ok=True)
            library.touch()
    run = subprocess.run([sys.executable, "setup.py", "-q", "build_ext", "--inplace", "--build-lib",
                          str(tmp_path / "lib"), "--build-temp", str(tmp_path / "tmp")], cwd=tmp_path,
                         capture_output=True, text=True, env={**os.environ, "CC": "/nonexistent/cc"}, timeout=300)
    assert run.returncode == 0, run.stderr
    assert not stale.exists() and (stale.parent / "_kernels_base.abi3.so").is_file()


def test_torch_comes_from_the_configured_index_within_seconds_where_pytorchs_is_not_reached():
    """An index that does not answer (a documentation-only address, never routed) costs seconds,
    not a hang; the script says which torch the environment has (here the one installed already,
    which pip keeps)."""
    import torch

    start = time.perf_counter()
    env = {**os.environ, "O3DVIS_TORCH_INDEX": "http://192.0.2.1/whl"}
    run = subprocess.run(["bash", str(ROOT / ".ci" / "torch"), sys.executable, f"torch=={torch.__version__}"],
                         capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr
    assert time.perf_counter() - start < 90  # the probe gives up at 10 s; pip's own retries would take minutes
    assert "http://192.0.2.1/whl not reached" in run.stderr
    assert run.stdout.startswith(f"torch {torch.__version__} (")
