"""Training data (``o3dvis.training.data``): the resumable, deterministic prepare, broken samples
refused, and the first-pass normals drawn for the share asked."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3dvis.training.data import label_mesh, load_sample, prepare


def _write_meshes(folder, formats=("ply", "obj", "off", "stl")) -> list:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, fmt in enumerate(formats):
        mesh = o3d.geometry.TriangleMesh.create_box(1.0 + i, 1.0, 0.5)
        mesh.compute_triangle_normals()  # STL needs them
        path = folder / f"box{i}.{fmt}"
        assert o3d.io.write_triangle_mesh(str(path), mesh)
        paths.append(path)
    return paths


def _box_analytic(sample) -> np.ndarray:
    """Visibility on a convex mesh: the point's face faces the camera (normals are oriented outward)."""
    to_cam = sample.cameras[:, None].astype(np.float64) - sample.points[None]
    return np.einsum("nk,vnk->vn", sample.normals.astype(np.float64), to_cam) > 0


def test_prepare_reads_all_formats_resumes_and_skips_broken(tmp_path):
    meshes = tmp_path / "meshes"
    _write_meshes(meshes)
    (meshes / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nthis is not a mesh\n")
    out = tmp_path / "out"
    first = prepare(meshes, out, num_points=2000, num_views=4, workers=1, progress=False)
    assert first["done"] == 4 and first["skipped"] == 0
    assert [p for p, _ in first["failed"]] == [str(meshes / "broken.ply")]
    files = sorted(out.glob("*.npz"))
    assert [f.name for f in files] == ["box0.npz", "box1.npz", "box2.npz", "box3.npz"]
    for f in files:
        s = load_sample(f)
        assert s.points.shape == (2000, 3) and s.normals.shape == (2000, 3)
        assert s.cameras.shape == (4, 3) and s.visibility.shape == (4, 2000)
        np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-5)
        assert (s.visibility == _box_analytic(s)).mean() > 0.99
        lo, hi = s.points.min(axis=0), s.points.max(axis=0)
        np.testing.assert_allclose(np.linalg.norm(s.cameras - (lo + hi) / 2, axis=1),
                                   np.linalg.norm(hi - lo), rtol=1e-3)
    stamps = [f.stat().st_mtime_ns for f in files]
    second = prepare(meshes, out, num_points=2000, num_views=4, workers=1, progress=False)
    assert second["done"] == 0 and second["skipped"] == 4 and len(second["failed"]) == 1
    assert [f.stat().st_mtime_ns for f in files] == stamps


def test_prepare_keeps_subfolder_as_category_prefix(tmp_path):
    _write_meshes(tmp_path / "meshes" / "cat", formats=("ply",))
    prepare(tmp_path / "meshes", tmp_path / "out", num_points=500, num_views=2, progress=False)
    assert [f.name for f in (tmp_path / "out").glob("*.npz")] == ["cat__box0.npz"]


def test_prepare_is_deterministic_for_a_seed(tmp_path):
    _write_meshes(tmp_path / "meshes", formats=("ply",))
    runs = {}
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        prepare(tmp_path / "meshes", tmp_path / name, num_points=1000, num_views=3, seed=seed, progress=False)
        runs[name] = load_sample(tmp_path / name / "box0.npz")
    for field in ("points", "normals", "cameras", "visibility"):
        np.testing.assert_array_equal(getattr(runs["a"], field), getattr(runs["b"], field))
    assert not np.array_equal(runs["a"].points, runs["c"].points)
    direct = label_mesh(tmp_path / "meshes" / "box0.ply", 1000, 3, seed=3)
    np.testing.assert_array_equal(direct.points, runs["a"].points)
    np.testing.assert_array_equal(direct.visibility, runs["a"].visibility)


def test_load_sample_rejects_a_broken_file(tmp_path):
    bad = tmp_path / "x.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(ValueError):
        load_sample(bad)


def test_training_draws_the_first_pass_normals_for_the_share_asked(tmp_path):
    """Augmentation(estimated_normals=1) gives each cloud the normals normals='estimate' computes
    (unit, mostly on the side of the exact ones, not equal to them: 5 000 points of a procedural
    shape); the points, cameras and labels are the draw of estimated_normals=0, which draws as before."""
    torch = pytest.importorskip("torch")
    from o3dvis.training.data.dataset import Augmentation, VisibilityDataset
    from o3dvis.training.data.prepare import label_mesh
    from o3dvis.training.data.sample import save_sample
    from o3dvis.training.data.shapes import write_shapes

    mesh = write_shapes(str(tmp_path / "meshes"), 1, seed=6)[0]
    sample = label_mesh(mesh, num_points=6000, num_views=4)
    save_sample(sample, tmp_path / "s.npz")
    draw = dict(min_points=5000, max_points=5001, noise_prob=0.0)
    exact = VisibilityDataset([tmp_path / "s.npz"], Augmentation(**draw), seed=2, length=2)
    estimated = VisibilityDataset([tmp_path / "s.npz"], Augmentation(**draw, estimated_normals=1.0), seed=2, length=2)
    for k in range(2):
        (p0, n0, c0, l0), (p1, n1, c1, l1) = exact[k], estimated[k]
        assert torch.equal(p0, p1) and torch.equal(c0, c1) and torch.equal(l0, l1)
        torch.testing.assert_close(n1.norm(dim=1), torch.ones(len(n1)), rtol=0, atol=1e-5)
        cosine = (n0 * n1).sum(dim=1)
        assert not torch.allclose(n0, n1, atol=1e-3) and (cosine > 0).float().mean() > 0.7  # random: 0.5
