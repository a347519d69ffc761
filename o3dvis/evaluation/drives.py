"""Accuracy of visibility methods on procedural driving logs, frame by frame, against ray casting.

A user of a driving log holds a map accumulated from LiDAR sweeps and asks, for
each camera frame, which of the map's points the camera sees. Here the logs are
procedural (:func:`~o3dvis.training.data.scenes.drive_log`); a frame's points are
those of the map as held (clean, or with noise, see ``DriveLog.noisy``) within
``max_range`` of its camera and inside its image, labelled by ray casting the
scene (:func:`~o3dvis.training.data.scenes.frame_truth`). Every method answers
them; counts are pooled over frames and seeds, and a baseline's parameter is
tuned per column (log length and noise level) on the set, for accuracy and for
balanced accuracy separately.

Methods (see :func:`drive_methods`):

* ``o3dvis``: :func:`o3dvis_frame`, the one call that answers a frame of a map;
  ``o3dvis-whole`` encodes the whole map once and queries each frame within its
  range instead; ``-crop<R>`` encodes the points within R metres of the camera;
  ``-x<K>`` averages K rotations; ``-object`` leaves out the scene model.
* ``hpr``: Open3D's Hidden Point Removal on the frame's points (radius = their
  bounding-box diagonal x 10^k, k swept).
* ``zbuffer``: the surfel z-buffer of :func:`o3dvis.baselines.zbuffer_mask` on the
  frame's points (disc radius swept).
* ``pixel-zbuffer``: the nearest point per pixel of the frame's image, as depth
  supervision code keeps it (pixels grouped into cells of 1-8 pixels, a point
  visible within a relative depth tolerance of its cell's nearest; both swept).
* ``everything``: every point of the frame visible (no occlusion test).

Frames: ``frames`` evenly spaced along each log, and in every longer log also
those of the shortest. A longer log of a seed extends the shorter ones, so the
latter (the "first metres" group) follow accuracy as the log grows on the same
frames of the same streets, with a map that holds more sweeps.
"""

from __future__ import annotations

import re
from collections.abc import Callable

import numpy as np
import torch

from ..apps.pinhole import camera_location_of
from ..baselines import sweep
from ..geometry import within_range
from ..training.data.scenes.drives import drive_log, frame_truth, frame_view
from .evaluate import Counts, _key, summarize
from .methods import neural_method

__all__ = ["FRAME_RANGE", "HPR_K", "SPLATS", "PIXEL_CELLS", "PIXEL_TOLERANCES", "METHOD_NAMES", "o3dvis_frame",
           "drive_methods", "evaluate_drives", "summarize_drives", "drives_table"]

FRAME_RANGE = 40.0
"""Metres: a frame's points lie this close to its camera."""
HPR_K = (2.75, 3.0, 3.25, 3.5, 4.0)
"""HPR's sweep (radius = diagonal x 10^k): a frame's points want a far larger radius than a closed shape."""
SPLATS = (0.5, 0.75, 1.0, 1.5)
"""The surfel z-buffer's sweep of disc radii, in point spacings."""
PIXEL_CELLS = (1, 2, 4, 8)
PIXEL_TOLERANCES = (0.05, 0.1, 0.25, 0.5)
"""The per-pixel z-buffer's sweep: cell sizes in pixels, relative depth tolerances."""
METHOD_NAMES = ("o3dvis", "hpr", "zbuffer", "pixel-zbuffer", "everything")

FrameAnswer = Callable[[object, np.ndarray, float], np.ndarray]
"""``answer(frame, indices, max_range) -> (M,) bool``: which of the map's points ``indices`` a frame sees."""
MapMethod = Callable[[np.ndarray], FrameAnswer]
"""``method(points) -> answer``: a method made ready for one map (an (N, 3) array, as held)."""

_O3DVIS = re.compile(r"o3dvis(-whole|-crop(\d+(?:\.\d+)?))?(?:-x([1-9][0-9]*))?(-object)?")


