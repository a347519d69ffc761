"""Camera frames of a driving log: time per frame, throughput, and accuracy against ray casting.

The log is one procedural street (``--segments 1``: about 100 m, 400 k points from 24 LiDAR sweeps)
or several end to end (``--segments 10``: close to a kilometre), with pinhole frames of 640 x 480
pixels, 90 degrees across, every 4 m along it, each seeing the points within ``--max-range``.
Printed: the map's encoding time; the median time of one frame once its encoding is made, as
``o3dvis.frames`` answers it (``FrameMap.frame``) and, for comparison, as a query of the whole map
with a range crop (``VisibilityField.query(camera, max_range=...)``); the throughput of ``frames()`` with 1 and 2
frames side by side (and with ``--ray-workers``, of ``frames_on_ray`` on a local Ray instance); the
process's peak memory; with ``--baselines``, the time of a frame with Open3D's HPR and the surfel
z-buffer on its points; with ``--truth``, accuracy and balanced accuracy against ray casting, of the
frames and of the map encoded whole.

    nice -n 10 python3 benchmarks/bench_frames.py                       # the 400 k-point street
    python3 benchmarks/bench_frames.py --segments 10 --points 300000 --truth
    python3 benchmarks/bench_frames.py --segments 10 --points 1000000 --spacing 0.87 --ray-workers 1,2 \
        --baselines 50  # 1 km, 10 M points, 1 001 frames
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis.apps.map_frames import FrameMap, pinhole_frames  # noqa: E402
from o3dvis.apps.pinhole import look_at  # noqa: E402
from o3dvis.groundtruth import visibility_from_mesh  # noqa: E402
from o3dvis.neural import NeuralVisibility  # noqa: E402
from o3dvis.training.data.scenes import random_street, sample_lidar  # noqa: E402

WIDTH, HEIGHT = 640, 480
INTRINSIC = np.array([[320.0, 0, 319.5], [0, 320.0, 239.5], [0, 0, 1]])  # 90 degrees across


def driving_log(segments: int, points: int, seed: int, spacing: float = 4.0):
    """``(points, (F, 4, 4) extrinsics, (vertices, triangles))`` of streets end to end along x."""
    rng = np.random.default_rng(seed)
    clouds, extrinsics, vertices, triangles, start, count = [], [], [], [], 0.0, 0
    scene_seed = seed
    while len(clouds) < segments:
        scene_seed += 1
        scene = random_street(np.random.default_rng(scene_seed))
        lo, hi = scene.region
        if hi[0] - lo[0] < 85 or hi[1] - lo[1] > 30:  # a long street, not a yard
            continue
        mesh = np.asarray(scene.mesh.vertices)
        shift = np.array([start - mesh[:, 0].min(), 0.0, 0.0])
        xs = np.linspace(lo[0] + 2, hi[0] - 2, 24)
        ys = rng.uniform(-1, 1, 24)
        sensors = np.column_stack([xs, ys, scene.floor(np.column_stack([xs, ys])) + 1.8])
        clouds.append(sample_lidar(scene, points, sensors, rng, max_range=60.0)[0] + shift)
        for x in np.arange(lo[0] + 3, hi[0] - 3, spacing):
            y = rng.uniform(-1.5, 1.5)
            eye = np.array([x, y, float(scene.floor(np.array([[x, y]]))[0]) + 1.6])
            yaw = rng.uniform(-0.6, 0.6) + (0 if rng.random() < 0.5 else np.pi)
            extrinsics.append(look_at(eye + shift, eye + shift + [np.cos(yaw), np.sin(yaw), 0.0]))
        vertices.append(mesh + shift)
        triangles.append(np.asarray(scene.mesh.triangles) + count)
        count += len(mesh)
        start += mesh[:, 0].max() - mesh[:, 0].min()
    return np.concatenate(clouds), np.stack(extrinsics), (np.concatenate(vertices), np.concatenate(triangles))


def _pinhole(view):
    """The view as ``o3d.camera.PinholeCameraParameters``, as a query of a field takes it."""
    import open3d as o3d

    params = o3d.camera.PinholeCameraParameters()
    k = view.intrinsic
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(view.width, view.height, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    params.extrinsic = view.extrinsic
    return params


def _median_ms(times: list[float]) -> str:
    return f"{1e3 * np.median(times):.0f} ms (p90 {1e3 * np.quantile(times, 0.9):.0f})"


def _scores(frames, views, points: np.ndarray, mesh, max_range: float) -> tuple[float, float]:
    """Accuracy and balanced accuracy of the frames' visible points against ray casting, over the
    points each frame's image holds within range."""
    seen, truth = [], []
    for frame, view in zip(frames, views):
        rows = _frame_points(points, view, max_range)
        truth.append(visibility_from_mesh(mesh, points[rows], view.location)[0])
        seen.append(np.isin(rows, frame.indices))
    seen, truth = np.concatenate(seen), np.concatenate(truth)
    return float((seen == truth).mean()), float((seen[truth].mean() + (~seen[~truth]).mean()) / 2)


