"""Neural hidden point removal: which points of a cloud each camera sees.

The network's U-Net runs once per cloud (:meth:`NeuralVisibility.encode`); each
view then costs a depth-buffer pass and a small MLP over the points
(:meth:`VisibilityField.query`). A camera may stand anywhere but on a point of
the cloud: outside it, or inside a room, a street or a scan, where a scene
model answers when one is installed (see :class:`NeuralVisibility`). A flat cloud (a plane, a
line, coincident points) seen from off its plane or line hides nothing: there
every point is visible, exactly, whatever the network says.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np
import open3d as o3d
import torch
from torch import Tensor

from .cameras import Views, as_vectors, as_views
from .clouds import cloud_arrays, cloud_device, unit_normals
from . import models
from .models import available_models, load_model, torch_device
from .nn import native
from .nn.calibration import calibration_terms
from .nn.network import VisibilityNetwork
from .nn.octree import bounding_box, morton_order, normalize_points
from .nn.predictor import resolve_precision

__all__ = ["NeuralVisibility", "VisibilityField", "RotatedEncoding", "hidden_point_removal_neural",
           "select_visible", "register", "fixed_rotations", "shared_pretrained", "DEFAULT_CHUNK"]

DEFAULT_CHUNK = 1 << 15
"""Rows (views x points) that one predictor call processes at most: small enough for the cache."""

_NORMALS_MODEL = "normals"
_SCENE_MODEL = "scene"
_INSIDE_TOL = 1e-6
_FLAT_TOL = 1e-9


def _threaded_map(fn: Callable, items: Iterable, workers: int) -> Iterator:
    """``map(fn, items)`` on ``workers`` threads, each running torch ops on one thread of its own.

    On a CPU, views answered side by side this way are faster than one view at a
    time with every op split over the threads: the per-view ops are many and small
    (a split op waits for its slowest part), and each thread's buffers stay in its
    own cache. Each item runs without autograd (grad mode is per thread). A
    worker takes its own thread count before setting it to 1, and the caller's
    count is put back when each item is done: ``torch.set_num_threads`` also sets
    the count that threads new to torch start with.
    """
    caller = torch.get_num_threads()

    def task(item):
        torch.get_num_threads()  # this thread's count is settled now, not at its first parallel op
        torch.set_num_threads(1)
        try:
            with torch.inference_mode():
                return fn(item)
        finally:
            torch.set_num_threads(caller)

    with ThreadPoolExecutor(workers, thread_name_prefix="o3dvis-views") as pool:
        yield from pool.map(task, items)


def _fmt(vector: Tensor) -> str:
    return "(" + ", ".join(f"{x:.6g}" for x in vector.detach().tolist()) + ")"


def _subset(views: Views, index: np.ndarray) -> Views:
    """The views ``index`` of ``views``."""
    rows = torch.from_numpy(index)
    pick = (lambda t: None if t is None else t[rows.to(t.device)])
    return Views(pick(views.positions), pick(views.directions), tuple(views.frustums[i] for i in index.tolist()))


def _checked_range(max_range) -> float | None:
    """``max_range`` as a positive float (None: no crop)."""
    if max_range is None:
        return None
    if isinstance(max_range, bool) or not isinstance(max_range, (int, float, np.floating, np.integer)):
        raise TypeError(f"max_range must be a number or None, got {type(max_range).__name__}")
    if not max_range > 0:  # NaN too
        raise ValueError(f"max_range must be positive, got {max_range}")
    return float(max_range)


def _inside_box(positions: Tensor, bounds: tuple[Tensor, Tensor]) -> Tensor:
    """(V,) bool: which of the (V, 3) positions lie in the box ``bounds``, up to a tolerance."""
    lo, hi = bounds
    tol = _INSIDE_TOL * (hi - lo).amax() / 2
    positions = positions.detach()
    return ((positions >= lo - tol) & (positions <= hi + tol)).all(dim=1)


def _flat_hull(points: Tensor) -> tuple[Tensor, Tensor] | None:
    """Centre and orthonormal basis (rows) of the affine hull of a flat cloud; None for a 3-D one.

    A cloud is flat when its third singular value (about its mean) is below ``_FLAT_TOL`` times
    the first; the singular values come from the 3x3 R of a QR, so this is O(N) and accurate.
    """
    centre = points.mean(dim=0)
    _, s, vt = torch.linalg.svd(torch.linalg.qr(points - centre, mode="r").R)
    rank = int((s > _FLAT_TOL * s[0]).sum()) if s[0] > 0 else 0
    return None if rank == 3 else (centre, vt[:rank])


def _normalize(points: Tensor, bounds: tuple[Tensor, Tensor] | None = None
               ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`normalize_points`, with scale 1 when all points coincide (any scale maps them to 0)."""
    lo, hi = bounding_box(points) if bounds is None else bounds
    if (hi - lo).amax() > 0:
        return normalize_points(points, bounds=(lo, hi))
    return points - lo, lo, torch.ones((), dtype=points.dtype, device=points.device)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed 3x3 rotation matrix."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def fixed_rotations(count: int) -> Tensor:
    """(count, 3, 3) float64 rotations: the identity, then uniformly random ones from fixed seeds.

    The same on every machine and every call, so that an ensemble over them is
    deterministic, and the first ``k`` of them are ``fixed_rotations(k)``.
    """
    turns = [np.eye(3)] + [random_rotation(np.random.default_rng([0, k])) for k in range(1, count)]
    return torch.from_numpy(np.stack(turns))


