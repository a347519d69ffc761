"""Publishing a checkpoint as a shipped model, and the shipped model card itself."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch

from o3dvis.models import WEIGHTS_DIR, file_sha256, load_model, read_model_card
from o3dvis.nn.network import NetworkConfig, VisibilityNetwork
from o3dvis.training.publish import portable_path, publish

SMALL = dict(depth=5, channels=(8, 8, 8))
ABSOLUTE = re.compile(r'"(/|[A-Za-z]:\\\\)[^"]*"')  # a JSON string that is an absolute path


def test_portable_path(tmp_path):
    assert portable_path(tmp_path / "data" / "train", tmp_path) == "data/train"
    assert portable_path("data/val", tmp_path) == "data/val"
    assert portable_path("/elsewhere/meshes/val", tmp_path) == "val"


def test_publish_writes_no_absolute_path(tmp_path):
    root = tmp_path / "project"
    run = root / "runs" / "small"
    run.mkdir(parents=True)
    torch.manual_seed(0)
    checkpoint = run / "last.safetensors"
    VisibilityNetwork(NetworkConfig(**SMALL)).save(checkpoint)
    (run / "config.json").write_text(json.dumps({
        "data": [str(root / "data" / "train"), "data/proc"], "out": str(run), "val": str(root / "data" / "val"),
        "init": str(tmp_path / "elsewhere" / "init.safetensors"), "steps": 2}))
    (run / "log.jsonl").write_text('{"step": 1, "time": 1.0, "val_acc": 0.5}\n{"step": 2, "time": 2.0}\n')
    report = {"settings": {"data": str(root / "data" / "val"), "files": 1},
              "results": [{"method": "neural", "param": "", "points": 2048, "noise": 0.0, "accuracy": 0.9,
                           "fn_rate": 0.1, "fp_rate": 0.1, "file_accuracy": {"a.npz": 0.9}, "sweep": {}}]}
    (root / "val.json").write_text(json.dumps(report))
    weights = tmp_path / "weights"

    entry = publish(checkpoint, "small", run=run, eval_json=root / "val.json",
                    commands=["o3dvis train data/train data/proc --out runs/small"],
                    weights_dir=weights, root=root)

    text = (weights / "model_card.json").read_text()
    assert not ABSOLUTE.search(text) and str(tmp_path) not in text
    card = read_model_card(weights)
    config = card["models"]["small"]["train_config"]
    assert config["data"] == ["data/train", "data/proc"] and config["out"] == "runs/small"
    assert config["val"] == "data/val" and config["init"] == "init.safetensors"
    assert card["validation"]["settings"]["data"] == "data/val"
    assert card["validation"]["results"] == [{k: report["results"][0][k] for k in
                                              ("method", "param", "points", "noise", "accuracy",
                                               "fn_rate", "fp_rate")}]
    assert entry["training_commands"] == ["o3dvis train data/train data/proc --out runs/small"]
    assert entry["sha256"] == file_sha256(weights / "small.safetensors")
    load_model("small", weights_dir=weights)  # the card's digest matches the copied file
    (root / "scenes.json").write_text(json.dumps({**report, "results": {"uniform": report["results"]}}))
    other = run / "other.safetensors"
    VisibilityNetwork(NetworkConfig(**SMALL)).save(other)
    with pytest.raises(ValueError, match="--scenes"):  # before anything is copied
        publish(other, "small", eval_json=root / "scenes.json", weights_dir=weights, root=root)
    load_model("small", weights_dir=weights)


def test_shipped_card_is_portable_and_complete():
    text = (WEIGHTS_DIR / "model_card.json").read_text()
    assert not ABSOLUTE.search(text), "the model card holds an absolute path"
    card = read_model_card()
    assert {"default", "normals"} <= set(card["models"])
    for name, entry in card["models"].items():
        assert entry["sha256"] == file_sha256(WEIGHTS_DIR / entry["file"]), name
        assert entry["architecture"]["use_normals"] == entry["use_normals"]
        assert entry["training_commands"] and entry["training_data_licences"]
        header = (WEIGHTS_DIR / entry["file"]).read_bytes()[:100_000].decode("utf-8", "replace")
        assert not re.search(r'\\"(/|[A-Za-z]:)[^"]*\\"', header), f"{entry['file']} holds an absolute path"
    methods = {row["method"] for row in card["validation"]["results"]}
    assert {"hpr", "neural", "neural-normals"} <= methods


@pytest.mark.parametrize("name", ["default", "normals"])
def test_shipped_models_load(name):
    assert isinstance(load_model(name), VisibilityNetwork)