def o3dvis_frame(model, points: np.ndarray, frame, max_range: float, crop: float | None = None) -> np.ndarray:
    """The indices of the map's points that one pinhole frame sees, by o3dvis.

    The points within ``crop`` of the camera are encoded (the network's cells then fit
    what the frame sees, whatever the map's extent) and the frame is queried within
    ``max_range``, culled to its image.

    Args:
        model: a ``NeuralVisibility``.
        points: (N, 3) the map.
        frame: ``o3d.camera.PinholeCameraParameters`` with an image size.
        max_range: metres; farther points are not the frame's.
        crop: radius of the encoded crop, at least ``max_range`` (default: ``max_range``).

    Returns:
        (M,) int64 ascending indices into ``points``.

    Raises:
        ValueError: a crop smaller than the range (points in range would go unanswered).
    """
    crop = max_range if crop is None else crop
    if crop < max_range:
        raise ValueError(f"the crop ({crop:g} m) must reach as far as the range ({max_range:g} m)")
    camera = camera_location_of(frame)
    near = within_range(torch.from_numpy(points), torch.from_numpy(camera.astype(points.dtype)), crop).numpy()
    if not len(near):
        return near
    field = model.encode(points[near].astype(np.float64), views=frame)
    return near[field.query(frame, max_range=max_range)[0]]


def _o3dvis(model, crop: float | None) -> MapMethod:
    def prepare(points: np.ndarray) -> FrameAnswer:
        return lambda frame, indices, max_range: np.isin(indices, o3dvis_frame(model, points, frame, max_range, crop))
    return prepare


def _o3dvis_whole(model) -> MapMethod:
    def prepare(points: np.ndarray) -> FrameAnswer:
        field = model.encode(points.astype(np.float64))
        return lambda frame, indices, max_range: field.query(frame, max_range=max_range, indices=indices)[0]
    return prepare


def _on_frame_points(method: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> MapMethod:
    """A method of ``(points, cameras) -> (V, N)`` answering the frame's points from its camera."""
    def prepare(points: np.ndarray) -> FrameAnswer:
        def answer(frame, indices: np.ndarray, max_range: float) -> np.ndarray:
            return method(points[indices].astype(np.float64), camera_location_of(frame))[0]
        return answer
    return prepare


def _pixel_zbuffer(cell: int, tolerance: float) -> MapMethod:
    """Nearest point per cell of ``cell`` x ``cell`` pixels of the frame's image; a point is visible
    when its depth exceeds its cell's nearest by at most ``tolerance`` times that depth."""
    def prepare(points: np.ndarray) -> FrameAnswer:
        def answer(frame, indices: np.ndarray, max_range: float) -> np.ndarray:
            view = frame_view(frame)
            uv, depth = view.project(points[indices].astype(np.float64))
            cells = np.floor((uv + 0.5) / cell).astype(np.int64)
            key = cells[:, 1] * (view.width // cell + 1) + cells[:, 0]
            _, slot = np.unique(key, return_inverse=True)
            nearest = np.full(slot.max() + 1 if len(slot) else 0, np.inf)
            np.minimum.at(nearest, slot, depth)
            return depth <= nearest[slot] * (1 + tolerance)
        return answer
    return prepare


def _everything(points: np.ndarray) -> FrameAnswer:
    return lambda frame, indices, max_range: np.ones(len(indices), dtype=bool)


def _o3dvis_model(checkpoint, rotations: int, scene: bool):
    """The ``NeuralVisibility`` of an ``o3dvis`` method name (see :func:`drive_methods`)."""
    from ..neural import NeuralVisibility

    model = neural_method(checkpoint, num_rotations=rotations).visibility
    if scene:
        return model
    return NeuralVisibility(model.network, model.normals_network, num_rotations=rotations,
                            small_network=model.small_network)


def drive_methods(names, checkpoint=None, hpr_k=None, splats=None
                  ) -> tuple[dict[str, dict[str, MapMethod]], dict[str, str]]:
    """The named methods for driving logs, each a sweep ``{parameter label: MapMethod}``.

    Args:
        names: from :data:`METHOD_NAMES`; ``o3dvis`` may end in ``-whole`` or ``-crop<R>``,
            then ``-x<K>``, then ``-object`` (see the module's docstring).
        checkpoint: network checkpoint for ``o3dvis`` (default: the shipped models).
        hpr_k, splats: sweeps replacing :data:`HPR_K` and :data:`SPLATS`.

    Returns:
        ``(methods, absent)``: ``absent[name]`` says why a method could not be built.

    Raises:
        ValueError: an unknown name.
    """
    methods: dict[str, dict[str, MapMethod]] = {}
    absent: dict[str, str] = {}
    for name in names:
        variant = _O3DVIS.fullmatch(name)
        if variant:
            try:
                model = _o3dvis_model(checkpoint, int(variant[3] or 1), not variant[4])
            except LookupError as e:
                absent[name] = str(e)
                continue
            whole, crop = variant[1] == "-whole", float(variant[2]) if variant[2] else None
            methods[name] = {"": _o3dvis_whole(model) if whole else _o3dvis(model, crop)}
        elif name == "hpr":
            methods[name] = {k: _on_frame_points(m) for k, m in sweep("hpr", hpr_k or HPR_K).items()}
        elif name == "zbuffer":
            methods[name] = {k: _on_frame_points(m) for k, m in sweep("zbuffer", splats or SPLATS).items()}
        elif name == "pixel-zbuffer":
            methods[name] = {f"cell={c},tol={t:g}": _pixel_zbuffer(c, t)
                             for c in PIXEL_CELLS for t in PIXEL_TOLERANCES}
        elif name == "everything":
            methods[name] = {"": _everything}
        else:
            raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHOD_NAMES)} (o3dvis may end in "
                             f"-whole or -crop<R>, -x<K>, -object, e.g. o3dvis-crop60-x4)")
    return methods, absent