class RotatedEncoding(NamedTuple):
    """The U-Net's features of a cloud turned by ``rotation`` and normalised anew.

    A point ``p`` of the field's normalised frame is at ``(rotation @ p - center) / scale``
    here; ``points`` and ``normals`` are the field's, so mapped, in the field's row order.
    """

    features: Tensor
    points: Tensor
    normals: Tensor | None
    rotation: Tensor
    center: Tensor
    scale: Tensor

    def views(self, cameras: Tensor | None, directions: Tensor | None
              ) -> tuple[Tensor | None, Tensor | None]:
        """Normalised cameras or directions of the field, mapped into this frame."""
        if cameras is not None:
            return (cameras @ self.rotation.T - self.center) / self.scale, None
        return None, directions @ self.rotation.T


class VisibilityField:
    """Per-point features of one cloud, answering visibility queries for any views.

    Made by :meth:`NeuralVisibility.encode`. The features are computed once
    (without autograd); each query runs the per-view predictor only, in
    batches of views and chunks of points of at most ``chunk_size`` rows.
    For a flat cloud (``hull``: centre and basis of its plane or line, in the
    normalised frame), views from off that plane or line see every point.
    With ``rotated`` encodings (see ``NeuralVisibility(num_rotations=...)``),
    a probability is the mean of the network's answers in every frame.
    ``calibration``: the ``(scale, shift)`` that a calibrated network applies
    to this cloud's margins in every frame (see :mod:`o3dvis.nn.calibration`).
    ``matmul_dtype``: the dtype of the per-view matrix products when no gradient
    is asked for (see ``NeuralVisibility(precision=...)``). ``scene``: makes the
    field of the same cloud that answers the cameras inside its bounding box
    (encoded with a scene model, on the first such camera); None: this field
    answers every view.

    The rows of ``features``, ``points_n`` and ``normals`` may be stored in
    another order than the cloud's (:meth:`NeuralVisibility.encode` sorts them
    along a Morton curve, which makes the per-view gathers cache-friendly):
    ``rank[i]`` is then the row of the cloud's point ``i``; None: the same order.
    Answers always come in the cloud's order.
    """

    def __init__(self, network: VisibilityNetwork, features: Tensor, points_n: Tensor,
                 normals: Tensor | None, center: Tensor, scale: Tensor, bounds: tuple[Tensor, Tensor],
                 chunk_size: int = DEFAULT_CHUNK, hull: tuple[Tensor, Tensor] | None = None,
                 rank: Tensor | None = None, rotated: Sequence[RotatedEncoding] = (),
                 calibration: tuple[float, float] | None = None, matmul_dtype: torch.dtype = torch.float32,
                 scene: Callable[[], "VisibilityField"] | None = None):
        self.network = network
        self.features = features
        self.points_n = points_n
        self.normals = normals
        self.center, self.scale = center, scale
        self.bounds = bounds
        self.chunk_size = chunk_size
        self.hull = hull
        self.rank = rank
        self.rotated = tuple(rotated)
        self.calibration = calibration
        self.matmul_dtype = matmul_dtype
        self._scene_factory, self._scene = scene, None
        self._scene_lock = threading.Lock()

    @property
    def num_points(self) -> int:
        return self.points_n.shape[0]

    @property
    def device(self) -> torch.device:
        return self.points_n.device

    def __repr__(self) -> str:
        normals = ", with normals" if self.normals is not None else ""
        frames = f", {1 + len(self.rotated)} frames" if self.rotated else ""
        return f"VisibilityField({self.num_points} points on {self.device}{normals}{frames})"

    def _normalised(self, views: Views) -> tuple[Tensor | None, Tensor | None]:
        """(V, 3) cameras or directions of ``views`` in the field's normalised frame."""
        dtype = self.points_n.dtype
        if views.directions is not None:
            return None, views.directions.to(self.device).to(dtype)
        positions = views.positions.to(self.device)
        lo, hi = self.bounds
        tol = _INSIDE_TOL * (hi - lo).amax() / 2  # zero when all points coincide: only they are inside
        for i in self._inside(views).nonzero()[:, 0].tolist():  # only a camera inside the box can be on a point
            gap = self._nearest_distance(positions[i].detach())
            if gap <= tol:
                raise ValueError(f"camera {i} at {_fmt(positions[i])} lies on a point of the cloud "
                                 f"(the nearest is {gap:.3g} away); move it off the surface")
        cameras = ((positions - self.center) / self.scale).to(dtype)
        if not torch.isfinite(cameras.detach()).all():
            raise ValueError("a camera is too far from the point cloud to be represented; "
                             "use direction= for a camera at infinity")
        return cameras, None

    def _inside(self, views: Views) -> Tensor | None:
        """(V,) bool: the cameras inside the cloud's bounding box (None for directions)."""
        return None if views.positions is None else _inside_box(views.positions.to(self.device), self.bounds)

    def _scene_field(self) -> "VisibilityField":
        """The field answering cameras inside the bounding box, encoded on first use (thread-safe)."""
        with self._scene_lock:
            if self._scene is None:
                self._scene = self._scene_factory()
            return self._scene

    def _parts(self, views: Views) -> list[tuple["VisibilityField", np.ndarray | None, Views]]:
        """``(field, the views' indices (None: all), those views)``: the cameras inside the bounding box
        go to the scene field where there is one, the other views stay with this one."""
        inside = self._inside(views)
        if self._scene_factory is None or inside is None or not inside.any():
            return [(self, None, views)]
        if inside.all():
            return [(self._scene_field(), None, views)]
        inside = inside.cpu().numpy()
        return [(field, index, _subset(views, index)) for field, index in
                ((self, np.flatnonzero(~inside)), (self._scene_field(), np.flatnonzero(inside)))]

    def _restricted(self, kept: Tensor) -> "VisibilityField":
        """This field on the stored rows ``kept`` only: they alone occlude and are answered, in that order."""
        def rows(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.index_select(0, kept)

        def channels_first(t: Tensor) -> Tensor:  # the layout encode() stores features in
            return t.t().index_select(1, kept).t()

        rotated = [e._replace(features=channels_first(e.features), points=rows(e.points), normals=rows(e.normals))
                   for e in self.rotated]
        return VisibilityField(self.network, channels_first(self.features), rows(self.points_n), rows(self.normals),
                               self.center, self.scale, self.bounds, self.chunk_size, self.hull, None, rotated,
                               self.calibration, self.matmul_dtype)

    def _cropped(self, view: Views, max_range: float) -> Tensor:
        """(1, N) probabilities, in the cloud's order, of one view that sees only the points within
        ``max_range`` of its camera: the others neither occlude nor are visible."""
        cameras, _ = self._normalised(view)
        if cameras is None:
            raise ValueError("max_range needs camera positions, not viewing directions")
        reach = (self.points_n - cameras[0].detach()).square().sum(dim=1) <= (max_range / float(self.scale)) ** 2
        kept = reach.nonzero()[:, 0]
        probs = self.features.new_zeros(1, self.num_points)
        if len(kept):
            near = torch.cat([p for _, p in self._restricted(kept)._batches(view)], dim=1)
            probs = probs.to(near.dtype).index_put((torch.zeros_like(kept), kept), near[0])
        return probs if self.rank is None else probs[:, self.rank]

    def _answers(self, views: Views, rows: Tensor | None, max_range: float | None,
                 finish: Callable[[Tensor], Tensor] | None = None) -> Iterator[tuple[np.ndarray | slice, Tensor]]:
        """Yields ``(views' indices, (v, M) probabilities)`` of the points ``rows`` (None: all) for
        every view, each view by its field (see :meth:`_parts`), or ``finish`` of them."""
        for field, index, part in self._parts(views):
            if max_range is None:
                for batch, probs in field._batches(part, rows, finish):
                    yield (batch if index is None else index[batch]), probs
                continue
            for j in range(len(part)):
                probs = field._cropped(_subset(part, np.array([j])), max_range)
                probs = probs if rows is None else probs[:, rows]
                yield (slice(j, j + 1) if index is None else index[j:j + 1]), (probs if finish is None else finish(probs))

    def _nearest_distance(self, position: Tensor) -> float:
        """The distance from a (3,) position in the cloud's frame to its nearest point: one pass over
        the points, in chunks (linear in N, the cost of one view's projection)."""
        camera = ((position - self.center) / self.scale).to(self.points_n.dtype)
        step = 1 << 20
        nearest = min(float((self.points_n[a:a + step] - camera).square().sum(dim=1).min())
                      for a in range(0, self.num_points, step))
        return float(nearest) ** 0.5 * float(self.scale)

    def _off_the_hull(self, views: Views) -> Tensor | None:
        """(V,) bool: the views from off the plane or line of a flat cloud (None for a 3-D cloud)."""
        if self.hull is None:
            return None
        centre, basis = self.hull
        if views.directions is not None:
            offset, tol = views.directions.detach().to(self.device), _INSIDE_TOL
        else:
            lo, hi = self.bounds
            offset = (views.positions.detach().to(self.device) - self.center) / self.scale - centre
            tol = _INSIDE_TOL * (hi - lo).amax() / 2 / self.scale
        return (offset - (offset @ basis.T) @ basis).norm(dim=1) > tol

    def _rows(self, indices) -> Tensor | None:
        """``indices`` as a checked (M,) long tensor on the field's device (None: all points)."""
        if indices is None:
            return None
        rows = torch.as_tensor(np.asarray(indices) if not isinstance(indices, Tensor) else indices)
        if rows.numel() == 0:
            rows = rows.long()
        if rows.dtype == torch.bool or rows.ndim != 1 or rows.is_floating_point() or rows.is_complex():
            raise TypeError(f"indices must be a 1-D sequence of integers, got {tuple(rows.shape)} "
                            f"{rows.dtype}")
        rows = rows.to(device=self.device, dtype=torch.long)
        if len(rows) and (int(rows.min()) < 0 or int(rows.max()) >= self.num_points):
            raise IndexError(f"indices must lie in [0, {self.num_points}), got "
                             f"{int(rows.min())} .. {int(rows.max())}")
        return rows

    def _frame_probabilities(self, features: Tensor, points: Tensor, normals: Tensor | None,
                             cameras: Tensor | None, directions: Tensor | None, batch: slice,
                             rows: Tensor | None, n: int, workers: int = 1) -> Tensor:
        """(v, n) probabilities of the views ``batch`` in one frame (features, points and views
        of that frame), streaming the points ``rows`` (None: all n) in cache-sized chunks, on
        ``workers`` threads side by side."""
        projections = [self.network.view(points, None if cameras is None else cameras[i],
                                         None if directions is None else directions[i])
                       for i in range(batch.start, batch.stop)]
        step = min(n, self.chunk_size)

        def chunk_margin(a: int) -> Tensor:
            chunk = slice(a, a + step) if rows is None else rows[a:a + step]
            return self.network.view_margin(projections, chunk, features, normals, self.matmul_dtype)

        starts = range(0, n, step)
        margin = torch.cat(list(_threaded_map(chunk_margin, starts, workers) if workers > 1 else
                                map(chunk_margin, starts)), dim=1)
        del projections
        if self.calibration is not None:
            scale, shift = self.calibration
            margin.mul_(scale).add_(shift)
        return torch.sigmoid(margin)

    def _batches(self, views: Views, rows: Tensor | None = None,
                 finish: Callable[[Tensor], Tensor] | None = None) -> Iterator[tuple[slice, Tensor]]:
        """Yields ``(views slice, (v, M) probabilities)`` of the points ``rows`` (None: all),
        with frustum culling applied, or ``finish`` of them (done on the thread that answered
        the views). Every point occludes, whichever rows are asked for."""
        cameras, directions = self._normalised(views)
        clear = self._off_the_hull(views)
        n, total = self.num_points if rows is None else len(rows), len(views)
        unsort = None  # the columns, in the cloud's order, of an answer for all stored rows
        if self.rank is not None:
            if rows is None:
                unsort = self.rank
            else:
                rows = self.rank[rows]
        if n == 0:
            empty = self.features.new_zeros(total, 0)
            yield slice(0, total), empty if finish is None else finish(empty)
            return
        asked = self.points_n if rows is None else self.points_n[rows]
        frames = [(self.features, self.points_n, self.normals, cameras, directions)] + [
            (e.features, e.points, e.normals, *e.views(cameras, directions)) for e in self.rotated]
        per_batch = max(1, self.chunk_size // n)
        batches = [slice(start, min(total, start + per_batch)) for start in range(0, total, per_batch)]

        def answer(batch: slice, workers: int = 1) -> Tensor:
            probs = self._frame_probabilities(*frames[0], batch, rows, n, workers)
            if frames[1:]:  # the mean over the frames
                for frame in frames[1:]:
                    probs = probs + self._frame_probabilities(*frame, batch, rows, n, workers)
                probs = probs / len(frames)
            if clear is not None:  # a flat cloud seen from off its plane or line hides nothing
                probs = torch.where(clear[batch, None], torch.ones_like(probs), probs)
            masks = [(j, f.contains(asked, self.center, self.scale))
                     for j, f in enumerate(views.frustums[batch]) if f is not None]
            if masks:
                keep = torch.ones_like(probs, dtype=torch.bool)
                for j, mask in masks:
                    keep[j] = mask
                probs = probs * keep
            probs = probs if unsort is None else torch.gather(probs, 1, unsort.expand(len(probs), -1))
            return probs if finish is None else finish(probs)

        # Views side by side on the CPU's threads, each on one: per-view ops are many and small, and
        # the C kernels (o3dvis.nn.native) run on one thread each. Without the kernels, a view of at
        # most one chunk of points is a few large torch ops that split well over the threads, and
        # is left to them. A single batch of views has its chunks side by side instead.
        threads = torch.get_num_threads()
        free = threads > 1 and self.device.type == "cpu" and not torch.is_grad_enabled()
        if free and len(batches) == 1 and n > self.chunk_size:
            torch.set_num_threads(1)  # no OpenMP team of the caller's to spin beside the workers
            try:
                result = answer(batches[0], threads)
            finally:
                torch.set_num_threads(threads)
            yield batches[0], result
            return
        workers = min(threads, len(batches))
        parallel = free and workers > 1 and (n > self.chunk_size or native.usable(self.features))
        yield from zip(batches, _threaded_map(answer, batches, workers) if parallel else map(answer, batches))

    def probabilities(self, cameras=None, direction=None, *, frustum: bool = True,
                      indices=None, max_range: float | None = None) -> Tensor:
        """Probability that each point is visible from each view.

        Differentiable with respect to camera positions (or directions) given
        as a torch tensor with ``requires_grad``; the point features are fixed.
        Without such a tensor the computation runs under ``torch.inference_mode``.

        Args:
            cameras: camera positions, (3,) or (V, 3), as list, tuple, numpy,
                torch or ``o3d.core.Tensor``; or ``o3d.camera.PinholeCameraParameters``,
                a list of them, or a ``PinholeCameraTrajectory``.
            direction: instead of ``cameras``, (3,) or (V, 3) viewing directions
                (from the camera into the scene) of orthographic views.
            frustum: for pinhole cameras with an image size, points that project
                outside the image or lie behind the camera get probability 0.
            indices: predict only these points (every point still occludes);
                None: all points. Costs in proportion to their number.
            max_range: only the points within this distance of a camera are seen
                by it: the others get probability 0 and hide nothing (a range crop,
                as a LiDAR's); None: no limit. Camera positions only.

        Returns:
            (V, N) float tensor on the field's device, (V, len(indices)) with ``indices``.

        Raises:
            ValueError: a camera on a point of the cloud, NaN/Inf, bad shapes,
                both or neither of cameras and direction, a max_range that is not
                positive or given with directions.
            TypeError: cameras that are not real numbers, or indices that are not integers.
            IndexError: an index out of range.
        """
        views = as_views(cameras, direction, frustum=frustum)
        rows, max_range = self._rows(indices), _checked_range(max_range)
        given = views.positions if views.positions is not None else views.directions
        grad = torch.is_grad_enabled() and given.requires_grad
        with contextlib.nullcontext() if grad else torch.inference_mode():
            parts = list(self._answers(views, rows, max_range))
            probs = torch.cat([p for _, p in parts])
            if all(isinstance(index, slice) for index, _ in parts):  # in the views' order already
                return probs
            order = np.concatenate([np.arange(len(views))[index] for index, _ in parts])
            return probs[torch.from_numpy(np.argsort(order)).to(probs.device)]

    def query(self, cameras=None, direction=None, threshold: float = 0.5, *,
              frustum: bool = True, indices=None, max_range: float | None = None) -> np.ndarray:
        """Which points each view sees.

        Args:
            cameras: camera positions or pinhole cameras, as in :meth:`probabilities`.
            direction: instead of ``cameras``, viewing directions of orthographic views.
            threshold: a point is visible when its probability exceeds this, in [0, 1].
            frustum: cull points outside the image of pinhole cameras with an image size.
            indices: answer only for these points, as in :meth:`probabilities`.
            max_range: points farther from a camera are not visible from it and
                hide nothing, as in :meth:`probabilities`.

        Returns:
            (V, N) bool numpy array, (V, len(indices)) with ``indices``.

        Raises:
            ValueError: as :meth:`probabilities`, or a threshold outside [0, 1].
            TypeError, IndexError: bad ``indices``, as in :meth:`probabilities`.
        """
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.floating, np.integer)):
            raise TypeError(f"threshold must be a number, got {type(threshold).__name__}")
        if not 0 <= threshold <= 1:
            raise ValueError(f"threshold must be in [0, 1], got {threshold}")
        views = as_views(cameras, direction, frustum=frustum)
        rows, max_range = self._rows(indices), _checked_range(max_range)
        out = np.empty((len(views), self.num_points if rows is None else len(rows)), dtype=bool)
        with torch.inference_mode():
            # thresholded on the threads that answer: an op here, on the caller's thread, would wake
            # the caller's OpenMP threads, which then spin for a while on the cores the workers use
            for batch, visible in self._answers(views, rows, max_range, lambda probs: (probs > threshold).cpu()):
                out[batch] = visible.numpy()
        return out


