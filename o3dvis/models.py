"""Checkpoints: shipped models described by a model card, or a user's file.

Only safetensors files are read, so loading never executes code (no pickle).
Every file is checked before it is opened: its header must be a valid
safetensors header whose tensors fill the file exactly (a truncated file or
trailing bytes are refused), and its sha256 must match the model card. The
shipped card is ``o3dvis/weights/model_card.json``::

    {"models": {"default": {"file": "default.safetensors", "sha256": "...",
                            "use_normals": false, ...},
                "normals": {...}}}

A user checkpoint is checked against the ``model_card.json`` next to it when
that card lists the file, and against an explicit ``sha256=`` argument.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import struct
import threading
from pathlib import Path

import torch

from .nn.network import VisibilityNetwork
from .nn.state import WeightsState

__all__ = ["WEIGHTS_DIR", "CARD_NAME", "read_model_card", "available_models", "file_sha256",
           "check_safetensors", "load_model", "is_shared", "torch_device"]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
CARD_NAME = "model_card.json"
_MAX_HEADER = 100 * 1024 * 1024
# (path, sha256, device): (the files' stats, the network, its weights when loaded)
_SHARED: dict[tuple[str, str | None, str], tuple[tuple, VisibilityNetwork, WeightsState]] = {}
_SHARED_LOCK = threading.Lock()


def torch_device(device: str | torch.device | None) -> torch.device:
    """A torch device (default: CPU), refusing CUDA when torch cannot use it.

    Args:
        device: e.g. ``"cpu"``, ``"cuda"``, ``"cuda:1"``, a ``torch.device`` or None.

    Returns:
        The ``torch.device``.

    Raises:
        ValueError: an unknown device name, or CUDA without a usable CUDA device.
    """
    try:
        device = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"unknown torch device {device!r} ({e})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device} requested but torch has no usable CUDA device here")
    return device


def read_model_card(weights_dir: str | Path | None = None) -> dict:
    """Reads and checks the model card of a weights folder.

    Args:
        weights_dir: folder holding ``model_card.json`` (default: the shipped
            ``o3dvis/weights``).

    Returns:
        The card as a dict with a ``"models"`` mapping of name to entry.

    Raises:
        FileNotFoundError: the folder has no model card.
        ValueError: the card is not valid JSON or lacks ``models``/``file``/``sha256``.
    """
    path = Path(WEIGHTS_DIR if weights_dir is None else weights_dir) / CARD_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: no trained weights are installed there; "
                                f"give the path of a .safetensors checkpoint as the model instead")
    try:
        card = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as e:  # nested deeper than json reads
        raise ValueError(f"{path}: model card is not valid JSON ({e})") from None
    models = card.get("models") if isinstance(card, dict) else None
    if not isinstance(models, dict):
        raise ValueError(f"{path}: model card needs a 'models' mapping of name to entry")
    for name, entry in models.items():
        if not (isinstance(entry, dict) and isinstance(entry.get("file"), str)
                and isinstance(entry.get("sha256"), str)):
            raise ValueError(f"{path}: entry {name!r} needs string 'file' and 'sha256' fields")
    return card


def available_models(weights_dir: str | Path | None = None) -> list[str]:
    """Names of the models in a weights folder's card (empty when there is no card).

    Args:
        weights_dir: folder holding ``model_card.json`` (default: the shipped one).

    Returns:
        Sorted model names.
    """
    try:
        return sorted(read_model_card(weights_dir)["models"])
    except FileNotFoundError:
        return []


def file_sha256(path: str | Path) -> str:
    """Hex sha256 digest of a file, read in 1 MiB blocks.

    Args:
        path: the file.

    Returns:
        64 lowercase hex digits.
    """
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _is_pickle_or_zip(head: bytes, size: int) -> bool:
    """Whether a file that starts with ``head`` (its first 9 bytes) is a zip archive (what
    ``torch.save`` writes) or a pickle of protocol 2 or later, rather than a safetensors file.

    A safetensors file starts with its header's length (8 bytes, little-endian) and the header's
    ``{``; a pickle starts with the PROTO opcode (0x80) and a protocol number (2 to 5). The two can
    share a first byte: a header 0x0280 bytes long starts like a protocol-2 pickle, so a file
    whose length field fits the file and is followed by ``{`` is taken as safetensors.
    """
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        return True
    if len(head) < 2 or head[0] != 0x80 or not 2 <= head[1] <= pickle.HIGHEST_PROTOCOL:
        return False
    plausible_safetensors = (len(head) == 9 and head[8:9] == b"{"
                             and struct.unpack("<Q", head[:8])[0] <= size - 8)
    return not plausible_safetensors


def check_safetensors(path: str | Path) -> None:
    """Checks that a file is a complete safetensors file, without reading its tensors.

    Args:
        path: the file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a folder, a pickle/zip checkpoint, a bad header, or tensors that do
            not fill the file exactly (truncated or with trailing bytes).
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder, not a checkpoint file")
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(9)
        if _is_pickle_or_zip(head, size):
            raise ValueError(f"{path}: a pickle/zip (torch.save) checkpoint; only safetensors "
                             f"files are loaded, since unpickling can execute code")
        if len(head) < 8:
            raise ValueError(f"{path}: not a safetensors file (truncated: {size} bytes)")
        (header_len,) = struct.unpack("<Q", head[:8])
        f.seek(8)
        if header_len > min(_MAX_HEADER, size - 8):
            raise ValueError(f"{path}: not a safetensors file or truncated "
                             f"(header of {header_len} bytes in a {size}-byte file)")
        try:
            header = json.loads(f.read(header_len))
        except (json.JSONDecodeError, UnicodeDecodeError):
            raise ValueError(f"{path}: not a safetensors file (its header is not JSON)") from None
        except RecursionError:
            raise ValueError(f"{path}: not a safetensors file (its header nests deeper than Python's JSON "
                             "reader goes)") from None
    if not isinstance(header, dict):
        raise ValueError(f"{path}: not a safetensors file (its header is not a JSON object)")
    try:
        end = max((int(v["data_offsets"][1]) for k, v in header.items() if k != "__metadata__"),
                  default=0)
    except (TypeError, KeyError, IndexError, ValueError):
        raise ValueError(f"{path}: not a safetensors file (malformed tensor entries)") from None
    data = size - 8 - header_len
    if end > data:
        raise ValueError(f"{path}: truncated checkpoint ({data} data bytes, tensors need {end})")
    if end < data:
        raise ValueError(f"{path}: corrupted checkpoint ({data - end} trailing bytes after the tensors)")


def _card_entry_for(path: Path) -> dict | None:
    """The entry of the card next to ``path`` that lists it, if any."""
    try:
        models = read_model_card(path.parent)["models"]
    except FileNotFoundError:
        return None
    return next((e for e in models.values() if e["file"] == path.name), None)


def _load_checked(path: Path, sha256: str | None, entry: dict | None,
                  device: str | torch.device) -> VisibilityNetwork:
    check_safetensors(path)
    if sha256 is not None:
        actual = file_sha256(path)
        if actual != sha256.lower():
            raise ValueError(f"{path}: sha256 mismatch (expected {sha256.lower()}, got {actual}); "
                             f"the file is corrupted or was modified")
    try:
        network = VisibilityNetwork.load(path)
    except ValueError:
        raise
    except Exception as e:  # safetensors errors, unknown config fields
        raise ValueError(f"{path}: cannot read checkpoint ({type(e).__name__}: {e})") from None
    card_normals = entry.get("use_normals") if entry is not None else None
    if card_normals is not None and bool(card_normals) != network.config.use_normals:
        raise ValueError(f"{path}: the model card says use_normals={card_normals} "
                         f"but the checkpoint's config says {network.config.use_normals}")
    return network.to(device).eval()


def load_model(name_or_path: str | Path, device: str | torch.device | None = None, *,
               weights_dir: str | Path | None = None, sha256: str | None = None,
               shared: bool = False) -> VisibilityNetwork:
    """Loads a shipped model by name or a safetensors checkpoint by path.

    A string is a model name when the card lists it; otherwise, and for a
    ``Path``, it is a file path.

    Args:
        name_or_path: a model name from the card (e.g. ``"default"``) or the
            path of a ``.safetensors`` file.
        device: torch device for the network (default: CPU).
        weights_dir: folder of the model card for names (default: the shipped
            ``o3dvis/weights``).
        sha256: expected digest of a file given by path (the card's digest is
            used for names and for files that the card next to them lists).
        shared: the network loaded (and checked) once per process and device, shared by every
            caller until the file or the card next to it is written anew, or someone changes the
            network (its weights, its device, its training mode: the next call loads it anew).
            False, the default, gives a network of one's own, e.g. to train.

    Returns:
        The network in eval mode on ``device``.

    Raises:
        FileNotFoundError: the card or the checkpoint file is missing.
        ValueError: unknown model name (the message lists the available ones),
            sha256 mismatch, tampered, truncated or non-safetensors file.
        TypeError: ``name_or_path`` is neither a string nor a path.
    """
    device = torch_device(device)
    path, expected, entry = _checkpoint(name_or_path, weights_dir, sha256)
    if not shared:
        return _load_checked(path, expected, entry, device)
    key = str(path.resolve()), expected, str(device)
    stats = _stats(path) + _stats(path.parent / CARD_NAME)
    with _SHARED_LOCK:
        kept = _SHARED.get(key)
        if kept is None or kept[0] != stats or kept[1].training or not kept[2].holds([kept[1]]):
            network = _load_checked(path, expected, entry, device)
            kept = _SHARED[key] = stats, network, WeightsState([network])
        return kept[1]


def is_shared(network: VisibilityNetwork) -> bool:
    """Whether ``network`` is one that ``load_model(..., shared=True)`` hands out."""
    with _SHARED_LOCK:
        return any(kept[1] is network for kept in _SHARED.values())


def _stats(path: Path) -> tuple:
    """What tells a file written anew: its inode, size and times (None for a missing file)."""
    try:
        stat = path.stat()
    except OSError:
        return (None,)
    return stat.st_ino, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns


def _checkpoint(name_or_path: str | Path, weights_dir: str | Path | None, sha256: str | None
                ) -> tuple[Path, str | None, dict | None]:
    """``(file, expected sha256 or None, card entry or None)`` of a model name or path (see
    :func:`load_model`)."""
    if not isinstance(name_or_path, (str, Path)):
        raise TypeError(f"name_or_path must be a model name or a path, got {type(name_or_path).__name__}")
    looks_like_path = isinstance(name_or_path, Path) or any(
        c in name_or_path for c in "/\\") or name_or_path.endswith(".safetensors")
    if not looks_like_path:
        card_dir = Path(WEIGHTS_DIR if weights_dir is None else weights_dir)
        try:
            models = read_model_card(card_dir)["models"]
        except FileNotFoundError:
            if not Path(name_or_path).is_file():
                raise
            models = {}
        if name_or_path in models:
            entry = models[name_or_path]
            path = card_dir / entry["file"]
            if not path.is_file():
                raise FileNotFoundError(f"model {name_or_path!r}: checkpoint {path} listed in "
                                        f"{card_dir / CARD_NAME} is missing")
            return path, entry["sha256"], entry
        if not Path(name_or_path).is_file():
            names = ", ".join(sorted(models)) or "none"
            raise ValueError(f"unknown model {name_or_path!r}; available: {names}")
    path = Path(name_or_path)
    entry = _card_entry_for(path) if path.is_file() else None
    return path, (sha256 if sha256 is not None else (entry["sha256"] if entry else None)), entry
