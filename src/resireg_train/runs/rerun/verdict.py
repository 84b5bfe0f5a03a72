"""The verdict on a run and its rerun (:func:`compare`): ``identical`` (every score bitwise
equal and the outputs' digests equal), ``within tolerance`` (every score within ``--rtol`` of
the run's, ``provenance.rerun_rtol`` by default) or ``differs`` (the scores that moved, by how
much, and the provenance fields that differ). The scores are the record's ``final`` and
``best`` values, the per-class IoU and a map's counts (:func:`scores`); timings (``seconds``,
``provenance.time``) and system metrics are not. The outputs are the files a run makes: an
export's weights and configs, a map's tensors and PLY (:func:`outputs`).

Imported by :mod:`~resireg_train.runs.rerun.command`.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from resireg.specs.tree import MISSING, flatten
from resireg_train.runs.diff import diff_runs
from resireg_train.runs.index import Run
from resireg_train.runs.rerun.drift import UNCOMPARED, short

__all__ = ["Verdict", "compare", "outputs", "scores"]


#: What ``final`` holds that is not a score: timings and system metrics.
_NOT_SCORES = ("time/", "system/", "perf/")


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def scores(record: Mapping[str, Any]) -> dict[str, float]:
    """A record's scores (module docstring): ``final/<k>``, ``best/<k>`` and its epoch,
    ``per_class_iou/<variant>/<class>`` and a map's counts; NaN where the record holds one."""
    from resireg_train.record.trackers.base import map_counts

    found: dict[str, float] = {}
    for key, value in (record.get("final") or {}).items():
        if _number(value) and not str(key).startswith(_NOT_SCORES):
            found[f"final/{key}"] = value
    for key, best in (record.get("best") or {}).items():
        if isinstance(best, Mapping) and _number(best.get("value")):
            found[f"best/{key}"] = best["value"]
            if _number(best.get("epoch")):
                found[f"best/{key}/epoch"] = best["epoch"]
    for key, value in flatten(record.get("per_class_iou") or {}).items():
        if _number(value):
            found[f"per_class_iou/{key.replace('.', '/')}"] = value
    for key, value in map_counts(record).items():
        found[key] = value
    return found


def outputs(record: Mapping[str, Any], folder: Path) -> dict[str, str]:
    """The SHA-256 of the files a run made: its export's weights and configs
    (``export/<file>``), a map's tensors (``map/tensors[<n>]``: their names are drawn per
    save, their content is the map) and ``map.ply``."""
    from resireg.integrity import sha256_file
    from resireg_train.record.provenance.inputs import export_identity

    found = {}
    export = record.get("export")
    if isinstance(export, str) and Path(export).is_dir():
        for name, digest in (export_identity(export)["files"] or {}).items():
            found[f"export/{name}"] = digest
    smap = record.get("map") if isinstance(record.get("map"), Mapping) else {}
    if smap:
        tensors = sorted(sha256_file(p) for p in (folder / "map").glob("*.safetensors"))
        found.update({f"map/tensors[{i}]": d for i, d in enumerate(tensors)})
        ply = folder / "map.ply"
        if ply.is_file():
            found["map.ply"] = sha256_file(ply)
    return found


def _bits(value: float) -> bytes:
    return struct.pack("<d", float(value)) if not math.isnan(value) else b"nan"