class NeuralVisibility:
    """A visibility network ready for Open3D clouds.

    The networks are moved to ``device`` and put in eval mode (in place).

    Args:
        network: the network used for clouds without normals (or for all
            clouds, when it takes normals itself).
        normals_network: optional network taking normals, used automatically
            for clouds that have normals.
        scene_network: optional network (without normals) that answers the
            cameras inside a cloud's bounding box (rooms, streets, scans);
            None: ``network`` answers them too.
        device: torch device to run on (default: the network's device).
        chunk_size: rows (views x points) per MLP call; bounds the memory of queries.
        num_rotations: answer with the mean of the network's answers for this many
            copies of the cloud (and its cameras), turned by fixed rotations, the
            first unturned. More accurate, and as many times slower: on the
            validation meshes 4 rotations raise the default model's accuracy
            by 0.5-1.3 points on clean clouds (see the README); 1, the default,
            is the fast single pass.
        precision: dtype of the per-view matrix products of queries without
            gradients: ``"auto"`` (default) is ``"bfloat16"`` on CPUs with native
            bfloat16 dot products (AVX512-BF16, AMX) and ``"float32"`` elsewhere.
            bfloat16 takes about a third off a view at 200 k points on such a CPU
            (6.9 against 11.0 ms on two threads) and changes 0.014 % of the
            answers there (see the README);
            probabilities differentiated w.r.t. cameras always use float32.

    Example:
        >>> vis = NeuralVisibility.pretrained()                     # doctest: +SKIP
        >>> field = vis.encode(pcd)                                 # doctest: +SKIP
        >>> mask = field.query([[0, 0, 5], [5, 0, 0]])              # doctest: +SKIP
    """

    def __init__(self, network: VisibilityNetwork, normals_network: VisibilityNetwork | None = None, *,
                 device: str | torch.device | None = None, chunk_size: int = DEFAULT_CHUNK,
                 num_rotations: int = 1, precision: str = "auto",
                 scene_network: VisibilityNetwork | None = None):
        for name, net in (("network", network), ("normals_network", normals_network),
                          ("scene_network", scene_network)):
            if net is not None and not isinstance(net, VisibilityNetwork):
                raise TypeError(f"{name} must be a VisibilityNetwork, got {type(net).__name__}")
        if normals_network is not None and not normals_network.config.use_normals:
            raise ValueError("normals_network must be a model that takes normals (config.use_normals)")
        if scene_network is not None and scene_network.config.use_normals:
            raise ValueError("scene_network must be a model that takes no normals")
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
            raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
        if isinstance(num_rotations, bool) or not isinstance(num_rotations, int) or num_rotations < 1:
            raise ValueError(f"num_rotations must be a positive int, got {num_rotations!r}")
        self.network = network
        self.normals_network = normals_network
        self.scene_network = scene_network
        self.chunk_size = chunk_size
        self.rotations = fixed_rotations(num_rotations)
        resolve_precision(precision, torch.device("cpu"))  # a bad value raises here, not at the first encode
        self.precision = precision
        self.to(next(network.parameters()).device if device is None else device)

    @classmethod
    def pretrained(cls, name: str = "default", device: str | torch.device | None = None, *,
                   use_normals: bool = True, weights_dir: str | Path | None = None,
                   num_rotations: int = 1, precision: str = "auto", use_scene: bool = True) -> "NeuralVisibility":
        """A shipped model from ``o3dvis/weights`` (sha256-checked, no pickle).

        With ``name="default"`` the shipped ``"normals"`` model, when there is
        one, is loaded too and used for clouds that have normals, and the
        shipped ``"scene"`` model, when there is one, for cameras inside a
        cloud's bounding box.

        Args:
            name: model name in the model card, or a ``.safetensors`` path.
            device: torch device (default: CPU).
            use_normals: False never loads the companion normals model.
            use_scene: False never loads the companion scene model.
            weights_dir: folder of the model card (default: the shipped one).
            num_rotations, precision: as in :class:`NeuralVisibility`.

        Returns:
            A ready :class:`NeuralVisibility`.

        Raises:
            FileNotFoundError: the model card or the checkpoint is missing
                (no trained weights installed); the message names the file.
            ValueError: unknown name (the message lists the available ones),
                tampered or truncated checkpoint.
        """
        network = load_model(name, device, weights_dir=weights_dir)
        normals_network = None
        if (use_normals and name == "default" and not network.config.use_normals
                and _NORMALS_MODEL in available_models(weights_dir)):
            normals_network = load_model(_NORMALS_MODEL, device, weights_dir=weights_dir)
        scene_network = None
        if use_scene and name == "default" and _SCENE_MODEL in available_models(weights_dir):
            scene_network = load_model(_SCENE_MODEL, device, weights_dir=weights_dir)
        return cls(network, normals_network, device=device, num_rotations=num_rotations, precision=precision,
                   scene_network=scene_network)

    @property
    def device(self) -> torch.device:
        return next(self.network.parameters()).device

    def to(self, device: str | torch.device) -> "NeuralVisibility":
        """Moves the networks to ``device`` (in place) and returns self."""
        device = torch_device(device)
        for net in (self.network, self.normals_network, self.scene_network):
            if net is not None:
                net.to(device).eval()
        return self

    def __repr__(self) -> str:
        normals = " + normals model" if self.normals_network is not None else ""
        normals += " + scene model" if self.scene_network is not None else ""
        turns = f", {len(self.rotations)} rotations" if len(self.rotations) > 1 else ""
        dtype = str(resolve_precision(self.precision, self.device)).removeprefix("torch.")
        return (f"NeuralVisibility({self.network.num_parameters()} parameters{normals}, {self.device}{turns}, "
                f"{dtype} products)")

    def _pick(self, cloud_normals: Tensor | None, normals, num_points: int
              ) -> tuple[VisibilityNetwork, Tensor | None]:
        """The network to use and the unit normals to feed it."""
        takes_normals = self.normals_network
        if takes_normals is None and self.network.config.use_normals:
            takes_normals = self.network
        if normals is None:
            normals = cloud_normals if takes_normals is not None else None
        elif normals is True:
            if cloud_normals is None:
                raise ValueError("normals=True but the point cloud has no normals")
            normals = cloud_normals
        elif normals is False:
            normals = None
        if normals is None:
            if self.network.config.use_normals:
                raise ValueError("this model needs normals and none were given (the cloud has none "
                                 "or normals=False)")
            return self.network, None
        if takes_normals is None:
            raise ValueError("normals were given but no loaded model takes normals")
        return takes_normals, unit_normals(normals, num_points)

    def encode(self, pcd, normals=None) -> VisibilityField:
        """Runs the U-Net once over a cloud.

        Args:
            pcd: ``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud``, or
                an (N, 3) numpy array / torch tensor of points.
            normals: None uses the cloud's normals when it has them and a model
                taking normals is loaded; False ignores normals; True requires
                the cloud's normals; an (N, 3) array gives them explicitly.

        Returns:
            A :class:`VisibilityField` to query with cameras.

        Raises:
            ValueError: an empty cloud, NaN/Inf coordinates, wrong shapes, or
                normals that the loaded models cannot use.
            TypeError: unsupported input types or dtypes.
        """
        return self._encode(pcd, normals)

    def _encode(self, pcd, normals=None, camera: Tensor | None = None) -> VisibilityField:
        """:meth:`encode`; given the (3,) ``camera`` of the only view to come, a camera inside the
        cloud's bounding box with a scene network gets the scene model's field alone."""
        points, cloud_normals = cloud_arrays(pcd)
        network, unit = self._pick(cloud_normals, normals, points.shape[0])
        points = points.to(self.device)
        lo, hi = bounding_box(points)
        points_n, center, scale = _normalize(points, (lo, hi))
        hull = _flat_hull(points_n)  # in float64, where a flat cloud is flat to the last bits
        points_n = points_n.float()
        order = morton_order(points_n)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(len(order), device=order.device)
        points_n = points_n.index_select(0, order)
        unit = None if unit is None else unit.to(self.device).index_select(0, order).float()
        frame = (points_n, center, scale, (lo, hi), hull, rank)
        scene = None
        if self.scene_network is not None and camera is not None and _inside_box(camera.to(lo)[None], (lo, hi))[0]:
            return self._field(self.scene_network, None, *frame)
        if self.scene_network is not None:
            def scene() -> VisibilityField:
                return self._field(self.scene_network, None, *frame)
        return self._field(network, unit, *frame, scene=scene)

    def _field(self, network: VisibilityNetwork, unit: Tensor | None, points_n: Tensor, center: Tensor,
               scale: Tensor, bounds: tuple[Tensor, Tensor], hull: tuple[Tensor, Tensor] | None, rank: Tensor,
               scene: Callable[[], VisibilityField] | None = None) -> VisibilityField:
        """The field of ``network`` over the normalised, Morton-ordered points of :meth:`encode`."""
        calibrated = network.calibration is not None
        with torch.no_grad():
            noise = network.cloud_noise(points_n, ordered=True) if network.config.noise_cues or calibrated else None
            features = network.encode(points_n, normals=unit, noise=noise)
            rotated = [self._rotated(network, points_n, unit, r) for r in self.rotations[1:]]
        calibration = (network.calibration.affine(calibration_terms(noise[0], len(points_n)))
                       if calibrated else None)
        return VisibilityField(network, features, points_n, unit, center, scale, bounds, self.chunk_size,
                               hull, rank, rotated, calibration, resolve_precision(self.precision, self.device),
                               scene)

    @staticmethod
    def _rotated(network: VisibilityNetwork, points_n: Tensor, normals: Tensor | None,
                 rotation: Tensor) -> RotatedEncoding:
        """The encoding of normalised points turned by ``rotation`` and normalised anew."""
        rotation = rotation.to(points_n)
        points, center, scale = _normalize(points_n @ rotation.T)
        normals = None if normals is None else normals @ rotation.T
        return RotatedEncoding(network.encode(points, normals=normals), points, normals, rotation,
                               center, scale)


