"""The whole visibility network and its checkpoint format (safetensors, no pickle)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import torch
from torch import Tensor, nn

from .calibration import CloudCalibration
from .conv import STEPS
from .fusion import ZBufferFusion
from . import native
from .cues import DEFAULT_SCALES, ViewProjection, num_cues, point_surfels
from .features import LeafFeatures
from .noise import NUM_NOISE_CUES, noise_cues
from .octree import Octree
from .predictor import VisibilityPredictor
from .state import WeightsState
from .unet import OctreeUNet

__all__ = ["NetworkConfig", "VisibilityNetwork"]

# bounds of a config (see NetworkConfig.check): (field, lowest, highest)
_INT_BOUNDS = (("depth", 2, 10), ("full_depth", 1, 5), ("blocks", 0, 8), ("feature_channels", 1, 1024),
               ("num_frequencies", 0, 16), ("fusion_hidden", 1, 128))
_MAX_WIDTH, _MAX_STAGES, _MAX_CUE_SCALE = 1024, 8, 256
# options that earlier versions stored in every checkpoint's config, with the only value any
# shipped model used: a config may still name them, with that value
_RETIRED_OPTIONS = {"interpolation": "nearest", "plane_cues": False, "extra": {}}
# the config options that add a part fitted after training, and that part's name in the state dict
_FITTED = {"calibrated": "calibration.", "fusion": "fusion."}


@dataclass
class NetworkConfig:
    """Hyper-parameters that define a network; stored in every checkpoint."""

    depth: int = 7
    full_depth: int = 2
    channels: tuple[int, ...] = (16, 32, 48, 64, 96)
    blocks: int = 1
    feature_channels: int = 32
    num_frequencies: int = 4
    hidden: tuple[int, ...] = (32, 32)
    cue_scales: tuple[int, ...] = DEFAULT_SCALES
    use_normals: bool = False
    noise_cues: bool = False
    footprints: bool = False
    calibrated: bool = False
    fusion: bool = False
    fusion_hidden: int = 16  # width of the fusion's hidden layer (with fusion)

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Checks every field against the bounds of a network that fits in memory.

        A checkpoint's config is read before its tensors, so these bounds keep a
        few bytes of crafted config from making the loader build a huge network.

        Raises:
            ValueError: a field of the wrong type or out of its bounds.
        """
        def integer(v, low: int, high: int) -> bool:
            return isinstance(v, int) and not isinstance(v, bool) and low <= v <= high

        def ints(name: str, values, low: int, high: int, most: int) -> None:
            if not (isinstance(values, tuple) and 1 <= len(values) <= most
                    and all(integer(v, low, high) for v in values)):
                raise ValueError(f"network config: {name} must be 1 to {most} integers in "
                                 f"[{low}, {high}], got {values!r}")

        for name, low, high in _INT_BOUNDS:
            if not integer(getattr(self, name), low, high):
                raise ValueError(f"network config: {name} must be an integer in [{low}, {high}], "
                                 f"got {getattr(self, name)!r}")
        ints("channels", self.channels, 1, _MAX_WIDTH, _MAX_STAGES)
        ints("hidden", self.hidden, 1, _MAX_WIDTH, _MAX_STAGES)
        ints("cue_scales", self.cue_scales, 1, _MAX_CUE_SCALE, _MAX_STAGES)
        if not (self.full_depth < self.depth and len(self.channels) < self.depth):
            raise ValueError(f"network config: depth {self.depth} must exceed full_depth {self.full_depth} "
                             f"and the number of stages {len(self.channels)}")
        for name in ("use_normals", "noise_cues", "footprints", "calibrated", "fusion"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"network config: {name} must be true or false, got {getattr(self, name)!r}")

    @classmethod
    def from_dict(cls, d: dict) -> "NetworkConfig":
        """The config of a mapping of field names (lists for the tuples), checked.

        Earlier versions stored ``interpolation``, ``plane_cues`` and ``extra`` in every
        config; a mapping may still name them at the one value every shipped model has.

        Raises:
            ValueError: not a mapping, an unknown field, a field out of bounds, or a
                retired option at another value.
        """
        if not isinstance(d, dict):
            raise ValueError(f"network config must be a mapping, got {type(d).__name__}")
        d = dict(d)
        for key, value in _RETIRED_OPTIONS.items():
            if key in d and (given := d.pop(key)) != value:
                raise ValueError(f"network config: {key} must be {value!r}, the only value this version "
                                 f"supports, got {given!r}")
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"network config: unknown fields {unknown}")
        for key in ("channels", "hidden", "cue_scales"):
            if isinstance(d.get(key), list):
                d[key] = tuple(d[key])
        return cls(**d)


