"""Per-view predictor: sinusoidal view embedding x point feature (+ cues) -> 2 logits."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from . import native
from .features import LeafFeatures
from .state import Derived

__all__ = ["ViewEmbedding", "VisibilityPredictor", "PRECISIONS", "resolve_precision"]

PRECISIONS = ("auto", "float32", "bfloat16")

_PACKED = Derived()
"""Each MLP as the per-view kernels read it (see :meth:`VisibilityPredictor.packed_mlp`)."""


def resolve_precision(precision: str, device: torch.device) -> torch.dtype:
    """The dtype of the per-view matrix products for ``precision`` on ``device``.

    ``"auto"`` is bfloat16 on a CPU with native bfloat16 dot products
    (AVX512-BF16 or AMX), where they run faster than float32 ones, and
    float32 elsewhere (an emulated bfloat16 product is slower).

    Raises:
        ValueError: ``precision`` is not one of :data:`PRECISIONS`.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if precision != "auto":
        return getattr(torch, precision)
    if device.type != "cpu":
        return torch.float32
    native = [getattr(torch.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    return torch.bfloat16 if any(check is not None and check() for check in native) else torch.float32


def _relu_(x: Tensor) -> Tensor:
    """``x.relu_()``; in bfloat16 as ``clamp_(min=0)`` of its bits read as int16 (a set sign bit is
    a negative int16; -0 becomes +0), which is faster than torch's bfloat16 ``relu_`` on the CPU."""
    if x.dtype == torch.bfloat16:
        x.view(torch.int16).clamp_(min=0)
        return x
    return x.relu_()


class ViewEmbedding(nn.Module):
    """NeRF-style embedding ``[d, sin(2^k pi d), cos(2^k pi d)]`` for k < ``num_frequencies``.

    Channels first: (..., 3, N) directions -> (..., dim, N), so that every
    step runs over contiguous rows. The sines and cosines come from the
    double-angle recurrence, so one ``sin``/``cos`` pair is evaluated per
    component instead of one per frequency.
    """

    def __init__(self, num_frequencies: int = 10):
        super().__init__()
        self.num_frequencies = num_frequencies

    @property
    def dim(self) -> int:
        return 3 + 6 * self.num_frequencies

    def forward(self, dirs: Tensor) -> Tensor:
        if torch.is_grad_enabled() and dirs.requires_grad:
            out = [dirs]
            s, c = torch.sin(torch.pi * dirs), torch.cos(torch.pi * dirs)
            for _ in range(self.num_frequencies):
                out += [s, c]
                s, c = 2 * s * c, 1 - 2 * s * s
            return torch.cat(out, dim=-2)
        # without autograd each term is written in place into its rows of the result
        out = dirs.new_empty(*dirs.shape[:-2], self.dim, dirs.shape[-1])
        rows = out.unflatten(-2, (-1, 3))  # (..., 1 + 2F, 3, N)
        rows[..., 0, :, :] = dirs
        if self.num_frequencies:
            torch.sin(torch.pi * dirs, out=rows[..., 1, :, :])
            torch.cos(torch.pi * dirs, out=rows[..., 2, :, :])
        for k in range(1, self.num_frequencies):
            s, c = rows[..., 2 * k - 1, :, :], rows[..., 2 * k, :, :]
            torch.mul(s, c, out=rows[..., 2 * k + 1, :, :]).mul_(2)
            torch.mul(s, s, out=rows[..., 2 * k + 2, :, :]).mul_(-2).add_(1)
        return out


class VisibilityPredictor(nn.Module):
    """Maps a point feature and its view (direction + cues) to visible/hidden logits.

    ``project`` runs once per cloud (view-independent); ``forward`` runs per view.
    """

    def __init__(self, feature_channels: int, num_frequencies: int = 10, num_cues: int = 8,
                 hidden: Sequence[int] = (64, 32)):
        super().__init__()
        self.embedding = ViewEmbedding(num_frequencies)
        self.project_feature = nn.Linear(feature_channels, self.embedding.dim)
        layers: list[nn.Module] = []
        width = self.embedding.dim + num_cues
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU(inplace=True)]
            width = h
        layers.append(nn.Linear(width, 2))
        self.mlp = nn.Sequential(*layers)

    def project(self, features: Tensor, points: Tensor, leaf: Tensor) -> LeafFeatures:
        """Projects ``[feature, point]`` to the embedding's width, stored per leaf.

        The projection is linear, so its feature part is computed once per octree
        leaf; a point's projected features are its leaf's plus the point's term
        (see :class:`~o3dvis.nn.features.LeafFeatures`).

        Args:
            features: (L, C) features of the octree leaves (the layer takes C + 3 inputs).
            points: (N, 3) normalised points, the layer's last 3 inputs.
            leaf: (N,) each point's leaf.
        """
        layer, c = self.project_feature, features.shape[1]
        per_leaf = torch.addmm(layer.bias[:, None], layer.weight[:, :c], features.transpose(0, 1))
        return LeafFeatures(per_leaf, leaf, layer.weight[:, c:].contiguous(), points)

    def forward(self, projected: Tensor, dirs: Tensor, cues: Tensor) -> Tensor:
        """(..., N, E) projected features, (..., N, 3) directions, (..., N, Z) cues -> (..., N, 2)."""
        return self.mlp[-1](self._hidden(projected, dirs, cues))

    def margin(self, projected: Tensor, dirs: Tensor, cues: Tensor, dtype: torch.dtype | None = None) -> Tensor:
        """(..., N) logit of "visible" minus that of "hidden", as from :meth:`forward`,
        with a last layer of one output instead of two (what a probability needs).

        ``dtype`` (e.g. ``torch.bfloat16``): run the matrix products in it, accumulated in
        float32, when no gradient is needed (see :meth:`_reduced_margin`); None: in the inputs' dtype.
        """
        weight, bias = self._margin_layer()
        grad = torch.is_grad_enabled() and any(t.requires_grad for t in (projected, dirs, cues, weight))
        if dtype is not None and dtype != projected.dtype and not grad:
            return self._reduced_margin(projected, dirs, cues, dtype)
        return F.linear(self._hidden(projected, dirs, cues), weight, bias)[..., 0]

    def _reduced_margin(self, projected: Tensor, dirs: Tensor, cues: Tensor, dtype: torch.dtype) -> Tensor:
        """:meth:`margin` with every matrix product in ``dtype``, no autograd.

        The embedding times the features is written straight into a ``dtype``
        buffer (the cast costs no pass of its own) and the cues are cast into
        the rows after it; :meth:`margin_from_inputs` does the rest. How much
        the answers differ from float32 ones is measured in ``docs/results.md``.
        """
        e = self.embedding.dim
        embedded = self.embedding(dirs.transpose(-1, -2))  # (..., E, n)
        shape = torch.broadcast_shapes(embedded.shape, projected.transpose(-1, -2).shape, cues.shape[:-2] + (1, 1))
        lead, n = shape[:-2], shape[-1]
        x = embedded.new_empty(*lead, e + cues.shape[-1], n, dtype=dtype)
        torch.mul(embedded, projected.transpose(-1, -2), out=x[..., :e, :])
        x[..., e:, :] = cues.transpose(-1, -2)
        return self.margin_from_inputs(x.reshape(-1, *x.shape[-2:])).view(*lead, n)

    def margin_from_inputs(self, x: Tensor) -> Tensor:
        """(B, n) margins (see :meth:`margin`) from the first layer's inputs, no autograd.

        Args:
            x: (B, E + Z, n) inputs, channels first: the embedding times the
                projected features, then the cues. Each matrix product runs in
                ``x``'s dtype as one batched ``baddbmm`` that accumulates in
                float32 and rounds its output to that dtype.
        """
        weight, bias = self._margin_layer()

        def product(h: Tensor, w: Tensor, b: Tensor) -> Tensor:
            return torch.baddbmm(b.to(x.dtype), h, w.to(x.dtype).T.expand(h.shape[0], -1, -1))

        h = x.transpose(1, 2)  # (B, n, E + Z), a view
        for layer in self.mlp[:-1:2]:  # the hidden layers, each followed by a ReLU
            h = _relu_(product(h, layer.weight, layer.bias))
        return product(h, weight, bias).float()[..., 0]

    def packed_mlp(self, dtype: torch.dtype) -> native.PackedMLP:
        """The MLP of :meth:`margin` as :func:`o3dvis.nn.native.view_margin` reads it for products
        in ``dtype``, packed again only when a weight has changed or another dtype was asked last."""
        def pack() -> native.PackedMLP:
            hidden = [(layer.weight, layer.bias) for layer in list(self.mlp)[:-1:2]]
            return native.pack_mlp(hidden + [self._margin_layer()], dtype)
        return _PACKED.get(self.mlp, (dtype,), pack)

    def _margin_layer(self) -> tuple[Tensor, Tensor]:
        """The last layer's (1, H) weight and (1,) bias of "visible" minus "hidden"."""
        last = self.mlp[-1]
        return last.weight[1:] - last.weight[:1], last.bias[1:] - last.bias[:1]

    def _hidden(self, projected: Tensor, dirs: Tensor, cues: Tensor) -> Tensor:
        """The activations before the last layer.

        The first layer sees ``[projected * embedding, cues]``; its weight is
        applied in two parts so that the concatenation is never built. The
        embedding is computed channels first (contiguous rows, see
        :class:`ViewEmbedding`), multiplied in place when nothing needs its
        gradient, and read transposed by the matrix product.
        """
        first, e = self.mlp[0], self.embedding.dim
        embedded, projected = self.embedding(dirs.transpose(-1, -2)), projected.transpose(-1, -2)
        grad = torch.is_grad_enabled() and (embedded.requires_grad or projected.requires_grad)
        if grad or torch.broadcast_shapes(embedded.shape, projected.shape) != embedded.shape:
            embedded = embedded * projected
        else:
            embedded.mul_(projected)
        x = F.linear(embedded.transpose(-1, -2), first.weight[:, :e], first.bias)
        return self.mlp[1:-1](x.add_(F.linear(cues, first.weight[:, e:])))
