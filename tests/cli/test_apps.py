"""The applications' commands (``o3dvis.cli.apps``): normals, render, shadow, reconstruct and
best-view on a sphere, the network's precision flag, the searches offered."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch

from o3dvis.cli import build_parser
from o3dvis.cli._common import split_vectors, visibility_method

from conftest import _cloud


def test_the_cli_offers_the_searches_of_best_view():
    from o3dvis.apps.views import SEARCHES
    from o3dvis.cli.apps import _SEARCHES

    assert _SEARCHES == SEARCHES


def _cli(*argv: str) -> int:
    """Runs a command as ``o3dvis`` parses it, but raising its errors."""
    args = build_parser().parse_args(split_vectors(list(argv)))
    return args.func(args)


def test_cli_normals_render_shadow_reconstruct(tmp_path, sphere):
    points, _, _ = sphere
    mesh_path, cloud_path = str(tmp_path / "sphere_mesh.ply"), str(tmp_path / "sphere.ply")
    o3d.io.write_triangle_mesh(mesh_path, o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60))
    o3d.io.write_point_cloud(cloud_path, _cloud(points))
    gt = ["--method", "gt", "--mesh", mesh_path]
    out = str(tmp_path / "normals.ply")
    assert _cli("normals", cloud_path, "-o", out, "--views", "12", *gt) == 0
    normals = np.asarray(o3d.io.read_point_cloud(out).normals)
    assert (np.einsum("ij,ij->i", normals, points) > 0).all()
    knn_out = str(tmp_path / "normals_knn.ply")
    assert _cli("normals", cloud_path, "-o", knn_out, "--views", "12", "--knn", "12", *gt) == 0
    knn_normals = np.asarray(o3d.io.read_point_cloud(knn_out).normals)
    assert (np.einsum("ij,ij->i", knn_normals, points) > 0).all()
    assert not np.allclose(knn_normals, normals)  # another fit: the flag reached the function
    with pytest.raises(ValueError, match="--orient-only"):
        _cli("normals", out, "-o", knn_out, "--orient-only", "--knn", "12", *gt)
    assert _cli("render", out, "--camera", "0,0,4", "-o", str(tmp_path / "r.png"), "--width", "80",
                "--height", "60", "--depth-output", str(tmp_path / "d.npy"), *gt) == 0
    assert np.asarray(o3d.io.read_image(str(tmp_path / "r.png"))).shape == (60, 80, 3)
    assert np.load(tmp_path / "d.npy").max() < 4.0
    assert _cli("shadow", cloud_path, "--light", "0,0,4", "--camera=4,0,0", "-o",
                str(tmp_path / "s.png"), "--width", "80", "--height", "60", *gt) == 0
    assert _cli("reconstruct", cloud_path, "-o", str(tmp_path / "m.ply"), "--camera", "0,0,4",
                *gt) == 0
    assert len(o3d.io.read_triangle_mesh(str(tmp_path / "m.ply")).triangles) > 1000
    assert _cli("reconstruct", cloud_path, "-o", str(tmp_path / "p.ply"), "--depth", "5", "--views", "12",
                "--knn", "12", *gt) == 0
    radii = np.linalg.norm(np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "p.ply")).vertices), axis=1)
    assert np.abs(radii - 1).mean() < 0.05  # inside out, or on unoriented normals, it would not be
    with pytest.raises(ValueError, match="three neighbours"):  # the flag reaches the fit
        _cli("reconstruct", cloud_path, "-o", str(tmp_path / "p.ply"), "--views", "12", "--knn", "2", *gt)
    with pytest.raises(ValueError, match="--knn"):
        _cli("reconstruct", cloud_path, "-o", str(tmp_path / "m.ply"), "--camera", "0,0,4", "--knn", "12", *gt)
    with pytest.raises(ValueError, match="--mesh"):
        _cli("normals", cloud_path, "-o", out, "--method", "gt")


def test_cli_network_precision(tmp_path):
    parser = build_parser()
    for flags, precision in (([], "auto"), (["--precision", "float32"], "float32"),
                             (["--precision", "bfloat16"], "bfloat16")):
        args = parser.parse_args(["normals", "in.ply", "-o", "out.ply", *flags])
        assert visibility_method(args).precision == precision
    with pytest.raises(SystemExit):
        parser.parse_args(["normals", "in.ply", "-o", "out.ply", "--precision", "float16"])


def test_cli_best_view_with_a_checkpoint(tmp_path, sphere):
    from o3dvis.nn import NetworkConfig, VisibilityNetwork

    torch.manual_seed(0)
    checkpoint = tmp_path / "tiny.safetensors"
    VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 16), feature_channels=8, num_frequencies=2,
                                    hidden=(16,))).save(checkpoint)
    cloud_path = str(tmp_path / "sphere.ply")
    o3d.io.write_point_cloud(cloud_path, _cloud(sphere[0][:1000]))
    assert _cli("best-view", cloud_path, "--model", str(checkpoint), "--steps", "3", "--starts", "2",
                "-o", str(tmp_path / "best.png"), "--plot", str(tmp_path / "loss.png")) == 0
    assert np.asarray(o3d.io.read_image(str(tmp_path / "best.png"))).shape == (480, 640, 3)
    assert (tmp_path / "loss.png").stat().st_size > 0
