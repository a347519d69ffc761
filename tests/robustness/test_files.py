"""The command line on bad files: crafted point cloud files (cut short, counts overstated, not points,
folders, headers Open3D's reader misreads) through every command that reads a cloud, bad checkpoints
through ``calibrate`` and ``publish``, an output folder that does not exist, an image too large: exit
code != 0 and one line naming the problem, nothing created. PCD files that crash Open3D's reader go
through a command in a child process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from conftest import SPHERE, as_cloud, lzf_literal
from .conftest import _CHILD_TIMEOUT


def _ply(fmt: str, count: int, body: bytes, props: str = "property float x\nproperty float y\nproperty float z\n"
         ) -> bytes:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {count}\n{props}end_header\n").encode() + body


def _pcd(data: str, points: int, body: bytes, fields: str = "x y z", sizes: str = "4 4 4", types: str = "F F F",
         counts: str = "1 1 1") -> bytes:
    return (f"VERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\nWIDTH {points}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n").encode() + body


_XYZ = "".join(f"{x} {y} {z}\n" for x, y, z in SPHERE[:10]).encode()
_FLOATS = SPHERE[:10].astype(np.float32).tobytes()
_XYZ_PROPS = "property float x\nproperty float y\nproperty float z\n"

FILE_CASES: dict[str, tuple[str, bytes | None, str]] = {
    # name: (file name, content (None: the folder itself), the error's message)
    "binary PLY declaring 100000 vertices, holding 30 floats": (
        "lie.ply", _ply("binary_little_endian", 100_000, np.arange(30, dtype=np.float32).tobytes()),
        "truncated PLY.*element vertex 100000"),
    "binary PLY cut short": ("cut.ply", _ply("binary_little_endian", 10, _FLOATS[:-6]), "truncated PLY"),
    "ASCII PLY cut short": ("cut_ascii.ply", _ply("ascii", 10, _XYZ[:len(_XYZ) // 2]), "truncated PLY"),
    "PLY without end_header": ("open.ply", _ply("ascii", 10, b"").replace(b"end_header\n", b""), "end_header"),
    "PLY with a negative count": ("negative.ply", _ply("ascii", -3, _XYZ), "bad count"),
    "PLY of an unknown format": ("format.ply", _ply("binary_middle_endian", 10, _FLOATS), "unknown PLY format"),
    "PLY without vertices": ("faces.ply", b"ply\nformat ascii 1.0\nelement face 0\n"
                                          b"property list uchar int vertex_indices\nend_header\n", "no vertex"),
    "binary PCD cut short": ("cut.pcd", _pcd("binary", 10, _FLOATS[:-5]), "truncated PCD"),
    "ASCII PCD declaring 1000 points, holding 10": ("lie.pcd", _pcd("ascii", 1000, _XYZ), "truncated PCD.*1000"),
    "compressed PCD cut short": ("cut_compressed.pcd", _pcd("binary_compressed", 10, b"\x40\0\0\0\x78\0\0\0"),
                                 "compressed PCD"),
    "PLY vertex without z": ("xy.ply", _ply("binary_little_endian", 10, SPHERE[:10, :2].astype(np.float32).tobytes(),
                                            "property float x\nproperty float y\n"), "lacks z"),
    "PLY vertex with x as a list": ("list.ply", _ply("binary_little_endian", 10, b"".join(
        b"\x01" + row.tobytes() for row in SPHERE[:10].astype(np.float32)), "property list uchar float x\n"
        "property float y\nproperty float z\n"), "'x' is a list"),
    "PLY vertex with nx but no ny, nz": ("nx.ply", _ply("binary_little_endian", 10, np.c_[
        SPHERE[:10], SPHERE[:10, :1]].astype(np.float32).tobytes(), _XYZ_PROPS + "property float nx\n"),
        "lacks ny, nz"),
    "PLY vertex with red but no green, blue": ("red.ply", _ply("binary_little_endian", 10, b"".join(
        row.tobytes() + b"\x80" for row in SPHERE[:10].astype(np.float32)), _XYZ_PROPS + "property uchar red\n"),
        "lacks green, blue"),
    "PLY vertex declaring z before y": ("xzy.ply", _ply("binary_little_endian", 10, _FLOATS,
                                                       "property float x\nproperty float z\nproperty float y\n"),
                                        "'z' before x, y"),
    "ASCII PLY with a word for a number": ("word.ply", _ply("ascii", 10, b"abc" + _XYZ[_XYZ.index(b" "):]),
                                           "not lines of 3 numbers.*'abc'"),
    "PCD of TYPE F SIZE 2": ("half.pcd", _pcd("binary", 10, SPHERE[:10].astype(np.float16).tobytes(), sizes="2 2 2"),
                             "'x' is TYPE F SIZE 2"),
    "PCD of TYPE F SIZE 1": ("byte.pcd", _pcd("binary", 10, bytes(30), sizes="1 1 1"), "'x' is TYPE F SIZE 1"),
    "compressed PCD of TYPE F SIZE 8": ("double.pcd", _pcd("binary_compressed", 10, lzf_literal(
        SPHERE[:10].tobytes()), sizes="8 8 8"), "'x' is TYPE F SIZE 8.*binary_compressed"),
    "PCD with x of COUNT 2": ("count.pcd", _pcd("binary", 10, np.c_[SPHERE[:10, :1], SPHERE[:10]].astype(
        np.float32).tobytes(), counts="2 1 1"), "'x' is TYPE F SIZE 4 COUNT 2"),
    "PCD with a TYPE letter not F, I or U": ("type.pcd", _pcd("binary", 10, _FLOATS, types="F F Q"),
                                             "unknown TYPE 'Q'"),
    "PCD with 2 TYPE letters for 3 fields": ("types.pcd", _pcd("binary", 10, _FLOATS, types="F F"),
                                             "TYPE line has 2 values for 3 fields"),
    "PCD with COUNT before SIZE": ("order.pcd", _pcd("binary", 10, _FLOATS).replace(b"SIZE 4 4 4\n", b"").replace(
        b"COUNT 1 1 1\n", b"COUNT 1 1 1\nSIZE 4 4 4\n"), "SIZE line comes before its COUNT"),
    "PCD with DATA in upper case": ("upper.pcd", _pcd("BINARY", 10, _FLOATS), "unknown PCD data kind 'BINARY'"),
    "ASCII PCD with a line of 2 numbers": ("short.pcd", _pcd("ascii", 2, b"1 2\n3 4 5 6\n"), "line 1 of its data"),
    "compressed PCD with corrupted compressed data": ("lzf.pcd", _pcd("binary_compressed", 10, np.array(
        [124, 120], dtype="<u4").tobytes() + b"\x20\x00" + bytes(122)), "corrupted compressed PCD"),
    "PTS declaring 100 points, holding 10": ("lie.pts", b"100\n" + _XYZ, "declares 100 points but 10"),
    "XYZ with a line of two numbers": ("short.xyz", _XYZ + b"1.5 2.5\n", "line 11 .* not a point"),
    "XYZ with a line of words": ("words.xyz", b"x y z\n" + _XYZ, "line 1 .* not a point"),
    "XYZN with points of 3 numbers": ("three.xyzn", _XYZ, "line 1 .* not a point of 6"),
    "XYZ with a NaN point": ("nan.xyz", _XYZ + b"nan 0 0\n", "1 of 11 points have NaN"),
    "empty XYZ": ("empty.xyz", b"", "no points"),
    "unknown suffix": ("cloud.txt", _XYZ, "unknown point cloud format"),
    "a folder": ("folder.ply", None, "is a folder"),
    "a missing file": ("missing.ply", b"", "not found"),
}
"""Point cloud files the CLI must refuse: each command that reads a cloud prints one line naming the problem."""

_NORMAL_X = {"fields": "x y z normal_x", "sizes": "4 4 4 4", "types": "F F F F", "counts": "1 1 1 1"}
_NORMALS = {"fields": "x y z normal_x normal_y normal_z", "sizes": "4 4 4 4 4 4", "types": "F F F F F F",
            "counts": "1 1 1 1 1 1"}
CRASH_CASES: dict[str, tuple[str, bytes, str]] = {
    "ASCII PCD with normal_x but no normal_y, normal_z": (
        "normal_ascii.pcd", _pcd("ascii", 1, b"1 2 3 4\n", **_NORMAL_X), "lacks normal_y, normal_z"),
    "binary PCD with normal_x but no normal_y, normal_z": (
        "normal_binary.pcd", _pcd("binary", 1, np.float32([1, 2, 3, 4]).tobytes(), **_NORMAL_X),
        "lacks normal_y, normal_z"),
    "compressed PCD with normal_x but no normal_y, normal_z": (
        "normal_compressed.pcd", _pcd("binary_compressed", 1, lzf_literal(np.float32([1, 2, 3, 4]).tobytes()),
                                      **_NORMAL_X), "lacks normal_y, normal_z"),
    "compressed PCD with one corrupted header byte (normal_Y)": (
        "corrupted.pcd", _pcd("binary_compressed", 1, lzf_literal(np.float32([1, 2, 3, 0, 0, 1]).tobytes()), **_NORMALS
                              ).replace(b"normal_y", b"normal_Y"), "lacks normal_y"),
}
"""PCD files Open3D's reader crashes the process on (SIGSEGV): refused by the command in a child process."""

