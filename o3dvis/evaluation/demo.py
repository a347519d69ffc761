"""The demo: neural visibility against Open3D's HPR on the shipped sample, as pictures.

The shipped sample is a procedural shape built at run time (no mesh file):
five primitives -- two tori, a bowl, a cup and a plate -- wound through each
other, so much of the surface hides behind other parts. Points are sampled on
its surface; the camera sits at one bounding-box diagonal from the centre (the
distance the network is trained at). Ground truth is ray-cast on the mesh.

The pictures show the cloud from an *observer* beside the camera (turned
``OBSERVER_TURN`` degrees about the z axis), so that both the side the camera
sees and the side it does not are in the image; the observer's own occlusion
is exact (ray-cast), so each picture shows only what the observer would see.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from .._optional import figure_class
from ..apps.render import image_from, lambert, splat, splat_size
from ..baselines import SWEEPS, hpr_method
from ..apps.pinhole import PinholeView, make_view
from ..cameras import as_camera_location
from ..methods import ground_truth_method
from ..training.data.sample import sample_surface
from ..training.data.shapes import random_shape
from .evaluate import Counts, EvalCloud
from .methods import NeuralMethod
from .speed import time_method

__all__ = ["SAMPLE_SEED", "SAMPLE_PARTS", "demo_sample", "default_camera", "observer_location",
           "MethodResult", "DemoResult", "run_demo", "error_colors", "IMAGES"]

SAMPLE_SEED = 7
"""Seed of :func:`o3dvis.training.data.shapes.random_shape` for the shipped sample."""
SAMPLE_PARTS = 5
CAMERA_DIRECTION = (1.0, -1.0, 0.6)
"""Direction from the sample's centre to the default camera."""
OBSERVER_TURN = 50.0
"""Degrees about the z axis between the camera and the observer the pictures are taken from."""

VISIBLE = np.array([0.95, 0.55, 0.10])
HIDDEN = np.array([0.78, 0.80, 0.86])
FALSE_POSITIVE = np.array([0.90, 0.05, 0.05])
FALSE_NEGATIVE = np.array([0.05, 0.25, 0.95])

IMAGES = {
    "input": "input point cloud",
    "ground_truth": "ground truth: visible from the camera (orange), hidden (grey)",
    "neural": "neural visible points (orange)",
    "hpr": "Open3D HPR visible points (orange)",
    "errors_neural": "neural errors: false positives red, false negatives blue",
    "errors_hpr": "HPR errors: false positives red, false negatives blue",
}
"""File stem -> caption of every picture the demo writes (``.png``), besides ``demo.png``."""


def demo_sample(num_points: int = 20_000, seed: int = 0
                ) -> tuple[o3d.geometry.PointCloud, o3d.geometry.TriangleMesh]:
    """The shipped sample: a fixed procedural mesh and a point cloud on its surface.

    Args:
        num_points: points sampled uniformly (by area) on the surface.
        seed: seed of the sampling (the mesh itself never changes).

    Returns:
        ``(pcd, mesh)``: the cloud, with the (unoriented) normals of the faces
        its points lie on, and the mesh for ground truth.
    """
    if isinstance(num_points, bool) or not isinstance(num_points, (int, np.integer)) or num_points < 4:
        raise ValueError(f"num_points must be an integer >= 4, got {num_points!r}")
    mesh = random_shape(np.random.default_rng(SAMPLE_SEED), parts=SAMPLE_PARTS)
    points, normals = sample_surface(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                                     int(num_points), np.random.default_rng(seed))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    return pcd, mesh


def _frame(points: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = points.min(axis=0), points.max(axis=0)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo))


def default_camera(points: np.ndarray) -> np.ndarray:
    """The demo's camera: one bounding-box diagonal from the centre, along ``CAMERA_DIRECTION``."""
    centre, diagonal = _frame(points)
    direction = np.asarray(CAMERA_DIRECTION)
    return centre + diagonal * direction / np.linalg.norm(direction)


def observer_location(points: np.ndarray, camera: np.ndarray, turn: float = OBSERVER_TURN) -> np.ndarray:
    """The camera's position turned ``turn`` degrees about the vertical (z) axis through the centre."""
    centre, _ = _frame(points)
    a = np.radians(turn)
    rotation = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return centre + rotation @ (np.asarray(camera, dtype=np.float64) - centre)


@dataclass
class MethodResult:
    """One method's answer for the demo's camera, scored against ground truth."""

    name: str
    mask: np.ndarray
    counts: Counts
    seconds: float
    detail: str = ""


