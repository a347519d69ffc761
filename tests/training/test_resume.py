"""The data pipeline loses nothing: interrupted ``o3dvis prepare`` and ``o3dvis train`` resume exactly.

Each run is a subprocess killed with SIGKILL (its whole process group: the prepare workers
too) part way, then run again to the end; the result must equal that of a run never
interrupted. A checkpoint interrupted while being written must not stop the resume either.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from o3dvis.training.data import load_sample, prepare, write_shapes
from o3dvis.nn import VisibilityNetwork
from o3dvis.training.train import TrainConfig, train

REPO = Path(__file__).resolve().parents[2]
MESHES = 6
PREPARE = ["--points", "20000", "--views", "6", "--workers", "1", "--seed", "3"]
TRAIN = ["--steps", "8", "--val-every", "2", "--batch-size", "2", "--min-points", "300", "--max-points", "600",
         "--views", "2", "--depth", "4", "--channels", "8,8", "--frequencies", "2", "--workers", "0",
         "--threads", "1", "--seed", "5"]


def _o3dvis(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-m", "o3dvis", *args], cwd=REPO, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _finish(proc: subprocess.Popen, timeout: float = 300) -> str:
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out[-3000:]
    return out


def _kill_when(proc: subprocess.Popen, ready, timeout: float = 300) -> None:
    """SIGKILLs the process group of ``proc`` as soon as ``ready()`` holds."""
    deadline = time.monotonic() + timeout
    while not ready():
        assert proc.poll() is None, f"finished before it could be interrupted: {proc.communicate()[0][-3000:]}"
        assert time.monotonic() < deadline, "timed out waiting to interrupt"
        time.sleep(0.01)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL


@pytest.fixture(scope="module")
def meshes(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("meshes")
    write_shapes(str(folder), MESHES, seed=11)
    return folder


@pytest.fixture(scope="module")
def prepared(meshes, tmp_path_factory) -> Path:
    """An uninterrupted prepare of the same meshes with the same settings."""
    out = tmp_path_factory.mktemp("prepared")
    result = prepare(meshes, out, num_points=20000, num_views=6, workers=1, seed=3, progress=False)
    assert result["done"] == MESHES and not result["failed"]
    return out


def _samples(folder: Path) -> list[Path]:
    return sorted(p for p in folder.glob("*.npz") if not p.name.endswith(".tmp.npz"))


def test_interrupted_prepare_resumes_to_the_same_files(meshes, prepared, tmp_path):
    out = tmp_path / "out"
    proc = _o3dvis("prepare", str(meshes), str(out), *PREPARE)
    _kill_when(proc, lambda: out.is_dir() and len(_samples(out)) >= 1)
    done = _samples(out)
    assert 1 <= len(done) < MESHES, f"killed after {len(done)} of {MESHES} files"
    stamps = {p.name: p.stat().st_mtime_ns for p in done}
    for p in done:  # what was written before the kill is complete
        assert load_sample(p).points.shape == (20000, 3)
    log = _finish(_o3dvis("prepare", str(meshes), str(out), *PREPARE))
    assert f"skipped {len(done)} finished" in log
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in _samples(prepared))
    assert {p.name: p.stat().st_mtime_ns for p in done} == stamps  # finished files were not redone
    for p in _samples(prepared):
        mine, reference = load_sample(out / p.name), load_sample(p)
        for field in ("points", "normals", "cameras", "visibility"):
            np.testing.assert_array_equal(getattr(mine, field), getattr(reference, field), err_msg=field)


def test_load_sample_refuses_a_truncated_file(prepared, tmp_path):
    data = _samples(prepared)[0].read_bytes()
    for size in (len(data) // 2, len(data) - 20, 100):
        broken = tmp_path / f"cut{size}.npz"
        broken.write_bytes(data[:size])
        with pytest.raises(ValueError, match=f"cut{size}.npz: not a readable o3dvis sample"):
            load_sample(broken)


def _steps(run: Path) -> list[int]:
    return [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]


def _weights(path: Path) -> dict:
    return VisibilityNetwork.load(path).state_dict()


def _assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)


@pytest.fixture(scope="module")
def reference_run(prepared, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("reference") / "run"
    _finish(_o3dvis("train", str(prepared), "--out", str(run), *TRAIN))
    return run


def test_interrupted_train_resumes_from_its_checkpoint(prepared, reference_run, tmp_path):
    run = tmp_path / "run"
    proc = _o3dvis("train", str(prepared), "--out", str(run), *TRAIN)
    _kill_when(proc, lambda: (run / "last_state.pt").is_file())  # the first checkpoint is complete
    saved = torch.load(run / "last_state.pt", weights_only=True)["step"]
    assert saved < 8 and saved in _steps(run)
    rerun = _finish(_o3dvis("train", str(prepared), "--out", str(run), *TRAIN))
    done = [json.loads(line)["step"] for line in rerun.splitlines() if line.startswith('{"step"')]
    assert done == list(range(saved + 2, 9, 2)), "the rerun did not start after the saved step"
    assert _steps(run) == _steps(reference_run) == [2, 4, 6, 8]
    # workers=0 and seeded items: the resumed run computes what the uninterrupted one did
    _assert_same_weights(_weights(run / "last.safetensors"), _weights(reference_run / "last.safetensors"))


class _Interrupted(BaseException):
    """Stands for the SIGKILL that hits while a checkpoint is being written."""


def test_a_checkpoint_interrupted_while_written_does_not_stop_the_resume(prepared, reference_run, tmp_path,
                                                                         monkeypatch):
    cfg = json.loads((reference_run / "config.json").read_text())
    cfg["out"] = str(tmp_path / "run")
    real_save, calls = torch.save, []

    def dies_half_way(obj, f, *args, **kwargs):
        calls.append(f)
        if len(calls) == 2:  # the second checkpoint: half of it reaches the disk
            buffer = io.BytesIO()
            real_save(obj, buffer, *args, **kwargs)
            Path(f).write_bytes(buffer.getvalue()[: len(buffer.getvalue()) // 2])
            raise _Interrupted
        real_save(obj, f, *args, **kwargs)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        monkeypatch.setattr(torch, "save", dies_half_way)
        with pytest.raises(_Interrupted):
            train(TrainConfig(**cfg), progress=False)
        monkeypatch.setattr(torch, "save", real_save)
        train(TrainConfig(**cfg), progress=False)
    finally:
        torch.set_num_threads(threads)
    assert _steps(tmp_path / "run") == [2, 4, 6, 8]
    _assert_same_weights(_weights(tmp_path / "run" / "last.safetensors"),
                         _weights(reference_run / "last.safetensors"))


_WITHOUT_OPEN3D = """
import importlib.abc, runpy, sys
class NoOpen3D(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] == "open3d":
            raise ImportError("no Open3D here")