@dataclass
class Verdict:
    """The comparison of a run and its rerun (:func:`compare`)."""

    kind: str  # "identical", "within tolerance", "differs"
    rtol: float
    compared: int
    moved: list[tuple[str, Any, Any, str]] = field(default_factory=list)  # beyond rtol
    nudged: list[tuple[str, Any, Any, str]] = field(default_factory=list)  # within rtol
    outputs: list[str] = field(default_factory=list)  # output files whose digest differs
    provenance: list[tuple[str, Any, Any]] = field(default_factory=list)
    config: list[tuple[str, Any, Any]] = field(default_factory=list)
    status: tuple[str, str] = ("completed", "completed")

    def record(self) -> dict[str, Any]:
        """What the new run's record keeps of it (``rerun.verdict``, ``rerun.moved``)."""
        return {"verdict": self.kind, "rtol": self.rtol, "scores": self.compared,
                "moved": {k: {"run": a, "rerun": b, "change": c} for k, a, b, c in self.moved},
                "outputs_differ": self.outputs}  # fmt: skip

    def lines(self) -> list[str]:
        """The verdict as printed: one line, then what supports it."""
        if self.kind == "identical":
            head = (f"verdict: identical ({self.compared} scores bitwise equal"
                    f"{', outputs equal' if not self.outputs else ''})")  # fmt: skip
        elif self.kind == "within tolerance":
            head = (f"verdict: within tolerance ({len(self.nudged)} of {self.compared} scores "
                    f"moved, none by more than rtol={self.rtol:g})")  # fmt: skip
        else:
            reason = (f"status {self.status[0]} -> {self.status[1]}" if
                      self.status[0] != self.status[1] else
                      f"{len(self.moved)} of {self.compared} scores moved beyond "
                      f"rtol={self.rtol:g}")  # fmt: skip
            head = f"verdict: differs ({reason})"
        lines = [head]
        if self.moved:
            lines.append("scores that moved:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)} ({c})" for k, a, b, c in self.moved]
        if self.nudged and self.kind != "identical":
            lines.append(f"scores within rtol={self.rtol:g}:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)} ({c})" for k, a, b, c in self.nudged]
        if self.outputs:
            lines.append("outputs whose SHA-256 differs: " + ", ".join(self.outputs))
        if self.provenance and self.kind != "identical":
            lines.append("provenance that differs:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)}" for k, a, b in self.provenance]
        if self.config:
            lines.append("config that differs:")
            lines += [f"  {k}: {_shown(a)} -> {_shown(b)}" for k, a, b in self.config]
        return lines


def _shown(value: Any, width: int = 100) -> str:
    """A value as a verdict shows it: a float to 8 digits, a long one cut at ``width``."""
    if value is None or value is MISSING:
        return "<absent>"
    if isinstance(value, float):
        return f"{value:.8g}"
    text = short(value)
    return text if len(text) <= width else f"{text[: width - 1]}…"


def _change(a: Any, b: Any) -> str:
    if not (_number(a) and _number(b)):
        return "absent on one side"
    if math.isnan(a) or math.isnan(b):
        return "NaN on one side"
    delta = b - a
    relative = f", {delta / abs(a):+.3%}" if a else ""
    return f"{delta:+.6g}{relative}"


def compare(a: Run, b: Run, rtol: float) -> Verdict:
    """The verdict on run ``a`` and its rerun ``b`` (module docstring): every score of either
    compared bitwise, then within ``rtol`` (relative to the larger magnitude), the outputs'
    digests, and the provenance and config that differ (:func:`resireg_train.runs.index.
    diff_runs`: what is the same for every rerun of a run is left out)."""
    sa, sb = scores(a.results), scores(b.results)
    keys = sorted(set(sa) | set(sb))
    moved, nudged = [], []
    for key in keys:
        x, y = sa.get(key), sb.get(key)
        if x is not None and y is not None and _bits(x) == _bits(y):
            continue
        row = (key, x, y, _change(x, y))
        close = (x is not None and y is not None and not math.isnan(x) and not math.isnan(y)
                 and abs(x - y) <= rtol * max(abs(x), abs(y)))  # fmt: skip
        (nudged if close else moved).append(row)
    oa, ob = outputs(a.results, a.path), outputs(b.results, b.path)
    differ = sorted(k for k in set(oa) | set(ob) if oa.get(k) != ob.get(k))
    status = (str(a.results.get("status")), str(b.results.get("status")))
    if moved or status[0] != status[1]:
        kind = "differs"
    elif nudged or differ:
        kind = "within tolerance"
    else:
        kind = "identical"
    found = diff_runs(a, b)
    config = [r for r in found["config"] if r[0].split(".")[0] not in UNCOMPARED]
    return Verdict(kind, rtol, len(keys), moved, nudged, differ, found["provenance"], config,
                   status)  # fmt: skip