_CACHE: dict[tuple[str, str, str], NeuralVisibility] = {}
_CACHE_LOCK = threading.Lock()


def shared_pretrained(name: str = "default", device: str | torch.device | None = None) -> NeuralVisibility:
    """The shipped model ``name`` on ``device``, loaded once per process and shared by every caller.

    What the functions of o3dvis use when given no model: loading the weights and
    checking their sha256 takes 0.16-0.19 s the first time in a process and
    0.06-0.07 s again (two CPU cores), longer than the visibility of a 2 k-point
    cloud. Thread-safe; the instance is shared, so do not move or change it
    (:meth:`NeuralVisibility.pretrained` gives a private one).

    Args:
        name: a model name of the model card (not a file path).
        device: torch device (default: CPU).

    Returns:
        The shared :class:`NeuralVisibility`, the same object on every call with
        the same name, device and weights folder.

    Raises:
        ValueError: ``name`` is not in the model card (the message lists the available ones).
    """
    key = _cache_key(name, device)
    with _CACHE_LOCK:
        if key not in _CACHE:  # the model card is read only here: a hit costs no file access
            names = available_models()
            if name not in names:
                raise ValueError(f"unknown model {name!r}; available: {', '.join(names) or 'none'}")
            _CACHE[key] = NeuralVisibility.pretrained(name, device)
        return _CACHE[key]


