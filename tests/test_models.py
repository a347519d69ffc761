"""Checkpoints (``o3dvis.models``): the model card, sha256, tampered and truncated files refused, no pickle
executed, ``NeuralVisibility.pretrained`` from a weights folder, a path's model loaded once."""

from __future__ import annotations

import json
import pickle
import struct
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis import models
from o3dvis.models import check_safetensors, file_sha256, load_model, read_model_card
from o3dvis.nn import NetworkConfig, VisibilityNetwork

from conftest import SMALL


def _network(seed: int, use_normals: bool = False) -> VisibilityNetwork:
    torch.manual_seed(seed)
    return VisibilityNetwork(NetworkConfig(**SMALL, use_normals=use_normals))


@pytest.fixture
def weights(tmp_path):
    """A weights folder with a default and a normals model and their card."""
    entries = {}
    for name, normals in (("default", False), ("normals", True)):
        path = tmp_path / f"{name}.safetensors"
        _network(len(entries), normals).save(path)
        entries[name] = {"file": path.name, "sha256": file_sha256(path), "use_normals": normals}
    (tmp_path / "model_card.json").write_text(json.dumps({"models": entries}))
    return tmp_path


def _same_weights(a: VisibilityNetwork, b: VisibilityNetwork) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_load_by_name_restores_the_saved_weights(weights):
    net = load_model("default", weights_dir=weights)
    assert _same_weights(net, _network(0))
    assert not net.training and next(net.parameters()).device.type == "cpu"
    normals = load_model("normals", weights_dir=weights)
    assert normals.config.use_normals and _same_weights(normals, _network(1, True))
    assert o3dvis.available_models(weights) == ["default", "normals"]


def test_user_path_loads_and_checks_an_explicit_sha256(weights, tmp_path):
    path = tmp_path / "elsewhere.safetensors"
    _network(7).save(path)
    assert _same_weights(load_model(path), _network(7))
    assert _same_weights(load_model(str(path), sha256=file_sha256(path)), _network(7))
    with pytest.raises(ValueError, match="sha256 mismatch"):
        load_model(path, sha256="0" * 64)


def _flip_byte(path, offset_from_end: int = 10) -> None:
    data = bytearray(path.read_bytes())
    data[-offset_from_end] ^= 0xFF
    path.write_bytes(bytes(data))


def test_tampered_file_is_refused_by_name_and_by_path(weights):
    path = weights / "default.safetensors"
    _flip_byte(path)
    with pytest.raises(ValueError, match="sha256 mismatch.*modified"):
        load_model("default", weights_dir=weights)
    # A path listed by the card next to it is checked against that card too.
    with pytest.raises(ValueError, match="sha256 mismatch"):
        load_model(path)


def test_truncated_file_gives_a_clear_error(weights):
    path = weights / "default.safetensors"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ValueError, match="truncated"):
        load_model("default", weights_dir=weights)
    path.write_bytes(path.read_bytes()[:5])
    with pytest.raises(ValueError, match="truncated"):
        check_safetensors(path)


def test_trailing_bytes_and_bad_headers_are_refused(tmp_path):
    path = tmp_path / "m.safetensors"
    _network(0).save(path)
    path.write_bytes(path.read_bytes() + b"\0" * 16)
    with pytest.raises(ValueError, match="trailing bytes"):
        load_model(path)
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(struct.pack("<Q", 4) + b"nope")
    with pytest.raises(ValueError, match="not JSON"):
        load_model(bad)
    huge = tmp_path / "huge.safetensors"
    huge.write_bytes(struct.pack("<Q", 10**12) + b"{}")
    with pytest.raises(ValueError, match="truncated"):
        load_model(huge)
    nested = b'{"x": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"  # JSON deeper than Python's reader goes
    deep = tmp_path / "deep.safetensors"
    deep.write_bytes(struct.pack("<Q", len(nested)) + nested)
    with pytest.raises(ValueError, match="header nests deeper"):
        load_model(deep)
    (tmp_path / "model_card.json").write_bytes(b'{"models": ' + nested + b"}")
    with pytest.raises(ValueError, match="model card is not valid JSON"):
        load_model("m", weights_dir=tmp_path)


class _Payload:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_pickle_checkpoints_are_never_unpickled(tmp_path):
    marker = tmp_path / "executed"
    for name, writer in (("zip.pt", lambda p: torch.save({"x": _Payload(marker)}, p)),
                         ("raw.pkl", lambda p: p.write_bytes(pickle.dumps(_Payload(marker))))):
        path = tmp_path / name
        writer(path)
        with pytest.raises(ValueError, match="pickle"):
            load_model(path)
        assert not marker.exists(), "loading executed the pickle payload"


