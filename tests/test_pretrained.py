"""The ``model=`` argument made a model (``o3dvis.pretrained``): the shipped model loaded once and
shared, copies moved to another device, the weights folder followed, unknown names refused."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis import models
from o3dvis.models import file_sha256
from o3dvis.pretrained import resolve_model

from conftest import _camera


def test_unknown_model_name(pcd, points, monkeypatch, tmp_path, network):
    network.save(tmp_path / "default.safetensors")
    card = {"models": {"default": {"file": "default.safetensors",
                                   "sha256": file_sha256(tmp_path / "default.safetensors")}}}
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    monkeypatch.setattr(models, "WEIGHTS_DIR", tmp_path)
    with pytest.raises(ValueError, match="unknown model 'tiny'; available: default"):
        o3dvis.hidden_point_removal_neural(pcd, _camera(points), model="tiny")
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, _camera(points), threshold=0.4)
    _, expected = o3dvis.hidden_point_removal_neural(pcd, _camera(points), threshold=0.4, model=network)
    assert pt_map == expected


def test_the_shipped_model_is_loaded_once_and_shared(pcd, monkeypatch):
    cpu = torch.device("cpu")
    shipped = resolve_model(None, cpu)
    assert resolve_model("default", cpu) is shipped
    with pytest.raises(ValueError, match="unknown model 'tiny'; available: default, normals"):
        resolve_model("tiny", cpu)

    def load_again(*args, **kwargs):
        raise AssertionError("the shipped weights were loaded again")

    monkeypatch.setattr(models, "_load_checked", load_again)
    cloud = o3d.geometry.PointCloud(pcd)
    o3dvis.estimate_normals_neural(cloud, num_views=4, refine_views=0)  # model=None: the shared model
    assert cloud.has_normals()
    _, pt_map = o3dvis.hidden_point_removal_neural(pcd, _camera(np.asarray(pcd.points)))
    assert len(pt_map) > 0
    mine = o3dvis.NeuralVisibility.pretrained()  # a model of its own over the networks loaded
    assert mine is not shipped and mine.networks() == shipped.networks()


def test_moving_a_pretrained_model_moves_copies_of_the_shared_networks():
    shipped = resolve_model(None, torch.device("cpu"))
    mine = o3dvis.NeuralVisibility.pretrained().to("meta")  # a device every torch build has
    assert all(next(net.parameters()).device.type == "meta" for net in mine.networks())
    assert all(next(net.parameters()).device.type == "cpu" for net in shipped.networks())
    assert resolve_model(None, torch.device("cpu")) is shipped


def test_the_shared_model_follows_the_weights_folder(pcd, monkeypatch, tmp_path, network):
    cpu = torch.device("cpu")
    shipped = resolve_model(None, cpu)
    network.save(tmp_path / "default.safetensors")
    card = {"models": {"default": {"file": "default.safetensors",
                                   "sha256": file_sha256(tmp_path / "default.safetensors")}}}
    (tmp_path / "model_card.json").write_text(json.dumps(card))
    monkeypatch.setattr(models, "WEIGHTS_DIR", tmp_path)
    other = resolve_model(None, cpu)
    assert other is not shipped and other.network.config == network.config
    assert resolve_model(None, cpu) is other
