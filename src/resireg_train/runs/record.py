"""``results.json``: a run's record, read and merged without Lightning (the entry points write
it before anything heavy is imported). The format is described in :mod:`resireg_train.runs.tracking`.

The file is strict JSON (RFC 8259), which has no NaN or infinity: Python's ``json`` would
write them as bare ``NaN`` / ``Infinity``, which strict parsers (``jq``, JavaScript's
``JSON.parse``, Go, serde) reject. :func:`update_results` writes such a value as ``null`` and
says why in the record: ``non_finite`` holds the reason and, per kind (``NaN``,
``Infinity``, ``-Infinity``), the JSON Pointers (RFC 6901) of the values it replaced, e.g.
``/per_class_iou/bb/wall`` or ``/final/val~1ovss~1ade20k~1miou_bb`` (``~1`` is a ``/`` inside a
key). :func:`read_results` puts the numbers back, so Python readers see what was recorded.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from resireg.integrity import atomic_write

__all__ = [
    "NON_FINITE",
    "RESULTS_FILE",
    "flat",
    "metric_mode",
    "read_results",
    "strict_json",
    "update_results",
]

RESULTS_FILE = "results.json"
#: The record's field that lists the non-finite values written as ``null``.
NON_FINITE = "non_finite"
_REASON = (
    "strict JSON has no NaN or infinity, so these values are null in this file. NaN is an "
    "undefined value, 0/0: e.g. the IoU of a class that neither the ground truth nor the "
    "prediction holds (excluded from the mIoU), or a score over no image. Keys are JSON "
    "Pointers (RFC 6901; ~1 stands for / in a key); resireg_train.runs.record.read_results "
    "restores the numbers"
)


def metric_mode(name: str) -> str | None:
    """``"min"`` for losses, ``"max"`` for the scores of the metric table
    (:func:`resireg.specs.metrics.direction`) and retrieval accuracies, else ``None``."""
    from resireg.specs.metrics import direction

    found = direction(name)
    if found is None and "retrieval" in name.lower():
        return "max"
    return found


def flat(text: str) -> str:
    """A multi-line message (``invalid config:`` and one indented line per key) as one line:
    ``invalid config: a=1: expected ...; b=2: expected ...``, for a table row or a list."""
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    if len(lines) <= 1:
        return lines[0] if lines else ""
    return f"{lines[0]} {'; '.join(lines[1:])}"


def _pointer(path: tuple[Any, ...]) -> str:
    """The RFC 6901 JSON Pointer of ``path`` (keys and list indices)."""
    return "".join("/" + str(p).replace("~", "~0").replace("/", "~1") for p in path)


def _kind(value: float) -> str:
    return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")


def strict_json(record: dict[str, Any]) -> tuple[dict[str, Any], dict[str, list[str]]]:
    """``record`` with every non-finite float replaced by ``None``, and the JSON Pointers of
    the replaced values by kind (``{"NaN": ["/per_class_iou/bb/wall"], ...}``)."""
    found: dict[str, list[str]] = {}

    def clean(value: Any, path: tuple[Any, ...]) -> Any:
        if isinstance(value, float) and not math.isfinite(value):
            found.setdefault(_kind(value), []).append(_pointer(path))
            return None
        if isinstance(value, dict):
            return {k: clean(v, (*path, k)) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v, (*path, i)) for i, v in enumerate(value)]
        return value

    return clean(record, ()), found


def _restore(record: dict[str, Any], found: dict[str, Any]) -> None:
    """Put the values :func:`strict_json` replaced back into ``record`` (in place)."""
    numbers = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}
    for kind, pointers in found.items():
        if kind not in numbers or not isinstance(pointers, list):
            continue  # the reason, or a field this version does not know
        for pointer in pointers:
            parts = [p.replace("~1", "/").replace("~0", "~") for p in str(pointer).split("/")[1:]]
            node: Any = record
            try:
                for part in parts[:-1]:
                    node = node[int(part)] if isinstance(node, list) else node[part]
                last = parts[-1]
                if isinstance(node, list):
                    node[int(last)] = numbers[kind]
                elif last in node:
                    node[last] = numbers[kind]
            except (KeyError, IndexError, ValueError, TypeError):
                continue  # the value is no longer there (the record was edited)


def read_results(directory: str | os.PathLike) -> dict[str, Any]:
    """The record of ``<directory>/results.json`` (``{}`` if absent), non-finite values
    restored (``null`` listed in ``non_finite`` -> NaN / inf; the field itself dropped)."""
    path = Path(directory) / RESULTS_FILE
    if not path.is_file():
        return {}
    record = json.loads(path.read_text())
    found = record.pop(NON_FINITE, None)
    if isinstance(found, dict):
        _restore(record, found)
    return record


def update_results(directory: str | os.PathLike, **fields: Any) -> dict[str, Any]:
    """Merge ``fields`` into ``<directory>/results.json`` (written atomically, strict JSON:
    see the module docstring); returns the merged record as Python values (NaN included)."""
    directory = Path(directory)
    results = {**read_results(directory), **fields}
    results.pop(NON_FINITE, None)
    written, found = strict_json(results)
    if found:
        written[NON_FINITE] = {"reason": _REASON, **found}
    directory.mkdir(parents=True, exist_ok=True)
    text = json.dumps(written, indent=2, allow_nan=False)
    atomic_write(directory / RESULTS_FILE, text, what="run record")
    return results
