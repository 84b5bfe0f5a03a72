"""The evaluation settings an export records (``resireg_eval.json``): written by the training
callback, read by ``resireg-eval`` before anything heavy is imported."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg.integrity import atomic_write
from resireg.specs.variants import PARAM_VARIANTS

__all__ = [
    "SETTINGS_FILE", "SETTING_KEYS", "VARIANT_PARAM_KEYS", "load_settings", "save_settings",
]  # fmt: skip

#: The file of an export recording the evaluation settings its training run scored it with.
SETTINGS_FILE = "resireg_eval.json"
#: The ``resireg`` config group's blocks of variant parameters (``calib``, ``lite``, ``full``:
#: the variants of the table, resireg.specs.variants, that take parameters).
VARIANT_PARAM_KEYS = PARAM_VARIANTS
#: Which settings it records (the ``resireg`` group and the pass settings of resireg-eval).
SETTING_KEYS = ("variants", *VARIANT_PARAM_KEYS, "batch_size", "precision", "temperature")


def save_settings(directory: str | os.PathLike, settings: Mapping[str, Any]) -> Path:
    """Record ``settings`` (keys :data:`SETTING_KEYS`) in ``<directory>/resireg_eval.json``."""
    unknown = set(settings) - set(SETTING_KEYS)
    if unknown:
        raise ValueError(f"unknown evaluation settings {sorted(unknown)}; known: {SETTING_KEYS}")
    return atomic_write(
        Path(directory) / SETTINGS_FILE, json.dumps(dict(settings), indent=2), "settings"
    )


def load_settings(directory: str | os.PathLike) -> dict[str, Any]:
    """The settings :func:`save_settings` recorded in ``directory`` (``{}`` when none)."""
    path = Path(directory) / SETTINGS_FILE
    return json.loads(path.read_text()) if path.is_file() else {}
