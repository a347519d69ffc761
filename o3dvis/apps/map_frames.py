"""Camera frames of a map: what each pinhole frame of a driving log sees, as its users need it.

A map (a LiDAR log accumulated into one cloud) is projected into camera frames for depth
supervision, label transfer, colouring points or initialising NeRF and splatting scenes.
For each frame, :func:`visible_in_frame` gives the visible points' indices, their pixel
coordinates and depths and, on request, the frame's depth image and index image (the
nearest visible point of each pixel), without the points behind cars and walls bleeding
through. :func:`frames` answers a whole trajectory from encodings shared by its frames.

A frame sees only the points that project into its image from in front of the camera,
and with ``max_range`` only those within that distance of it: the others neither occlude
nor are visible. Each frame answers that crop alone (a query costs in proportion to the
points in view), from the encoding of the map or, where the map is larger than what
its frames see, of a crop of it around a group of nearby frames: the network's octree
spans the cloud it encodes, so a map of a kilometre encoded whole would blur what
a frame of 40 metres sees (see :class:`FrameMap`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Iterator

import numpy as np
import torch

from ..cameras import Views, frustum_from_pinhole, intrinsic_matrix, is_open3d, real_array, require_open3d
from ..clouds import cloud_arrays, cloud_device
from ..field import VisibilityField, checked_range
from ..models import torch_device
from ..threads import plan_threads, threaded_map
from .frame_tiles import Frame, FrameTile, empty_frame
from .pinhole import MAX_PIXELS, PinholeView

__all__ = ["Frame", "FrameMap", "visible_in_frame", "frames", "pinhole_frames", "tile_centres", "checked_frame_indices",
           "TILE_SLACK"]

TILE_SLACK = 0.5
"""With ``max_range`` R, a crop of the map of radius (1 + TILE_SLACK) R is encoded for the frames
whose cameras lie within TILE_SLACK R of its centre: each sees all of its range inside the crop."""
_KEPT_TILES = 2  # encodings of crops kept for the frames to come (the current one and the last)
_LOOKAHEAD = 4  # frames a worker has at most in hand ahead of those yielded
_SIDE_BY_SIDE_POINTS = 1 << 16  # a smaller map's frames are answered one at a time


def _checked_size(width, height) -> tuple[int, int]:
    """``(width, height)`` of a frame's image, positive ints of at most :data:`MAX_PIXELS` pixels."""
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"a frame's {name} must be a positive int, got {value!r}")
    if int(width) * int(height) > MAX_PIXELS:
        raise ValueError(f"a {width} x {height} frame has more than the {MAX_PIXELS} pixels an image may have")
    return int(width), int(height)


def _view_of_pinhole(params) -> PinholeView:
    """The checked :class:`PinholeView` of ``PinholeCameraParameters`` (a rigid extrinsic, a valid intrinsic
    with an image size)."""
    _, frustum = frustum_from_pinhole(params)
    if frustum is None:
        raise ValueError("the camera's intrinsic has no image size (width and height must be positive)")
    return PinholeView(frustum.extrinsic, frustum.intrinsic, frustum.width, frustum.height)


def _view_of_arrays(extrinsic, intrinsic, width, height) -> PinholeView:
    """The checked :class:`PinholeView` of a 4x4 world-to-camera matrix and an intrinsic."""
    o3d = require_open3d("pinhole frames")
    if is_open3d(intrinsic, "camera.PinholeCameraIntrinsic"):
        width, height = intrinsic.width, intrinsic.height
    if intrinsic is None or width is None or height is None:
        raise ValueError("a frame given as a 4x4 extrinsic needs intrinsic= (a 3x3 matrix or a "
                         "PinholeCameraIntrinsic) and, with a matrix, width= and height=")
    k = intrinsic_matrix(intrinsic)
    width, height = _checked_size(width, height)
    params = o3d.camera.PinholeCameraParameters()
    params.extrinsic = real_array(extrinsic, "extrinsic", "a 4x4 matrix")
    frustum_from_pinhole(params)  # checks the extrinsic: finite and rigid
    return PinholeView(np.asarray(params.extrinsic, dtype=np.float64), k, width, height)


