"""Installing a trained checkpoint as a shipped model, with its model-card entry."""

from __future__ import annotations

import csv
import json
import shutil
from collections import Counter
from pathlib import Path

from .models import CARD_NAME, WEIGHTS_DIR, file_sha256
from .nn.network import VisibilityNetwork

__all__ = ["publish", "licence_summary"]


def licence_summary(manifest: str | Path) -> list[dict]:
    """Training meshes per source and licence statement, from a ``MANIFEST.csv``."""
    with open(manifest, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("pool") == "train"]
    counts = Counter((r["source_repo"], r["license_if_stated"]) for r in rows)
    return [{"source": s, "licence": lic, "meshes": n} for (s, lic), n in sorted(counts.items())]


def _run_summary(run: Path) -> dict:
    config = json.loads((run / "config.json").read_text())
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines() if line.strip()]
    vals = [r for r in log if "val_acc" in r]
    steps = max((r["step"] for r in log), default=0)
    return {"train_config": config, "steps_run": steps,
            "validation_curve": [{"step": r["step"], "val_acc": round(r["val_acc"], 5)} for r in vals],
            "train_seconds_last_segment": round(max((r["time"] for r in log), default=0.0), 1)}


def publish(checkpoint: str | Path, name: str, run: str | Path | None = None,
            manifest: str | Path | None = None, eval_json: str | Path | None = None,
            command: str | None = None, weights_dir: str | Path | None = None) -> dict:
    """Copies ``checkpoint`` to ``weights_dir/<name>.safetensors`` and records it in the card.

    Args:
        checkpoint: a safetensors file written by ``VisibilityNetwork.save``.
        name: the model's name (``"default"``, ``"normals"``).
        run: the training run folder, whose config and log go into the card.
        manifest: the training meshes' ``MANIFEST.csv`` (licences).
        eval_json: results of ``o3dvis eval`` to record as the validation table.
        command: the training command line.
        weights_dir: target folder (default: the package's weights folder).

    Returns:
        The card entry.
    """
    weights = Path(weights_dir or WEIGHTS_DIR)
    weights.mkdir(parents=True, exist_ok=True)
    net = VisibilityNetwork.load(checkpoint)
    target = weights / f"{name}.safetensors"
    shutil.copyfile(checkpoint, target)
    entry = {"file": target.name, "sha256": file_sha256(target), "bytes": target.stat().st_size,
             "use_normals": net.config.use_normals, "parameters": net.num_parameters(),
             "architecture": json.loads(json.dumps(net.config.__dict__))}
    if run:
        entry.update(_run_summary(Path(run)))
    if command:
        entry["training_command"] = command
    if manifest:
        entry["training_data_licences"] = licence_summary(manifest)
    if eval_json:
        entry["validation"] = json.loads(Path(eval_json).read_text())
    card_path = weights / CARD_NAME
    card = json.loads(card_path.read_text()) if card_path.exists() else {"models": {}}
    card["models"][name] = entry
    card_path.write_text(json.dumps(card, indent=1) + "\n")
    return entry
