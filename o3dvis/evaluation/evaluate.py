"""Accuracy of visibility methods against ray-cast labels, the paper's protocol.

For every labelled file, density and noise level, each method (and each
parameter of a baseline's sweep) labels a subsample of the points from the
file's viewpoints. Counts of true/false positives/negatives are pooled over
points, views and files; a baseline's parameter is then tuned per density and
noise level over the whole set (the best of its sweep), as the paper did.

* Subsampling is seeded by (seed, file name, density): every method and noise
  level sees the same points.
* Noise is added after labelling: each point moves in a uniformly random
  direction by a distance uniform in [0, level x bounding-box diagonal].
* Category = the file's subfolder below the data folder, else the part of its
  name before ``__``.

Scenes (``inside=True``, samples from ``o3dvis prepare --scenes``) are scored
from the cameras inside the cloud's bounding box only, and their noise is
relative to the median distance from those cameras to the points instead of
the diagonal (a street's diagonal is ten times what its cameras look across).
:func:`scene_table` reports accuracy and balanced accuracy per sampling, each
baseline tuned per column for each of the two, and the differences to tuned HPR.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..baselines import Method
from ..geometry import diagonal
from ..training.data.perturb import add_noise
from ..training.data.sample import Sample, load_sample

__all__ = ["Counts", "category_of", "subsample_indices", "EvalCloud", "eval_cloud",
           "run_method", "inside_cameras", "camera_distance",
           "evaluate_sample", "evaluate", "summarize", "markdown_table", "scene_table"]


@dataclass
class Counts:
    """Confusion counts, positive = visible."""

    tp: int = 0
    fp: int = 0
    fn: int = 0
    tn: int = 0

    @classmethod
    def of(cls, predicted: np.ndarray, truth: np.ndarray) -> "Counts":
        """Counts of a predicted mask against the true one (same shape, bool)."""
        predicted, truth = np.asarray(predicted, dtype=bool), np.asarray(truth, dtype=bool)
        if predicted.shape != truth.shape:
            raise ValueError(f"prediction shape {predicted.shape} differs from labels {truth.shape}")
        tp = int(np.count_nonzero(predicted & truth))
        fp = int(np.count_nonzero(predicted & ~truth))
        fn = int(np.count_nonzero(~predicted & truth))
        return cls(tp, fp, fn, truth.size - tp - fp - fn)

    def __add__(self, other: "Counts") -> "Counts":
        return Counts(self.tp + other.tp, self.fp + other.fp, self.fn + other.fn, self.tn + other.tn)

    @property
    def total(self) -> int:
        return self.tp + self.fp + self.fn + self.tn

    @property
    def accuracy(self) -> float:
        """Correct labels / all labels."""
        return (self.tp + self.tn) / self.total if self.total else float("nan")

    @property
    def balanced_accuracy(self) -> float:
        """Mean of the recall of visible points and the recall of hidden points."""
        return (self.tp / (self.tp + self.fn) + self.tn / (self.tn + self.fp)) / 2 \
            if self.tp + self.fn and self.tn + self.fp else float("nan")

    @property
    def fn_rate(self) -> float:
        """Share of visible points predicted hidden."""
        return self.fn / (self.tp + self.fn) if self.tp + self.fn else float("nan")

    @property
    def fp_rate(self) -> float:
        """Share of hidden points predicted visible."""
        return self.fp / (self.fp + self.tn) if self.fp + self.tn else float("nan")


def category_of(path: Path, data_dir: Path) -> str:
    """Subfolder below ``data_dir``, else the file-name prefix before ``__``, else ``all``."""
    rel = Path(path).relative_to(data_dir)
    if len(rel.parts) > 1:
        return rel.parts[0]
    return rel.stem.split("__")[0] if "__" in rel.stem else "all"


def _key(x: float) -> str:
    return f"{x:g}"


def _rng(seed: int, name: str, *more: int) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(name.encode()), *more])


def subsample_indices(num_total: int, num_points: int, seed: int, name: str) -> np.ndarray:
    """Sorted indices of ``num_points`` of ``num_total`` points (all when fewer), seeded by name."""
    if num_points >= num_total:
        return np.arange(num_total)
    return np.sort(_rng(seed, name, num_points).choice(num_total, num_points, replace=False))


class EvalCloud(NamedTuple):
    """What a method is scored on: points, cameras, true labels, and the points' normals."""

    points: np.ndarray
    cameras: np.ndarray
    labels: np.ndarray
    normals: np.ndarray