def _cache_key(name: str, device: str | torch.device | None) -> tuple[str, str, str]:
    return str(models.WEIGHTS_DIR), name, str(torch_device(device))


def _resolve_model(model, device: torch.device) -> NeuralVisibility:
    """A :class:`NeuralVisibility` from the ``model=`` argument of the functions below."""
    if isinstance(model, NeuralVisibility):
        return model.to(device)
    if isinstance(model, VisibilityNetwork):
        return NeuralVisibility(model, device=device)
    if model is None or isinstance(model, (str, Path)):
        name = "default" if model is None else model
        if isinstance(name, str) and (_cache_key(name, device) in _CACHE or name in available_models()):
            return shared_pretrained(name, device)
        return NeuralVisibility.pretrained(name, device)
    raise TypeError("model must be None, a model name or path, a NeuralVisibility or a "
                    f"VisibilityNetwork, got {type(model).__name__}")


def _visible_indices(pcd, cameras, direction, threshold: float, model, device, normals,
                     frustum: bool = True, max_range: float | None = None) -> np.ndarray:
    """Sorted int64 indices of the points of ``pcd`` visible from one view.

    With ``max_range``, only the points within it of the camera are encoded and
    answered (the octree's cells then fit the crop, not the whole cloud)."""
    views = as_views(cameras, direction, frustum=frustum)
    if len(views) != 1:
        raise ValueError(f"give one camera, got {len(views)}")
    max_range = _checked_range(max_range)
    device = torch_device(device) if device is not None else cloud_device(pcd)
    model = _resolve_model(model, device)
    camera = None if views.positions is None else views.positions[0]
    if max_range is None:
        field = model._encode(pcd, normals, camera)
        return np.flatnonzero(field.query(views, threshold=threshold)[0]).astype(np.int64)
    if views.positions is None:
        raise ValueError("max_range needs a camera position, not a viewing direction")
    points, cloud_normals = cloud_arrays(pcd)
    _, unit = model._pick(cloud_normals, normals, points.shape[0])
    camera = camera.detach().to(points.device)
    near = torch.nonzero((points - camera).square().sum(dim=1) <= max_range ** 2)[:, 0]
    if len(near) == 0:
        return np.zeros(0, dtype=np.int64)
    field = model._encode(points[near], False if unit is None else unit[near.to(unit.device)], camera)
    return near.cpu().numpy()[np.flatnonzero(field.query(views, threshold=threshold)[0])].astype(np.int64)