class VisibilityNetwork(nn.Module):
    """Octree U-Net features (once per cloud) + per-view predictor.

    All inputs are in normalised coordinates (see
    :func:`~o3dvis.nn.octree.normalize_points`).
    """

    def __init__(self, config: NetworkConfig | None = None):
        super().__init__()
        self.config = config = config or NetworkConfig()
        in_channels = 6 + (3 if config.use_normals else 0) + (NUM_NOISE_CUES if config.noise_cues else 0)
        self.unet = OctreeUNet(in_channels, config.channels, config.blocks, config.feature_channels)
        self.predictor = VisibilityPredictor(
            config.feature_channels + 3, config.num_frequencies,
            num_cues(config.cue_scales, config.footprints) + (1 if config.use_normals else 0), config.hidden)
        # fitted after training (o3dvis calibrate); applied to the margins by o3dvis.VisibilityField
        self.calibration = CloudCalibration() if config.calibrated else None
        # fitted after training (o3dvis fuse); applied to the margins of camera views by o3dvis.VisibilityField
        self.fusion = ZBufferFusion(config.fusion_hidden) if config.fusion else None

    def _signal(self, points: Tensor, batch: Tensor, octree: Octree, normals: Tensor | None,
                noise: Tensor | None = None) -> Tensor:
        """(L, C) input of the U-Net per leaf: mean local and global coordinates (and normals),
        then the cloud's noise cues when the network reads them (``noise``: precomputed, or None)."""
        n = octree.num_nodes(octree.depth)
        if native.usable(points, normals) and octree.point_leaf.device.type == "cpu":  # the same in one pass of C
            signal = native.leaf_means(points.contiguous(), None if normals is None else normals.contiguous(),
                                       octree.point_leaf.contiguous(), octree.depth, n)
        else:
            res = 1 << octree.depth
            local = ((points + 1) * (res / 2)).frac() * 2 - 1
            per_point = torch.cat([local, points] + ([normals] if normals is not None else []), dim=1)
            sums = per_point.new_zeros(n, per_point.shape[1]).index_add_(0, octree.point_leaf, per_point)
            counts = per_point.new_zeros(n).index_add_(0, octree.point_leaf, torch.ones_like(points[:, 0]))
            signal = sums / counts[:, None]
        if not self.config.noise_cues:
            return signal
        if noise is None:
            noise = self.cloud_noise(points, batch, octree.batch_size)
        return torch.cat([signal, noise.index_select(0, octree.batch_of(octree.depth))], dim=1)

    @staticmethod
    def cloud_noise(points: Tensor, batch: Tensor | None = None, batch_size: int = 1,
                    ordered: bool = False) -> Tensor:
        """(B, 2) noise cues of each cloud (see :func:`~o3dvis.nn.noise.noise_cues`; ``ordered``:
        one cloud's points in :func:`~o3dvis.nn.octree.morton_order`)."""
        if batch is None or batch_size == 1:
            return noise_cues(points, ordered)[None]
        return torch.stack([noise_cues(points[batch == b]) for b in range(batch_size)])

    def octree(self, points: Tensor, batch: Tensor | None = None, batch_size: int | None = None,
               keys: Tensor | None = None) -> Octree:
        """The octree of normalised points at this network's depths (what :meth:`encode` builds);
        ``keys``: the points' cell keys at this network's depth where known (see :class:`Octree`)."""
        return Octree(points, batch, self.config.depth, self.config.full_depth, batch_size, keys)

    def encode(self, points: Tensor, batch: Tensor | None = None, normals: Tensor | None = None,
               batch_size: int | None = None, noise: Tensor | None = None) -> Tensor:
        """Per-point view-independent features, (N, E), stored channels first (strides (1, N)):
        :meth:`encode_leaves` carried to every point. Takes the arguments of :meth:`encode_leaves`."""
        return self.encode_leaves(points, batch, normals, batch_size, noise).rows()

    def encode_leaves(self, points: Tensor, batch: Tensor | None = None, normals: Tensor | None = None,
                      batch_size: int | None = None, noise: Tensor | None = None,
                      octree: Octree | None = None) -> LeafFeatures:
        """View-independent features, stored per octree leaf (what the per-view predictor reads).

        Args:
            points: (N, 3) normalised points of one or several clouds.
            batch: (N,) cloud index of each point (None: one cloud).
            normals: (N, 3) unit normals, required by a normals model.
            batch_size: number of clouds (default: ``batch.max() + 1``).
            noise: the clouds' :meth:`cloud_noise`, when the caller has it already.
            octree: the points' :meth:`octree`, when the caller has it already (another network of
                the same depths built it: its neighbour tables are reused too).

        Raises:
            ValueError: normals given to a points-only model or missing for a normals model, or an
                ``octree`` of other depths than this network's.
        """
        if self.config.use_normals != (normals is not None):
            raise ValueError("this model needs normals" if self.config.use_normals else
                             "this model takes no normals")
        if batch is None:
            batch = torch.zeros(points.shape[0], dtype=torch.long, device=points.device)
        if octree is None:
            octree = self.octree(points, batch, batch_size)
        elif (octree.depth, octree.full_depth) != (self.config.depth, self.config.full_depth):
            raise ValueError(f"an octree of depths {octree.depth}/{octree.full_depth} given to a network of "
                             f"depths {self.config.depth}/{self.config.full_depth}")
        leaf = self.unet(self._signal(points, batch, octree, normals, noise), octree)
        return self.predictor.project(leaf, points, octree.point_leaf)

    def view(self, points: Tensor, camera: Tensor | None = None, direction: Tensor | None = None,
             surfels: Tensor | None = None) -> ViewProjection:
        """The projection of one cloud for one camera position or viewing direction.

        ``surfels``: the cloud's :meth:`surfels` when the caller keeps them for several views
        (computed here when needed and not given)."""
        if not self.config.footprints:
            surfels = None
        elif surfels is None:
            surfels = self.surfels(points)
        return ViewProjection(points, camera, direction, self.config.cue_scales, surfels)

    def surfels(self, points: Tensor) -> Tensor | None:
        """(N, 4) the points' :func:`~o3dvis.nn.cues.point_surfels` for a network whose depth
        buffers splat each point over its footprint (``config.footprints``), else None."""
        return point_surfels(points) if self.config.footprints else None

    def view_inputs(self, view: ViewProjection, rows: slice | Tensor = slice(None),
                    normals: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(n, 3) view directions and (n, Z) cues of ``points[rows]`` for one view."""
        dirs, cues = view.dirs[rows], view.cues(rows)
        if self.config.use_normals:
            cues = torch.cat([cues, self._normal_cue(normals, rows, dirs)[:, None]], dim=1)
        return dirs, cues

    def _normal_cue(self, normals: Tensor | None, rows: slice | Tensor, dirs: Tensor) -> Tensor:
        """(n,) cosine between the normals of ``points[rows]`` and the reversed view directions."""
        if normals is None:
            raise ValueError("this model needs normals")
        return -(normals[rows] * dirs).sum(dim=1)

    def view_margin(self, views: Sequence[ViewProjection], rows: slice | Tensor, projected: Tensor | LeafFeatures,
                    normals: Tensor | None = None, dtype: torch.dtype | None = None) -> Tensor:
        """(V, n) margins (see :meth:`VisibilityPredictor.margin`) of ``points[rows]`` for ``views``.

        Args:
            views: the views' projections of the cloud.
            rows: the points, a slice or a (n,) long tensor.
            projected: the cloud's :meth:`encode_leaves` output, or (N, E) its :meth:`encode` output.
            normals: (N, 3) the cloud's unit normals, for a normals model.
            dtype: the dtype of the matrix products (None: ``projected``'s).

        Two implementations give the same margins, up to float rounding: the torch
        ops, the reference, which any device, dtype and autograd can run; and, for
        views built by the C kernels (:attr:`ViewProjection.native`) where
        :func:`~o3dvis.nn.native.has_view_margin` of ``dtype``, one pass of C per
        view that computes the inputs and runs the MLP on them while they are in cache.
        """
        predictor = self.predictor
        leaves = isinstance(projected, LeafFeatures)
        stored = projected.leaves if leaves else projected
        dtype = dtype or stored.dtype
        if self.native_margin(views, projected, dtype):
            if self.config.use_normals and normals is None:
                raise ValueError("this model needs normals")
            n_points = projected.num_points if leaves else projected.shape[0]
            n = len(range(*rows.indices(n_points))) if isinstance(rows, slice) else len(rows)
            frequencies = predictor.embedding.num_frequencies
            mlp, out = predictor.packed_mlp(dtype), stored.new_empty(len(views), n)
            for j, view in enumerate(views):
                view.margin(rows, projected, frequencies, normals if self.config.use_normals else None, mlp, out[j])
            return out
        inputs = [self.view_inputs(view, rows, normals) for view in views]
        dirs, cues = ((inputs[0][0][None], inputs[0][1][None]) if len(inputs) == 1 else
                      (torch.stack([d for d, _ in inputs]), torch.stack([c for _, c in inputs])))
        return predictor.margin(projected.rows(rows) if leaves else projected[rows], dirs, cues, dtype)

    @staticmethod
    def native_margin(views: Sequence[ViewProjection], projected: Tensor | LeafFeatures,
                      dtype: torch.dtype | None = None) -> bool:
        """Whether :meth:`view_margin` runs one pass of C per view for these arguments (streaming
        the points through the cache itself), not the torch ops."""
        leaves = isinstance(projected, LeafFeatures)
        stored = projected.leaves if leaves else projected
        return (all(v.native for v in views) and native.usable(stored) and native.has_view_margin(dtype or stored.dtype)
                and (leaves or projected.stride(0) == 1))  # stored channels first, as encode() stores it

    def predict(self, features: Tensor, points: Tensor, camera: Tensor | None = None,
                direction: Tensor | None = None, normals: Tensor | None = None,
                surfels: Tensor | None = None) -> Tensor:
        """(N, 2) logits of one cloud for one camera position or viewing direction (``surfels``:
        as in :meth:`view`)."""
        return self.predictor(features, *self.view_inputs(self.view(points, camera, direction, surfels),
                                                          normals=normals))

    def without(self, option: str) -> "VisibilityNetwork":
        """This network, or where its config sets ``option`` (``"calibrated"`` or ``"fusion"``, the
        parts fitted after training) a copy without that part, to fit it anew.

        Raises:
            ValueError: another option.
        """
        if option not in _FITTED:
            raise ValueError(f"option must be one of {sorted(_FITTED)}, got {option!r}")
        if not getattr(self.config, option):
            return self
        plain = VisibilityNetwork(NetworkConfig.from_dict({**asdict(self.config), option: False}))
        plain.load_state_dict({k: v for k, v in self.state_dict().items() if not k.startswith(_FITTED[option])})
        return plain

    def weights_state(self) -> list[tuple[nn.Module, WeightsState]]:
        """Each child of this network with the state of its weights (see :class:`~o3dvis.nn.state.WeightsState`),
        the U-Net's as its kept layers checked them in the last encode (not walked again: in a small
        cloud's call a walk over its tensors costs as much as some of its kernels); for
        :meth:`weights_unchanged`."""
        if self._parameters or self._buffers:  # tensors of its own: the whole network at once
            return [(self, WeightsState([self]))]
        return [(child, (STEPS.state(child) if child is self.unet else None) or WeightsState([child]))
                for child in self.children()]

    def weights_unchanged(self, state: list[tuple[nn.Module, WeightsState]]) -> bool:
        """Whether this network holds the children and weights of ``state`` (:meth:`weights_state`) still."""
        if len(state) == 1 and state[0][0] is self:
            return state[0][1].holds([self])
        children = list(self.children())
        return (len(children) == len(state) and all(child is kept for child, (kept, _) in zip(children, state))
                and all(weights.holds([child]) for child, weights in state))

    @property
    def device(self) -> torch.device:
        """Where the weights are (all on one device): its U-Net's last layer's, read without a walk
        of the modules."""
        return self.unet.head.weight.device

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def save(self, path: str | Path, metadata: dict | None = None) -> None:
        """Writes a safetensors file with the config (and ``metadata``) in its header."""
        from safetensors.torch import save_file

        meta = {"config": json.dumps(asdict(self.config))}
        meta.update({k: json.dumps(v) for k, v in (metadata or {}).items()})
        save_file({k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()},
                  str(path), metadata=meta)

    @classmethod
    def load(cls, path: str | Path, map_location: str | torch.device = "cpu") -> "VisibilityNetwork":
        """Builds a network from a safetensors checkpoint written by :meth:`save`, on the device
        ``map_location``.

        The config is checked against :meth:`NetworkConfig.check`'s bounds and
        every tensor's shape against the config before anything is allocated.

        Raises:
            ValueError: no config or a config out of bounds, tensors missing,
                unexpected or of the wrong shape, or non-finite weights.
        """
        from safetensors import safe_open

        with safe_open(str(path), framework="pt", device=str(map_location)) as f:
            meta = f.metadata() or {}
            if "config" not in meta:
                raise ValueError(f"{path}: not an o3dvis checkpoint (no config in its header)")
            try:
                config = NetworkConfig.from_dict(json.loads(meta["config"]))
            except (json.JSONDecodeError, ValueError, TypeError) as e:
                raise ValueError(f"{path}: bad network config ({e})") from None
            with torch.device("meta"):
                expected = {k: tuple(v.shape) for k, v in cls(config).state_dict().items()}
            stored = {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
            missing, unexpected = sorted(expected.keys() - stored.keys()), sorted(stored.keys() - expected.keys())
            if missing or unexpected:
                raise ValueError(f"{path}: checkpoint does not match its config "
                                 f"(missing {missing[:3]}, unexpected {unexpected[:3]})")
            wrong = [f"{k} {stored[k]} (config: {expected[k]})" for k in sorted(expected) if stored[k] != expected[k]]
            if wrong:
                raise ValueError(f"{path}: tensor shapes do not match the checkpoint's config: {', '.join(wrong[:3])}")
            state = {k: f.get_tensor(k) for k in f.keys()}
        bad = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
        if bad:
            raise ValueError(f"{path}: non-finite (NaN or Inf) weights in {', '.join(sorted(bad)[:3])}")
        net = cls(config)
        net.load_state_dict(state)
        return net.to(map_location)