def inside_cameras(sample: Sample) -> np.ndarray:
    """(V,) bool: the cameras strictly inside the bounding box of the sample's points."""
    lo, hi = sample.points.min(axis=0), sample.points.max(axis=0)
    return ((sample.cameras > lo) & (sample.cameras < hi)).all(axis=1)


def camera_distance(points: np.ndarray, cameras: np.ndarray, count: int = 4096) -> float:
    """Median distance from the cameras to (the first ``count`` of) the points."""
    return float(np.median(np.linalg.norm(points[None, :count] - cameras[:, None], axis=2)))


def eval_cloud(sample: Sample, num_points: int, noise: float, seed: int = 0,
               views: int | None = None, inside: bool = False) -> EvalCloud:
    """The cloud a method is scored on.

    Args:
        sample: a labelled sample.
        num_points: density (all points when the sample has fewer).
        noise: noise level as a fraction of the bounding-box diagonal, or with
            ``inside`` of :func:`camera_distance` (normals are not perturbed).
        seed: seed of subsampling and noise.
        views: use the first ``views`` viewpoints (default: all).
        inside: keep only those of them inside the cloud's bounding box (scenes;
            there may be none).

    Returns:
        ``EvalCloud(points (n, 3) float64, cameras (V, 3), labels (V, n) bool, normals (n, 3))``.

    Raises:
        ValueError: fewer viewpoints than ``views``.
    """
    views = len(sample.cameras) if views is None else views
    if not 1 <= views <= len(sample.cameras):
        raise ValueError(f"{sample.name} has {len(sample.cameras)} viewpoints, {views} were asked for")
    keep = np.arange(views)
    if inside:
        keep = keep[inside_cameras(sample)[:views]]
    cameras = sample.cameras[keep].astype(np.float64)
    idx = subsample_indices(len(sample.points), num_points, seed, sample.name)
    points = sample.points[idx].astype(np.float64)
    if noise and len(cameras):
        rng = _rng(seed, sample.name, num_points, round(noise * 1e6))
        scale = camera_distance(sample.points, cameras) if inside else diagonal(sample.points)
        points = add_noise(points, noise, scale, rng)
    return EvalCloud(points, cameras, sample.visibility[keep][:, idx], sample.normals[idx].astype(np.float64))


def run_method(method: Method, cloud: EvalCloud) -> np.ndarray:
    """``method(points, cameras)``, with ``normals=`` for methods that declare ``needs_normals``."""
    if getattr(method, "needs_normals", False):
        return method(cloud.points, cloud.cameras, normals=cloud.normals)
    return method(cloud.points, cloud.cameras)


def evaluate_sample(sample: Sample, methods: dict[str, dict[str, Method]], densities: Iterable[int],
                    noises: Iterable[float], seed: int = 0, views: int | None = None,
                    done: dict | None = None, inside: bool = False) -> dict:
    """Confusion counts of every method and parameter on one sample.

    Args:
        sample: a labelled sample.
        methods: ``{method name: {parameter label: method}}``.
        densities: numbers of points.
        noises: noise levels (fractions of the bounding-box diagonal).
        seed: seed of subsampling and noise.
        views: number of viewpoints (default: all of the sample's).
        done: results already known (same layout as the return value); kept, not recomputed.
        inside: score the cameras inside the cloud only (see :func:`eval_cloud`).

    Returns:
        ``result[method][label][f"{density:g}"][f"{noise:g}"] = [tp, fp, fn, tn]``.
    """
    result = json.loads(json.dumps(done or {}))
    for density in densities:
        for noise in noises:
            todo = [(name, label, method) for name, sweep in methods.items() for label, method in sweep.items()
                    if _key(noise) not in result.get(name, {}).get(label, {}).get(_key(density), {})]
            if not todo:
                continue
            cloud = eval_cloud(sample, density, noise, seed, views, inside)
            for name, label, method in todo:
                c = Counts.of(run_method(method, cloud), cloud.labels) if len(cloud.cameras) else Counts()
                result.setdefault(name, {}).setdefault(label, {}).setdefault(_key(density), {})[_key(noise)] = \
                    [c.tp, c.fp, c.fn, c.tn]
    return result


