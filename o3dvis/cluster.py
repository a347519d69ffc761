"""Camera frames of a map on a Ray cluster, with Ray Data (the ``ray`` extra).

The frames of :func:`o3dvis.frames` spread over the workers of a Ray cluster: the map is
put in the object store once, each worker is an actor that holds the model and the map's
encodings (a :class:`~o3dvis.apps.map_frames.FrameMap`), and the frames go to the actors in
batches through ``Dataset.map_batches``. Each frame is answered from the crop of the map
that a single process gives it (:func:`~o3dvis.apps.map_frames.tile_centres` is a function of
the map and the cameras), so the answers are those of the single-process call. Batches of
consecutive frames share their crops' encodings on an actor.

On a cluster of several machines, start Ray on each (``ray start --head`` on one,
``ray start --address=HEAD:6379`` on the others, each with o3dvis installed), then run
``o3dvis frames MAP POSES -o OUT --ray auto`` on the head node, or call :func:`frames_on_ray`
there; the results come back to the calling process, which alone reads the map and writes.
"""

from __future__ import annotations

import io
from collections.abc import Iterator

import numpy as np

from .apps.map_frames import Frame, FrameMap, checked_frame_indices, pinhole_frames, tile_centres
from .apps.pinhole import PinholeView
from .clouds import cloud_arrays
from .field import checked_range

__all__ = ["frames_on_ray", "require_ray"]


def require_ray():
    """The ``ray`` module, with Ray Data.

    Raises:
        ImportError: where Ray Data is not installed, naming the extra that installs it.
    """
    try:
        import ray
        import ray.data  # noqa: F401
    except ImportError:
        raise ImportError('frames on a Ray cluster need Ray Data; install it with: pip install "o3dvis[ray]"') from None
    return ray


class _FrameWorker:
    """A Ray Data actor: the model and the map's encodings, answering batches of frames.

    Args:
        points: a one-element list holding the object reference of the (N, 3) map (a nested
            reference, which Ray hands over as it is: the actor fetches the map itself).
        max_range, threshold, images, model: as in :func:`frames_on_ray`.
    """

    def __init__(self, points: list, max_range: float | None, threshold: float, images: bool, model):
        import ray

        self.map = FrameMap(ray.get(points[0]), max_range=max_range, model=model)
        self.threshold, self.images = threshold, images

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``{"frame": its index, "data": the frame's .npz bytes (Frame.save)}`` of each frame of the batch."""
        data = []
        for extrinsic, intrinsic, size, centre in zip(batch["extrinsic"], batch["intrinsic"], batch["size"],
                                                      batch["centre"]):
            view = PinholeView(np.asarray(extrinsic, dtype=np.float64), np.asarray(intrinsic, dtype=np.float64),
                        int(size[0]), int(size[1]))
            frame = self.map.frame(view, centre=None if np.isnan(centre).any() else centre,
                                   threshold=self.threshold, images=self.images)
            buffer = io.BytesIO()
            frame.save(buffer)
            data.append(buffer.getvalue())
        return {"frame": np.asarray(batch["frame"]), "data": np.array(data, dtype=object)}


def frames_on_ray(pcd, trajectory, *, intrinsic=None, width: int | None = None, height: int | None = None,
                  max_range: float | None = None, threshold: float = 0.5, images: bool = False, model=None,
                  workers: int | None = None, batch_size: int = 8, indices=None,
                  address: str | None = None) -> Iterator[tuple[int, Frame]]:
    """What each pinhole frame of a trajectory sees of a map, answered by the actors of a Ray cluster.

    The answers are those of :func:`o3dvis.frames`. The cameras are checked before any work;
    Ray is started (or joined) where the calling process has not done so.

    Args:
        pcd: the map, as :func:`o3dvis.frames` takes it (not a field: the actors encode it).
        trajectory, intrinsic, width, height: the cameras, as :func:`o3dvis.frames` takes them.
        max_range, threshold, images: as in :func:`o3dvis.frames`.
        model: None (the shipped default), a model name or checkpoint path (each actor loads it),
            or a :class:`~o3dvis.NeuralVisibility` (sent to each actor).
        workers: actors, each on one CPU (default: the CPUs of the cluster).
        batch_size: consecutive frames an actor answers at a time.
        indices: answer only these frames (their indices in the trajectory), with the crops the
            whole trajectory gives them; None: all.
        address: the cluster ``ray.init`` joins where Ray is not started yet (``"auto"``: the
            one running on this machine; None: a new local one).

    Returns:
        An iterator of ``(frame index, Frame)`` pairs, in the order the actors finish them.

    Raises:
        ImportError: Ray Data is not installed.
        ValueError, TypeError: as :func:`o3dvis.frames`; a bad ``workers``, ``batch_size`` or index.
    """
    ray = require_ray()
    views = pinhole_frames(trajectory, intrinsic, width, height)
    points, max_range = cloud_arrays(pcd)[0].cpu().numpy(), checked_range(max_range)
    for name, value in (("workers", workers), ("batch_size", batch_size)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    chosen = checked_frame_indices(indices, len(views))
    centres = tile_centres(points, views, max_range)
    rows = [{"frame": i, "extrinsic": views[i].extrinsic, "intrinsic": views[i].intrinsic,
             "size": np.array([views[i].width, views[i].height]),
             "centre": np.full(3, np.nan) if centres[i] is None else centres[i]} for i in chosen]
    return _answers(ray, points, rows, max_range, threshold, images, model, workers, batch_size, address)


def _answers(ray, points: np.ndarray, rows: list[dict], max_range, threshold, images, model, workers,
             batch_size, address) -> Iterator[tuple[int, Frame]]:
    """The actors' answers to ``rows`` (see :func:`frames_on_ray`)."""
    if not rows:
        return
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False)
    workers = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
    context = ray.data.DataContext.get_current()
    bars, context.enable_progress_bars = context.enable_progress_bars, False
    try:
        dataset = ray.data.from_items(rows).map_batches(
            _FrameWorker, batch_size=batch_size, num_cpus=1, compute=ray.data.ActorPoolStrategy(size=workers),
            fn_constructor_kwargs={"points": [ray.put(points)], "max_range": max_range, "threshold": threshold,
                                   "images": images, "model": model})
        for row in dataset.iter_rows():
            yield int(row["frame"]), Frame.load(io.BytesIO(row["data"]))
    finally:
        context.enable_progress_bars = bars
