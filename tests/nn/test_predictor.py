"""The per-view predictor (``o3dvis.nn.predictor``): the view embedding and the MLP on the
concatenation, with and without autograd."""

import pytest
import torch

from o3dvis.nn import ViewEmbedding, VisibilityPredictor


@pytest.mark.parametrize("frequencies", [0, 1, 6])
@pytest.mark.parametrize("grad", [False, True])
def test_embedding_matches_direct_sinusoids(frequencies, grad):
    """Both the autograd path and the in-place one; (V, 3, N) batches of views too."""
    d = torch.nn.functional.normalize(torch.randn(2, 100, 3, dtype=torch.float64), dim=-1).requires_grad_(grad)
    emb = ViewEmbedding(frequencies)(d.transpose(-1, -2))  # channels first
    ref = [d] + [f(2**k * torch.pi * d) for k in range(frequencies) for f in (torch.sin, torch.cos)]
    assert emb.shape == (2, 3 + 6 * frequencies, 100) and emb.requires_grad == grad
    torch.testing.assert_close(emb, torch.cat(ref, dim=-1).transpose(-1, -2))


@pytest.mark.parametrize("grad", [False, True])
def test_predictor_equals_the_plain_mlp_on_the_concatenation(grad):
    torch.manual_seed(0)
    pred = VisibilityPredictor(8, num_frequencies=3, num_cues=5, hidden=(16, 12)).double()
    projected = torch.randn(2, 50, pred.embedding.dim, dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(2, 50, 3, dtype=torch.float64), dim=-1).requires_grad_(grad)
    cues = torch.randn(2, 50, 5, dtype=torch.float64)
    emb = pred.embedding(dirs.transpose(-1, -2)).transpose(-1, -2)
    expected = pred.mlp(torch.cat([projected * emb, cues], dim=-1))
    with torch.set_grad_enabled(grad):
        torch.testing.assert_close(pred(projected, dirs, cues), expected)
        torch.testing.assert_close(pred.margin(projected, dirs, cues), expected[..., 1] - expected[..., 0])
        # one view's directions against features of two: broadcast, not written in place
        torch.testing.assert_close(pred(projected, dirs[0], cues[0]),
                                   pred.mlp(torch.cat([projected * emb[0], cues[0].expand(2, -1, -1)], dim=-1)))
