"""The evaluation protocol a run followed, recorded in ``results.json`` (``protocol``) and
printed by ``resireg-report`` under each table (docs/protocol.md).

:func:`protocol_record` is the one rule that picks, from a run's parameters, the settings a
score depends on beyond the model: for ``task=scannet3d`` the dataset entry's protocol keys
(:data:`MAPPING_KEYS`, ``conf/dataset/scannet.yaml``); for ``task=ovss`` the shorter side, the
resize rule, the prompt templates, the softmax temperature, ``reduce_zero_label``, the class
list and (where the encoder config has one) the encoder's ``dense_path``. Its name is the
dataset entry's ``protocol`` key (or the task and dataset kind).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["MAPPING_KEYS", "OVSS_KEYS", "protocol_record", "protocol_text"]

#: The 3D task's protocol keys of a ScanNet entry (docs/protocol.md section 4).
MAPPING_KEYS = (
    "frame_skip", "image_size", "short_side", "resize", "intrinsics", "gt_resolution",
    "gt_unlabelled", "points", "lattice", "voxel_size", "knn", "prediction_threshold",
    "prompt_denoising", "metric", "class_names", "classes_to_ignore",
)  # fmt: skip
#: The 2D task's protocol keys of a segmentation entry, where the entry has them (docs/protocol.md
#: section 1); the others are taken from the built dataset (:func:`protocol_record`).
OVSS_KEYS = ("short_side", "resize", "templates", "reduce_zero_label", "classes", "sliding_window")


def protocol_record(params: Mapping[str, Any], dataset: Any = None) -> dict[str, Any]:
    """``{"name": ..., "settings": {...}}`` of a ``resireg-eval`` run (module docstring).

    Args:
        params: the run's ``params`` (``task``, ``dataset``, ``encoder``, ``temperature``).
        dataset: for ``task=ovss``, the built segmentation set: its ``reduce_zero_label`` and
            class list fill the settings its entry does not name.
    """
    task = str(params.get("task") or "ovss")
    spec = params.get("dataset") or {}
    encoder = params.get("encoder") or {}
    if task == "scannet3d":
        settings = {k: spec[k] for k in MAPPING_KEYS if k in spec}
    else:
        settings = {k: spec[k] for k in OVSS_KEYS if k in spec}
        settings["temperature"] = params.get("temperature")
        if dataset is not None:
            from resireg.ovss import TEMPLATES

            settings.setdefault("reduce_zero_label", bool(dataset.reduce_zero_label))
            settings.setdefault("classes", f"{spec.get('kind')} ({len(dataset.classes)})")
            settings.setdefault(
                "templates", f"open_clip OPENAI_IMAGENET_TEMPLATES ({len(TEMPLATES)})"
            )
    if "dense_path" in encoder:
        settings["encoder.dense_path"] = encoder["dense_path"]
    name = spec.get("protocol") or f"{task}/{spec.get('kind', '?')}"
    return {"name": str(name), "settings": settings}


def _value(v: Any) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return "null" if v is None else str(v)


def protocol_text(record: Mapping[str, Any]) -> str:
    """One line: ``<name>: key=value, key=value, ...``."""
    settings = record.get("settings") or {}
    body = ", ".join(f"{k}={_value(v)}" for k, v in settings.items())
    return f"{record.get('name', '?')}: {body}" if body else str(record.get("name", "?"))