def pinhole_frames(cameras, intrinsic=None, width: int | None = None, height: int | None = None) -> list[PinholeView]:
    """The checked cameras of frames, each a :class:`~o3dvis.apps.pinhole.PinholeView`.

    Args:
        cameras: ``o3d.camera.PinholeCameraParameters``, a list of them, a
            ``PinholeCameraTrajectory`` (as ``o3d.io.read_pinhole_camera_trajectory``
            reads it), a :class:`~o3dvis.apps.pinhole.PinholeView` or a list of them, or world-to-camera
            extrinsics: one 4x4 matrix or an (F, 4, 4) array, with ``intrinsic``.
        intrinsic: for extrinsics, ``o3d.camera.PinholeCameraIntrinsic`` or a 3x3 matrix (with
            ``width`` and ``height``), or (F, 3, 3) matrices, one per frame.
        width, height: the image size, for intrinsics given as matrices.

    Returns:
        One :class:`PinholeView` per frame.

    Raises:
        ValueError: a pose that is not a rigid transform (a rotation with determinant +1 and
            last row 0 0 0 1), NaN or Inf, a bad intrinsic, a missing or bad image size, no frame;
            the message names the frame.
        TypeError: cameras of another kind.
    """
    if is_open3d(cameras, "camera.PinholeCameraTrajectory"):
        cameras = list(cameras.parameters)
    if isinstance(cameras, PinholeView) or is_open3d(cameras, "camera.PinholeCameraParameters"):
        cameras = [cameras]
    if isinstance(cameras, (list, tuple)) and cameras and all(
            isinstance(c, PinholeView) or is_open3d(c, "camera.PinholeCameraParameters") for c in cameras):
        return [_framed(i, lambda c=c: c if isinstance(c, PinholeView) else _view_of_pinhole(c))
                for i, c in enumerate(cameras)]
    if isinstance(cameras, (list, tuple)) and not cameras:
        raise ValueError("no frame: the trajectory holds no camera")
    extrinsics = real_array(cameras, "cameras", "an (F, 4, 4) array of extrinsics")
    if extrinsics.shape == (4, 4):
        extrinsics = extrinsics[None]
    if extrinsics.ndim != 3 or extrinsics.shape[1:] != (4, 4) or len(extrinsics) == 0:
        raise ValueError(f"cameras given as extrinsics must be a 4x4 matrix or an (F, 4, 4) array, "
                         f"got shape {extrinsics.shape}")
    intrinsics = [intrinsic] * len(extrinsics)
    if intrinsic is not None and not is_open3d(intrinsic, "camera.PinholeCameraIntrinsic"):
        matrices = real_array(intrinsic, "intrinsic", "a 3x3 matrix or an (F, 3, 3) array")
        if matrices.ndim == 3:
            if len(matrices) != len(extrinsics):
                raise ValueError(f"{len(matrices)} intrinsics for {len(extrinsics)} frames")
            intrinsics = list(matrices)
    return [_framed(i, lambda e=e, k=k: _view_of_arrays(e, k, width, height))
            for i, (e, k) in enumerate(zip(extrinsics, intrinsics))]


def _framed(index: int, make) -> PinholeView:
    """``make()``, its ValueError naming the frame ``index``."""
    try:
        return make()
    except ValueError as error:
        raise ValueError(f"frame {index}: {error}") from None


def _encoded_whole(points: np.ndarray, max_range: float | None) -> bool:
    """Whether a map of these points is encoded whole for frames of ``max_range``: without a range,
    and where its bounding box is no longer than a crop's diameter (its octree no coarser)."""
    return max_range is None or float((points.max(axis=0) - points.min(axis=0)).max()) <= \
        2 * (1 + TILE_SLACK) * max_range


