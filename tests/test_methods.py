"""Visibility sources (``o3dvis.methods``): a resolved method answers for some points as for all, and
encodes a cloud once."""

from __future__ import annotations

import numpy as np
import pytest
import torch


def test_methods_answer_for_indices_and_encode_a_cloud_once(sphere):
    from o3dvis.apps import resolve_method
    from o3dvis.nn import NetworkConfig, VisibilityNetwork
    from o3dvis.neural import NeuralVisibility

    points, _, truth = sphere
    cameras = np.array([[0.0, 0.0, 4.0], [4.0, 1.0, 0.0]])
    indices = np.arange(0, len(points), 7)
    exact = resolve_method(truth)
    np.testing.assert_array_equal(exact(points, cameras, indices), truth(points, cameras)[:, indices])
    with pytest.raises(ValueError, match="returned shape"):
        resolve_method(lambda p, c: np.ones((1, 3), bool))(points, cameras, indices)

    def answers_for_all(points, cameras, indices=None):  # claims to take indices, ignores them
        return truth(points, cameras)
    answers_for_all.takes_indices = True
    with pytest.raises(ValueError, match="returned shape"):
        resolve_method(answers_for_all)(points, cameras, indices)

    torch.manual_seed(0)
    network = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 16), feature_channels=8,
                                              num_frequencies=2, hidden=(16,))).eval()
    vis = NeuralVisibility(network)
    encoded = []
    vis.encode = lambda cloud, _encode=vis.encode: encoded.append(1) or _encode(cloud)
    method = resolve_method(vis)
    full = method(points, cameras)
    np.testing.assert_array_equal(method(points, cameras, indices), full[:, indices])
    assert len(encoded) == 1
    again = resolve_method(method)  # a resolved method keeps its indices and its encoding
    np.testing.assert_array_equal(again(points, cameras, indices), full[:, indices])
    assert len(encoded) == 1
    method(points.copy(), cameras)  # another array: encoded afresh
    assert len(encoded) == 2