def _chosen(count: int, frames: int) -> np.ndarray:
    """``frames`` frame indices evenly spaced over ``count`` (all when fewer)."""
    return np.unique(np.round(np.linspace(0, count - 1, min(frames, count))).astype(np.int64))


def evaluate_drives(lengths, noises, methods: dict[str, dict[str, MapMethod]], seeds=(0,), frames: int = 6,
                    max_range: float = FRAME_RANGE, log_options: dict | None = None, progress: bool = True) -> dict:
    """Confusion counts of every method and parameter on the frames of procedural driving logs.

    Args:
        lengths: log lengths, metres (the shortest gives the frames followed as logs grow).
        noises: noise levels of the map (see ``DriveLog.noisy``).
        methods: ``{name: {parameter label: MapMethod}}`` (see :func:`drive_methods`).
        seeds: one log of each length per seed.
        frames: frames evaluated evenly spaced along each log.
        max_range: a frame's range, metres.
        log_options: keyword arguments of :func:`~o3dvis.training.data.scenes.drive_log`.
        progress: show a tqdm bar.

    Returns:
        ``{frame name: {"seed", "length", "distance" (along the log, metres), "points" (the map's),
        "along" (one of the evenly spaced frames), "first" (one of the shortest log's), "counts"}}``
        with ``counts[method][label][f"{length:g}"][f"{noise:g}"] = [tp, fp, fn, tn]``.

    Raises:
        ValueError: no length, no noise level, fewer than one frame.
    """
    from tqdm import tqdm

    lengths = sorted(float(x) for x in lengths)
    if not lengths or not list(noises) or frames < 1:
        raise ValueError("give at least one log length, one noise level and one frame")
    out: dict[str, dict] = {}
    with tqdm(desc="eval-drives", unit="frame", disable=not progress) as bar:
        for seed in seeds:
            first = None
            for length in lengths:
                log = drive_log(length, seed, **(log_options or {}))
                along = _chosen(len(log.frames), frames)
                first = log.frame_distance[along] if first is None else first
                common = np.flatnonzero(np.isin(log.frame_distance, first))
                for noise in noises:
                    held = log.noisy(noise, seed)
                    ready = {name: {label: m(held) for label, m in sw.items()} for name, sw in methods.items()}
                    for index in np.union1d(along, common):
                        indices, truth = frame_truth(log, int(index), held, max_range)
                        entry = out.setdefault(f"s{seed}-{length:g}m-{log.frame_distance[index]:g}m", {
                            "seed": seed, "length": length, "distance": float(log.frame_distance[index]),
                            "points": len(log.points), "along": bool(index in along),
                            "first": bool(index in common), "counts": {}})
                        for name, answers in ready.items():
                            for label, answer in answers.items():
                                c = Counts.of(answer(log.frames[index], indices, max_range), truth) \
                                    if len(indices) else Counts()
                                entry["counts"].setdefault(name, {}).setdefault(label, {}).setdefault(
                                    _key(length), {})[_key(noise)] = [c.tp, c.fp, c.fn, c.tn]
                        bar.update()
    return out


def summarize_drives(per_frame: dict, methods: dict, noises) -> dict[str, list[dict]]:
    """Pooled scores per method, log length and noise level, for the frames ``along`` each log and the
    ``first`` frames (the shortest log's, in every log); see :func:`~o3dvis.evaluation.evaluate.summarize`
    (a row's ``points`` is the log's length)."""
    out: dict[str, list[dict]] = {"along": [], "first": []}
    for group, rows in out.items():
        for length in sorted({e["length"] for e in per_frame.values()}):
            frames = {k: {**e, "category": group} for k, e in per_frame.items() if e["length"] == length and e[group]}
            rows += summarize(frames, methods, [length], list(noises)) if frames else []
    return out