def _cache_path(cache_dir: Path, path: Path, seed: int, views: int | None, inside: bool) -> Path:
    return cache_dir / f"{path.stem}.s{seed}.v{views or 'all'}{'.inside' if inside else ''}.json"


def _read_cache(cache: Path, path: Path) -> dict:
    stat = path.stat()
    try:
        data = json.loads(cache.read_text())
    except (OSError, ValueError):
        return {}
    return data["counts"] if data.get("file") == [stat.st_size, stat.st_mtime_ns] else {}


def _write_cache(cache: Path, path: Path, fresh: dict) -> None:
    """Adds ``fresh`` results (whole methods) to the cache, re-read now: runs of other methods may share it."""
    stat = path.stat()
    tmp = cache.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps({"file": [stat.st_size, stat.st_mtime_ns],
                               "counts": {**_read_cache(cache, path), **fresh}}))
    os.replace(tmp, cache)


def evaluate(files: list[Path], data_dir: str | Path, methods: dict[str, dict[str, Method]],
             densities: list[int], noises: list[float], seed: int = 0, views: int | None = None,
             cache_dir: str | Path | None = None, cached: Iterable[str] = (), progress: bool = True,
             inside: bool = False) -> dict:
    """Confusion counts of every method on every file, resuming from a cache.

    Args:
        files: sample files (see :func:`o3dvis.training.data.sample.list_samples`).
        data_dir: their root folder (for categories).
        methods: ``{method name: {parameter label: method}}``.
        densities: numbers of points.
        noises: noise levels.
        seed: seed of subsampling and noise.
        views: number of viewpoints per file (default: all).
        cache_dir: folder keeping per-file counts, so a rerun resumes.
        cached: names of the methods whose results may be cached (deterministic ones).
        progress: show a tqdm bar.
        inside: score the cameras inside the cloud only (see :func:`eval_cloud`).

    Returns:
        ``{file name: {"category": str, "counts": counts as in :func:`evaluate_sample`}}``.
    """
    from tqdm import tqdm

    data_dir = Path(data_dir)
    cache_root = Path(cache_dir) if cache_dir else None
    if cache_root:
        cache_root.mkdir(parents=True, exist_ok=True)
    out = {}
    for path in tqdm(files, desc="eval", unit="file", disable=not progress):
        cache = _cache_path(cache_root, path, seed, views, inside) if cache_root else None
        stored = _read_cache(cache, path) if cache else {}
        done = {name: stored[name] for name in cached if name in stored}
        counts = evaluate_sample(load_sample(path), methods, densities, noises, seed, views, done, inside)
        fresh = {n: counts[n] for n in cached if n in counts and counts[n] != stored.get(n)}
        if cache and fresh:
            _write_cache(cache, path, fresh)
        out[path.name] = {"category": category_of(path, data_dir), "counts": counts}
    return out


