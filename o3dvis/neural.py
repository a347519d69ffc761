"""The visibility model: a trained network ready for Open3D clouds, encoding each cloud once.

:meth:`NeuralVisibility.encode` normalises a cloud, sorts it along a Morton curve,
runs the U-Net once (and once per extra rotation of an ensemble) and returns the
:class:`~o3dvis.field.VisibilityField` that answers queries for any views.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from .cameras import Views, as_views
from .clouds import cloud_arrays, unit_normals
from .geometry import fixed_rotations
from .field import DEFAULT_CHUNK, RotatedEncoding, VisibilityField
from .models import available_models, is_shared, load_model, torch_device
from .nn.calibration import calibration_terms
from .nn.network import VisibilityNetwork
from .nn.frame import CloudFrame, normalized
from .nn.octree import MORTON_DEPTH, coarser_keys, morton_sort
from .nn.conv import products_in
from .nn.predictor import resolve_precision
from .threads import plan_threads, torch_threads
from . import two_pass

__all__ = ["NeuralVisibility", "QUALITIES"]

QUALITIES = ("fast", "balanced", "best")
"""The accuracies :meth:`NeuralVisibility.encode` offers, from the cheapest (docs/results.md)."""

_NORMALS_MODEL = "normals"
_SCENE_MODEL = "scene"
_SMALL_MODEL = "small"
# the clouds a small network answers (points only): fewer points than this. The shipped one, on a
# depth-6 octree, is as accurate as the default below it on the validation meshes, less accurate
# above, and faster
_SMALL_MAX_POINTS = 5500
# quality="best": each pass the mean of the answers for this many turned copies of the cloud
_BEST_ROTATIONS = 4


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

        The networks are loaded and checked once per process and device
        (:func:`~o3dvis.models.load_model` with ``shared=True``): a repeated call
        costs no load. The models it returns share them until their files are
        written anew or one is changed (its weights, device or mode: the next call
        loads it anew; :meth:`to` moves copies). To train or change a network,
        take one of one's own: ``NeuralVisibility(load_model(name))``.

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
        network = load_model(name, device, weights_dir=weights_dir, shared=True)
        normals_network = None
        names = available_models(weights_dir) if name == "default" else []
        if use_normals and _NORMALS_MODEL in names and not network.config.use_normals:
            normals_network = load_model(_NORMALS_MODEL, device, weights_dir=weights_dir, shared=True)
        companions = {}
        for model, wanted, keyword in ((_SCENE_MODEL, use_scene, "scene_network"),
                                       (_SMALL_MODEL, use_small, "small_network")):
            if wanted and model in names:
                companions[keyword] = load_model(model, device, weights_dir=weights_dir, shared=True)
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
        """Moves the networks to ``device`` (in place; copies of shared ones, see :meth:`pretrained`),
        in eval mode, and returns self. A network there already and in eval mode is left as it is:
        walking its modules costs more than a small cloud's encode."""
        device = torch_device(device)
        for name in ("network", "normals_network", "scene_network", "small_network"):
            net = getattr(self, name)
            if net is not None and (net.training or next(net.parameters()).device != device):
                setattr(self, name, (copy.deepcopy(net) if is_shared(net) else net).to(device).eval())
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

    def encode(self, pcd, normals=None, *, views: Views | None = None, quality: str = "fast") -> VisibilityField:
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

        ``quality`` chooses how a cloud without normals (``normals=None``) is
        answered: ``"fast"`` (default) in one pass; ``"balanced"`` in two passes
        where they pay, as with ``"estimate"``; ``"best"`` as ``"balanced"``,
        each pass (and any pass of ``normals=False`` or ``"estimate"``) the mean
        of the network's answers for 4 turned copies of the cloud, as
        ``num_rotations=4`` gives them (a model with more keeps its own).
        docs/results.md measures each level's accuracy and cost.

        On the CPU, its ops split over the threads that :mod:`o3dvis.threads`
        plans (one for small clouds or a busy machine).

        Args:
            pcd: ``o3d.geometry.PointCloud``, ``o3d.t.geometry.PointCloud``, an
                (N, 3) numpy array / torch tensor of points, or a
                :class:`~o3dvis.clouds.Cloud`.
            normals: None uses the cloud's normals when it has them, a model
                taking normals is loaded and they face out (see above);
                ``"estimate"`` estimates them as above (the cloud's own are
                ignored; a normals model is needed); False ignores normals; True
                requires the cloud's normals and uses them as they are; an
                (N, 3) array gives them explicitly.
            views: the views (:func:`~o3dvis.cameras.as_views`) the field will
                answer, where the caller knows them: when every one is a camera
                inside the cloud's bounding box and a scene model is loaded,
                that model's encoding alone is made (the object model's is
                never needed); None: any view may come.
            quality: ``"fast"`` (default), ``"balanced"`` or ``"best"`` (see above).

        Returns:
            A :class:`VisibilityField` to query with cameras; its ``normals`` are
            the unit normals the network used (estimated ones included), in its
            row order.

        Raises:
            ValueError: an empty cloud, NaN/Inf coordinates, a cloud wider than float64 holds, wrong shapes,
                normals that the loaded models cannot use (``"estimate"``
                without a normals model), or an unknown ``quality``.
            TypeError: unsupported input types or dtypes.
        """
        if quality not in QUALITIES:
            raise ValueError(f"quality must be one of {', '.join(map(repr, QUALITIES))}, got {quality!r}")
        points, cloud_normals = cloud_arrays(pcd)
        views = None if views is None else as_views(views)
        estimate = isinstance(normals, str)
        if estimate and normals != "estimate":
            raise ValueError(f"normals must be None, True, False, 'estimate' or an (N, 3) array, got {normals!r}")
        if estimate and self.normals_network is None:
            raise ValueError("normals='estimate' needs a normals model (NeuralVisibility.pretrained() "
                             "loads the shipped one)")
        if normals is None and cloud_normals is None and self.normals_network is not None:
            estimate = quality != "fast"
        rotations = (fixed_rotations(_BEST_ROTATIONS) if quality == "best" and len(self.rotations) < _BEST_ROTATIONS
                     else self.rotations)
        network, unit = (self._points_network(points.shape[0]), None) if estimate else self._network_and_normals(
            cloud_normals, normals, points.shape[0])
        check = normals is None and unit is not None and network is self.normals_network
        if self.device.type != "cpu":
            return self._encode_points(network, unit, points, views, estimate, check, rotations)
        # every cloud is encoded on the threads the load allows: two measured faster than one
        # down to 16 points (the U-Net's products split, its many small ops do not slow down)
        with torch_threads(plan_threads(points.shape[0], 1)):
            return self._encode_points(network, unit, points, views, estimate, check, rotations)

    def _encode_points(self, network: VisibilityNetwork, unit: Tensor | None, points: Tensor,
                       views: Views | None, estimate: bool = False, check: bool = False,
                       rotations: Tensor | None = None) -> VisibilityField:
        """:meth:`encode` of checked points and unit normals (or None) with ``network``; ``estimate``:
        normals estimated in a first pass where that pays (see :meth:`encode`); ``check``: ``unit``
        are the cloud's own normals, estimated instead where they look unoriented
        (:func:`~o3dvis.two_pass.facing_away_share`) and the estimates do not side with them;
        ``rotations``: those each pass averages over (None: the model's)."""
        unit_points, keys, frame = CloudFrame.of(points.to(self.device))
        keys, order, rank = morton_sort(unit_points, keys=keys)
        unit_points = unit_points.index_select(0, order)
        unit = None if unit is None else unit.to(self.device).index_select(0, order).float()
        cloud = (unit_points, frame, rank)
        scene = None
        if self.scene_network is not None:
            if views is not None and views.positions is not None and bool(frame.contains(views.positions).all()):
                return self._field(self.scene_network, None, *cloud, rotations=rotations)
            scene = functools.partial(self._field, self.scene_network, None, *cloud, rotations=rotations)
        doubted, share = None, 0.0  # the cloud's own normals where they look unoriented, and why
        if check and frame.hull is None:
            share = two_pass.facing_away_share(
                lambda sample: self._encode_points(self._points_network(len(sample)), None, sample, None),
                points, order, unit)
            if share > two_pass.MAX_FACING_AWAY:
                doubted, network, unit, estimate = unit, self._points_network(len(points)), None, True
        # a flat cloud hides nothing from off its plane: one pass is exact there
        twice = estimate and frame.hull is None and len(unit_points) >= two_pass.ESTIMATE_MIN_POINTS
        shared = {"keys": keys}
        field = self._field(network, unit, *cloud, scene=scene, shared=shared, rotations=rotations)
        if twice:
            unit, doubted = two_pass.second_pass_normals(field, points, order, doubted)
            if unit is not None:
                first, field = field.network, self._field(self.normals_network, unit, *cloud, scene=scene,
                                                          shared=shared, rotations=rotations)
                field.encoders = (first, field.network)
        if doubted is not None:
            two_pass.warn_ignored(share)
        return field

    def _field(self, network: VisibilityNetwork, unit: Tensor | None, unit_points: Tensor, frame: CloudFrame,
               rank: Tensor, scene: Callable[[], VisibilityField] | None = None,
               shared: dict | None = None, rotations: Tensor | None = None) -> VisibilityField:
        """The field of ``network`` over the normalised, Morton-ordered points of :meth:`encode`.

        ``shared``: a dict that the passes over the same points fill and reuse: their noise cues
        and their octree per pair of depths, from the points' sorted Morton keys at
        :data:`~o3dvis.nn.octree.MORTON_DEPTH` under ``"keys"`` where given (None: nothing kept).
        ``rotations``: the turns whose answers the field averages, the first none (None: the model's)."""
        rotations = self.rotations if rotations is None else rotations
        calibrated, fused = network.calibration is not None, network.fusion is not None
        precision = resolve_precision(self.precision, self.device)
        shared = {} if shared is None else shared
        with torch.no_grad(), products_in(precision):
            cues = shared.get("noise")  # the field keeps them: the two passes read the cloud's noise too
            if cues is None:
                cues = shared["noise"] = network.cloud_noise(unit_points, ordered=True)
            noise = cues if network.config.noise_cues or calibrated or fused else None
            depths = (network.config.depth, network.config.full_depth)
            octree = shared.get(depths)
            if octree is None:
                keys = shared.get("keys")
                keys = None if keys is None else coarser_keys(keys, MORTON_DEPTH, network.config.depth)
                octree = shared[depths] = network.octree(unit_points, keys=keys)
            features = network.encode_leaves(unit_points, normals=unit, noise=noise, octree=octree)
            rotated = [self._rotated(network, unit_points, unit, r) for r in rotations[1:]]
        calibration = (network.calibration.affine(calibration_terms(noise[0], len(unit_points)))
                       if calibrated else None)
        return VisibilityField(network, features, unit_points, unit, frame, chunk_size=self.chunk_size, rank=rank,
                               rotated=rotated, calibration=calibration, matmul_dtype=precision, scene=scene,
                               noise=cues[0])

    @staticmethod
    def _rotated(network: VisibilityNetwork, unit_points: Tensor, normals: Tensor | None,
                 rotation: Tensor) -> RotatedEncoding:
        """The encoding of normalised points turned by ``rotation`` and normalised anew."""
        rotation = rotation.to(unit_points)
        points, center, scale = normalized(unit_points @ rotation.T)
        normals = None if normals is None else normals @ rotation.T
        return RotatedEncoding(network.encode(points, normals=normals), points, normals, rotation,
                               center, scale)