def tile_centres(points: np.ndarray, views: list[PinholeView], max_range: float | None) -> list[np.ndarray | None]:
    """The centre of the crop of the map each frame is answered from (None: the map encoded whole).

    Consecutive frames share a crop while the bounding box of their cameras has a half diagonal
    of at most ``TILE_SLACK * max_range``: its centre, the crop's, is that near each of them. A
    function of the map's extent and the cameras only, so that any process answers a frame alike.

    Args:
        points: (N, 3) the map's points.
        views: the frames' cameras, in their order.
        max_range: the frames' range (None: the map is encoded whole).

    Returns:
        A (3,) centre, or None, per frame.
    """
    if _encoded_whole(points, max_range):
        return [None] * len(views)
    reach, centres = TILE_SLACK * max_range, []
    locations = np.array([view.location for view in views])
    start = 0
    while start < len(locations):
        lo = hi = locations[start]
        stop = start + 1
        while stop < len(locations):
            wider_lo, wider_hi = np.minimum(lo, locations[stop]), np.maximum(hi, locations[stop])
            if np.linalg.norm(wider_hi - wider_lo) / 2 > reach:
                break
            lo, hi, stop = wider_lo, wider_hi, stop + 1
        centres += [(lo + hi) / 2] * (stop - start)
        start = stop
    return centres


def checked_frame_indices(indices, count: int) -> list[int]:
    """``indices`` of frames of a trajectory of ``count``, ascending and distinct (None: all).

    Raises:
        TypeError: indices that are not integers.
        ValueError: an index out of range.
    """
    if indices is None:
        return list(range(count))
    chosen = np.unique(np.asarray(list(indices) if not isinstance(indices, np.ndarray) else indices))
    if len(chosen) and chosen.dtype.kind not in "iu":
        raise TypeError(f"frame indices must be integers, got {chosen.dtype}")
    if len(chosen) and not 0 <= chosen[0] <= chosen[-1] < count:
        raise ValueError(f"frame indices must lie in [0, {count}), got {chosen[0]} .. {chosen[-1]}")
    return chosen.astype(int).tolist()


def _runs(centres: list, limit: int) -> Iterator[list[int]]:
    """The frames in runs of at most ``limit`` consecutive ones answered from the same crop."""
    run: list[int] = []
    for i, centre in enumerate(centres):
        if run and (len(run) == limit or not _same_centre(centres[run[0]], centre)):
            yield run
            run = []
        run.append(i)
    if run:
        yield run