def summarize(per_file: dict, methods: dict[str, dict[str, Method]], densities: list[int],
              noises: list[float]) -> list[dict]:
    """Pooled scores per method, density and noise, with the sweep's best parameter.

    Returns:
        One row per (method, density, noise): ``method, points, noise, param``
        (best label), ``accuracy, fn_rate, fp_rate, categories`` ({category:
        accuracy}), ``sweep`` ({label: accuracy}), ``files`` (their number),
        ``file_accuracy`` ({file name: accuracy}, with the best parameter),
        ``balanced_param`` (the label best by balanced accuracy),
        ``balanced_accuracy`` (with it), ``balanced_sweep`` ({label: balanced accuracy}).
    """
    rows = []
    for name, sweep in methods.items():
        for density in densities:
            for noise in noises:
                pooled: dict[str, Counts] = {}
                by_cat: dict[str, dict[str, Counts]] = {}
                by_file: dict[str, dict[str, Counts]] = {}
                for file, entry in per_file.items():
                    for label in sweep:
                        c = Counts(*entry["counts"][name][label][_key(density)][_key(noise)])
                        pooled[label] = pooled.get(label, Counts()) + c
                        cat = by_cat.setdefault(label, {})
                        cat[entry["category"]] = cat.get(entry["category"], Counts()) + c
                        by_file.setdefault(label, {})[file] = c
                best = max(sweep, key=lambda label: pooled[label].accuracy)
                balanced = max(sweep, key=lambda label: pooled[label].balanced_accuracy)
                rows.append({"method": name, "points": density, "noise": noise, "param": best,
                             "accuracy": pooled[best].accuracy, "fn_rate": pooled[best].fn_rate,
                             "fp_rate": pooled[best].fp_rate,
                             "categories": {k: v.accuracy for k, v in sorted(by_cat[best].items())},
                             "sweep": {label: pooled[label].accuracy for label in sweep},
                             "files": len(per_file),
                             "file_accuracy": {k: v.accuracy for k, v in by_file[best].items()},
                             "balanced_param": balanced,
                             "balanced_accuracy": pooled[balanced].balanced_accuracy,
                             "balanced_sweep": {label: pooled[label].balanced_accuracy for label in sweep}})
    return rows


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


def markdown_table(rows: list[dict], absent: dict[str, str] | None = None,
                   category_files: dict[str, int] | None = None) -> str:
    """Markdown: a summary (accuracy % per density, best parameter in brackets), then details.

    Args:
        rows: from :func:`summarize`.
        absent: methods that could not run, with the reason (listed under the tables).
        category_files: number of files per category (shown in the column headers).
    """
    densities = sorted({r["points"] for r in rows})
    keys = sorted({(r["method"], r["noise"]) for r in rows}, key=lambda k: (k[1], k[0]))
    by = {(r["method"], r["noise"], r["points"]): r for r in rows}
    lines = ["Accuracy % = correct labels / all labels, pooled over points, views and files; "
             "(best parameter of the sweep, tuned over the whole set per column).", "",
             "| method | noise | " + " | ".join(f"{d:,} pts" for d in densities) + " |",
             "|---|---|" + "---|" * len(densities)]
    for method, noise in keys:
        cells = []
        for d in densities:
            r = by.get((method, noise, d))
            cells.append("" if r is None else _pct(r["accuracy"]) + (f" ({r['param']})" if r["param"] else ""))
        lines.append(f"| {method} | {100 * noise:g} % | " + " | ".join(cells) + " |")
    categories = sorted({c for r in rows for c in r["categories"]})
    counts = category_files or {}
    lines += ["", "| method | param | points | noise | accuracy % | FN rate % | FP rate % | "
              + " | ".join(f"{c} ({counts[c]})" if c in counts else c for c in categories) + " |", "|---" * (7 + len(categories)) + "|"]
    for r in sorted(rows, key=lambda r: (r["noise"], r["method"], r["points"])):
        lines.append(f"| {r['method']} | {r['param'] or '-'} | {r['points']:,} | {100 * r['noise']:g} % | "
                     f"{_pct(r['accuracy'])} | {_pct(r['fn_rate'])} | {_pct(r['fp_rate'])} | "
                     + " | ".join(_pct(r["categories"][c]) if c in r["categories"] else "" for c in categories)
                     + " |")
    lines += _gap_tables(rows)
    for name, reason in (absent or {}).items():
        lines.append(f"\n{name}: absent ({reason})")
    return "\n".join(lines) + "\n"


