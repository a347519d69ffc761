"""``o3dvis visible`` (``o3dvis.cli.visible``): the visible points written, at each precision, and
bad arguments refused."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

import o3dvis
from o3dvis.cli import build_parser
from o3dvis.cli._common import split_vectors

from conftest import _camera


def test_cli_visible_writes_the_visible_points(tmp_path, network, pcd, points, capsys):
    ckpt = tmp_path / "m.safetensors"
    network.save(ckpt)
    src, dst = tmp_path / "in.ply", tmp_path / "out.ply"
    o3d.io.write_point_cloud(str(src), pcd)
    parser = build_parser()
    camera = _camera(points)
    args = parser.parse_args(["visible", str(src), "--camera", *map(str, camera), "-o", str(dst),
                              "--model", str(ckpt), "--threshold", "0.4"])
    assert args.func(args) == 0
    written = np.asarray(o3d.io.read_point_cloud(str(dst)).points)
    expected = np.flatnonzero(o3dvis.NeuralVisibility(network).encode(points).query(camera, threshold=0.4)[0])
    np.testing.assert_allclose(written, points[expected])
    assert f"{len(expected)} of {len(points)} points visible" in capsys.readouterr().out
    for precision in ("float32", "bfloat16"):
        args = parser.parse_args(split_vectors(["visible", str(src), f"--camera={','.join(map(str, camera))}",
                                                "-o", str(dst), "--model", str(ckpt), "--precision", precision]))
        assert args.func(args) == 0
        field = o3dvis.NeuralVisibility(network, precision=precision).encode(points)
        np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(dst)).points),
                                   points[np.flatnonzero(field.query(camera)[0])])
    with pytest.raises(SystemExit):
        parser.parse_args(["visible", str(src), "--camera", "0", "0", "5", "-o", str(dst), "--precision", "half"])
    with pytest.raises(SystemExit):
        parser.parse_args(split_vectors(["visible", str(src), "--camera", "1,2", "-o", str(dst)]))
    args = parser.parse_args(["visible", str(tmp_path / "none.ply"), "--camera", "0", "0", "5", "-o", str(dst)])
    with pytest.raises(FileNotFoundError, match="none.ply"):
        args.func(args)