def _same_centre(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return a is b or (a is not None and b is not None and np.array_equal(a, b))


class FrameMap:
    """A map encoded for pinhole frames, answering each frame from the encoding of what it sees.

    Without ``max_range``, or where the map's bounding box is no longer than
    ``2 (1 + TILE_SLACK) max_range``, the map is encoded once, whole, on the first frame. A larger
    map is encoded in crops: the points within ``(1 + TILE_SLACK) max_range`` of a centre, for
    the frames whose cameras lie within ``TILE_SLACK max_range`` of it (:func:`tile_centres`
    groups consecutive frames so), so that each crop's octree has the detail of a map of that
    size; the last two crops are kept. Each frame then costs a query of the points in its view.

    Args:
        pcd: the map: ``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud`` or an (N, 3)
            array; or a :class:`~o3dvis.VisibilityField` of it (answered as encoded, whole).
            Its normals are not used: the scene model, which answers cameras inside a map,
            takes none.
        max_range: each frame sees only the points within this distance of its camera; None:
            all the points in its image.
        model: None (the shipped default), a model name or checkpoint path, a
            :class:`~o3dvis.NeuralVisibility` or a ``VisibilityNetwork``.
        device: torch device (default: where the map lives, else the CPU).

    Raises:
        ValueError: an empty map, NaN or Inf, a max_range that is not positive.
        TypeError: a map of another type.
    """

    def __init__(self, pcd, *, max_range: float | None = None, model=None, device=None):
        from ..pretrained import resolve_model

        self.max_range = checked_range(max_range)
        self._lock = threading.Lock()  # guards the kept encodings
        self._tiles: OrderedDict[tuple | None, FrameTile | None] = OrderedDict()
        if isinstance(pcd, VisibilityField):
            world = pcd.points.detach().double() * pcd.frame.scale + pcd.frame.center
            world = (world if pcd.rank is None else world[pcd.rank]).cpu().numpy()
            self.points, self.model, self._whole, self._device = world, None, True, pcd.device
            self._tiles[None] = FrameTile(pcd, np.arange(len(world)), world)
            return
        self.points = cloud_arrays(pcd)[0].cpu().numpy()
        self.model = resolve_model(model, torch_device(device) if device is not None else cloud_device(pcd))
        self._whole, self._device = _encoded_whole(self.points, self.max_range), self.model.device

    def tile_centres(self, views: list[PinholeView]) -> list[np.ndarray | None]:
        """:func:`tile_centres` of this map."""
        return [None] * len(views) if self._whole else tile_centres(self.points, views, self.max_range)

    def frame(self, camera, *, intrinsic=None, width: int | None = None, height: int | None = None,
              threshold: float = 0.5, images: bool = False, centre=None) -> Frame:
        """What one pinhole frame sees of the map (see :func:`visible_in_frame`).

        Args:
            camera, intrinsic, width, height: one frame's camera, as :func:`pinhole_frames` takes it.
            threshold: a point is visible when its probability exceeds this.
            images: also make the frame's depth and index images.
            centre: the (3,) centre of the crop that answers it (one of :meth:`tile_centres`, so
                that the frames of a trajectory are answered as :meth:`frames` answers them);
                None: the camera's own position. Unused where the map is encoded whole.

        Returns:
            The :class:`Frame`.

        Raises:
            ValueError: bad cameras (see :func:`pinhole_frames`), more than one, or a centre
                farther than ``TILE_SLACK * max_range`` from the camera.
        """
        views = pinhole_frames(camera, intrinsic, width, height)
        if len(views) != 1:
            raise ValueError(f"give one camera, got {len(views)}; frames() answers a trajectory")
        return self._answer(views[0], centre, threshold, images)

    def frames(self, cameras, *, intrinsic=None, width: int | None = None, height: int | None = None,
               threshold: float = 0.5, images: bool = False, progress: bool = True, indices=None,
               workers: int | None = None) -> Iterator[Frame]:
        """What each frame of a trajectory sees of the map, in its order (see :func:`frames`).

        The cameras are checked before any frame is answered. Each crop is encoded on the threads
        the load allows, then the frames it answers are answered side by side on ``workers``
        threads, each frame on one.

        Args:
            cameras, intrinsic, width, height: the cameras, as :func:`pinhole_frames` takes them.
            threshold, images, progress: as in :func:`frames`.
            indices: answer only these frames of the trajectory, in ascending order, each from
                the crop the whole trajectory gives it (a run resumed answers as a whole one);
                None: all.
            workers: frames answered side by side (default: on the CPU, the cores the load leaves
                free, see :mod:`o3dvis.threads`; 1 on other devices).

        Raises:
            ValueError: as :func:`pinhole_frames`, an index out of range, workers below 1.
        """
        views = pinhole_frames(cameras, intrinsic, width, height)
        chosen = checked_frame_indices(indices, len(views))
        if workers is None:
            workers = plan_threads(len(self.points), _SIDE_BY_SIDE_POINTS) if self.device.type == "cpu" else 1
        elif isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers must be a positive int, got {workers!r}")
        centres = self.tile_centres(views)
        return self._frames([views[i] for i in chosen], [centres[i] for i in chosen], threshold, images, progress,
                            workers)

    def _frames(self, views: list[PinholeView], centres: list, threshold: float, images: bool, progress: bool,
                workers: int) -> Iterator[Frame]:
        from tqdm import tqdm

        def answer(i: int) -> Frame:
            return self._answer(views[i], centres[i], threshold, images)

        with tqdm(total=len(views), unit="frame", desc="frames", disable=not progress) as bar:
            for run in _runs(centres, _LOOKAHEAD * workers):
                tile = self._tile(views[run[0]], centres[run[0]])  # encoded here, on the threads the load allows
                if tile is not None:  # and the field that answers its first camera
                    tile.field_for(torch.from_numpy(views[run[0]].location))
                for frame in threaded_map(answer, run, workers) if workers > 1 else map(answer, run):
                    yield frame
                    bar.update()

    @property
    def device(self) -> torch.device:
        """Where the map's encodings live."""
        return self._device

    def _answer(self, view: PinholeView, centre, threshold: float, images: bool) -> Frame:
        """:meth:`frame` of a checked camera."""
        tile = self._tile(view, centre)
        return empty_frame(view, images) if tile is None else tile.frame(view, self.max_range, threshold, images)

    def _tile(self, view: PinholeView, centre) -> FrameTile | None:
        """The encoding that answers ``view`` (None: no point within its reach), encoded where it
        is not kept (thread-safe)."""
        with self._lock:
            return self._kept_tile(view, centre)

    def _kept_tile(self, view: PinholeView, centre) -> FrameTile | None:
        """:meth:`_tile`, under the lock."""
        if self._whole:
            if None not in self._tiles:
                self._tiles[None] = self._new_tile(self.points, np.arange(len(self.points)), view.location)
            return self._tiles[None]
        location = view.location
        centre = location if centre is None else real_array(centre, "centre", "a (3,) position")
        reach = TILE_SLACK * self.max_range
        if centre.shape != (3,) or not np.isfinite(centre).all() or np.linalg.norm(location - centre) > reach:
            raise ValueError(f"a crop's centre must be a finite position within {reach:g} (TILE_SLACK x max_range) "
                             f"of the camera at {location.tolist()}, got {np.asarray(centre).tolist()}")
        key = tuple(centre.tolist())
        tile = self._tiles.pop(key) if key in self._tiles else self._encode_crop(centre)
        self._tiles[key] = tile
        while len(self._tiles) > _KEPT_TILES:
            self._tiles.popitem(last=False)
        return tile

    def _encode_crop(self, centre: np.ndarray) -> FrameTile | None:
        """The encoding of the map's points within ``(1 + TILE_SLACK) max_range`` of ``centre``."""
        reach = (1 + TILE_SLACK) * self.max_range
        offset = self.points - centre
        index = np.flatnonzero(np.einsum("ni,ni->n", offset, offset) <= reach * reach)
        if len(index) == 0:
            return None
        return self._new_tile(self.points[index], index, centre)

    def _new_tile(self, world: np.ndarray, index: np.ndarray, location: np.ndarray) -> FrameTile:
        """The tile of the map's points ``index`` (at ``world``), encoded for the side of its bounding
        box ``location`` is on (see :class:`FrameTile`)."""
        model = self.model
        if model.scene_network is None:  # one network answers every camera
            return FrameTile(model.encode(world), index, world)
        lo, hi = world.min(axis=0), world.max(axis=0)
        centre = Views(torch.from_numpy((lo + hi) / 2)[None], None, (None,))

        def encode(inside: bool) -> VisibilityField:  # the scene model's alone for the cameras inside
            return model.encode(world, views=centre) if inside else model.encode(world)

        inside = bool(((location >= lo) & (location <= hi)).all())  # the side encoded first
        return FrameTile(encode(inside), index, world, encode, inside)


def visible_in_frame(pcd, camera, *, intrinsic=None, width: int | None = None, height: int | None = None,
                     max_range: float | None = None, threshold: float = 0.5, images: bool = False,
                     model=None, device=None) -> Frame:
    """What one pinhole frame sees of a map: the visible points, their pixels and depths.

    A point is seen when it projects into the image from in front of the camera, lies
    within ``max_range`` of it, and the network finds it visible among the points of the
    frame's view (the others neither occlude nor are visible). Each call encodes the map
    (or the crop around the camera that the frame's range needs, see :class:`FrameMap`);
    :func:`frames` answers a trajectory from shared encodings, and a
    :class:`~o3dvis.VisibilityField` given instead of the map answers as encoded.

    Args:
        pcd: the map (``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud``, an (N, 3)
            array) or its :class:`~o3dvis.VisibilityField`.
        camera: ``o3d.camera.PinholeCameraParameters`` (with its image size), a
            :class:`~o3dvis.apps.pinhole.PinholeView`, or a 4x4 world-to-camera extrinsic with ``intrinsic``.
        intrinsic: for an extrinsic, ``o3d.camera.PinholeCameraIntrinsic`` or a 3x3 matrix.
        width, height: the image size, with an intrinsic given as a matrix.
        max_range: only the points within this distance of the camera are seen; None: all.
        threshold: a point is visible when its probability exceeds this, in [0, 1].
        images: also make the frame's depth image and index image.
        model: None (the shipped default), a model name or checkpoint path, a
            :class:`~o3dvis.NeuralVisibility` or a ``VisibilityNetwork``.
        device: torch device (default: where the map lives, else the CPU).

    Returns:
        The :class:`Frame`: empty where no point is in view.

    Raises:
        ValueError: a pose that is not a rigid transform, NaN or Inf in the camera, a bad
            intrinsic or image size, an empty map, a max_range that is not positive, a
            camera on a point of the map.
        TypeError: inputs of the wrong type.
    """
    return FrameMap(pcd, max_range=max_range, model=model, device=device).frame(
        camera, intrinsic=intrinsic, width=width, height=height, threshold=threshold, images=images)


def frames(pcd, trajectory, *, intrinsic=None, width: int | None = None, height: int | None = None,
           max_range: float | None = None, threshold: float = 0.5, images: bool = False, progress: bool = True,
           model=None, device=None, workers: int | None = None) -> Iterator[Frame]:
    """What each pinhole frame of a trajectory sees of a map, frame by frame, with a progress bar.

    The map is encoded once, or in crops shared by nearby frames where it is much larger than
    what a frame sees (see :class:`FrameMap`); each frame then costs a query of the points in
    its view. The cameras are all checked before the first frame is answered.

    Args:
        pcd: the map, as :func:`visible_in_frame` takes it.
        trajectory: ``o3d.camera.PinholeCameraTrajectory`` (as
            ``o3d.io.read_pinhole_camera_trajectory`` reads it), a list of
            ``PinholeCameraParameters`` or of :class:`~o3dvis.apps.pinhole.PinholeView`, or (F, 4, 4)
            world-to-camera extrinsics with ``intrinsic`` (one, or (F, 3, 3)).
        intrinsic, width, height: for extrinsics, as in :func:`visible_in_frame`.
        max_range, threshold, images, model, device: as in :func:`visible_in_frame`.
        progress: show a progress bar (tqdm) of the frames answered.
        workers: frames answered side by side, each on one thread (default: on the CPU, the
            cores the load leaves free, see :mod:`o3dvis.threads`).

    Returns:
        An iterator of one :class:`Frame` per camera, in the trajectory's order.

    Raises:
        ValueError, TypeError: as :func:`visible_in_frame`; a bad camera's message names its frame.
    """
    return FrameMap(pcd, max_range=max_range, model=model, device=device).frames(
        trajectory, intrinsic=intrinsic, width=width, height=height, threshold=threshold, images=images,
        progress=progress, workers=workers)
