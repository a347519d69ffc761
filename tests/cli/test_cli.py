"""The ``o3dvis`` command as users run it: ``python -m o3dvis`` in a subprocess."""

import ast
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

import o3dvis
from o3dvis.cli import _common

_ROOT = Path(__file__).resolve().parents[2]
_USER_COMMANDS = ["visible", "normals", "reconstruct", "shadow", "best-view", "render", "frames", "demo"]
_TRAINING_COMMANDS = ["shapes", "prepare", "train", "calibrate", "fuse", "publish", "eval", "eval-drives", "bench"]


def _o3dvis(*argv: str, python: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """The command's run, its output decoded with carriage returns kept (see :func:`_screen`)."""
    env = {**os.environ, "PYTHONPATH": str(_ROOT)}
    run = subprocess.run([sys.executable, *python, "-m", "o3dvis", *argv], capture_output=True, env=env, timeout=300)
    run.stdout, run.stderr = run.stdout.decode(), run.stderr.decode()
    return run


def _screen(text: str) -> list[str]:
    """The lines a terminal shows of ``text``: what follows a carriage return overwrites the line."""
    lines = []
    for raw in text.split("\n"):
        line = ""
        for part in raw.split("\r"):
            line = part + line[len(part):]
        if line.strip():
            lines.append(line.rstrip())
    return lines


@pytest.fixture(scope="module")
def sphere_file(tmp_path_factory) -> Path:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(3000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    path = tmp_path_factory.mktemp("cli") / "sphere.ply"
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    return path


def test_help_lists_the_user_commands_first_and_imports_nothing_heavy():
    run = _o3dvis("--help", python=("-X", "importtime"))
    assert run.returncode == 0, run.stderr
    listed = re.findall(r"^    (\S+)", run.stdout, flags=re.MULTILINE)
    assert listed == _USER_COMMANDS + _TRAINING_COMMANDS
    imported = {line.split("|")[-1].strip() for line in run.stderr.splitlines() if line.startswith("import time:")}
    assert not imported & {"torch", "open3d", "numpy", "scipy", "tqdm"}, sorted(imported & {"torch", "open3d"})


def test_help_answers_within_half_a_second_of_the_interpreters_start():
    def best(*argv: str) -> float:
        times = []
        for _ in range(3):
            start = time.perf_counter()
            assert subprocess.run([sys.executable, *argv], capture_output=True, cwd=_ROOT).returncode == 0
            times.append(time.perf_counter() - start)
        return min(times)

    assert best("-m", "o3dvis", "--help") - best("-c", "pass") < 0.5


def test_version():
    run = _o3dvis("--version")
    assert run.returncode == 0 and run.stdout.strip() == f"o3dvis {o3dvis.__version__}"


def test_every_command_has_help_with_no_path_of_the_development_tree():
    for command in _USER_COMMANDS + _TRAINING_COMMANDS:
        run = _o3dvis(command, "--help")
        assert run.returncode == 0 and f"usage: o3dvis {command}" in run.stdout, command
        assert "../" not in run.stdout and "shared/" not in run.stdout, command


# (command line, what the error names): OUT stands for the test's folder
_UNWRITABLE = [
    (["visible", "in.ply", "--camera", "0", "0", "5", "-o", "OUT/v.xyzq"],
     "extension .xyzq names no point cloud format"),
    (["visible", "in.ply", "--camera", "0", "0", "5", "-o", "OUT/none/v.ply"], "no folder"),
    (["visible", "in.ply", "--camera", "0", "0", "5", "-o", "OUT"], "is a folder"),
    (["normals", "in.ply", "-o", "OUT/n.obj"], "extension .obj names no point cloud format"),
    (["reconstruct", "in.ply", "-o", "OUT/m.pcd"], "extension .pcd names no mesh format"),
    (["shadow", "in.ply", "--light", "0", "0", "5", "--camera", "0", "5", "0", "-o", "OUT/s.bmp"],
     "extension .bmp names no image format"),
    (["shadow", "in.ply", "--light", "0", "0", "5", "--camera", "0", "5", "0", "-o", "OUT/s.png",
      "--shadow-map", "OUT/s.txt"], "--shadow-map"),
    (["render", "in.ply", "--camera", "0", "0", "5", "-o", "OUT/r"], "extension (none) names no image format"),
    (["render", "in.ply", "--camera", "0", "0", "5", "-o", "OUT/r.png", "--depth-output", "OUT/none/d.npy"],
     "--depth-output"),
    (["best-view", "in.ply", "-o", "OUT/b.tif"], "extension .tif names no image format"),
    (["best-view", "in.ply", "--plot", "OUT/loss.xyz"], "--plot"),
    (["demo", "--out", "OUT/file.txt/demo"], "is a file, not a folder"),
    (["eval", "--data", "OUT", "--out", "OUT/none/val.json"], "no folder"),
    (["bench", "--out", "OUT/none/bench.json"], "no folder"),
    (["shapes", "OUT/file.txt"], "is a file, not a folder"),
    (["train", "OUT", "-o", "OUT/file.txt/run"], "is a file, not a folder"),
    (["calibrate", "c.safetensors", "OUT", "-o", "OUT/none/c.safetensors"], "no folder"),
]


@pytest.mark.parametrize("argv, error", _UNWRITABLE, ids=[" ".join(a[:1] + a[-2:]) for a, _ in _UNWRITABLE])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys, argv, error):
    """The input (in.ply) does not exist: only a check of the output before any reading says the output."""
    from o3dvis.cli import main
    from o3dvis.evaluation import demo

    (tmp_path / "file.txt").write_text("")
    argv = [a.replace("OUT", str(tmp_path)) for a in argv]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(demo, "run_demo", lambda *a, **k: pytest.fail("the demo ran"))
        assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"o3dvis {argv[0]}: error: ") and error in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]


