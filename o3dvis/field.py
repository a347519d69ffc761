"""The query engine: per-point features of one cloud answering visibility queries for any views.

A :class:`VisibilityField` holds what the network's U-Net computed once for a cloud
(:meth:`o3dvis.NeuralVisibility.encode` makes it); each query then costs a
depth-buffer pass and a small MLP over the points per view. A camera may stand
anywhere but on a point of the cloud: outside it, or inside a room, a street or a
scan, where a scene model answers when one is installed. A camera more than a
thousand bounding-box diagonals away is answered as the orthographic view in its
direction, the limit it tends to (a sun as a light). A flat cloud (a plane, a
line, coincident points, or one off them by a millionth of its size) seen from
off its plane or line hides nothing: there every point is visible, exactly,
whatever the network says.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .cameras import Views, as_views
from .geometry import within_range
from .nn import native
from .nn.network import VisibilityNetwork
from .nn.cues import point_surfels
from .nn.features import LeafFeatures
from .nn.frame import CloudFrame
from .nn.zbuffer import surfel_zbuffer
from .threads import plan_threads, threaded_map, torch_threads

__all__ = ["VisibilityField", "RotatedEncoding", "DEFAULT_CHUNK", "checked_range", "OnPointError"]

DEFAULT_CHUNK = 1 << 15
"""Rows (views x points) that one predictor call processes at most: small enough for the cache."""

_FAR_VIEW = 1e3
"""A camera farther than this many bounding-box diagonals from the cloud's centre is answered as
the orthographic view in its direction, the limit of ever farther cameras. The per-view steps work
in float32 relative to the cloud, where a camera 10^5 diagonals away starts to lose the points'
depth differences (accuracy falls from 10^5 on, to half at 10^7): the switch sits well below that,
where a perspective view differs from the orthographic one by a thousandth of a radian."""
# points a leaf from which every query the C kernels answer reads the features from the leaves (see
# _query_features): with fewer, views that read them again and again cost more than carrying them
# to the points once. A first query of one view reads the leaves at any density: it reads each leaf
# at most as often as carrying the features would write each point
_LEAF_READ_POINTS = 4
# queries of fewer rows (views x points) run on one thread where the C kernels answer: their helper
# threads (see native.kernel_threads) take over some blocks of a view from there
_KERNEL_SPLIT_ROWS = 4096


def _fmt(vector: Tensor) -> str:
    return "(" + ", ".join(f"{x:.6g}" for x in vector.detach().tolist()) + ")"


class OnPointError(ValueError):
    """A camera (or light) that lies on a point of the cloud, where visibility is undefined.

    Attributes:
        view: the index of the camera among the views asked.
    """

    def __init__(self, view: int, position: str, nearest: str, name: str | None = None):
        self.view, self.position, self.nearest = view, position, nearest
        super().__init__(f"{name or f'camera {view}'} at {position} lies on a point of the cloud ({nearest}); "
                         "move it off the surface")

    def named(self, name: str) -> "OnPointError":
        """This error, its camera called ``name`` (as ``"the light"``)."""
        return OnPointError(self.view, self.position, self.nearest, name)


def _subset(views: Views, index: np.ndarray) -> Views:
    """The views ``index`` of ``views``."""
    rows = torch.from_numpy(index)
    pick = (lambda t: None if t is None else t[rows.to(t.device)])
    return Views(pick(views.positions), pick(views.directions), tuple(views.frustums[i] for i in index.tolist()))


def checked_range(max_range) -> float | None:
    """``max_range`` as a positive float (None: no crop)."""
    if max_range is None:
        return None
    if isinstance(max_range, bool) or not isinstance(max_range, (int, float, np.floating, np.integer)):
        raise TypeError(f"max_range must be a number or None, got {type(max_range).__name__}")
    if not max_range > 0:  # NaN too
        raise ValueError(f"max_range must be positive, got {max_range}")
    return float(max_range)


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

    def views(self, cameras: Tensor | None, directions: Tensor
              ) -> tuple[Tensor | None, Tensor]:
        """Normalised cameras (None: none) and directions of the field, mapped into this frame."""
        mapped = None if cameras is None else (cameras @ self.rotation.T - self.center) / self.scale
        return mapped, directions @ self.rotation.T


class VisibilityField:
    """Per-point features of one cloud, answering visibility queries for any views.

    Made by :meth:`NeuralVisibility.encode`. On the CPU, queries run on the
    threads that :mod:`o3dvis.threads` plans. The features are computed once
    (without autograd); each query runs the per-view predictor only, in
    batches of views of at most ``chunk_size`` rows (views x points), the
    points of a view cut into such chunks too where the torch ops answer it
    or its chunks run side by side on several threads.
    ``frame`` is the cloud's normalisation (:class:`~o3dvis.nn.frame.CloudFrame`):
    ``points`` are in its frame; for a flat cloud (the frame's ``hull``), views
    from off its plane or line see every point.
    With ``rotated`` encodings (see ``NeuralVisibility(num_rotations=...)``),
    a probability is the mean of the network's answers in every frame.
    ``calibration``: the ``(scale, shift)`` that a calibrated network applies
    to this cloud's margins in every frame (see :mod:`o3dvis.nn.calibration`).
    ``matmul_dtype``: the dtype of the per-view matrix products when no gradient
    is asked for (see ``NeuralVisibility(precision=...)``). ``noise``: the cloud's (2,)
    noise cues (a network that fuses its answers with the surfel z-buffer's reads
    them, see :mod:`o3dvis.nn.fusion`; so does :mod:`o3dvis.two_pass`). ``scene``: makes the
    field of the same cloud that answers the cameras inside its bounding box
    (encoded with a scene model, on the first such camera); None: this field
    answers every view.

    The rows of ``features``, ``points`` and ``normals`` may be stored in
    another order than the cloud's (:meth:`NeuralVisibility.encode` sorts them
    along a Morton curve, which makes the per-view gathers cache-friendly):
    ``rank[i]`` is then the row of the cloud's point ``i``; None: the same order.
    Answers always come in the cloud's order.
    """

    def __init__(self, network: VisibilityNetwork, features: Tensor | LeafFeatures, points: Tensor,
                 normals: Tensor | None, frame: CloudFrame, *, chunk_size: int = DEFAULT_CHUNK,
                 rank: Tensor | None = None, rotated: Sequence[RotatedEncoding] = (),
                 calibration: tuple[float, float] | None = None, matmul_dtype: torch.dtype = torch.float32,
                 scene: Callable[[], "VisibilityField"] | None = None, noise: Tensor | None = None):
        self.network = network
        self.encoders: tuple[VisibilityNetwork, ...] = (network,)
        """The networks whose answers made the features: ``network``, after the first pass's of a
        two-pass encoding (:mod:`o3dvis.two_pass`)."""
        # the features as encoded, per leaf (or per point), and carried to every point on first use
        self._leaves = features if isinstance(features, LeafFeatures) else None
        self._features = None if self._leaves is not None else features
        self._queried = False
        self.points = points
        self.normals = normals
        self.frame = frame
        self.chunk_size = chunk_size
        self.rank = rank
        self.rotated = tuple(rotated)
        self.calibration = calibration
        self.matmul_dtype = matmul_dtype
        self.noise = noise
        self._scene_factory, self._scene = scene, None
        self._lazy_lock = threading.Lock()  # guards what is made on first use: the scene field, the surfels, features
        # each frame's point surfels (and with their area spacing), by its points' storage
        self._surfels: dict[int, tuple[Tensor | None, Tensor | None]] = {}

    @property
    def num_points(self) -> int:
        return self.points.shape[0]

    @property
    def features(self) -> Tensor:
        """(N, E) each stored point's projected features, stored channels first (strides (1, N))."""
        with self._lazy_lock:
            if self._features is None:
                with torch.inference_mode(False), torch.no_grad():  # fixed, yet readable by a later autograd query
                    self._features = self._leaves.rows()
            return self._features

    def _kernels_answer(self) -> bool:
        """Whether the C kernels answer this field's queries on the calling thread now (on the CPU,
        without autograd, with a per-view kernel in the field's product dtype)."""
        return native.usable(self.points) and native.has_view_margin(self.matmul_dtype)

    def _query_features(self, views: int) -> Tensor | LeafFeatures:
        """The features a query of ``views`` views reads: from the leaves for a first query of one
        view (it reads less than carrying them to every point writes) and, for a cloud of several
        points a leaf (:data:`_LEAF_READ_POINTS`), for every query that the C kernels answer (each
        point's term added as they read); any other query reads those carried to the points
        (:attr:`features`)."""
        first, self._queried = not self._queried, True
        if self._features is None and ((first and views == 1) or (
                self.num_points >= _LEAF_READ_POINTS * self._leaves.leaves.shape[1] and self._kernels_answer())):
            return self._leaves
        return self.features

    @property
    def device(self) -> torch.device:
        return self.points.device

    def __repr__(self) -> str:
        normals = ", with normals" if self.normals is not None else ""
        frames = f", {1 + len(self.rotated)} frames" if self.rotated else ""
        return f"VisibilityField({self.num_points} points on {self.device}{normals}{frames})"

    def _normalised(self, views: Views) -> tuple[Tensor | None, Tensor, list[bool]]:
        """The views in the field's normalised frame: (V, 3) camera positions (None for views
        given as directions), (V, 3) unit viewing directions, and which views are orthographic:
        those given as directions, and cameras beyond ``_FAR_VIEW`` diagonals, whose direction is
        the one from the camera to the cloud's centre."""
        dtype = self.points.dtype
        if views.directions is not None:
            return None, views.directions.to(self.device).to(dtype), [True] * len(views)
        offsets = self.frame.to_unit(views.positions.to(self.device))  # float64: exact enough at any distance
        # scaled by the largest coordinate first, so that no norm overflows
        largest = offsets.detach().abs().amax(dim=1, keepdim=True).clamp_min(torch.finfo(offsets.dtype).tiny)
        directions = -torch.nn.functional.normalize(offsets / largest, dim=1)
        # in the normalised frame: the world's diagonal squared underflows below 1e-154, overflows above 1e154
        far = offsets.detach().norm(dim=1) > _FAR_VIEW * self.frame.unit_diagonal
        return offsets.to(dtype), directions.to(dtype), far.tolist()

    def _inside(self, views: Views) -> Tensor | None:
        """(V,) bool: the cameras inside the cloud's bounding box (None for directions)."""
        return None if views.positions is None else self.frame.contains(views.positions.to(self.device))

    def _scene_field(self) -> "VisibilityField":
        """The field answering cameras inside the bounding box, encoded on first use (thread-safe)."""
        with self._lazy_lock:
            if self._scene is None:
                with torch.inference_mode(False):  # features a later query may differentiate through
                    self._scene = self._scene_factory()
            return self._scene

    def _parts(self, views: Views) -> list[tuple["VisibilityField", np.ndarray | None, Views]]:
        """``(field, the views' indices (None: all), those views)``: the cameras inside the bounding
        box go to the scene field where there is one, the other views stay with this one.

        Raises:
            OnPointError: a camera on a point of the cloud (see :meth:`_check_off_points`).
        """
        inside = self._inside(views)
        if inside is not None:
            self._check_off_points(views.positions, inside)
        if self._scene_factory is None or inside is None or not inside.any():
            return [(self, None, views)]
        if inside.all():
            return [(self._scene_field(), None, views)]
        flags = inside.cpu().numpy()
        return [(field, index, _subset(views, index))
                for field, index in ((self, np.flatnonzero(~flags)), (self._scene_field(), np.flatnonzero(flags)))]

    def _restricted(self, kept: Tensor) -> "VisibilityField":
        """This field on the stored rows ``kept`` only: they alone occlude and are answered, in that order."""
        def rows(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.index_select(0, kept)

        def channels_first(t: Tensor) -> Tensor:  # the layout encode() stores features in
            return t.t().index_select(1, kept).t()

        rotated = [e._replace(features=channels_first(e.features), points=rows(e.points), normals=rows(e.normals))
                   for e in self.rotated]
        features = channels_first(self._features) if self._leaves is None else self._leaves.restricted(kept)
        return VisibilityField(self.network, features, rows(self.points), rows(self.normals), self.frame,
                               chunk_size=self.chunk_size, rotated=rotated, calibration=self.calibration,
                               matmul_dtype=self.matmul_dtype, noise=self.noise)

    def restricted(self, rows) -> "VisibilityField":
        """This field as if the cloud were its points ``rows`` (indices in its order; None: all) alone, with
        no new encoding: they alone occlude and are answered, in that order, with the whole cloud's features
        and surfels (a crop's border keeps its spacing), the scene field cropped alike. Raises as ``indices``."""
        stored = self._checked_indices(torch.arange(self.num_points) if rows is None else rows)
        stored = stored if self.rank is None else self.rank[stored]
        kept, order = (stored, None) if len(stored) < 2 or bool((stored[1:] >= stored[:-1]).all()) else stored.sort()
        field = self._restricted(kept)  # stored along the Morton curve, as encode() stores them
        if order is not None:  # answered in the rows' order
            field.rank = torch.empty_like(order).scatter_(0, order, torch.arange(len(order), device=order.device))
        with torch.no_grad():  # the whole cloud's surfels, made once (by the C kernels)
            surfels = self._surfels_of(self.points)
        if any(s is not None for s in surfels):
            field._surfels[field.points.data_ptr()] = tuple(s if s is None else s[kept] for s in surfels)
        if self._scene_factory is not None:
            field._scene_factory = lambda: self._scene_field().restricted(rows)
        return field

    def _cropped(self, view: Views, max_range: float) -> Tensor:
        """(1, N) probabilities, in the cloud's order, of one view that sees only the points within
        ``max_range`` of its camera: the others neither occlude nor are visible."""
        cameras, _, _ = self._normalised(view)
        if cameras is None:
            raise ValueError("max_range needs camera positions, not viewing directions")
        kept = within_range(self.points, cameras[0].detach(), max_range / float(self.frame.scale))
        probs = self.points.new_zeros(1, self.num_points)
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
                batch = slice(j, j + 1) if index is None else index[j:j + 1]
                yield batch, (probs if finish is None else finish(probs))

    def _check_off_points(self, positions: Tensor, inside: Tensor) -> None:
        """Raises :class:`OnPointError` for the first of the (V, 3) cameras that lies on a point: within
        a millionth of the cloud's extent of one (zero when all points coincide). Only a camera inside
        the bounding box (``inside``) can be. The points are float32 in the normalised frame: a distance
        below their rounding (a cloud stretched by a far outlier) is given as that bound, not as a figure."""
        lo, hi = self.frame.bounds
        tol = float(self.frame.tolerance())
        rounding = 3 ** 0.5 * torch.finfo(self.points.dtype).eps * float(self.frame.scale)
        for i in inside.nonzero()[:, 0].tolist():
            gap = self._nearest_distance(positions[i].detach().to(self.device))
            if gap <= tol:
                nearest = (f"the nearest is {gap:.3g} away, within a millionth of its extent" if gap > rounding else
                           f"the nearest is within {rounding:.3g}, what the network resolves in a cloud "
                           f"{float((hi - lo).amax()):.3g} across")
                raise OnPointError(i, _fmt(positions[i]), nearest)

    def _nearest_distance(self, position: Tensor) -> float:
        """The distance from a (3,) position in the cloud's frame to its nearest point: one pass over
        the points, in chunks (linear in N, the cost of one view's projection)."""
        camera = self.frame.to_unit(position).to(self.points.dtype)
        step = 1 << 20
        nearest = min(float((self.points[a:a + step] - camera).square().sum(dim=1).min())
                      for a in range(0, self.num_points, step))
        return float(nearest) ** 0.5 * float(self.frame.scale)

    def _checked_indices(self, indices) -> Tensor | None:
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

    def _surfels_of(self, points: Tensor) -> tuple[Tensor | None, Tensor | None]:
        """The network's :meth:`~o3dvis.nn.network.VisibilityNetwork.surfels` of one frame's points
        (None for a network that needs none) and, for a network with a fusion, those surfels with
        their area spacing for its z-buffer (else None); computed on the first view and kept."""
        config = self.network.config
        if not (config.footprints or config.fusion):
            return None, None
        key = points.data_ptr()
        with self._lazy_lock:
            if key not in self._surfels:
                if config.fusion:  # one pass for both
                    full = point_surfels(points, areas=True)
                    self._surfels[key] = (full[:, :4].contiguous() if config.footprints else None, full)
                else:
                    self._surfels[key] = (self.network.surfels(points), None)
            return self._surfels[key]

    def _frame_probabilities(self, features: Tensor | LeafFeatures, points: Tensor, normals: Tensor | None,
                             cameras: Tensor | None, directions: Tensor, orthographic: list[bool],
                             batch: slice, rows: Tensor | None, n: int, workers: int = 1) -> Tensor:
        """(v, n) probabilities of the views ``batch`` in one frame (features, points and views
        of that frame, see :meth:`_normalised`), streaming the points ``rows`` (None: all n) in
        cache-sized chunks, on ``workers`` threads side by side."""
        surfels, with_areas = self._surfels_of(points)
        fusion, views = self.network.fusion, range(batch.start, batch.stop)

        def prepare(task: tuple[str, int]) -> object:  # a view's projection, or its camera's z-buffer test
            kind, i = task
            if kind == "zbuffer":
                return None if orthographic[i] else surfel_zbuffer(points, with_areas, cameras[i])
            return (self.network.view(points, direction=directions[i], surfels=surfels) if orthographic[i]
                    else self.network.view(points, cameras[i], surfels=surfels))

        # with a fusion, a view's projection and its z-buffer are independent passes of C: side by side
        tasks = [("view", i) for i in views] + ([("zbuffer", i) for i in views] if fusion is not None else [])
        prepared = list(threaded_map(prepare, tasks, workers) if workers > 1 and fusion is not None else
                        map(prepare, tasks))
        projections, zbuffers = prepared[:len(views)], prepared[len(views):]
        fuse = fusion.bind(self.noise) if any(z is not None for z in zbuffers) else None
        # chunks bound the memory of the torch ops and split a view over the workers; one pass of C
        # streams all the points through the cache itself (each chunk would pay its setup again)
        # and shares its blocks out among the workers' count of threads (native.kernel_threads)
        whole = fuse is None and self.network.native_margin(projections, features, self.matmul_dtype)
        step = n if whole else min(n, self.chunk_size)

        def chunk_margin(a: int) -> Tensor:
            chunk = slice(a, a + step) if rows is None else rows[a:a + step]
            margin = self.network.view_margin(projections, chunk, features, normals, self.matmul_dtype)
            if fuse is not None:  # camera views: fused with the z-buffer's test
                margin = torch.stack([m if z is None else fuse(m, z, chunk) for m, z in zip(margin, zbuffers)])
            return margin

        if whole:  # workers: the kernels' threads here (else those the caller set)
            with torch_threads(workers) if workers > 1 else contextlib.nullcontext():
                margin = chunk_margin(0)
        else:
            starts = range(0, n, step)
            margin = torch.cat(list(threaded_map(chunk_margin, starts, workers) if workers > 1 else
                                    map(chunk_margin, starts)), dim=1)
        del projections, zbuffers, prepared
        if self.calibration is not None:
            scale, shift = self.calibration
            margin.mul_(scale).add_(shift)
        return torch.sigmoid(margin)

    def _batches(self, views: Views, rows: Tensor | None = None,
                 finish: Callable[[Tensor], Tensor] | None = None, stored: bool = False
                 ) -> Iterator[tuple[slice, Tensor]]:
        """Yields ``(views slice, (v, M) probabilities)`` of the points ``rows`` (None: all),
        with frustum culling applied, or ``finish`` of them (done on the thread that answered
        the views). Every point occludes, whichever rows are asked for. ``stored``: ``rows`` and
        the answers in the order the points are stored in (along the Morton curve), not the cloud's."""
        cameras, directions, orthographic = self._normalised(views)
        clear = self.frame.off_the_hull(views.positions, views.directions)
        n, total = self.num_points if rows is None else len(rows), len(views)
        unsort = None  # the columns, in the cloud's order, of an answer for all stored rows
        if self.rank is not None and not stored:
            if rows is None:
                unsort = self.rank
            else:
                rows = self.rank[rows]
        if n == 0:
            empty = self.points.new_zeros(total, 0)
            yield slice(0, total), empty if finish is None else finish(empty)
            return
        asked_points = self.points if rows is None else self.points[rows]
        frames = [(self._query_features(total), self.points, self.normals, cameras, directions, orthographic)] + [
            (e.features, e.points, e.normals, *e.views(cameras, directions), orthographic)
            for e in self.rotated]
        per_batch = max(1, self.chunk_size // n)
        batches = [slice(start, min(total, start + per_batch)) for start in range(0, total, per_batch)]

        def probabilities_of(batch: slice, workers: int = 1) -> Tensor:
            probs = self._frame_probabilities(*frames[0], batch, rows, n, workers)
            if frames[1:]:  # the mean over the frames
                for frame in frames[1:]:
                    probs = probs + self._frame_probabilities(*frame, batch, rows, n, workers)
                probs = probs / len(frames)
            if clear is not None:  # a flat cloud seen from off its plane or line hides nothing
                probs = torch.where(clear[batch, None], torch.ones_like(probs), probs)
            masks = [(j, f.contains(asked_points, self.frame.center, self.frame.scale))
                     for j, f in enumerate(views.frustums[batch]) if f is not None]
            if masks:
                keep = torch.ones_like(probs, dtype=torch.bool)
                for j, mask in masks:
                    keep[j] = mask
                probs = probs * keep
            probs = probs if unsort is None else torch.gather(probs, 1, unsort.expand(len(probs), -1))
            return probs if finish is None else finish(probs)

        # Views side by side on the CPU's threads, each on one: per-view ops are many and small. The
        # C kernels (o3dvis.nn.native) share one view's points out among threads themselves, from
        # smaller views on than torch ops split well. Without the kernels, a view of at most one
        # chunk of points is a few large torch ops that split well over the threads, and is left to
        # them. A single batch of views has its chunks side by side instead.
        cpu = self.device.type == "cpu"
        split_from = _KERNEL_SPLIT_ROWS if self._kernels_answer() else self.chunk_size
        threads = plan_threads(n * total, split_from) if cpu else 1
        side_by_side = cpu and not torch.is_grad_enabled()
        if side_by_side and threads > 1 and len(batches) == 1 and n > self.chunk_size:
            with torch_threads(1):  # no OpenMP team of the caller's to spin beside the workers
                result = probabilities_of(batches[0], threads)
            yield batches[0], result
            return
        workers = min(threads, len(batches))
        if side_by_side and workers > 1 and (n > self.chunk_size or native.usable(self.points)):
            yield from zip(batches, threaded_map(probabilities_of, batches, workers))
            return
        for batch in batches:  # one at a time, the ops split over the threads planned
            with torch_threads(threads) if cpu else contextlib.nullcontext():
                result = probabilities_of(batch)
            yield batch, result

    def stored_probabilities(self, cameras, rows=None) -> Tensor:
        """(V, N) :meth:`probabilities` of camera positions, with the points in the order they are
        stored in (along the Morton curve: ``rank`` maps the cloud's order to it), for callers that
        work in that order: no permutation either way. ``rows``: only these points, by their
        place in that order ((V, len(rows)); every point still occludes)."""
        views = as_views(cameras, None)
        rows = self._checked_indices(rows)
        with torch.inference_mode():
            parts = [(index, torch.cat([p for _, p in field._batches(part, rows, stored=True)]))
                     for field, index, part in self._parts(views)]
            if len(parts) == 1:
                return parts[0][1]
            out = parts[0][1].new_empty(len(views), parts[0][1].shape[1])
            for index, probs in parts:
                out[torch.from_numpy(index).to(out.device)] = probs
            return out

    def probabilities(self, cameras=None, direction=None, *, frustum: bool = True,
                      indices=None, max_range: float | None = None, as_numpy: bool = False) -> Tensor | np.ndarray:
        """Probability that each point is visible from each view.

        Differentiable with respect to camera positions (or directions) given
        as a torch tensor with ``requires_grad``; the point features are fixed.
        Without such a tensor the computation runs under ``torch.inference_mode``.
        A torch tensor by default, since gradients flow through it; ``as_numpy=True``
        gives the numpy array :meth:`query` gives by default.

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
            as_numpy: return a float numpy array (on the CPU, no gradient) instead.

        Returns:
            (V, N) float tensor on the field's device, (V, len(indices)) with ``indices``;
            a numpy array with ``as_numpy``.

        Raises:
            ValueError: a camera on a point of the cloud, NaN/Inf, bad shapes,
                both or neither of cameras and direction, a max_range that is not
                positive or given with directions, ``as_numpy`` with cameras that
                require a gradient (numpy would drop it).
            TypeError: cameras that are not real numbers, or indices that are not integers.
            IndexError: an index out of range.
        """
        views = as_views(cameras, direction, frustum=frustum)
        rows, max_range = self._checked_indices(indices), checked_range(max_range)
        given = views.positions if views.positions is not None else views.directions
        grad = torch.is_grad_enabled() and given.requires_grad
        if grad and as_numpy:
            raise ValueError("as_numpy=True drops the gradient the cameras require; leave it False")
        with contextlib.nullcontext() if grad else torch.inference_mode():
            parts = list(self._answers(views, rows, max_range))
            probs = torch.cat([p for _, p in parts])
            if not all(isinstance(index, slice) for index, _ in parts):  # back to the views' order
                order = np.concatenate([np.arange(len(views))[index] for index, _ in parts])
                probs = probs[torch.from_numpy(np.argsort(order)).to(probs.device)]
            return probs.cpu().numpy() if as_numpy else probs

    def query(self, cameras=None, direction=None, threshold: float = 0.5, *, frustum: bool = True,
              indices=None, max_range: float | None = None, as_numpy: bool = True) -> np.ndarray | Tensor:
        """Which points each view sees.

        A numpy array by default, as Open3D's ``select_by_index`` and numpy masks take it;
        ``as_numpy=False`` gives the torch tensor :meth:`probabilities` gives by default.

        Args:
            cameras: camera positions or pinhole cameras, as in :meth:`probabilities`.
            direction: instead of ``cameras``, viewing directions of orthographic views.
            threshold: a point is visible when its probability exceeds this, in [0, 1].
            frustum: cull points outside the image of pinhole cameras with an image size.
            indices: answer only for these points, as in :meth:`probabilities`.
            max_range: points farther from a camera are not visible from it and
                hide nothing, as in :meth:`probabilities`.
            as_numpy: False returns a bool torch tensor on the field's device instead.

        Returns:
            (V, N) bool numpy array, (V, len(indices)) with ``indices``; a torch tensor
            without ``as_numpy``.

        Raises:
            ValueError: as :meth:`probabilities`, or a threshold outside [0, 1].
            TypeError, IndexError: bad ``indices``, as in :meth:`probabilities`.
        """
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float, np.floating, np.integer)):
            raise TypeError(f"threshold must be a number, got {type(threshold).__name__}")
        if not 0 <= threshold <= 1:
            raise ValueError(f"threshold must be in [0, 1], got {threshold}")
        views = as_views(cameras, direction, frustum=frustum)
        rows, max_range = self._checked_indices(indices), checked_range(max_range)
        out = np.empty((len(views), self.num_points if rows is None else len(rows)), dtype=bool)
        with torch.inference_mode():
            # thresholded on the threads that answer: an op here, on the caller's thread, would wake
            # the caller's OpenMP threads, which then spin for a while on the cores the workers use
            for batch, visible in self._answers(views, rows, max_range, lambda probs: (probs > threshold).cpu()):
                out[batch] = visible.numpy()
        return out if as_numpy else torch.from_numpy(out).to(self.device)