def _gap_tables(rows: list[dict], baseline: str = "hpr", worst: int = 8) -> list[str]:
    """Markdown lines: per method, the files where it trails the tuned ``baseline`` most.

    Files are ranked by the mean over the columns (density, noise) of the method's
    accuracy minus the baseline's (with the baseline's parameter tuned over the
    whole set, as in the summary); each column's difference is shown, in points.
    """
    base = {(r["points"], r["noise"]): r["file_accuracy"] for r in rows if r["method"] == baseline}
    lines = []
    for method in sorted({r["method"] for r in rows} - {baseline}):
        mine = [r for r in sorted(rows, key=lambda r: (r["noise"], r["points"]))
                if r["method"] == method and (r["points"], r["noise"]) in base]
        if not mine:
            continue
        gaps = {f: [100 * (r["file_accuracy"][f] - base[r["points"], r["noise"]][f]) for r in mine]
                for f in mine[0]["file_accuracy"]}
        ranked = sorted(gaps, key=lambda f: sum(gaps[f]) / len(gaps[f]))[:worst]
        lines += ["", f"Files where {method} trails {baseline} most (accuracy difference, points):", "",
                  "| file | " + " | ".join(f"{r['points']:,} / {100 * r['noise']:g} %" for r in mine) + " |",
                  "|---|" + "---|" * len(mine)]
        lines += [f"| {f} | " + " | ".join(f"{g:+.1f}" for g in gaps[f]) + " |" for f in ranked]
    return lines


def _bracket(label: str) -> str:
    return f" ({label})" if label else ""


def scene_table(rows_by_group: dict[str, list[dict]], absent: dict[str, str] | None = None,
                documented: tuple[str, str] = ("hpr", "k=2"), baseline: str = "hpr") -> str:
    """Markdown for scenes: per group (sampling), accuracy and balanced accuracy of every method.

    Each baseline is tuned per column twice, for accuracy and for balanced
    accuracy (its best parameter in brackets); the ``documented`` setting of
    one baseline (Open3D's radius = diameter x 100) gets its own row; then the
    differences of every method to the tuned ``baseline``, in points.

    Args:
        rows_by_group: ``{group: rows of summarize() over that group's files}``.
        absent: methods that could not run, with the reason.
        documented: (method, label) of the documented setting.
        baseline: the method the differences are taken to.
    """
    lines = ["Accuracy % / balanced accuracy % (mean of the recalls of visible and of hidden points), "
             "pooled over points, cameras inside the cloud and files; a baseline's parameter is tuned "
             "per column, for each score separately (in brackets)."]
    for group, rows in rows_by_group.items():
        columns = sorted({(r["noise"], r["points"]) for r in rows})
        by = {(r["method"], r["noise"], r["points"]): r for r in rows}
        methods = list(dict.fromkeys(r["method"] for r in rows))
        files = rows[0]["files"] if rows else 0
        lines += ["", f"### {group} ({files} files)", "",
                  "| method | " + " | ".join(f"{p:,} pts, noise {100 * n:g} %" for n, p in columns) + " |",
                  "|---|" + "---|" * len(columns)]
        for m in methods:
            cells = []
            for n, p in columns:
                r = by[m, n, p]
                cells.append(f"{_pct(r['accuracy'])}{_bracket(r['param'])} / "
                             f"{_pct(r['balanced_accuracy'])}{_bracket(r['balanced_param'])}")
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        method, label = documented
        if all((method, n, p) in by and label in by[method, n, p]["sweep"] for n, p in columns):
            lines.append(f"| {method} {label} (documented) | " + " | ".join(
                f"{_pct(by[method, n, p]['sweep'][label])} / {_pct(by[method, n, p]['balanced_sweep'][label])}"
                for n, p in columns) + " |")
        for m in methods:
            if m == baseline or not all((baseline, n, p) in by for n, p in columns):
                continue
            lines.append(f"| {m} - tuned {baseline} (points) | " + " | ".join(
                f"{100 * (by[m, n, p]['accuracy'] - by[baseline, n, p]['accuracy']):+.1f} / "
                f"{100 * (by[m, n, p]['balanced_accuracy'] - by[baseline, n, p]['balanced_accuracy']):+.1f}"
                for n, p in columns) + " |")
    for name, reason in (absent or {}).items():
        lines.append(f"\n{name}: absent ({reason})")
    return "\n".join(lines) + "\n"
