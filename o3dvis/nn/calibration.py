"""Per-cloud recalibration of the predictor's logit margin, fitted after training.

The network's best decision threshold moves with a cloud's noise and density:
dense noisy clouds want a lower one, sparse clean clouds a higher one.
A calibrated network maps the margin ``m``
(logit of "visible" minus that of "hidden") of every point of a cloud to

    m * exp(u . g) + w . g,   g = (1, c1, c2, s, c1 s, c2 s),

where ``c1, c2`` are the cloud's noise cues (:mod:`.noise`) and ``s`` its
centred log size. ``u`` and ``w`` (12 numbers) are fitted on training clouds by
cross-entropy (:func:`fit_calibration`); zeros are the identity.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

__all__ = ["CloudCalibration", "calibration_terms", "calibration_loss", "fit_calibration", "NUM_TERMS"]

NUM_TERMS = 6
_LOG_SIZE_CENTRE, _LOG_SIZE_SCALE = 9.5, 1.5  # ln(N) of 2 k - 82 k points maps to about -1.3 .. +1.2


def calibration_terms(noise: Tensor, num_points: int) -> Tensor:
    """(6,) float64 ``g`` of a cloud from its (2,) noise cues and its number of points."""
    c1, c2 = noise.detach().double().cpu().tolist()
    s = (math.log(max(num_points, 1)) - _LOG_SIZE_CENTRE) / _LOG_SIZE_SCALE
    return torch.tensor([1.0, c1, c2, s, c1 * s, c2 * s], dtype=torch.float64)


class CloudCalibration(nn.Module):
    """The coefficients ``u`` and ``w`` (buffers, saved with the network)."""

    def __init__(self):
        super().__init__()
        self.register_buffer("u", torch.zeros(NUM_TERMS, dtype=torch.float64))
        self.register_buffer("w", torch.zeros(NUM_TERMS, dtype=torch.float64))

    def affine(self, terms: Tensor) -> tuple[float, float]:
        """``(scale, shift)`` of one cloud's margins, from its :func:`calibration_terms`."""
        terms = terms.to(self.u)
        return float(torch.exp(terms @ self.u)), float(terms @ self.w)


def calibration_loss(u: Tensor, w: Tensor, terms: Tensor, cloud: Tensor, margins: Tensor,
                     labels: Tensor) -> Tensor:
    """Cross-entropy of ``margins * exp(terms u) + terms w``, each sample with its cloud's terms.

    Args:
        u, w: (6,) coefficients.
        terms: (C, 6) the :func:`calibration_terms` of each cloud.
        cloud: (M,) the cloud of each sample.
        margins: (M,) the network's margins.
        labels: (M,) 1 for visible, 0 for hidden.
    """
    scale, shift = torch.exp(terms @ u).index_select(0, cloud), (terms @ w).index_select(0, cloud)
    return nn.functional.binary_cross_entropy_with_logits(margins * scale + shift, labels)


def fit_calibration(terms: Tensor, cloud: Tensor, margins: Tensor, labels: Tensor, max_iter: int = 300
                    ) -> tuple[Tensor, Tensor]:
    """``(u, w)`` minimising :func:`calibration_loss` (L-BFGS, from the identity).

    Returns:
        float64 ``u`` and ``w``, (6,) each.
    """
    terms, margins, labels = terms.double(), margins.double(), labels.double()
    u = torch.zeros(NUM_TERMS, dtype=torch.float64, requires_grad=True)
    w = torch.zeros(NUM_TERMS, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([u, w], max_iter=max_iter, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        loss = calibration_loss(u, w, terms, cloud, margins, labels)
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    return u.detach(), w.detach()
