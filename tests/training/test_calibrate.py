"""The per-cloud calibration: its fit, its use by the field, its checkpoint and its command."""

import math

import numpy as np
import pytest
import torch

from o3dvis.nn.calibration import NUM_TERMS, calibration_terms, fit_calibration
from o3dvis.nn.network import NetworkConfig, VisibilityNetwork
from o3dvis.nn.octree import normalize_points
from o3dvis.neural import NeuralVisibility

SMALL = dict(depth=6, channels=(8, 16, 16, 16, 16), noise_cues=True)


def _cloud(n=2500, seed=0):
    g = np.random.default_rng(seed)
    p = g.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return p * (1 + 0.3 * (p[:, :1] > 0.6))


def test_fit_recovers_a_known_affine_map():
    g = torch.Generator().manual_seed(0)
    clouds, per_cloud = 40, 2000
    noise = torch.rand(clouds, 2, generator=g, dtype=torch.float64) * 0.5
    sizes = torch.randint(2000, 80000, (clouds,), generator=g)
    terms = torch.stack([calibration_terms(c, int(n)) for c, n in zip(noise, sizes)])
    cloud = torch.arange(clouds).repeat_interleave(per_cloud)
    u = torch.tensor([0.3, -0.8, 0.5, 0.1, 0.4, -0.2], dtype=torch.float64)
    w = torch.tensor([-0.5, 2.0, -1.0, 0.3, 1.0, -0.6], dtype=torch.float64)
    margins = 3 * torch.randn(len(cloud), generator=g, dtype=torch.float64)
    labels = torch.bernoulli(torch.sigmoid(margins * torch.exp(terms @ u)[cloud] + (terms @ w)[cloud]), generator=g)
    fit_u, fit_w = fit_calibration(terms, cloud, margins, labels)
    torch.testing.assert_close(fit_u, u, atol=0.25, rtol=0)
    torch.testing.assert_close(fit_w, w, atol=0.4, rtol=0)
    # a calibrated network's own answers need none: the fit stays near the identity
    labels = torch.bernoulli(torch.sigmoid(margins), generator=g)
    fit_u, fit_w = fit_calibration(terms, cloud, margins, labels)
    assert fit_u.abs().max() < 0.15 and fit_w.abs().max() < 0.3


def test_terms_of_a_cloud():
    t = calibration_terms(torch.tensor([0.2, 0.4]), int(math.exp(11)))
    torch.testing.assert_close(t, torch.tensor([1, 0.2, 0.4, 1, 0.2, 0.4], dtype=torch.float64), atol=1e-5, rtol=0)
    assert t.shape == (NUM_TERMS,)


def test_field_applies_the_calibration_to_every_margin(tmp_path):
    torch.manual_seed(0)
    plain = VisibilityNetwork(NetworkConfig(**SMALL)).eval()
    calibrated = VisibilityNetwork(NetworkConfig(**SMALL, calibrated=True)).eval()
    calibrated.load_state_dict({**plain.state_dict(), "calibration.u": calibrated.calibration.u,
                                "calibration.w": calibrated.calibration.w})
    pts, cams = _cloud(), np.array([[3.0, 0.5, 0.2], [-1.0, 3.0, 1.0]])
    before = NeuralVisibility(plain).encode(pts).probabilities(cams).double()
    # zeros are the identity
    torch.testing.assert_close(NeuralVisibility(calibrated).encode(pts).probabilities(cams).double(), before)
    calibrated.calibration.u.copy_(torch.tensor([0.3, -0.5, 0.2, 0.1, 0.3, -0.1]))
    calibrated.calibration.w.copy_(torch.tensor([-0.4, 1.5, -0.7, 0.2, 0.8, -0.3]))
    path = tmp_path / "calibrated.safetensors"
    calibrated.save(path)
    loaded = VisibilityNetwork.load(path)
    torch.testing.assert_close(loaded.calibration.w, calibrated.calibration.w)
    after = NeuralVisibility(loaded).encode(pts).probabilities(cams).double()
    noise = plain.cloud_noise(normalize_points(torch.from_numpy(pts))[0].float())[0]
    terms = calibration_terms(noise, len(pts))
    scale, shift = torch.exp(terms @ loaded.calibration.u), terms @ loaded.calibration.w
    logit = torch.log(before) - torch.log1p(-before)
    keep = before.sub(0.5).abs() < 0.49  # away from float32 saturation
    torch.testing.assert_close(after[keep], torch.sigmoid(logit * scale + shift)[keep], atol=2e-4, rtol=0)
    assert (after != before).float().mean() > 0.9


def test_warm_start_drops_a_calibration():
    from o3dvis.training.train import warm_start

    torch.manual_seed(0)
    source = VisibilityNetwork(NetworkConfig(**SMALL, calibrated=True))
    source.calibration.w.fill_(1.0)
    target = VisibilityNetwork(NetworkConfig(**SMALL))
    warm_start(target, source.state_dict())
    for name, value in target.state_dict().items():
        torch.testing.assert_close(value, source.state_dict()[name])


def test_calibrate_command_writes_a_calibrated_network(tmp_path, monkeypatch):
    from o3dvis.training.calibrate import calibrate
    from o3dvis.training.data.dataset import Augmentation
    from o3dvis.training.data.prepare import label_mesh
    from o3dvis.training.data.sample import save_sample
    from o3dvis.training.data.shapes import write_shapes

    data = tmp_path / "data"
    data.mkdir()
    for m in write_shapes(str(tmp_path / "meshes"), 2, seed=3):
        s = label_mesh(m, num_points=3000, num_views=8)
        save_sample(s, data / f"{s.name}.npz")
    torch.manual_seed(0)
    ckpt = tmp_path / "net.safetensors"
    VisibilityNetwork(NetworkConfig(**SMALL)).save(ckpt)
    out = tmp_path / "calibrated.safetensors"
    monkeypatch.chdir(tmp_path)  # the data root: the checkpoint records paths relative to it
    summary = calibrate(ckpt, [data], out, clouds=6, keep=2000,
                        augmentation=Augmentation(min_points=1000, max_points=3000), progress=False)
    net = VisibilityNetwork.load(out)
    assert net.config.calibrated and summary["samples"] == 6 * 2000
    torch.testing.assert_close(net.calibration.u, torch.tensor(summary["u"], dtype=torch.float64))
    assert summary["cross_entropy_after"] < summary["cross_entropy_before"]  # an untrained network's margins
    assert summary["data"] == ["data"] and summary["checkpoint"] == "net.safetensors"
    assert str(tmp_path) not in out.read_bytes()[:100_000].decode("utf-8", "replace")
    with pytest.raises(ValueError, match="positive"):
        calibrate(ckpt, [data], out, clouds=0)