CLI_READERS = {
    "visible": ["--camera", "0,0,3", "-o", "{out}.ply"],
    "normals": ["-o", "{out}.ply"],
    "reconstruct": ["-o", "{out}.ply"],
    "shadow": ["--light", "0,0,3", "--camera", "0,3,0", "-o", "{out}.png"],
    "best-view": [],
    "render": ["--camera", "0,0,3", "-o", "{out}.png"],
}


def _write_case(folder: Path, name: str) -> Path:
    file_name, content, _ = FILE_CASES[name]
    path = folder / file_name
    if content is None:
        path.mkdir()
    elif name != "a missing file":
        path.write_bytes(content)
    return path


def _cli_error(capsys, *argv: str) -> str:
    """Runs the ``o3dvis`` command; asserts it failed with one line and no traceback; returns that line."""
    from o3dvis.cli import main

    code = main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0, "the command succeeded"
    assert err and not any("Traceback" in line for line in err)
    return err[-1]


@pytest.mark.parametrize("command", CLI_READERS)
@pytest.mark.parametrize("case", FILE_CASES)
def test_cli_refuses_a_bad_point_cloud_file(tmp_path, capsys, command, case):
    path = _write_case(tmp_path, case)
    args = [a.format(out=tmp_path / "out") for a in CLI_READERS[command]]
    line = _cli_error(capsys, command, str(path), *args)
    assert line.startswith(f"o3dvis {command}: error: ")
    assert __import__("re").search(FILE_CASES[case][2], line), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if case == "a missing file" else [path.name])