def test_unknown_name_lists_the_available_models(weights):
    with pytest.raises(ValueError, match="unknown model 'nope'.*default, normals"):
        load_model("nope", weights_dir=weights)


def test_missing_card_or_file_names_the_missing_file(weights, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="model_card.json"):
        load_model("default", weights_dir=empty)
    (weights / "normals.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="normals.safetensors"):
        load_model("normals", weights_dir=weights)
    with pytest.raises(FileNotFoundError, match="missing.safetensors"):
        load_model(tmp_path / "missing.safetensors")


def test_card_inconsistent_with_checkpoint_or_malformed(weights):
    card = json.loads((weights / "model_card.json").read_text())
    card["models"]["default"]["use_normals"] = True
    (weights / "model_card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match="use_normals"):
        load_model("default", weights_dir=weights)
    del card["models"]["default"]["sha256"]
    (weights / "model_card.json").write_text(json.dumps(card))
    with pytest.raises(ValueError, match="sha256"):
        read_model_card(weights)
    (weights / "model_card.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_model("default", weights_dir=weights)


def test_safetensors_without_o3dvis_config_is_refused(tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(3)}, str(path))
    with pytest.raises(ValueError, match="not an o3dvis checkpoint"):
        load_model(path)
    with pytest.raises(TypeError, match="name_or_path"):
        load_model(3)


def test_pretrained_pairs_the_normals_model(weights):
    vis = o3dvis.NeuralVisibility.pretrained(weights_dir=weights)
    assert vis.normals_network is not None and vis.normals_network.config.use_normals
    assert o3dvis.NeuralVisibility.pretrained(weights_dir=weights, use_normals=False).normals_network is None
    points = np.random.default_rng(0).normal(size=(300, 3))
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert vis.encode(points).network is vis.network
    assert vis.encode(points, normals=normals).network is vis.normals_network


def test_pretrained_from_the_shipped_folder(monkeypatch, weights):
    card = models.WEIGHTS_DIR / models.CARD_NAME
    if card.is_file():
        entry = read_model_card()["models"]["default"]
        assert file_sha256(models.WEIGHTS_DIR / entry["file"]) == entry["sha256"]
        assert isinstance(o3dvis.NeuralVisibility.pretrained(), o3dvis.NeuralVisibility)
    else:
        with pytest.raises(FileNotFoundError, match="model_card.json"):
            o3dvis.NeuralVisibility.pretrained()
    monkeypatch.setattr(models, "WEIGHTS_DIR", weights)
    assert _same_weights(o3dvis.NeuralVisibility.pretrained().network, _network(0))


def _padded_checkpoint(tmp_path, network: VisibilityNetwork, low_bytes: bytes) -> "Path":
    """``network`` saved with metadata padded until its header length starts with ``low_bytes``."""
    path = tmp_path / "padded.safetensors"
    for pad in range(4096):
        network.save(path, {"pad": "x" * pad})
        if path.read_bytes()[:len(low_bytes)] == low_bytes:
            return path
    raise AssertionError("no padding gives that header length")


def test_safetensors_whose_header_length_starts_with_0x80_loads(tmp_path):
    path = _padded_checkpoint(tmp_path, _network(3), b"\x80")
    assert _same_weights(load_model(path), _network(3))


def test_safetensors_that_starts_like_a_pickle_protocol_is_not_taken_for_one(tmp_path):
    from safetensors.torch import save_file

    # a header 0x0280 bytes long: its first two bytes are pickle's PROTO 2 opcode
    path = tmp_path / "proto.safetensors"
    for pad in range(2048):
        save_file({"w": torch.zeros(3)}, str(path), metadata={"pad": "x" * pad})
        if path.read_bytes()[:2] == b"\x80\x02":
            break
    check_safetensors(path)
    path.write_bytes(pickle.dumps({"w": [0.0] * 200}, protocol=2))
    with pytest.raises(ValueError, match="pickle"):
        check_safetensors(path)


def _with_config(tmp_path, network: VisibilityNetwork, **changes) -> "Path":
    """``network``'s tensors saved under its config with ``changes``."""
    from dataclasses import asdict

    from safetensors.torch import save_file

    path = tmp_path / "crafted.safetensors"
    config = {**asdict(network.config), **changes}
    save_file({k: v.contiguous() for k, v in network.state_dict().items()}, str(path),
              metadata={"config": json.dumps(config)})
    return path


@pytest.mark.parametrize("changes, message", [
    (dict(channels=[4096, 4096]), "channels must be"),
    (dict(depth=12, full_depth=9), "depth must be"),
    (dict(full_depth=5), "full_depth"),
    (dict(hidden=[]), "hidden must be"),
    (dict(interpolation="cubic"), "interpolation"),
    (dict(use_normals="yes"), "use_normals"),
    (dict(widths=[8]), "unknown fields"),
])
def test_config_out_of_bounds_is_refused_before_building(tmp_path, monkeypatch, changes, message):
    path = _with_config(tmp_path, _network(0), **changes)
    built = []
    init = VisibilityNetwork.__init__
    monkeypatch.setattr(VisibilityNetwork, "__init__",
                        lambda self, *a, **k: (built.append(torch.empty(0).device.type), init(self, *a, **k))[1])
    with pytest.raises(ValueError, match=message):
        load_model(path)
    assert "cpu" not in built


def test_tensor_shapes_are_checked_against_the_config_before_building(tmp_path, monkeypatch):
    # a config in bounds but far wider than its tensors: refused without building it
    path = _with_config(tmp_path, _network(0), channels=[1024, 1024])
    built = []
    init = VisibilityNetwork.__init__
    monkeypatch.setattr(VisibilityNetwork, "__init__",
                        lambda self, *a, **k: (built.append(torch.empty(0).device.type), init(self, *a, **k))[1])
    with pytest.raises(ValueError, match=r"tensor shapes do not match.*\(8,\) \(config: \(1024,\)\)"):
        load_model(path)
    assert built == ["meta"]


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused(tmp_path, value):
    network = _network(0)
    with torch.no_grad():
        network.predictor.mlp[0].weight[0, 0] = value
    path = tmp_path / "nan.safetensors"
    network.save(path)
    with pytest.raises(ValueError, match="non-finite.*predictor.mlp.0.weight"):
        load_model(path)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_load_builds_the_network_on_map_location(tmp_path):
    from o3dvis.nn import morton_order, normalize_points

    path = tmp_path / "net.safetensors"
    _network(3).save(path)
    gpu, cpu = VisibilityNetwork.load(path, "cuda").eval(), VisibilityNetwork.load(path).eval()
    assert {t.device.type for t in gpu.state_dict().values()} == {"cuda"}
    points = normalize_points(torch.rand(3000, 3, generator=torch.Generator().manual_seed(0)))[0].float()
    points = points[morton_order(points)]
    with torch.no_grad():
        torch.testing.assert_close(gpu.encode(points.cuda()).cpu(), cpu.encode(points), atol=1e-4, rtol=1e-4)


def test_a_path_model_is_loaded_once_until_its_file_changes(tmp_path, monkeypatch):
    """``model=path`` loads (and hashes) the checkpoint once per process, so that the drop-ins' kept
    encoding holds across calls; a file written anew, or the card next to it, is read again."""
    from o3dvis import encodings, models, neural
    from o3dvis.pretrained import resolve_model

    path = tmp_path / "mine.safetensors"
    _network(7).save(path)
    loads, encodes = [], []
    load, encode = models._load_checked, neural.NeuralVisibility.encode
    monkeypatch.setattr(models, "_load_checked", lambda *a, **k: loads.append(a) or load(*a, **k))
    monkeypatch.setattr(neural.NeuralVisibility, "encode", lambda *a, **k: encodes.append(a) or encode(*a, **k))
    encodings.clear()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).normal(size=(500, 3))))
    answers = [o3dvis.hidden_point_removal_neural(pcd, [0, 0, 5.0], model=m)[1] for m in (path, str(path), path)]
    assert len(loads) == 1 and len(encodes) == 1 and answers[0] == answers[1] == answers[2]
    assert resolve_model(path, torch.device("cpu")) is resolve_model(str(path), torch.device("cpu"))
    _network(8).save(path)  # written anew
    assert _same_weights(resolve_model(path, torch.device("cpu")).network, _network(8)) and len(loads) == 2
    (tmp_path / "model_card.json").write_text(json.dumps({"models": {"mine": {"file": path.name, "sha256": "0" * 64}}}))
    with pytest.raises(ValueError, match="sha256 mismatch"):
        resolve_model(path, torch.device("cpu"))
    encodings.clear()