def _surface_triangles(vertices: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """Triangles over ``vertices`` as the camera sees them, facing it (see :mod:`.apps.triangulation`)."""
    from .apps.triangulation import DEFAULT_EDGE_FACTOR, local_spacing, visible_triangles

    return visible_triangles(vertices, camera, np.arange(len(vertices)),
                             DEFAULT_EDGE_FACTOR * local_spacing(vertices))


def hidden_point_removal_neural(pcd, camera_location, radius: float | None = None, *,
                                threshold: float = 0.5, model=None, device=None, triangulate: bool = False,
                                max_range: float | None = None):
    """Removes hidden points with the neural network: a drop-in for ``hidden_point_removal``.

    Returns what Open3D's ``PointCloud.hidden_point_removal`` returns, so
    ``mesh, pt_map = pcd.hidden_point_removal(camera, radius)`` can become
    ``mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera, radius)``.
    The mesh's vertices are exactly ``points[pt_map]``. By default it has no
    triangles (most callers use only ``pt_map``, and triangulating costs about
    as much as the visibility query); with ``triangulate=True`` its triangles
    are the surface the camera sees: a Delaunay triangulation of those points
    in the image plane without the triangles whose edges are much longer than
    the local point spacing, ordered counter-clockwise as seen from the camera
    (none when fewer than 3 points are visible or they project onto a line). Unlike Open3D, ``pt_map`` is sorted. Point
    normals are used when the cloud has them and a normals model is installed.

    Args:
        pcd: ``o3d.geometry.PointCloud`` or ``o3d.t.geometry.PointCloud``.
        camera_location: (3,) camera position (list, tuple, numpy, torch or
            ``o3d.core.Tensor``), anywhere but on a point of the cloud: outside
            it, or inside a room, a street or a scan.
        radius: unused; accepted so that existing calls work unchanged.
        threshold: a point is visible when its probability exceeds this.
        model: None (the shipped default), a model name or checkpoint path, a
            :class:`NeuralVisibility` or a ``VisibilityNetwork``.
        device: torch device, e.g. ``"cuda"`` (default: where the cloud lives, else CPU).
        triangulate: also triangulate the visible surface (see above).
        max_range: only the points within this distance of the camera are
            considered (as a LiDAR's range): the others are not visible and hide
            nothing; None: all points.

    Returns:
        ``(mesh, pt_map)``: for a legacy cloud an ``o3d.geometry.TriangleMesh``
        and a ``list[int]``; for a tensor cloud an ``o3d.t.geometry.TriangleMesh``
        and an Int64 ``o3d.core.Tensor``.

    Raises:
        ValueError: an empty cloud, NaN/Inf, a camera on a point of the cloud,
            a camera that is not one position, a max_range that is not positive.
        TypeError: ``pcd`` is not an Open3D PointCloud, or bad dtypes.
        FileNotFoundError: no installed model and no ``model`` given.
    """
    if not isinstance(pcd, (o3d.geometry.PointCloud, o3d.t.geometry.PointCloud)):
        raise TypeError(f"pcd must be an Open3D PointCloud (legacy or tensor), got {type(pcd).__name__}")
    camera = as_vectors(camera_location, "camera_location")
    if camera.shape[0] != 1:
        raise ValueError(f"camera_location must be one position of shape (3,), got {tuple(camera.shape)}")
    index = _visible_indices(pcd, camera[0], None, threshold, model, device, None, max_range=max_range)
    eye = camera[0].detach().cpu().numpy()
    if isinstance(pcd, o3d.geometry.PointCloud):
        vertices = np.asarray(pcd.points)[index]
        mesh = o3d.geometry.TriangleMesh()
        mesh.vertices = o3d.utility.Vector3dVector(vertices)
        if triangulate:
            mesh.triangles = o3d.utility.Vector3iVector(_surface_triangles(vertices, eye))
        return mesh, index.tolist()
    positions = pcd.point.positions
    pt_map = o3d.core.Tensor(index, dtype=o3d.core.Dtype.Int64, device=positions.device)
    mesh = o3d.t.geometry.TriangleMesh(positions.device)
    mesh.vertex.positions = positions[pt_map]
    if triangulate:
        triangles = _surface_triangles(mesh.vertex.positions.cpu().numpy().astype(np.float64), eye)
        mesh.triangle.indices = o3d.core.Tensor(triangles, dtype=o3d.core.Dtype.Int64,
                                                device=positions.device)
    return mesh, pt_map


def select_visible(pcd, camera=None, *, direction=None, threshold: float = 0.5, model=None,
                   device=None, normals=None, frustum: bool = True, max_range: float | None = None):
    """The points of a cloud that one camera sees, as a point cloud.

    Colours, normals and every other per-point attribute are kept.

    Args:
        pcd: ``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud``, or an
            (N, 3) numpy array / torch tensor of points.
        camera: one camera position (3,) or ``o3d.camera.PinholeCameraParameters``
            (with an image size, points outside the image are dropped too).
        direction: instead of ``camera``, the (3,) viewing direction of an
            orthographic view.
        threshold: a point is visible when its probability exceeds this.
        model: None (the shipped default), a model name or checkpoint path, a
            :class:`NeuralVisibility` or a ``VisibilityNetwork``.
        device: torch device (default: where the cloud lives, else CPU).
        normals: as in :meth:`NeuralVisibility.encode`.
        frustum: False ignores the image bounds of a pinhole camera.
        max_range: only the points within this distance of the camera are
            considered; None: all points. Camera positions only.

    Returns:
        A cloud of the same kind as ``pcd`` (a legacy ``PointCloud`` for arrays)
        holding the visible points in their original order.

    Raises:
        ValueError: an empty cloud, NaN/Inf, a camera on a point of the cloud,
            more than one camera, a max_range that is not positive or given with a direction.
        TypeError: unsupported input types or dtypes.
    """
    index = _visible_indices(pcd, camera, direction, threshold, model, device, normals, frustum, max_range)
    if isinstance(pcd, o3d.geometry.PointCloud):
        return pcd.select_by_index(index.tolist())
    if isinstance(pcd, o3d.t.geometry.PointCloud):
        device = pcd.point.positions.device
        return pcd.select_by_index(o3d.core.Tensor(index, dtype=o3d.core.Dtype.Int64, device=device))
    points, _ = cloud_arrays(pcd)
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.cpu().numpy()[index]))


def register() -> None:
    """Adds ``hidden_point_removal_neural`` as a method of Open3D's point clouds.

    Open3D's pybind11 classes accept new Python attributes, so after this call
    ``pcd.hidden_point_removal_neural(camera_location, radius)`` works on both
    ``o3d.geometry.PointCloud`` and ``o3d.t.geometry.PointCloud``.
    """
    for cls in (o3d.geometry.PointCloud, o3d.t.geometry.PointCloud):
        cls.hidden_point_removal_neural = hidden_point_removal_neural