def test_a_camera_is_three_numbers_negative_ones_too(sphere_file, tmp_path):
    pcd = o3d.io.read_point_cloud(str(sphere_file))
    _, expected = o3dvis.hidden_point_removal_neural(pcd, [-2.0, 0.5, -3.0])
    for camera in (["-2", "0.5", "-3"], ["-2,0.5,-3"], ["--camera=-2,0.5,-3"]):
        out = tmp_path / "out.ply"
        argv = camera if camera[0].startswith("--") else ["--camera", *camera]
        run = _o3dvis("visible", str(sphere_file), *argv, "-o", str(out))
        assert run.returncode == 0, run.stderr
        assert f"{len(expected)} of 3000 points visible" in run.stdout
        assert len(o3d.io.read_point_cloud(str(out)).points) == len(expected)
        out.unlink()


@pytest.mark.parametrize("camera", [["1", "2"], ["1", "2", "x"], ["1,2"]])
def test_a_camera_of_other_than_three_numbers_is_a_usage_error(sphere_file, tmp_path, camera):
    run = _o3dvis("render", str(sphere_file), "--camera", *camera, "-o", str(tmp_path / "r.png"))
    assert run.returncode == 2 and "--camera" in run.stderr and "Traceback" not in run.stderr


def test_reconstruct_refuses_a_poisson_depth_open3d_cannot_build(sphere_file, tmp_path):
    run = _o3dvis("reconstruct", str(sphere_file), "-o", str(tmp_path / "mesh.ply"), "--depth", "30")
    assert run.returncode == 2, run.stderr
    assert "depth=30 is beyond 16" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "mesh.ply").exists()


@pytest.mark.parametrize("case", ["missing file", "camera on a point"])
def test_a_user_error_is_one_line_with_no_traceback_and_no_bar(sphere_file, tmp_path, case):
    """Also an error found after the command's progress bar has started (a camera on a point)."""
    if case == "missing file":
        source, camera = tmp_path / "none.ply", ["0", "0", "5"]
    else:
        source, camera = sphere_file, [repr(float(x)) for x in o3d.io.read_point_cloud(str(sphere_file)).points[0]]
    run = _o3dvis("visible", str(source), "--camera", *camera, "-o", str(tmp_path / "out.ply"))
    assert run.returncode == 2
    screen = _screen(run.stderr)
    assert len(screen) == 1 and screen[0].startswith("o3dvis visible: error: "), run.stderr
    assert not (tmp_path / "out.ply").exists()


@pytest.mark.parametrize("content", [b"", b"ply\nformat ascii 1.0\nend_header\n", os.urandom(4096)],
                         ids=["empty", "header only", "random bytes"])
@pytest.mark.parametrize("command", [["visible", "--camera", "0", "0", "5", "-o", "out.ply"],
                                     ["render", "--camera", "0", "0", "5", "-o", "out.png"]])
def test_a_corrupt_input_exits_non_zero(tmp_path, content, command):
    source = tmp_path / "corrupt.ply"
    source.write_bytes(content)
    run = _o3dvis(command[0], str(source), *[str(tmp_path / a) if a.startswith("out.") else a for a in command[1:]])
    assert run.returncode != 0 and "Traceback" not in run.stderr, run.stderr
    assert not list(tmp_path.glob("out.*"))


def test_the_precision_choices_are_the_networks():
    from o3dvis.nn.predictor import PRECISIONS

    assert _common._PRECISIONS == PRECISIONS


def test_the_command_modules_share_helpers_through_one_module_only():
    """No command module imports another (``apps`` and ``visible`` once imported each other)."""
    for path in (_ROOT / "o3dvis" / "cli").glob("*.py"):
        siblings = {node.module for node in ast.walk(ast.parse(path.read_text()))
                    if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module}
        assert siblings <= {"_common"}, (path.name, siblings)
