"""The visibility model: a trained network ready for Open3D clouds, encoding each cloud once.

:meth:`NeuralVisibility.encode` normalises a cloud, sorts it along a Morton curve,
runs the U-Net once (and once per extra rotation of an ensemble) and returns the
:class:`~o3dvis.field.VisibilityField` that answers queries for any views.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .cameras import viewpoints_around
from .clouds import cloud_arrays, unit_normals
from .geometry import fixed_rotations
from .field import DEFAULT_CHUNK, RotatedEncoding, VisibilityField, inside_box
from .models import available_models, load_model, torch_device
from .nn.calibration import calibration_terms
from .nn import native
from .nn.network import VisibilityNetwork
from .nn.noise import noise_cues
from .nn.octree import MORTON_DEPTH, bounding_box, coarser_keys, cube_frame, morton_sort, normalize_points
from .nn.conv import products_in
from .nn.predictor import resolve_precision
from .orientation import NeighbourSearch, facing_away, oriented_planes, surface_variation
from .threads import plan_threads, torch_threads, workers_only

__all__ = ["NeuralVisibility"]

_NORMALS_MODEL = "normals"
_SCENE_MODEL = "scene"
_SMALL_MODEL = "small"
# the clouds a small network answers (points only): fewer points than this. The shipped one, on a
# depth-6 octree, measured on the validation meshes (clean / 1 % / 2 % noise) +0.0 / +0.1 / +0.7
# points against the default at 4 k points, -0.1 / -0.0 / +0.7 at 5 k and -0.3 / -0.2 / +0.5 at 6 k,
# hence a bound between those; encode + one query of 5 k points take two thirds of the default's
# time on one thread
_SMALL_MAX_POINTS = 5500
_FLAT_TOL = 1e-6
"""A cloud is flat along a direction when no point lies farther from its mean along it than this
many bounding-box diagonals: below what the network's float32 coordinates (about 2^-23 of the box)
resolve, so such a cloud is answered as the exactly flat one."""
# the two-pass encoding: cameras whose first-pass answers orient the normals, points per plane fit
_ORIENTING_VIEWS = 14
_PLANE_NEIGHBOURS = 8
# where normals="estimate" takes two passes: clouds of at least _ESTIMATE_MIN_POINTS points whose
# noise cue (the cell thickness in spacings of o3dvis.nn.noise) is under _ESTIMATE_MAX_NOISE and,
# below _CUE_ALONE_POINTS points, where the cue cannot see noise finer than the spacing, whose
# plane fits' neighbourhoods have a lower quartile of surface variation
# (o3dvis.orientation.surface_variation, over an even sample of _VARIATION_SAMPLE of them) under
# _ESTIMATE_MAX_VARIATION. On the validation meshes two passes everywhere gained 1.1-2.0 points on
# clean clouds and lost 0.2-5.2 points on those with 0.5-2 % noise; with this rule the clean
# columns (2-81 k points) came within 0.2 point of that gain, and the noisy ones lost at most
# 0.3 point (0.5 % noise at 8 k points)
_ESTIMATE_MIN_POINTS = 1_000
_ESTIMATE_MAX_NOISE = 0.2
_CUE_ALONE_POINTS = 65_536
_ESTIMATE_MAX_VARIATION = 0.01
_VARIATION_SAMPLE = 4096
# a cloud's own normals are held against what the points-only network sees of _CHECK_POINTS of its
# points, spread along the Morton curve, from _CHECK_VIEWS cameras around it: where more than
# _MAX_FACING_AWAY of the cameras' vote is against them, they are taken as unoriented. On the
# validation meshes at 2-32 k points that vote was 0.35-0.72 for normals from estimate_normals(),
# 0.48-0.53 for randomly flipped ones and 0.41-0.65 for ones facing a sensor, and at most 0.44 for
# oriented ones (0-0.05 on closed surfaces; bowls, cups, chairs and vases, whose thin walls the
# points-only network answers worst, reach 0.35-0.44). Those the check doubts are kept after all
# where, in the two passes that follow, at least _MIN_SAME_SIDE of them lie on the side of the
# estimated normals: 0.64-1 for oriented normals there, at most 0.53 for the others (2 k and 8 k points)
_CHECK_POINTS = 4096
_CHECK_VIEWS = 14
_MAX_FACING_AWAY = 0.35
_MIN_SAME_SIDE = 0.6


def _flat_hull(points: Tensor, diagonal: Tensor) -> tuple[Tensor, Tensor] | None:
    """Centre and orthonormal basis (rows) of the affine hull of a flat cloud; None for a 3-D one.

    A cloud extends along a direction when some point lies farther than ``_FLAT_TOL`` x
    ``diagonal`` (its bounding box's) from the mean along it. Most clouds are told 3-D by the
    3x3 scatter matrix alone: when the root-mean-square spread along its least direction,
    less the matrix's rounding, exceeds that, so does every direction's largest one. The others'
    principal directions come from the SVD of the 3x3 R of a QR of the centred points (O(N) and
    accurate), and the largest distances along them decide, so that a cloud a hair off its
    plane is answered as the exactly flat one.
    """
    centre = points.mean(dim=0)
    offsets = points - centre
    if _solid(offsets.T @ offsets, len(points), diagonal):
        return None
    bound = _FLAT_TOL * diagonal
    _, _, vt = torch.linalg.svd(torch.linalg.qr(offsets, mode="r").R)
    spans = (offsets @ vt.T).abs().max(dim=0).values > bound
    return None if bool(spans.all()) else (centre, vt[spans])


def _solid(scatter: Tensor, count: int, diagonal: Tensor) -> bool:
    """Whether the (3, 3) float64 scatter matrix of ``count`` points about their mean (or a point
    a few ulps from it) tells that they extend along every direction (see :func:`_flat_hull`)."""
    least, _, largest = torch.linalg.eigvalsh(scatter).tolist()
    bound = _FLAT_TOL * float(diagonal)
    return least - 1e3 * torch.finfo(scatter.dtype).eps * largest > bound * bound * count


def _unit_frame(points: Tensor) -> tuple[Tensor, Tensor | None, Tensor, Tensor, tuple[Tensor, Tensor],
                                         tuple[Tensor, Tensor] | None]:
    """``(normalised float32 points, their keys at MORTON_DEPTH or None, center, scale, bounds,
    flat hull)`` of (N, 3) float64 points: :func:`_normalize`, then :func:`_flat_hull` of the
    float64 normalised points and :func:`~o3dvis.nn.octree.cell_keys` of the float32 ones; on the
    CPU in two passes of C (the float64 normalised points are made only for a cloud that may be
    flat)."""
    in_c = points.device.type == "cpu" and points.dtype == torch.float64 and native.available()
    if in_c:
        points = points.contiguous()
        lo, hi, total = native.bounds(points)
    else:
        lo, hi = bounding_box(points)
    if not bool(torch.isfinite(hi - lo).all()):
        raise ValueError(f"the cloud spans more than float64 holds: its bounding box runs from {lo.tolist()} to "
                         f"{hi.tolist()}, whose sides overflow; scale it down")
    if not (in_c and (hi - lo).amax() > 0):  # torch ops, or all points coincide
        normalized, center, scale = _normalize(points, (lo, hi))
        hull = _flat_hull(normalized, ((hi - lo) / scale).norm())  # float64: flat to the last bits
        return normalized.float(), None, center, scale, (lo, hi), hull
    center, scale = cube_frame(lo, hi)
    normalized, keys, scatter = native.normalize(points, center, float(scale), (total / len(points) - center) / scale)
    diagonal = ((hi - lo) / scale).norm()
    hull = None if _solid(scatter, len(points), diagonal) else _flat_hull(_normalize(points, (lo, hi))[0], diagonal)
    return normalized, keys, center, scale, (lo, hi), hull


def first_pass_normals(field: VisibilityField, points: np.ndarray, stored: bool = False) -> np.ndarray | None:
    """The normals ``normals="estimate"`` gives the normals model: a plane through each point's
    nearest neighbours, those the first pass sees alike from a few cameras around the cloud
    weighing most, oriented by the vote of those cameras, or where they split, by the side of its
    neighbours the point lies on (:func:`o3dvis.orientation.oriented_planes` of what ``field``
    answers); None where the cloud looks too noisy for that to pay (see :data:`_ESTIMATE_MAX_NOISE`)
    or no plane fits any of its neighbourhoods.

    Args:
        field: a points-only model's encoding of the cloud.
        points: (N, 3) the cloud's points, in its order.
        stored: ``points``, and the normals returned, in the order the field stores them (along
            the Morton curve; see :meth:`VisibilityField.stored_probabilities`).

    Returns:
        (N, 3) unit normals, or None.
    """
    return estimated_normals(field, points, stored)[0]


def estimated_normals(field: VisibilityField, points: np.ndarray, stored: bool = False,
                      clean_only: bool = True) -> tuple[np.ndarray | None, bool]:
    """:func:`first_pass_normals`, and whether the cloud looks clean enough for them to pay.

    Args:
        field, points, stored: as in :func:`first_pass_normals`.
        clean_only: False estimates the normals of a cloud that looks noisy too (to compare
            other normals with them, not to give them to the normals model).

    Returns:
        (N, 3) unit normals, or None (no plane fits, or a noisy cloud with ``clean_only``), and
        whether the cloud looks clean.
    """
    noise = field.noise if field.noise is not None else noise_cues(field.points, ordered=True)
    clean = float(noise[0]) < _ESTIMATE_MAX_NOISE
    if clean_only and not clean:
        return None, False
    # in the field's order along the Morton curve: neighbours close in memory make the KNN search
    # and the plane fits cache-friendly (at 200 k points 380 -> 245 ms)
    rank = None if stored or field.rank is None else field.rank.cpu().numpy()
    if rank is not None:
        order = np.empty_like(rank)
        order[rank] = np.arange(len(rank))
        points = points[order]
    search = NeighbourSearch(points)
    near = search.query(min(_PLANE_NEIGHBOURS, len(points)))  # the weak votes' wider planes: asked later
    if clean and len(points) < _CUE_ALONE_POINTS:
        sample = near[::max(1, len(near) // _VARIATION_SAMPLE), :_PLANE_NEIGHBOURS]
        clean = bool(np.quantile(surface_variation(points, sample), 0.25) < _ESTIMATE_MAX_VARIATION)
        if clean_only and not clean:
            return None, False
    cameras = viewpoints_around(points, _ORIENTING_VIEWS)
    visibility = field.stored_probabilities(cameras).cpu().numpy()
    try:
        normals = oriented_planes(points, near, cameras, visibility, fit=_PLANE_NEIGHBOURS, search=search)
    except ValueError:  # no plane fits anywhere: every neighbourhood is one point repeated, or a line
        return None, clean
    return (normals if rank is None else normals[rank]), clean


def _normalize(points: Tensor, bounds: tuple[Tensor, Tensor] | None = None
               ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`normalize_points`, with scale 1 when all points coincide (any scale maps them to 0)."""
    lo, hi = bounding_box(points) if bounds is None else bounds
    if (hi - lo).amax() > 0:
        return normalize_points(points, bounds=(lo, hi))
    return points - lo, lo, torch.ones((), dtype=points.dtype, device=points.device)


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
        small_network: optional network (without normals) that encodes the
            clouds of fewer than 5 500 points in ``network``'s stead (the
            shipped one, on a coarser octree, is faster there and as accurate).
        device: torch device to run on (default: the network's device).
        chunk_size: rows (views x points) per MLP call; bounds the memory of queries. A view
            that the C kernels answer goes in one call (they stream its points through the
            cache), unless its chunks are answered side by side on several threads.
        num_rotations: answer with the mean of the network's answers for this many
            copies of the cloud (and its cameras), turned by fixed rotations, the
            first unturned: the pixels of the depth buffers fall differently in each
            frame, so the mean is more accurate, and as many times slower
            (docs/results.md); 1, the default, is the single pass.
        precision: dtype of the matrix products of the encoding's convolutions
            and of the per-view step of queries without gradients: ``"auto"``
            (default) is ``"bfloat16"`` on CPUs with native bfloat16 dot products
            (AVX512-BF16, AMX) and ``"float32"`` elsewhere, where bfloat16
            products are faster and change about one answer in a thousand
            (docs/results.md); probabilities differentiated w.r.t. cameras always
            use float32 per-view products.

    Example:
        >>> vis = NeuralVisibility.pretrained()                     # doctest: +SKIP
        >>> field = vis.encode(pcd)                                 # doctest: +SKIP
        >>> mask = field.query([[0, 0, 5], [5, 0, 0]])              # doctest: +SKIP
    """

    def __init__(self, network: VisibilityNetwork, normals_network: VisibilityNetwork | None = None, *,
                 device: str | torch.device | None = None, chunk_size: int = DEFAULT_CHUNK,
                 num_rotations: int = 1, precision: str = "auto",
                 scene_network: VisibilityNetwork | None = None, small_network: VisibilityNetwork | None = None):
        for name, net in (("network", network), ("normals_network", normals_network),
                          ("scene_network", scene_network), ("small_network", small_network)):
            if net is not None and not isinstance(net, VisibilityNetwork):
                raise TypeError(f"{name} must be a VisibilityNetwork, got {type(net).__name__}")
        if normals_network is not None and not normals_network.config.use_normals:
            raise ValueError("normals_network must be a model that takes normals (config.use_normals)")
        for name, net in (("scene_network", scene_network), ("small_network", small_network)):
            if net is not None and net.config.use_normals:
                raise ValueError(f"{name} must be a model that takes no normals")
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
            raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
        if isinstance(num_rotations, bool) or not isinstance(num_rotations, int) or num_rotations < 1:
            raise ValueError(f"num_rotations must be a positive int, got {num_rotations!r}")
        self.network = network
        self.normals_network = normals_network
        self.scene_network = scene_network
        self.small_network = small_network
        self.chunk_size = chunk_size
        self.rotations = fixed_rotations(num_rotations)
        resolve_precision(precision, torch.device("cpu"))  # a bad value raises here, not at the first encode
        self.precision = precision
        self.to(next(network.parameters()).device if device is None else device)

    @classmethod
    def pretrained(cls, name: str = "default", device: str | torch.device | None = None, *,
                   use_normals: bool = True, weights_dir: str | Path | None = None,
                   num_rotations: int = 1, precision: str = "auto", use_scene: bool = True,
                   use_small: bool = True) -> "NeuralVisibility":
        """A shipped model from ``o3dvis/weights`` (sha256-checked, no pickle).

        With ``name="default"`` the shipped ``"normals"`` model, when there is
        one, is loaded too and used for clouds that have normals, the shipped
        ``"scene"`` model, when there is one, for cameras inside a cloud's
        bounding box, and the shipped ``"small"`` model, when there is one, for
        clouds of fewer than 5 500 points without normals.

        Args:
            name: model name in the model card, or a ``.safetensors`` path.
            device: torch device (default: CPU).
            use_normals: False never loads the companion normals model.
            use_scene: False never loads the companion scene model.
            use_small: False never loads the companion small model.
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
        companions = {}
        for model, wanted, keyword in ((_SCENE_MODEL, use_scene, "scene_network"),
                                       (_SMALL_MODEL, use_small, "small_network")):
            if wanted and name == "default" and model in available_models(weights_dir):
                companions[keyword] = load_model(model, device, weights_dir=weights_dir)
        return cls(network, normals_network, device=device, num_rotations=num_rotations, precision=precision,
                   **companions)

    def networks(self) -> list[VisibilityNetwork]:
        """Every network this holds: the main one, then the normals, scene and small ones it has."""
        return [net for net in (self.network, self.normals_network, self.scene_network, self.small_network)
                if net is not None]

    @property
    def device(self) -> torch.device:
        return self.network.device

    def to(self, device: str | torch.device) -> "NeuralVisibility":
        """Moves the networks to ``device`` (in place), in eval mode, and returns self. A network
        there already and in eval mode is left as it is: walking its modules cost more than a
        small cloud's encode."""
        device = torch_device(device)
        for net in self.networks():
            if net.training or next(net.parameters()).device != device:
                net.to(device).eval()
        return self

    def __repr__(self) -> str:
        normals = " + normals model" if self.normals_network is not None else ""
        normals += " + scene model" if self.scene_network is not None else ""
        normals += " + small model" if self.small_network is not None else ""
        turns = f", {len(self.rotations)} rotations" if len(self.rotations) > 1 else ""
        dtype = str(resolve_precision(self.precision, self.device)).removeprefix("torch.")
        return (f"NeuralVisibility({self.network.num_parameters()} parameters{normals}, {self.device}{turns}, "
                f"{dtype} products)")

    def _points_network(self, num_points: int) -> VisibilityNetwork:
        """The network for a cloud of ``num_points`` points without normals."""
        small = self.small_network is not None and num_points < _SMALL_MAX_POINTS
        return self.small_network if small else self.network

    def _network_and_normals(self, cloud_normals: Tensor | None, normals, num_points: int
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
            return self._points_network(num_points), None
        if takes_normals is None:
            raise ValueError("normals were given but no loaded model takes normals")
        return takes_normals, unit_normals(normals, num_points)

    def encode(self, pcd, normals=None) -> VisibilityField:
        """Runs the U-Net over a cloud: once, or twice to estimate oriented normals first.

        With ``normals="estimate"``, a cloud is encoded in two passes where
        that measured more accurate: the network without normals answers for
        14 cameras around the cloud; each point's normal is the plane through
        its 8 nearest points, those the cameras see alike weighing most,
        turned to face the cameras that see the point, or where they split
        (the two faces of a thin wall), to the side of its 16 nearest points
        it lies on (:func:`o3dvis.orientation.voted_normals`); the normals
        model then encodes the cloud with those normals. It costs a second
        encoding, the 14 views and the plane fits. Clouds of fewer than 1 000
        points, flat ones, and noisy ones (see :func:`first_pass_normals`)
        keep the first pass, without normals.

        A cloud's own normals (``normals=None``) are used only where they face
        out: the cameras around the cloud vote on those of a few thousand of its
        points with what the network without normals sees of them, and where
        more than about a third of the vote is against them (normals from
        ``estimate_normals()``, which point either way, or ones that face a
        sensor) normals are estimated as above, and the cloud's are kept only
        where most lie on the estimates' side; else they are ignored, with a
        warning. ``normals=True`` or an array skips that check.

        On the CPU, its ops split over the threads that :mod:`o3dvis.threads`
        plans (one for small clouds or a busy machine).

        Args:
            pcd: ``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud``, or
                an (N, 3) numpy array / torch tensor of points.
            normals: None uses the cloud's normals when it has them, a model
                taking normals is loaded and they face out (see above);
                ``"estimate"`` estimates them as above (the cloud's own are
                ignored; a normals model is needed); False ignores normals; True
                requires the cloud's normals and uses them as they are; an
                (N, 3) array gives them explicitly.

        Returns:
            A :class:`VisibilityField` to query with cameras; its ``normals`` are
            the unit normals the network used (estimated ones included), in its
            row order.

        Raises:
            ValueError: an empty cloud, NaN/Inf coordinates, a cloud wider than float64 holds, wrong shapes, or
                normals that the loaded models cannot use (``"estimate"``
                without a normals model).
            TypeError: unsupported input types or dtypes.
        """
        return self._encode(pcd, normals)

    def _encode(self, pcd, normals=None, camera: Tensor | None = None,
                arrays: tuple[Tensor, Tensor | None] | None = None) -> VisibilityField:
        """:meth:`encode`; given the (3,) ``camera`` of the only view to come, a camera inside the
        cloud's bounding box with a scene network gets the scene model's field alone. ``arrays``:
        the cloud's :func:`~o3dvis.clouds.cloud_arrays`, where the caller has them already."""
        points, cloud_normals = cloud_arrays(pcd) if arrays is None else arrays
        estimate = isinstance(normals, str)
        if estimate and normals != "estimate":
            raise ValueError(f"normals must be None, True, False, 'estimate' or an (N, 3) array, got {normals!r}")
        if estimate and self.normals_network is None:
            raise ValueError("normals='estimate' needs a normals model (NeuralVisibility.pretrained() "
                             "loads the shipped one)")
        network, unit = (self._points_network(points.shape[0]), None) if estimate else self._network_and_normals(
            cloud_normals, normals, points.shape[0])
        check = normals is None and unit is not None and network is self.normals_network
        if self.device.type != "cpu":
            return self._encode_points(network, unit, points, camera, estimate, check)
        # every cloud is encoded on the threads the load allows: two measured faster than one
        # down to 16 points (the U-Net's products split, its many small ops do not slow down)
        with torch_threads(plan_threads(points.shape[0], 1)):
            return self._encode_points(network, unit, points, camera, estimate, check)

    def _encode_points(self, network: VisibilityNetwork, unit: Tensor | None, points: Tensor,
                       camera: Tensor | None, estimate: bool = False, check: bool = False) -> VisibilityField:
        """:meth:`_encode` of checked points and unit normals (or None) with ``network``; ``estimate``:
        normals estimated in a first pass where that pays (see :meth:`encode`); ``check``: ``unit``
        are the cloud's own normals, estimated instead where they look unoriented
        (:meth:`_facing_away`) and the estimates do not side with them."""
        normalized, keys, center, scale, (lo, hi), hull = _unit_frame(points.to(self.device))
        keys, order, rank = morton_sort(normalized, keys=keys)
        normalized = normalized.index_select(0, order)
        unit = None if unit is None else unit.to(self.device).index_select(0, order).float()
        frame = (normalized, center, scale, (lo, hi), hull, rank)
        scene = None
        if self.scene_network is not None:
            if camera is not None and inside_box(camera.to(lo)[None], (lo, hi))[0]:
                return self._field(self.scene_network, None, *frame)
            scene = functools.partial(self._field, self.scene_network, None, *frame)
        doubted, share = None, 0.0  # the cloud's own normals where they look unoriented, and why
        if check and hull is None:
            share = self._facing_away(points, order, unit)
            if share > _MAX_FACING_AWAY:
                doubted, network, unit, estimate = unit, self._points_network(len(points)), None, True
        # a flat cloud hides nothing from off its plane: one pass is exact there
        two_pass = estimate and hull is None and len(normalized) >= _ESTIMATE_MIN_POINTS
        shared = {"keys": keys}
        field = self._field(network, unit, *frame, scene=scene, shared=shared)
        if two_pass:
            with workers_only():
                stored = points.detach().cpu().double().index_select(0, order.cpu()).numpy()
                normals, clean = estimated_normals(field, stored, stored=True, clean_only=doubted is None)
            if normals is not None:
                unit = torch.from_numpy(normals).to(self.device).float()
                if doubted is not None and float(((doubted * unit).sum(dim=1) > 0).float().mean()) >= _MIN_SAME_SIDE:
                    unit, clean, doubted = doubted, True, None  # on the estimates' side: oriented after all
                if clean:
                    field = self._field(self.normals_network, unit, *frame, scene=scene, shared=shared)
        if doubted is not None:
            warnings.warn(f"o3dvis: the cloud's normals look unoriented ({100 * share:.0f} % of the vote of cameras "
                          "around it is against them) and are ignored, as with normals='estimate'; orient them "
                          "first (o3dvis.orient_normals_neural) or pass normals=True to use them as they are",
                          stacklevel=4)
        return field

    def _facing_away(self, points: Tensor, order: Tensor, normals: Tensor) -> float:
        """How much of the vote of cameras around a cloud (:func:`~o3dvis.orientation.facing_away`)
        on the normals (in Morton ``order``) of :data:`_CHECK_POINTS` of its points, evenly spread
        along that order, is against them, with the cameras' answers from the points-only network's
        encoding of those points alone."""
        rows = torch.arange(0, len(order), max(1, len(order) // _CHECK_POINTS), device=order.device)
        sample = points.index_select(0, order.index_select(0, rows).to(points.device))
        field = self._encode_points(self._points_network(len(rows)), None, sample, None)
        sample = sample.detach().cpu().double().numpy()
        cameras = viewpoints_around(sample, _CHECK_VIEWS)
        sampled = normals.index_select(0, rows.to(normals.device)).detach().cpu().double().numpy()
        return facing_away(sample, sampled, cameras, field.probabilities(cameras).cpu().numpy())

    def _field(self, network: VisibilityNetwork, unit: Tensor | None, normalized: Tensor, center: Tensor,
               scale: Tensor, bounds: tuple[Tensor, Tensor], hull: tuple[Tensor, Tensor] | None, rank: Tensor,
               scene: Callable[[], VisibilityField] | None = None, shared: dict | None = None) -> VisibilityField:
        """The field of ``network`` over the normalised, Morton-ordered points of :meth:`encode`.

        ``shared``: a dict that the passes over the same points fill and reuse: their noise cues
        and their octree per pair of depths, from the points' sorted Morton keys at
        :data:`~o3dvis.nn.octree.MORTON_DEPTH` under ``"keys"`` where given (None: nothing kept)."""
        calibrated, fused = network.calibration is not None, network.fusion is not None
        precision = resolve_precision(self.precision, self.device)
        shared = {} if shared is None else shared
        with torch.no_grad(), products_in(precision):
            noise = None
            if network.config.noise_cues or calibrated or fused:
                noise = shared.get("noise")
                if noise is None:
                    noise = shared["noise"] = network.cloud_noise(normalized, ordered=True)
            depths = (network.config.depth, network.config.full_depth)
            octree = shared.get(depths)
            if octree is None:
                keys = shared.get("keys")
                keys = None if keys is None else coarser_keys(keys, MORTON_DEPTH, network.config.depth)
                octree = shared[depths] = network.octree(normalized, keys=keys)
            features = network.encode_leaves(normalized, normals=unit, noise=noise, octree=octree)
            rotated = [self._rotated(network, normalized, unit, r) for r in self.rotations[1:]]
        calibration = (network.calibration.affine(calibration_terms(noise[0], len(normalized)))
                       if calibrated else None)
        return VisibilityField(network, features, normalized, unit, center, scale, bounds, self.chunk_size,
                               hull, rank, rotated, calibration, precision, scene, None if noise is None else noise[0])

    @staticmethod
    def _rotated(network: VisibilityNetwork, normalized: Tensor, normals: Tensor | None,
                 rotation: Tensor) -> RotatedEncoding:
        """The encoding of normalised points turned by ``rotation`` and normalised anew."""
        rotation = rotation.to(normalized)
        points, center, scale = _normalize(normalized @ rotation.T)
        normals = None if normals is None else normals @ rotation.T
        return RotatedEncoding(network.encode(points, normals=normals), points, normals, rotation,
                               center, scale)