@dataclass
class DemoResult:
    """What :func:`run_demo` computed and wrote."""

    num_points: int
    camera: np.ndarray
    truth: np.ndarray
    methods: list[MethodResult]
    images: dict[str, Path] = field(default_factory=dict)
    figure_missing: str = ""
    """Why ``demo.png`` was not drawn (matplotlib, the ``demo`` extra, is not installed); empty when it was."""

    def table(self) -> str:
        """A plain-text table: accuracy, false positives/negatives and time of each method."""
        lines = [f"{'method':<34} {'accuracy':>9} {'false pos.':>11} {'false neg.':>11} {'time':>10}"]
        for m in self.methods:
            lines.append(f"{m.name:<34} {100 * m.counts.accuracy:>8.2f}% {m.counts.fp:>11,} "
                         f"{m.counts.fn:>11,} {1e3 * m.seconds:>7.1f} ms")
        return "\n".join(lines)


def error_colors(predicted: np.ndarray, truth: np.ndarray, shade: np.ndarray) -> np.ndarray:
    """Per-point RGB of an error picture: false positives red, false negatives blue, the rest grey.

    Args:
        predicted: (N,) bool, the method's visibility.
        truth: (N,) bool, ground truth.
        shade: (N,) brightness of the correct points, in [0, 1].

    Returns:
        (N, 3) colours in [0, 1].
    """
    colors = shade[:, None] * HIDDEN
    colors[predicted & ~truth] = FALSE_POSITIVE
    colors[~predicted & truth] = FALSE_NEGATIVE
    return colors


def _visible_colors(mask: np.ndarray, shade: np.ndarray) -> np.ndarray:
    return shade[:, None] * np.where(mask[:, None], VISIBLE, HIDDEN)


def _neural(model, device) -> tuple[object, str]:
    from ..neural import NeuralVisibility

    name = "default" if model is None else str(model)
    return NeuralMethod(NeuralVisibility.pretrained(name, device=device), name), f"neural ({Path(name).name})"


def _hpr(cloud: EvalCloud, exponents) -> MethodResult:
    """Open3D HPR at the best of ``exponents`` (radius = diagonal x 10^k) against ground truth."""
    best = None
    for k in exponents:
        method = hpr_method(float(k))
        start = time.perf_counter()
        mask = method(cloud.points, cloud.cameras)[0]
        seconds = time.perf_counter() - start
        counts = Counts.of(mask, cloud.labels[0])
        if best is None or counts.accuracy > best.counts.accuracy:
            best = MethodResult(f"Open3D HPR (k={k:g})", mask, counts, seconds,
                                f"radius = diagonal x 10^{k:g}")
    if len(exponents) > 1:
        best.detail += f", best of k = {', '.join(f'{k:g}' for k in exponents)} against ground truth"
    return best


def _pictures(out: Path, pcd: o3d.geometry.PointCloud, mesh: o3d.geometry.TriangleMesh,
              result: DemoResult, width: int, height: int, figure: type | None) -> dict[str, Path]:
    points = np.asarray(pcd.points)
    observer = observer_location(points, result.camera)
    view = make_view(points, observer, width, height)
    seen = ground_truth_method(mesh)(points, view.location[None])[0]
    index, _ = splat(view, points, splat_size(points, None), seen)
    shade = 0.35 + 0.65 * lambert(pcd, points, view.location)
    neural, hpr = result.methods
    colors = {
        "input": shade[:, None] * np.array([0.85, 0.85, 0.9]),
        "ground_truth": _visible_colors(result.truth, shade),
        "neural": _visible_colors(neural.mask, shade),
        "hpr": _visible_colors(hpr.mask, shade),
        "errors_neural": error_colors(neural.mask, result.truth, shade),
        "errors_hpr": error_colors(hpr.mask, result.truth, shade),
    }
    images = {name: np.asarray(image_from(index, c, (1.0, 1.0, 1.0))) for name, c in colors.items()}
    paths = {}
    for name, image in images.items():
        paths[name] = out / f"{name}.png"
        if not o3d.io.write_image(str(paths[name]), o3d.geometry.Image(image)):
            raise RuntimeError(f"could not write {paths[name]}")
    if figure is not None:
        paths["demo"] = out / "demo.png"
        _montage(figure, paths["demo"], images, result, _camera_arrow(view, _frame(points)[0], result.camera))
    return paths