@pytest.mark.parametrize("case", CRASH_CASES)
def test_cli_refuses_a_pcd_that_crashes_open3d_in_a_child_process(tmp_path, case):
    file_name, content, message = CRASH_CASES[case]
    path = tmp_path / file_name
    path.write_bytes(content)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    run = subprocess.run([sys.executable, "-m", "o3dvis", "visible", str(path), "--camera", "0,0,3", "-o",
                          str(tmp_path / "out.ply")], capture_output=True, text=True, env=env, timeout=_CHILD_TIMEOUT)
    assert run.returncode > 0, f"exit code {run.returncode}: {run.stderr[-2000:]}"  # < 0: killed by a signal
    err = run.stderr.strip().splitlines()
    assert err and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert err[-1].startswith("o3dvis visible: error: ") and __import__("re").search(message, err[-1]), err[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == [file_name]


@pytest.mark.parametrize("command", ["calibrate", "publish"])
@pytest.mark.parametrize("what", ["not safetensors", "a folder"])
def test_cli_checkpoint_commands_refuse_a_bad_file_in_one_line(tmp_path, capsys, command, what):
    path = tmp_path / "ckpt.safetensors"
    if what == "a folder":
        path.mkdir()
    else:
        path.write_bytes(b"this is no checkpoint at all, just some text" * 10)
    rest = [str(tmp_path), "-o", str(tmp_path / "out.safetensors")] if command == "calibrate" else [
        "--name", "x", "--root", str(tmp_path)]
    before = sorted(tmp_path.rglob("*"))
    line = _cli_error(capsys, command, str(path), *rest)
    assert __import__("re").search("is a folder" if what == "a folder" else "not a safetensors file", line), line
    assert sorted(tmp_path.rglob("*")) == before


def test_cli_bench_creates_no_folder_it_was_not_given(tmp_path, capsys):
    out = tmp_path / "missing" / "b.json"
    line = _cli_error(capsys, "bench", "--methods", "hpr", "--points", "200", "--views", "1", "-o", str(out))
    assert "no folder" in line and str(out.parent) in line
    assert not out.parent.exists()


@pytest.mark.parametrize("command", ["render", "shadow"])
def test_cli_refuses_an_image_too_large_in_one_line(tmp_path, capsys, command):
    path = tmp_path / "sphere.ply"
    o3d.io.write_point_cloud(str(path), as_cloud(SPHERE))
    args = [a.format(out=tmp_path / "out") for a in CLI_READERS[command]]
    line = _cli_error(capsys, command, str(path), *args, "--width", "1000000", "--height", "1000000")
    assert line.startswith(f"o3dvis {command}: error: ") and "1000000 x 1000000 image" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sphere.ply"]
