"""Installing a trained checkpoint as a shipped model, with its model-card entry.

The card records paths relative to the data root (the folder the training
commands ran in), never absolute paths of the machine a model was trained on.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
from collections import Counter
from pathlib import Path

from ..models import CARD_NAME, WEIGHTS_DIR, file_sha256, load_model

__all__ = ["publish", "licence_summary", "portable_path", "portable_paths", "validation_table"]

_VALIDATION_FIELDS = ("method", "param", "points", "noise", "accuracy", "fn_rate", "fp_rate")


def portable_path(path: str | Path, root: str | Path) -> str:
    """A path as a card or a checkpoint may record it: never an absolute path.

    Args:
        path: a file or folder, absolute or relative.
        root: the data root that relative paths are taken from.

    Returns:
        ``path`` unchanged when it is relative; relative to ``root`` when it
        lies below it; otherwise only its last component.
    """
    path = Path(path)
    if not path.is_absolute():
        return path.as_posix()
    root = Path(os.path.abspath(root))
    try:
        return Path(os.path.abspath(path)).relative_to(root).as_posix()
    except ValueError:
        return path.name


def portable_paths(value, root: str | Path):
    """``value`` with every string that is an absolute path made portable (see :func:`portable_path`).

    Args:
        value: JSON-like data (dicts, lists, strings, numbers).
        root: the data root.

    Returns:
        A copy of ``value``.
    """
    if isinstance(value, dict):
        return {k: portable_paths(v, root) for k, v in value.items()}
    if isinstance(value, list):
        return [portable_paths(v, root) for v in value]
    if isinstance(value, str) and os.path.isabs(value):
        return portable_path(value, root)
    return value


def licence_summary(manifest: str | Path) -> list[dict]:
    """Training meshes per source and licence statement, from a ``MANIFEST.csv``."""
    with open(manifest, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("pool") == "train"]
    counts = Counter((r["source_repo"], r["license_if_stated"]) for r in rows)
    return [{"source": s, "licence": lic, "meshes": n} for (s, lic), n in sorted(counts.items())]


def validation_table(report: dict, root: str | Path) -> dict:
    """The card's validation table from an ``o3dvis eval`` report: one row per method and column.

    Args:
        report: the JSON that ``o3dvis eval -o`` writes.
        root: the data root, for the settings' data path.

    Returns:
        ``{"settings": ..., "results": [...]}`` without the per-file and per-category detail.

    Raises:
        ValueError: a report of ``o3dvis eval --scenes`` (results per sampling): the card's
            table is the objects' one.
    """
    if not isinstance(report.get("results"), list):
        raise ValueError("the validation table is the objects' one (o3dvis eval without --scenes); this "
                         "report holds no list of results (a --scenes report has them per sampling)")
    return {"settings": portable_paths(report["settings"], root),
            "results": [{k: row[k] for k in _VALIDATION_FIELDS} for row in report["results"]]}


def _run_summary(run: Path, root: Path) -> dict:
    config = json.loads((run / "config.json").read_text())
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    vals = [r for r in log if "val_acc" in r]
    steps = max((r["step"] for r in log), default=0)
    return {"train_config": portable_paths(config, root), "steps_run": steps,
            "validation_curve": [{"step": r["step"], "val_acc": round(r["val_acc"], 5)} for r in vals],
            "train_seconds_last_segment": round(max((r["time"] for r in log), default=0.0), 1)}


def publish(checkpoint: str | Path, name: str, run: str | Path | None = None,
            manifest: str | Path | None = None, eval_json: str | Path | None = None,
            commands: list[str] | None = None, weights_dir: str | Path | None = None,
            root: str | Path | None = None) -> dict:
    """Copies ``checkpoint`` to ``weights_dir/<name>.safetensors`` and records it in the card.

    Args:
        checkpoint: a safetensors file written by ``VisibilityNetwork.save``.
        name: the model's name (``"default"``, ``"normals"``).
        run: the training run folder, whose config and log go into the card.
        manifest: the training meshes' ``MANIFEST.csv`` (licences).
        eval_json: results of ``o3dvis eval``, recorded as the card's validation table
            (one for the whole card: the newest replaces the one before).
        commands: the commands that made the model, oldest first.
        weights_dir: target folder (default: the package's weights folder).
        root: the data root that the card's paths are made relative to
            (default: the current directory).

    Returns:
        The card entry.
    """
    root = Path(os.getcwd() if root is None else root)
    net = load_model(Path(checkpoint))
    validation = validation_table(json.loads(Path(eval_json).read_text()), root) if eval_json else None
    weights = Path(weights_dir or WEIGHTS_DIR)
    weights.mkdir(parents=True, exist_ok=True)
    target = weights / f"{name}.safetensors"
    shutil.copyfile(checkpoint, target)
    entry = {"file": target.name, "sha256": file_sha256(target), "bytes": target.stat().st_size,
             "use_normals": net.config.use_normals, "parameters": net.num_parameters(),
             "architecture": json.loads(json.dumps(net.config.__dict__))}
    if run:
        entry.update(_run_summary(Path(run), root))
    if commands:
        entry["training_commands"] = list(commands)
    if manifest:
        entry["training_data_licences"] = licence_summary(manifest)
    card_path = weights / CARD_NAME
    card = json.loads(card_path.read_text()) if card_path.exists() else {"models": {}}
    card["models"][name] = entry
    if validation:
        card["validation"] = validation
    card_path.write_text(json.dumps(card, indent=1) + "\n")
    return entry