def _camera_arrow(view: PinholeView, centre: np.ndarray, camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image-plane start and end of an arrow from the border towards the centre, coming from the camera."""
    uv, _ = view.project(np.stack([centre, centre + 0.05 * (camera - centre)]))
    direction = uv[1] - uv[0]
    direction /= max(np.linalg.norm(direction), 1e-12)
    middle = np.array([view.width / 2, view.height / 2])
    tail = middle + direction * 0.48 * min(view.width, view.height)
    return tail, middle + direction * 0.3 * min(view.width, view.height)


def _montage(figure: type, path: Path, images: dict[str, np.ndarray], result: DemoResult,
             arrow: tuple[np.ndarray, np.ndarray]) -> None:
    neural, hpr = result.methods
    titles = {
        "input": f"input: {result.num_points:,} points",
        "ground_truth": f"ground truth ({int(result.truth.sum()):,} visible)",
        "neural": f"{neural.name}: {100 * neural.counts.accuracy:.1f}%",
        "hpr": f"{hpr.name}: {100 * hpr.counts.accuracy:.1f}%",
        "errors_neural": f"neural errors: {neural.counts.fp:,} FP, {neural.counts.fn:,} FN",
        "errors_hpr": f"HPR errors: {hpr.counts.fp:,} FP, {hpr.counts.fn:,} FN",
    }
    order = ["input", "ground_truth", "errors_neural", "neural", "hpr", "errors_hpr"]
    fig = figure(figsize=(12, 7.2))
    axes = fig.subplots(2, 3)
    tail, head = arrow
    for ax, name in zip(axes.ravel(), order):
        ax.imshow(images[name])
        ax.set_title(titles[name], fontsize=11)
        ax.axis("off")
        ax.annotate("camera", xy=head, xytext=tail, fontsize=9, color="0.3", ha="center",
                    arrowprops={"arrowstyle": "->", "color": "0.3"})
    fig.suptitle("Visible points from the camera (orange), seen from beside it.  "
                 "Errors: false positives red, false negatives blue.", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def run_demo(out_dir: str | Path = "o3dvis-demo", num_points: int = 20_000, camera=None, *,
             model=None, device=None, hpr_k=None, width: int = 480, height: int = 400,
             progress: bool = True) -> DemoResult:
    """Neural visibility and Open3D's HPR on the shipped sample, scored and drawn.

    Args:
        out_dir: folder for the PNGs (created).
        num_points: points on the sample.
        camera: (3,) camera position (default: :func:`default_camera`), not on a point.
        model: shipped model name or ``.safetensors`` path (default: the shipped default).
        device: torch device of the network (default: CPU).
        hpr_k: HPR radius exponents, radius = diagonal x 10^k; the most accurate
            against ground truth is shown (default: the sweep ``o3dvis eval`` tunes over).
        width, height: size of each picture in pixels.
        progress: show a progress bar over the stages.

    Returns:
        A :class:`DemoResult`; ``images`` maps each name of :data:`IMAGES` and
        ``"demo"`` (all pictures in one figure) to its file. Without matplotlib (the
        ``demo`` extra) there is no ``"demo"``, and ``figure_missing`` says why.
    """
    from tqdm import tqdm

    try:
        figure, missing = figure_class("the demo's figure (demo.png)"), ""
    except ImportError as e:
        figure, missing = None, str(e)
    pcd, mesh = demo_sample(num_points)
    points = np.asarray(pcd.points)
    camera = default_camera(points) if camera is None else as_camera_location(camera, "camera")
    exponents = SWEEPS["hpr"][2] if hpr_k is None else tuple(hpr_k)
    if not exponents:
        raise ValueError("hpr_k must hold at least one exponent")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with tqdm(total=4, desc="demo", unit="stage", disable=not progress, leave=False) as bar:
        truth = ground_truth_method(mesh)(points, camera[None])
        cloud = EvalCloud(points, camera[None], truth, np.asarray(pcd.normals))
        bar.update()
        method, name = _neural(model, device)
        timing = time_method(method, cloud)
        mask = method(points, camera[None])[0]
        neural = MethodResult(name, mask, Counts.of(mask, truth[0]), timing["seconds"],
                              f"encode {1e3 * timing['encode_s']:.0f} ms + "
                              f"query {1e3 * timing['query_s']:.0f} ms")
        bar.update()
        hpr = _hpr(cloud, exponents)
        bar.update()
        result = DemoResult(len(points), camera, truth[0], [neural, hpr], figure_missing=missing)
        result.images = _pictures(out, pcd, mesh, result, width, height, figure)
        bar.update()
    return result
