"""Per-view predictor: sinusoidal view embedding x point feature (+ cues) -> 2 logits."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["ViewEmbedding", "VisibilityPredictor"]


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

    def project(self, features: Tensor, points: Tensor, carry: Callable[[Tensor], Tensor]) -> Tensor:
        """Projects ``[feature, point]`` to the embedding's width, (N, E), stored channels first.

        The projection is linear, so the features are projected where they are
        computed, once per octree leaf, and ``carry`` then takes the (E, L)
        projected leaf features to the (E, N) points (a gather, or an
        interpolation whose weights sum to 1, which keeps the bias exact).

        Args:
            features: (L, C) features of the octree leaves (the layer takes C + 3 inputs).
            points: (N, 3) normalised points, the layer's last 3 inputs.
            carry: (E, L) -> (E, N) leaf values at the points.
        """
        layer, c = self.project_feature, features.shape[1]
        per_leaf = torch.addmm(layer.bias[:, None], layer.weight[:, :c], features.transpose(0, 1))
        return carry(per_leaf).addmm_(layer.weight[:, c:], points.transpose(0, 1)).transpose(0, 1)

    def forward(self, projected: Tensor, dirs: Tensor, cues: Tensor) -> Tensor:
        """(..., N, E) projected features, (..., N, 3) directions, (..., N, Z) cues -> (..., N, 2)."""
        return self.mlp[-1](self._hidden(projected, dirs, cues))

    def margin(self, projected: Tensor, dirs: Tensor, cues: Tensor) -> Tensor:
        """(..., N) logit of "visible" minus that of "hidden", as from :meth:`forward`,
        with a last layer of one output instead of two (what a probability needs)."""
        last = self.mlp[-1]
        weight, bias = last.weight[1:] - last.weight[:1], last.bias[1:] - last.bias[:1]
        return F.linear(self._hidden(projected, dirs, cues), weight, bias)[..., 0]

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