_BASELINES = ("hpr", "zbuffer", "pixel-zbuffer")


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


def _bracket(label: str) -> str:
    return f" ({label})" if label else ""


def _group_table(rows: list[dict]) -> list[str]:
    """Markdown lines: balanced accuracy / accuracy of every method per column (noise, length), then the
    differences of each o3dvis method to each tuned baseline, in points."""
    columns = sorted({(r["noise"], r["points"]) for r in rows})
    by = {(r["method"], r["noise"], r["points"]): r for r in rows}
    names = list(dict.fromkeys(r["method"] for r in rows))
    lines = ["| method | " + " | ".join(f"{length:g} m, {'clean' if not noise else f'{100 * noise:g} % noise'}"
                                       for noise, length in columns) + " |", "|---|" + "---|" * len(columns)]
    for m in names:
        lines.append(f"| {m} | " + " | ".join(
            f"{_pct(by[m, n, p]['balanced_accuracy'])}{_bracket(by[m, n, p]['balanced_param'])} / "
            f"{_pct(by[m, n, p]['accuracy'])}{_bracket(by[m, n, p]['param'])}" for n, p in columns) + " |")
    for m in (m for m in names if m.startswith("o3dvis")):
        for base in (b for b in _BASELINES if b in names):
            lines.append(f"| {m} - tuned {base} | " + " | ".join(
                f"{100 * (by[m, n, p]['balanced_accuracy'] - by[base, n, p]['balanced_accuracy']):+.1f} / "
                f"{100 * (by[m, n, p]['accuracy'] - by[base, n, p]['accuracy']):+.1f}" for n, p in columns) + " |")
    return lines


def _growth(rows: list[dict]) -> list[str]:
    """Markdown lines: each method's balanced accuracy on the first frames, shortest log minus longest."""
    lengths = sorted({r["points"] for r in rows})
    noises = sorted({r["noise"] for r in rows})
    by = {(r["method"], r["noise"], r["points"]): r["balanced_accuracy"] for r in rows}
    lines = ["| method | " + " | ".join('clean' if not n else f'{100 * n:g} % noise' for n in noises) + " |",
             "|---|" + "---|" * len(noises)]
    for m in dict.fromkeys(r["method"] for r in rows):
        lines.append(f"| {m} | " + " | ".join(f"{100 * (by[m, n, lengths[0]] - by[m, n, lengths[-1]]):+.1f}"
                                            for n in noises) + " |")
    return lines


def drives_table(summary: dict[str, list[dict]], settings: dict, absent: dict[str, str] | None = None) -> str:
    """Markdown of :func:`summarize_drives`: the frames along each log and, with several lengths, the first
    frames in every log and the balanced accuracy each method loses on them from the shortest log to the
    longest.

    Args:
        summary: from :func:`summarize_drives`.
        settings: the run's settings (``seeds``, ``frames``, ``max_range``, ``lengths``), for the captions,
            and the ``command`` that made it, if known.
        absent: methods that could not run, with the reason.
    """
    lengths = sorted(settings["lengths"])
    lines = ["Balanced accuracy % (mean of the recalls of visible and of hidden points) / accuracy %, pooled "
             f"over the points of the frames (within {settings['max_range']:g} m of the camera and inside its "
             f"image) and seeds {', '.join(map(str, settings['seeds']))}; a baseline's parameter is tuned on the "
             "set per column, for each score separately (in brackets); differences in points.", "",
             f"### {settings['frames']} frames evenly spaced along each log", ""]
    lines += _group_table(summary["along"])
    if len(lengths) > 1:
        lines += ["", f"### The frames of the {lengths[0]:g} m log, in every log", ""]
        lines += _group_table(summary["first"])
        lines += ["", f"### Balanced accuracy lost on those frames from the {lengths[0]:g} m log to the "
                  f"{lengths[-1]:g} m log (points; negative: gained)", ""]
        lines += _growth(summary["first"])
    for name, reason in (absent or {}).items():
        lines.append(f"\n{name}: absent ({reason})")
    if settings.get("command"):
        lines += ["", f"Made by `{settings['command']}`."]
    return "\n".join(lines) + "\n"
