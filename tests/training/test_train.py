"""Training (``o3dvis.training.train``) on tiny procedural data: the loss falls, footprints are found
once a cloud, a warm start with added inputs keeps the function."""

import numpy as np
import pytest
import torch

from o3dvis.nn import NetworkConfig, VisibilityNetwork, normalize_points

from conftest import _sphere_with_bump


def test_training_smoke_loss_falls(tmp_path):
    """A few steps on tiny procedural data: the loss must fall."""
    from o3dvis.training.data.prepare import label_mesh
    from o3dvis.training.data.sample import save_sample
    from o3dvis.training.data.shapes import write_shapes
    from o3dvis.training.train import TrainConfig, train

    meshes = write_shapes(str(tmp_path / "meshes"), 3, seed=5)
    data = tmp_path / "data"
    data.mkdir()
    for m in meshes:
        s = label_mesh(m, num_points=3000, num_views=8)
        save_sample(s, data / f"{s.name}.npz")
    torch.manual_seed(0)
    cfg = TrainConfig(data=[str(data)], out=str(tmp_path / "run"), steps=40, batch_size=2, lr=3e-3,
                      warmup=5, val_every=1000, log_every=5, network={"depth": 6},
                      augmentation={"min_points": 1500, "max_points": 3000, "views": 4, "noise": 0})
    train(cfg, progress=False)
    log = [__import__("json").loads(line) for line in open(tmp_path / "run" / "log.jsonl")]
    losses = [r["loss"] for r in log if "loss" in r]
    assert len(losses) == 8 and np.mean(losses[-2:]) < 0.8 * np.mean(losses[:2])


def test_training_with_footprints_finds_each_clouds_surfels_once(tmp_path, monkeypatch):
    """Training and validation of a network with footprints run, and each cloud's surfels are
    found once for all its views."""
    from o3dvis.nn import network as network_module
    from o3dvis.training.data.prepare import label_mesh
    from o3dvis.training.data.sample import save_sample
    from o3dvis.training.data.shapes import write_shapes
    from o3dvis.training.train import TrainConfig, train

    data = tmp_path / "data"
    data.mkdir()
    for m in write_shapes(str(tmp_path / "meshes"), 2, seed=3):
        s = label_mesh(m, num_points=2000, num_views=4)
        save_sample(s, data / f"{s.name}.npz")
    found = []
    monkeypatch.setattr(network_module, "point_surfels",
                        lambda points, find=network_module.point_surfels: found.append(len(points)) or find(points))
    cfg = TrainConfig(data=[str(data)], out=str(tmp_path / "run"), val=str(data), steps=2, batch_size=2,
                      val_every=2, val_points=1000, val_views=3, network={"depth": 6, "footprints": True},
                      augmentation={"min_points": 1000, "max_points": 2000, "views": 3, "noise": 0})
    train(cfg, progress=False)
    assert len(found) == 2 * 2 + 2  # two steps of two clouds, then two validation files
    assert found[-2:] == [1000, 1000]


@pytest.mark.parametrize("added", [{"use_normals": True}, {"noise_cues": True}])
def test_warm_start_with_added_inputs_keeps_the_function(added, torch_ops):
    from o3dvis.training.train import warm_start

    torch.manual_seed(0)
    small = dict(depth=6, channels=(8, 16, 16, 16, 16))
    source = VisibilityNetwork(NetworkConfig(**small))
    for p in source.parameters():  # non-trivial BN statistics and weights
        p.data.normal_()
    for m in source.modules():
        if isinstance(m, torch.nn.BatchNorm1d):
            m.running_mean.normal_()
            m.running_var.uniform_(0.5, 2)
    target = VisibilityNetwork(NetworkConfig(**small, **added))
    warm_start(target, source.state_dict())
    source.eval(), target.eval()
    pn, _, _ = normalize_points(_sphere_with_bump())
    normals = torch.nn.functional.normalize(torch.randn_like(pn), dim=1) if target.config.use_normals else None
    cam = torch.tensor([2.0, 0.5, 0.3])
    with torch.no_grad():
        a = source.predict(source.encode(pn), pn, cam)
        b = target.predict(target.encode(pn, normals=normals), pn, cam, normals=normals)
    torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
