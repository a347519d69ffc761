"""The accuracy bench (`o3dvis eval`) and the timing bench (`o3dvis bench`) on tiny data."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from o3dvis.baselines import hidden_point_removal_mask
from o3dvis.cli import main
from o3dvis.evaluation.evaluate import (Counts, category_of, eval_cloud, evaluate, markdown_table, subsample_indices,
                                        summarize)
from o3dvis.evaluation.speed import bench_cloud, benchmark, time_method
from o3dvis.training.data import list_samples, load_sample, prepare, write_shapes
from o3dvis.training.data.perturb import add_noise

POINTS, VIEWS = 2000, 3


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """Two labelled procedural shapes (category ``procedural``) and one in a subfolder ``sub``."""
    root = tmp_path_factory.mktemp("eval")
    meshes = root / "meshes"
    write_shapes(str(meshes), 2, seed=5)
    write_shapes(str(meshes / "sub"), 1, seed=6)
    report = prepare(meshes, root / "data", num_points=POINTS, num_views=VIEWS, progress=False)
    assert report["done"] == 3 and not report["failed"]
    return root / "data"


def _run(args: list[str], capsys) -> tuple[int, str]:
    code = main(["eval", *args])
    return code, capsys.readouterr().out


def _independent_hpr(data: Path, ks: list[float]) -> dict:
    """Pooled accuracy per k and per (k, category), computed from the files directly."""
    acc, by_cat = {}, {}
    for path in sorted(data.rglob("*.npz")):
        s = load_sample(path)
        cat = path.parent.name if path.parent != data else path.name.split("__")[0]
        points = s.points.astype(np.float64)
        diagonal = np.linalg.norm(points.max(axis=0) - points.min(axis=0))
        for k in ks:
            mask = hidden_point_removal_mask(points, s.cameras.astype(np.float64), diagonal * 10 ** k)
            right = mask == s.visibility
            for key, table in ((k, acc), ((k, cat), by_cat)):
                table.setdefault(key, []).append(right)
    pool = lambda lists: float(np.mean(np.concatenate([r.ravel() for r in lists])))  # noqa: E731
    return {"acc": {k: pool(v) for k, v in acc.items()}, "cat": {k: pool(v) for k, v in by_cat.items()}}


def test_eval_matches_an_independent_computation(data, tmp_path, capsys):
    out = tmp_path / "r.json"
    code, text = _run(["--data", str(data), "--points", str(POINTS), "--noise", "0", "--methods", "hpr",
                       "--hpr-k", "1,2,3", "--out", str(out)], capsys)
    assert code == 0
    report = json.loads(out.read_text())
    assert report["categories"] == {"procedural": 2, "sub": 1}
    (row,) = report["results"]
    truth = _independent_hpr(data, [1.0, 2.0, 3.0])
    best = max(truth["acc"], key=truth["acc"].get)
    assert row["param"] == f"k={best:g}"
    assert row["accuracy"] == pytest.approx(truth["acc"][best], abs=1e-12)
    for k in (1.0, 2.0, 3.0):
        assert row["sweep"][f"k={k:g}"] == pytest.approx(truth["acc"][k], abs=1e-12)
    for cat in ("procedural", "sub"):
        assert row["categories"][cat] == pytest.approx(truth["cat"][(best, cat)], abs=1e-12)
    assert f"{100 * truth['acc'][best]:.1f} (k={best:g})" in text
    assert out.with_suffix(".md").read_text() in text + "\n"


@pytest.fixture(scope="module")
def all_and_hpr(data):
    """(files, methods, rows by method) of "all points visible" and HPR on 500 noisy points."""
    files = list_samples(data)
    methods = {"all": {"": lambda p, c: np.ones((len(c), len(p)), dtype=bool)},
               "hpr": {"k=2": lambda p, c: hidden_point_removal_mask(
                   p, c, 100 * np.linalg.norm(p.max(axis=0) - p.min(axis=0)))}}
    per_file = evaluate(files, data, methods, [500], [0.02], seed=1, views=2, progress=False)
    rows = {r["method"]: r for r in summarize(per_file, methods, [500], [0.02])}
    return files, methods, rows


def test_fn_fp_rates_and_subsampled_noisy_clouds(data, all_and_hpr):
    files, methods, rows = all_and_hpr
    labels = np.concatenate([eval_cloud(load_sample(f), 500, 0.02, seed=1, views=2).labels.ravel() for f in files])
    assert labels.size == 3 * 2 * 500
    assert rows["all"]["accuracy"] == pytest.approx(labels.mean())
    assert rows["all"]["fn_rate"] == 0 and rows["all"]["fp_rate"] == 1
    tp = fp = fn = tn = 0
    for f in files:
        points, cameras, truth, _ = eval_cloud(load_sample(f), 500, 0.02, seed=1, views=2)
        pred = methods["hpr"]["k=2"](points, cameras)
        tp += (pred & truth).sum()
        fp += (pred & ~truth).sum()
        fn += (~pred & truth).sum()
        tn += (~pred & ~truth).sum()
    assert rows["hpr"]["accuracy"] == pytest.approx((tp + tn) / (tp + fp + fn + tn))
    assert rows["hpr"]["fn_rate"] == pytest.approx(fn / (tp + fn))
    assert rows["hpr"]["fp_rate"] == pytest.approx(fp / (fp + tn))


def test_per_file_accuracy_and_the_files_a_method_trails_the_baseline_most(all_and_hpr):
    files, _, rows = all_and_hpr
    for f in files:
        labels = eval_cloud(load_sample(f), 500, 0.02, seed=1, views=2).labels
        assert rows["all"]["file_accuracy"][f.name] == pytest.approx(labels.mean())
    gaps = {f.name: 100 * (rows["all"]["file_accuracy"][f.name] - rows["hpr"]["file_accuracy"][f.name])
            for f in files}
    text = markdown_table(list(rows.values())).splitlines()
    header = text.index("Files where all trails hpr most (accuracy difference, points):")
    assert text[header + 2] == "| file | 500 / 2 % |"
    assert text[header + 4:] == [f"| {f} | {gaps[f]:+.1f} |" for f in sorted(gaps, key=gaps.get)]


def test_subsampling_and_noise_are_seeded_and_bounded(data):
    s = load_sample(list_samples(data)[0])
    a, _, la, na = eval_cloud(s, 700, 0.01, seed=3)
    b, _, lb, _ = eval_cloud(s, 700, 0.01, seed=3)
    c, _, _, nc = eval_cloud(s, 700, 0.0, seed=3)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(la, lb)
    idx = subsample_indices(len(s.points), 700, 3, s.name)
    assert len(np.unique(idx)) == 700
    np.testing.assert_array_equal(c, s.points[idx])  # same points with and without noise
    np.testing.assert_array_equal(na, nc)
    np.testing.assert_array_equal(nc, s.normals[idx])
    diagonal = np.linalg.norm(s.points.max(axis=0) - s.points.min(axis=0))
    moved = np.linalg.norm(a - c, axis=1)
    assert moved.max() <= 0.01 * diagonal * (1 + 1e-9) and moved.max() > 0.008 * diagonal
    assert not np.array_equal(subsample_indices(len(s.points), 700, 4, s.name), idx)
    np.testing.assert_array_equal(subsample_indices(10, 50, 0, "x"), np.arange(10))
    with pytest.raises(ValueError):
        add_noise(c, -0.1, 1.0, np.random.default_rng())
    with pytest.raises(ValueError):
        eval_cloud(s, 700, 0.0, views=VIEWS + 1)


def test_absent_method_stays_absent(data, tmp_path, capsys):
    out = tmp_path / "r.json"
    code, text = _run(["--data", str(data), "--points", "300", "--methods", "hpr,neural", "--hpr-k", "2",
                       "--checkpoint", str(tmp_path / "missing.safetensors"), "--out", str(out)], capsys)
    assert code == 0
    report = json.loads(out.read_text())
    assert {r["method"] for r in report["results"]} == {"hpr"}
    assert "missing.safetensors" in report["absent"]["neural"]
    assert "neural: absent" in text and "| neural |" not in text
    code, _ = _run(["--data", str(data), "--methods", "neural", "--checkpoint", str(tmp_path / "no")], capsys)
    assert code == 1


def test_neural_checkpoint_is_scored_like_any_method(data, tmp_path, capsys):
    pytest.importorskip("o3dvis.neural")
    import torch

    from o3dvis.nn import VisibilityNetwork
    from o3dvis.nn.network import NetworkConfig
    from o3dvis.neural import NeuralVisibility

    torch.manual_seed(0)
    for use_normals, name, other in ((False, "neural", "neural-normals"), (True, "neural-normals", "neural")):
        ckpt = tmp_path / f"tiny{use_normals}.safetensors"
        VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8, 8), feature_channels=8, hidden=(8,),
                                        use_normals=use_normals)).save(ckpt)
        out = tmp_path / "r.json"
        code, _ = _run(["--data", str(data), "--points", "800", "--methods", f"{name},{other}",
                        "--checkpoint", str(ckpt), "--out", str(out)], capsys)
        assert code == 0
        report = json.loads(out.read_text())
        (row,) = report["results"]
        assert row["method"] == name and other in report["absent"]
        vis = NeuralVisibility(VisibilityNetwork.load(ckpt))
        total = Counts()
        for f in list_samples(data):
            points, cameras, truth, normals = eval_cloud(load_sample(f), 800, 0.0)
            field = vis.encode(points, normals=normals if use_normals else False)
            total = total + Counts.of(field.query(cameras), truth)
        assert row["accuracy"] == pytest.approx(total.accuracy)


def test_neural_names_take_a_number_of_rotations_and_a_precision(tmp_path):
    pytest.importorskip("o3dvis.neural")
    from o3dvis.evaluation.methods import resolve_methods
    from o3dvis.nn import VisibilityNetwork
    from o3dvis.nn.network import NetworkConfig

    ckpt = tmp_path / "tiny.safetensors"
    VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8), feature_channels=8, hidden=(8,))).save(ckpt)
    methods, absent = resolve_methods(["neural", "neural-x3", "neural-normals-x2", "neural-float32",
                                       "neural-x2-bfloat16", "neural-estimate"], ckpt)
    assert "neural-estimate" in absent and "no normals model" in absent["neural-estimate"]
    assert len(methods["neural"][""].visibility.rotations) == 1
    assert len(methods["neural-x3"][""].visibility.rotations) == 3
    assert "3 rotations" in methods["neural-x3"][""].__name__
    assert "neural-normals-x2" in absent and "take no normals" in absent["neural-normals-x2"]
    assert methods["neural"][""].visibility.precision == "auto"
    assert methods["neural-float32"][""].visibility.precision == "float32"
    bf16 = methods["neural-x2-bfloat16"][""]
    assert bf16.visibility.precision == "bfloat16" and len(bf16.visibility.rotations) == 2
    assert "float32" in methods["neural-float32"][""].__name__ and "2 rotations, bfloat16" in bf16.__name__
    for bad in ("neural-x0", "neural-x", "hpr-x2", "neural-x2-x2", "neural-float16", "neural-float32-x2",
                "hpr-float32"):
        with pytest.raises(ValueError, match="unknown method"):
            resolve_methods([bad], ckpt)


def test_cache_resumes(data, tmp_path, capsys):
    cache = tmp_path / "cache"
    args = ["--data", str(data), "--points", "400", "--methods", "hpr", "--hpr-k", "2", "--cache", str(cache),
            "--out", str(tmp_path / "a.json")]
    assert _run(args, capsys)[0] == 0
    files = sorted(cache.glob("*.json"))
    assert len(files) == 3
    # doctor one file's cached counts: a rerun must read them instead of recomputing
    stored = json.loads(files[0].read_text())
    stored["counts"]["hpr"]["k=2"]["400"]["0"] = [0, 0, 0, 400 * VIEWS]
    files[0].write_text(json.dumps(stored))
    assert _run(args[:-1] + [str(tmp_path / "b.json")], capsys)[0] == 0
    first = json.loads((tmp_path / "a.json").read_text())["results"][0]["accuracy"]
    second = json.loads((tmp_path / "b.json").read_text())["results"][0]["accuracy"]
    assert second != first


def test_category_of(tmp_path):
    assert category_of(tmp_path / "a" / "x.npz", tmp_path) == "a"
    assert category_of(tmp_path / "src__x.npz", tmp_path) == "src"
    assert category_of(tmp_path / "x.npz", tmp_path) == "all"
    with pytest.raises(FileNotFoundError):
        list_samples(tmp_path / "none")
    with pytest.raises(ValueError):
        list_samples(tmp_path)


class _TwoStage:
    """A method with separate encode/query stages, like the network."""

    def __init__(self):
        self.threads = []  # threads alive at each encode

    def encode(self, points):
        self.threads.append(threading.active_count())
        return self

    def query(self, cameras):
        return np.ones((len(cameras), 1), dtype=bool)

    def __call__(self, points, cameras):
        return self.encode(points).query(cameras)


def test_benchmark_times_methods_against_open3d(capsys):
    two = _TwoStage()
    t = time_method(two, bench_cloud(10, 4), repeats=2)
    assert set(t) == {"seconds", "encode_s", "query_s", "peak_mib"}
    # warm-up, the untimed run with the memory sampler's thread beside it, 2 timed runs without it
    warm, sampled, *timed = two.threads
    assert len(timed) == 2 and sampled == warm + 1 and timed == [warm, warm]
    rows = benchmark({"hpr": lambda p, c: hidden_point_removal_mask(p, c, 1e3)}, [2048], [1, 3],
                     progress=False)
    assert [(r["method"], r["views"]) for r in rows] == [("Open3D HPR", 1), ("hpr", 1), ("Open3D HPR", 3),
                                                         ("hpr", 3)]
    for ref, row in zip(rows[::2], rows[1::2]):
        assert row["reference_s"] == ref["seconds"] > 0
        assert row["speedup"] == pytest.approx(ref["seconds"] / row["seconds"])
    assert main(["bench", "--points", "2048", "--views", "2", "--methods", "hpr,neural",
                 "--checkpoint", "/nonexistent.safetensors"]) == 0
    text = capsys.readouterr().out
    assert "| 2,048 | 2 | Open3D HPR |" in text and "| 2,048 | 2 | hpr |" in text
    assert "neural: absent" in text
    from o3dvis.nn import native

    from o3dvis.clib import cpu_name
    from o3dvis.threads import usable_cores

    said = (f"C kernels (o3dvis.nn.native, {native.variant()} variant)" if native.available()
            else "torch ops (no C kernels built)")
    assert f"per-view steps of the neural methods on the CPU: {said}; " in text
    assert f"{cpu_name() or 'CPU unnamed'}, {usable_cores()} cores usable" in text


def test_the_octree_column_is_the_part_of_the_encoding_that_built_it(monkeypatch):
    """Timed within the encoding it belongs to: an octree built apart, at a slower moment (here a
    standalone build made slow on purpose), never shows, and the columns add up."""
    import time as _time

    from o3dvis.neural import NeuralVisibility
    from o3dvis.nn import NetworkConfig, VisibilityNetwork
    from o3dvis.evaluation.methods import NeuralMethod

    encoding = threading.local()
    encode, build = NeuralVisibility.encode, VisibilityNetwork.octree

    def flagged_encode(self, *args, **kwargs):
        encoding.on = True
        try:
            return encode(self, *args, **kwargs)
        finally:
            encoding.on = False

    def octree(self, *args, **kwargs):
        if not getattr(encoding, "on", False):
            _time.sleep(0.3)
        return build(self, *args, **kwargs)

    monkeypatch.setattr(NeuralVisibility, "encode", flagged_encode)
    monkeypatch.setattr(VisibilityNetwork, "octree", octree)
    network = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8), feature_channels=8, hidden=(8,))).eval()
    method = NeuralMethod(NeuralVisibility(network), "tiny")
    rows = benchmark({"neural": method}, [2048], [2], repeats=2, progress=False)
    neural = next(r for r in rows if r["method"] == "neural")
    assert 0 < neural["octree_s"] <= neural["encode_s"] <= neural["seconds"]
    assert VisibilityNetwork.octree is octree  # the bench's timing hook is gone


def test_peak_memory_sees_a_transient_allocation():
    import time as _time

    from o3dvis.evaluation.speed import PeakMemory

    with PeakMemory() as memory:
        block = np.ones(64 * 2**20 // 8)  # 64 MiB, touched
        _time.sleep(0.02)
        del block
    if memory.peak_mib is None:
        pytest.skip("no /proc/self/statm here")
    assert 50 < memory.peak_mib < 200


def test_balanced_accuracy_is_the_mean_of_both_recalls():
    c = Counts(tp=8, fp=1, fn=2, tn=9)
    assert c.balanced_accuracy == pytest.approx((0.8 + 0.9) / 2)
    assert np.isnan(Counts(tp=3, fp=0, fn=1, tn=0).balanced_accuracy)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    """Two procedural scenes (rooms, street), each sampled uniformly and LiDAR-like, 6 cameras inside, 2 out."""
    from o3dvis.training.data.prepare import prepare_scenes

    root = tmp_path_factory.mktemp("scenes")
    assert prepare_scenes(root, 2, None, num_points=3000, num_views=8, progress=False)["done"] == 2
    return root


def test_scene_clouds_keep_inside_cameras_and_scale_noise_by_camera_distance(scenes):
    from o3dvis.evaluation.evaluate import camera_distance, inside_cameras

    sample = load_sample(scenes / "street-uniform__00001.npz")
    inside = inside_cameras(sample)
    assert inside.tolist() == [True] * 6 + [False] * 2
    clean = eval_cloud(sample, 3000, 0.0, inside=True)
    np.testing.assert_array_equal(clean.cameras, sample.cameras[:6])
    np.testing.assert_array_equal(clean.labels, sample.visibility[:6])
    assert eval_cloud(sample, 3000, 0.0, views=4, inside=True).cameras.shape == (4, 3)
    noisy = eval_cloud(sample, 3000, 0.01, inside=True)
    moved = np.linalg.norm(noisy.points - clean.points, axis=1)
    scale = camera_distance(sample.points, sample.cameras[:6].astype(np.float64))
    assert scale < 0.5 * np.linalg.norm(np.ptp(sample.points, axis=0))  # not the diagonal
    assert 0.9 * 0.01 * scale < moved.max() <= 0.01 * scale + 1e-9


def test_scene_eval_tables_per_sampling_match_an_independent_computation(scenes, tmp_path, capsys):
    out = tmp_path / "s.json"
    code, text = _run(["--scenes", "--data", str(scenes), "--points", "3000", "--noise", "0",
                       "--methods", "hpr,zbuffer", "--hpr-k", "1,2", "--splat", "1", "--out", str(out)], capsys)
    assert code == 0
    assert "### lidar (2 files)" in text and "### uniform (2 files)" in text
    assert "| hpr k=2 (documented) |" in text and "| zbuffer - tuned hpr (points) |" in text
    report = json.loads(out.read_text())
    for sampling in ("uniform", "lidar"):
        right = []
        for path in sorted(scenes.glob(f"*-{sampling}__*.npz")):
            s = load_sample(path)
            points = s.points.astype(np.float64)
            diagonal = np.linalg.norm(points.max(axis=0) - points.min(axis=0))
            inside = ((s.cameras > points.min(axis=0)) & (s.cameras < points.max(axis=0))).all(axis=1)
            mask = hidden_point_removal_mask(points, s.cameras[inside].astype(np.float64), diagonal * 100)
            right.append(mask == s.visibility[inside])
        row = next(r for r in report["results"][sampling] if r["method"] == "hpr")
        assert row["sweep"]["k=2"] == pytest.approx(np.mean(np.concatenate([r.ravel() for r in right])))
        assert row["accuracy"] == max(row["sweep"].values())
        assert row["balanced_accuracy"] == max(row["balanced_sweep"].values())


def test_a_scene_file_without_a_camera_inside_counts_nothing(scenes):
    from o3dvis.baselines import hpr_method
    from o3dvis.evaluation.evaluate import evaluate_sample

    sample = load_sample(scenes / "rooms-uniform__00000.npz")
    outside = sample.__class__(sample.points, sample.normals, sample.cameras[6:], sample.visibility[6:], "out")
    assert eval_cloud(outside, 3000, 0.01, inside=True).cameras.shape == (0, 3)
    counts = evaluate_sample(outside, {"hpr": {"k=2": hpr_method(2.0)}}, [3000], [0.0], inside=True)
    assert counts["hpr"]["k=2"]["3000"]["0"] == [0, 0, 0, 0]


def test_neural_estimate_encodes_with_normals_estimated_first(monkeypatch):
    pytest.importorskip("o3dvis.neural")
    from o3dvis.evaluation.methods import resolve_methods

    names = ["neural-estimate", "neural", "neural-balanced", "neural-best"]
    methods, absent = resolve_methods(names)
    if absent:
        pytest.skip(f"no shipped weights: {absent}")
    asked = []
    for name in methods:
        monkeypatch.setattr(methods[name][""].visibility, "encode",
                            lambda points, normals=None, quality=None: asked.append((normals, quality)))
    for name in names:
        methods[name][""].encode(np.zeros((4, 3)))
    assert asked == [("estimate", "fast"), (None, "fast"), (None, "balanced"), (None, "best")]
    assert "estimated normals" in methods["neural-estimate"][""].__name__
    assert "best" in methods["neural-best"][""].__name__


def test_a_normals_checkpoint_answers_the_second_pass_after_the_shipped_first(tmp_path):
    pytest.importorskip("o3dvis.neural")
    import torch

    from o3dvis.models import load_model
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork
    from o3dvis.evaluation.methods import resolve_methods

    ckpt = tmp_path / "normals.safetensors"
    VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8), feature_channels=8, hidden=(8,),
                                    use_normals=True)).save(ckpt)
    methods, absent = resolve_methods(["neural-estimate", "neural-normals", "neural"], ckpt)
    assert "neural" in absent and "need normals" in absent["neural"]
    two_pass = methods["neural-estimate"][""].visibility
    assert two_pass.normals_network.config.channels == (8, 8)
    shipped = load_model("default")
    assert two_pass.network.config == shipped.config
    torch.testing.assert_close(next(two_pass.network.parameters()), next(shipped.parameters()))
    assert methods["neural-normals"][""].visibility.network.config.use_normals