def _time_one_frame(model, points: np.ndarray, views, max_range: float, compare: bool) -> None:
    """Prints the median time of one frame once its crop is encoded (and, with ``compare``, of a
    range-cropped query of the whole map)."""
    fmap = FrameMap(points, max_range=max_range, model=model)
    centres = fmap.tile_centres(views)
    start = time.perf_counter()
    fmap.frame(views[0], centre=centres[0])  # encodes the map (or the first crop), and the scene field
    print(f"encoding (map or first crop): {time.perf_counter() - start:.2f} s")
    after = []
    for view, centre in zip(views, centres):
        fmap.frame(view, centre=centre)  # encodes the frame's crop where it is a new one
        start = time.perf_counter()
        fmap.frame(view, centre=centre)
        after.append(time.perf_counter() - start)
    print(f"one frame after its encoding, FrameMap.frame: {_median_ms(after)}")
    if compare:
        field = model.encode(points)
        field.query(_pinhole(views[0]), max_range=max_range)
        before = []
        for view in views:
            start = time.perf_counter()
            field.query(_pinhole(view), max_range=max_range)
            before.append(time.perf_counter() - start)
        print(f"one frame, VisibilityField.query(max_range=...) of the whole map: {_median_ms(before)}")


def _frame_points(points: np.ndarray, view, max_range: float) -> np.ndarray:
    """Indices of the points within ``max_range`` of the view's camera and inside its image."""
    near = np.flatnonzero(np.linalg.norm(points - view.location, axis=1) <= max_range)
    uv, depth = view.project(points[near])
    inside = (depth > 0) & (uv >= -0.5).all(axis=1) & (uv[:, 0] < WIDTH - 0.5) & (uv[:, 1] < HEIGHT - 0.5)
    return near[inside]


def _baseline_times(points: np.ndarray, views, max_range: float, count: int) -> None:
    """Prints the median time a frame takes with Open3D's HPR (the radius tuned on the logs of
    ``o3dvis eval-drives``) and with the surfel z-buffer, over ``count`` frames evenly spaced,
    the selection of the frame's points (range and image) included."""
    import open3d as o3d

    from o3dvis.baselines import zbuffer_mask

    chosen = [views[i] for i in np.linspace(0, len(views) - 1, min(count, len(views))).astype(int)]
    times: dict[str, list[float]] = {"Open3D HPR": [], "surfel z-buffer": []}
    for view in chosen:
        start = time.perf_counter()
        rows = _frame_points(points, view, max_range)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[rows]))
        radius = np.linalg.norm(np.ptp(points[rows], axis=0)) * 10 ** 3.25
        cloud.hidden_point_removal(view.location, radius)
        times["Open3D HPR"].append(time.perf_counter() - start)
        start = time.perf_counter()
        rows = _frame_points(points, view, max_range)
        zbuffer_mask(points[rows], view.location[None], splat=1.0)
        times["surfel z-buffer"].append(time.perf_counter() - start)
    for name, spent in times.items():
        print(f"one frame, {name} on its points ({len(chosen)} frames): {_median_ms(spent)}, "
              f"{1 / np.median(spent):.1f} frames/s")


def _throughput(model, points: np.ndarray, views, max_range: float, ray_workers: list[int]) -> list:
    """Prints the frames per second of ``frames()`` (encodings included) with 1 and 2 frames side by
    side, and on a local Ray instance with each of ``ray_workers``; returns the frames answered."""
    for workers in (1, 2):
        start = time.perf_counter()
        answered = list(FrameMap(points, max_range=max_range, model=model).frames(
            views, workers=workers, progress=False))
        print(f"frames(), {workers} side by side, encodings included: {len(views) / (time.perf_counter() - start):.1f}"
              " frames/s")
    if ray_workers:
        import ray

        from o3dvis.cluster import frames_on_ray

        ray.init(num_cpus=max(ray_workers), include_dashboard=False, logging_level="ERROR")
        for workers in ray_workers:
            start = time.perf_counter()
            count = sum(1 for _ in frames_on_ray(points, views, max_range=max_range, workers=workers))
            print(f"frames_on_ray, {workers} workers, actors' start and encodings included: "
                  f"{count / (time.perf_counter() - start):.1f} frames/s")
        ray.shutdown()
    return answered


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--segments", type=int, default=1, help="streets end to end (default 1)")
    parser.add_argument("--points", type=int, default=400_000, help="points per street (default 400 000)")
    parser.add_argument("--spacing", type=float, default=4.0, help="metres between frames (default 4)")
    parser.add_argument("--max-range", type=float, default=40.0)
    parser.add_argument("--frames", type=int, default=24, help="frames timed one by one (default 24)")
    parser.add_argument("--ray-workers", type=str, default="", help="e.g. 1,2: also time Ray with these workers")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--baselines", type=int, default=0, metavar="FRAMES",
                        help="also time Open3D's HPR and the surfel z-buffer on this many frames")
    parser.add_argument("--truth", action="store_true", help="also score against ray casting (slow)")
    args = parser.parse_args()

    points, extrinsics, mesh = driving_log(args.segments, args.points, args.seed, args.spacing)
    views = pinhole_frames(extrinsics, INTRINSIC, WIDTH, HEIGHT)
    print(f"{len(points)} points, {len(views)} frames, {np.ptp(points[:, 0]):.0f} m long")
    model = NeuralVisibility.pretrained()
    _time_one_frame(model, points, views[:args.frames], args.max_range, args.segments == 1)
    answered = _throughput(model, points, views, args.max_range, [int(w) for w in args.ray_workers.split(",") if w])
    if args.baselines:
        _baseline_times(points, views, args.max_range, args.baselines)
    print(f"peak memory of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
    if args.truth:
        accuracy, balanced = _scores(answered, views, points, mesh, args.max_range)
        print(f"frames: accuracy {100 * accuracy:.2f}, balanced {100 * balanced:.2f}")
        whole = FrameMap(model.encode(points), max_range=args.max_range)
        accuracy, balanced = _scores(whole.frames(views, progress=False), views, points, mesh, args.max_range)
        print(f"map encoded whole: accuracy {100 * accuracy:.2f}, balanced {100 * balanced:.2f}")


if __name__ == "__main__":
    main()
