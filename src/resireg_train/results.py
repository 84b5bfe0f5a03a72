"""``results.json``: a run's record, read and merged without Lightning (the entry points write
it before anything heavy is imported). The format is described in :mod:`resireg_train.tracking`."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from resireg_train.files import write_atomic

__all__ = ["RESULTS_FILE", "metric_mode", "read_results", "update_results"]

RESULTS_FILE = "results.json"
_HIGHER = ("miou", "iou", "acc", "retrieval")


def metric_mode(name: str) -> str | None:
    """``"min"`` for losses, ``"max"`` for accuracy / retrieval / IoU metrics, else ``None``."""
    lower = name.lower()
    if "loss" in lower:
        return "min"
    if any(tag in lower for tag in _HIGHER):
        return "max"
    return None


def read_results(directory: str | os.PathLike) -> dict[str, Any]:
    path = Path(directory) / RESULTS_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def update_results(directory: str | os.PathLike, **fields: Any) -> dict[str, Any]:
    """Merge ``fields`` into ``<directory>/results.json`` (written atomically)."""
    directory = Path(directory)
    results = {**read_results(directory), **fields}
    directory.mkdir(parents=True, exist_ok=True)
    write_atomic(directory / RESULTS_FILE, json.dumps(results, indent=2), what="run record")
    return results
