"""The evaluation protocol a run followed, recorded in ``results.json`` (``protocol``) and
printed by ``resireg-report`` under each table (docs/protocol.md).

:func:`protocol_record` is the one rule that picks, from a run's parameters, the settings a
score depends on beyond the model: the dataset entry's keys its task records (the task table's
:attr:`~resireg_train.evaluation.specs.TaskSpec.protocol_keys`: for ``task=scannet3d`` those of
``conf/dataset/scannet.yaml``; for ``task=ovss`` the shorter side, the resize rule, ...), the
run parameters it records (:attr:`~resireg_train.evaluation.specs.TaskSpec.protocol_params`: ``ovss``'s
softmax temperature), what the built dataset fills where the entry has none (its
``reduce_zero_label``, class list and prompt template set) and (where the encoder config has one)
the encoder's ``dense_path``. Its name is the dataset entry's ``protocol`` key (or the task and
dataset kind).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from resireg_train.evaluation.specs import find_task

__all__ = ["protocol_record", "protocol_text"]


def protocol_record(params: Mapping[str, Any], dataset: Any = None) -> dict[str, Any]:
    """``{"name": ..., "settings": {...}}`` of a ``resireg-eval`` run (module docstring).

    Args:
        params: the run's ``params`` (``task``, ``dataset``, ``encoder``, the task's
            ``protocol_params``).
        dataset: the built segmentation set (the 2D task passes it): its ``reduce_zero_label``,
            class list and prompt template set fill the settings its entry does not name.
    """
    task = str(params.get("task") or "ovss")
    entry = find_task(task)
    keys, recorded = (entry.protocol_keys, entry.protocol_params) if entry else ((), ())
    spec = params.get("dataset") or {}
    encoder = params.get("encoder") or {}
    settings = {k: spec[k] for k in keys if k in spec}
    settings.update({k: params.get(k) for k in recorded})
    if dataset is not None:
        from resireg.ovss import template_label

        settings.pop("templates", None)  # the built set's, last, by open_clip's constant and count
        settings.setdefault("reduce_zero_label", bool(dataset.reduce_zero_label))
        # the class-name file (conf/classes/) or the kind's built-in list, and the class count
        settings["classes"] = f"{spec.get('classes') or spec.get('kind')} ({len(dataset.classes)})"
        settings["templates"] = template_label(dataset.templates)
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