sys.meta_path.insert(0, NoOpen3D())
sys.argv = ["o3dvis"] + sys.argv[1:]
runpy.run_module("o3dvis", run_name="__main__")
"""


def test_a_time_limited_run_without_open3d_stops_with_a_checkpoint_and_resumes(prepared, reference_run, tmp_path):
    """What tools/device_train.sh relies on: training from prepared files imports no Open3D, and
    --time-limit checkpoints and stops after the step it runs out in; run again, it goes on to
    what a run never stopped computes."""
    run = tmp_path / "run"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    stopped = subprocess.run([sys.executable, "-c", _WITHOUT_OPEN3D, "train", str(prepared), "--out", str(run),
                              *TRAIN, "--time-limit", "0"], cwd=REPO, env=env, capture_output=True, text=True,
                             timeout=300)
    assert stopped.returncode == 0, stopped.stdout[-2000:] + stopped.stderr[-2000:]
    assert _steps(run) == [1] and (run / "last.safetensors").is_file()
    _finish(_o3dvis("train", str(prepared), "--out", str(run), *TRAIN))
    assert _steps(run) == [1, 2, 4, 6, 8]
    _assert_same_weights(_weights(run / "last.safetensors"), _weights(reference_run / "last.safetensors"))


def test_an_orientation_head_trains_beside_the_network_and_resumes(prepared, reference_run, tmp_path):
    """--orientation-weight changes what the U-Net learns, saves nothing into the network, and a
    run stopped part way goes on with the head where it was (the same weights as a run never
    stopped)."""
    args = [*TRAIN, "--orientation-weight", "0.5"]
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    _finish(_o3dvis("train", str(prepared), "--out", str(whole), *args))
    _finish(_o3dvis("train", str(prepared), "--out", str(parts), *args, "--time-limit", "0"))
    assert _steps(parts) == [1]
    _finish(_o3dvis("train", str(prepared), "--out", str(parts), *args))
    _assert_same_weights(_weights(parts / "last.safetensors"), _weights(whole / "last.safetensors"))
    with_head, without = _weights(whole / "last.safetensors"), _weights(reference_run / "last.safetensors")
    assert with_head.keys() == without.keys()
    assert any(not torch.equal(with_head[k], without[k]) for k in with_head if k.startswith("unet."))
