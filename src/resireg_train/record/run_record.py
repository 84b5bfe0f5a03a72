"""``results.json``, a run's record, and :class:`RunRecord`, its one owner.

A job (``resireg-train``, ``resireg-eval``, ``resireg-map``, each job of a multirun or search)
holds one :class:`RunRecord` for its run folder from start to end: the job wrapper
(:func:`resireg_train.cli.job.run_task`) creates it, :meth:`RunRecord.start` writes the status
``running`` and the provenance and starts the run's trackers (each tracker that needs a
network is checked first), the job body adds its fields through :meth:`RunRecord.update`, and
:meth:`RunRecord.finish` writes the final status (``completed`` whenever the body returns) and
the provenance's end, then hands the record to the trackers. Nothing else writes the file;
readers of many records (``resireg-runs``, ``resireg-report``) use :meth:`RunRecord.read`.
The fields are listed in docs/runs.md#run-records-and-faults.

The file is strict JSON (RFC 8259), which has no NaN or infinity: Python's ``json`` would
write them as bare ``NaN`` / ``Infinity``, which strict parsers (``jq``, JavaScript's
``JSON.parse``, Go, serde) reject. :meth:`RunRecord.update` writes such a value as ``null`` and
says why in the record: ``non_finite`` holds the reason and, per kind (``NaN``,
``Infinity``, ``-Infinity``), the JSON Pointers (RFC 6901) of the values it replaced, e.g.
``/per_class_iou/bb/wall`` or ``/final/val~1ovss~1ade20k~1miou_bb`` (``~1`` is a ``/`` inside a
key). :meth:`RunRecord.read` puts the numbers back, so Python readers see what was recorded.
Every string is written with the password of any URL in it masked
(:func:`resireg.secrets.mask_text`): a command line or a config value holding
``http://user:pass@host`` is recorded as ``http://user:***@host``.

While the run runs, a background thread of the job rewrites the record's ``heartbeat``
(:mod:`resireg_train.record.heartbeat`). Writes from the job's threads are serialised (one lock
per folder).
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from resireg.errors import ResiregError
from resireg.integrity import atomic_write
from resireg.secrets import mask_text
from resireg_train.record.heartbeat import HEARTBEAT, Heartbeat
from resireg_train.record.masking import mask_saved_configs
from resireg_train.record.settings import RecordSettings

__all__ = [
    "NON_FINITE",
    "RESULTS_FILE",
    "RecordError",
    "RunRecord",
    "enclosing_run",
    "flat",
    "metric_mode",
    "strict_json",
    "target_problem",
]

RESULTS_FILE = "results.json"
#: The record's field that lists the non-finite values written as ``null``.
NON_FINITE = "non_finite"
_REASON = (
    "strict JSON has no NaN or infinity, so these values are null in this file. NaN is an "
    "undefined value, 0/0: e.g. the IoU of a class that neither the ground truth nor the "
    "prediction holds (excluded from the mIoU), or a score over no image. Keys are JSON "
    "Pointers (RFC 6901; ~1 stands for / in a key); resireg_train.record.run_record.RunRecord.read "
    "restores the numbers"
)

#: The fields every reader relies on, with the JSON types they may hold (``None``: null). A
#: ``results.json`` whose fields do not fit (another tool's file, a JSON list) is not a run
#: record (:class:`RecordError`).
_FIELDS: dict[str, tuple[type, ...]] = {
    "status": (str,),
    "name": (str, int, float, type(None)),
    "error": (str, type(None)),
    "output_dir": (str, type(None)),
    "export": (str, type(None)),
    "final": (dict,),
    "best": (dict,),
    "history": (list,),
    "params": (dict,),
    "encoder": (dict,),
    "tracking": (dict,),
    "provenance": (dict,),
    "system": (dict,),
    HEARTBEAT: (dict,),
}
_PROVENANCE: dict[str, tuple[type, ...]] = {
    "run_id": (str,),
    "cli": (str, type(None)),
    **{k: (dict, type(None)) for k in ("code", "environment", "machine", "time", "seeds",
                                       "data", "models")},
}  # fmt: skip


class RecordError(ResiregError, ValueError):
    """A ``results.json`` that is not a run record: not JSON, not a JSON object, or a field of
    another type than a run record's (the message names the file and the field)."""


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
    """``record`` with every non-finite float replaced by ``None`` and every string's URL
    passwords masked, and the JSON Pointers of the replaced numbers by kind
    (``{"NaN": ["/per_class_iou/bb/wall"], ...}``)."""
    found: dict[str, list[str]] = {}

    def clean(value: Any, path: tuple[Any, ...]) -> Any:
        if isinstance(value, float) and not math.isfinite(value):
            found.setdefault(_kind(value), []).append(_pointer(path))
            return None
        if isinstance(value, str):
            return mask_text(value)
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


def _type_name(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean",
            type(None): "null"}.get(type(value), "a number")  # fmt: skip


def _check_shape(record: Any, path: Path) -> dict[str, Any]:
    """``record`` if it has a run record's shape (:data:`_FIELDS`), else :class:`RecordError`."""
    if not isinstance(record, dict):
        raise RecordError(f"{path}: not a run record (a JSON document holding "
                          f"{_type_name(record)}, not an object)")  # fmt: skip
    if "status" not in record:
        raise RecordError(f"{path}: not a run record (no 'status' field; another tool's file?)")
    blocks = ((_FIELDS, "", record), (_PROVENANCE, "provenance.", record.get("provenance") or {}))
    for fields, where, node in blocks:
        for key, types in fields.items():
            if key in node and not isinstance(node[key], types):
                raise RecordError(
                    f"{path}: not a run record ('{where}{key}' holds {_type_name(node[key])})"
                )
    return record


#: One lock per record file of this process: the job's threads (its body, the per-epoch
#: callback, the heartbeat) read, merge and write the file one at a time.
_LOCKS: dict[str, threading.Lock] = {}
_LOCKS_GUARD = threading.Lock()


def _lock(path: Path) -> threading.Lock:
    with _LOCKS_GUARD:
        return _LOCKS.setdefault(str(path.resolve()), threading.Lock())


def target_problem(path: Path, folder: bool) -> str | None:
    """Why a command cannot write its output at ``path`` (``None`` when it can), checked
    before any work: a new run's folder (``folder``) must be absent or empty (another run's
    otherwise) and lie inside no other run's folder or map (:func:`enclosing_run`), a file
    must not be a folder, and no folder above it may be a file."""
    path = Path(path)
    if path.is_dir():
        if not folder:
            return "a folder, not a file"
        if any(path.iterdir()):
            return "not empty"
    elif folder and (path.exists() or path.is_symlink()):
        return "not a folder"
    else:
        for parent in path.absolute().parents:
            if parent.exists():
                if not parent.is_dir():
                    return f"{parent} is not a folder"
                break
    if folder and (above := enclosing_run(path)) is not None:
        return f"inside the folder of another run or map ({above})"
    return None


def enclosing_run(path: str | os.PathLike) -> Path | None:
    """The folder above ``path`` that holds a run's record (a ``results.json`` that is a run
    record) or a saved map (``map.json``), else ``None``: a new run's folder never lies inside
    another run's (its ``.hydra/``, its map). Another tool's ``results.json`` is no run's."""
    from resireg.mapping.map_file import MAP_JSON

    for above in Path(path).resolve().parents:
        try:
            if (above / MAP_JSON).is_file() or RunRecord.read(above):
                return above
        except (RecordError, OSError):  # another tool's results.json, an unreadable one
            continue
    return None


class RunRecord:
    """The record of the run in ``folder`` (its ``results.json``), for the run's whole life.

    Args:
        folder: the run folder.
        writer: whether this process writes the record (rank 0 of a run; ranks > 0 only read:
            their :meth:`update` and :meth:`finish` do nothing and return ``{}``).
        report: where a final status that could not be written is reported besides stderr
            (the job wrapper passes a writer to the run's log file).
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        writer: bool = True,
        report: Callable[[str], None] | None = None,
    ) -> None:
        self.folder = Path(folder)
        self.writer = writer
        self._report = report
        self.trackers: Any = None  # the run's trackers (RunTrackers), once started
        self.sampler: Any = None  # its system metrics (runs.system.SystemSampler), once started
        self._heartbeat: Heartbeat | None = None

    def __repr__(self) -> str:
        return f"RunRecord({str(self.folder)!r})"

    def __getstate__(self) -> dict[str, Any]:
        """A copy sent to another process (a spawned DDP rank: the per-epoch callback holds the
        record) only adds fields; the run's start, end and trackers stay with the job's own
        process."""
        return {
            "folder": self.folder,
            "writer": self.writer,
            "_report": None,
            "trackers": None,
            "sampler": None,
            "_heartbeat": None,
        }

    # -- reading ----------------------------------------------------------------------------
    @property
    def path(self) -> Path:
        """The record's file, ``<folder>/results.json``."""
        return self.folder / RESULTS_FILE

    @staticmethod
    def exists(folder: str | os.PathLike) -> bool:
        """Whether ``folder`` holds a run record (a ``results.json`` file)."""
        return (Path(folder) / RESULTS_FILE).is_file()

    @staticmethod
    def read(folder: str | os.PathLike) -> dict[str, Any]:
        """The record of ``<folder>/results.json`` (``{}`` if absent), non-finite values
        restored (``null`` listed in ``non_finite`` -> NaN / inf; the field itself dropped).
        A file that is not a run record (not JSON, not an object, a field of another type)
        raises :class:`RecordError` naming it; an unreadable one, ``OSError``."""
        path = Path(folder) / RESULTS_FILE
        if not path.is_file():
            return {}
        try:
            record = json.loads(path.read_bytes())
        except (UnicodeDecodeError, json.JSONDecodeError) as err:
            raise RecordError(f"{path}: not a run record (not JSON: {err})") from None
        found = _check_shape(record, path).pop(NON_FINITE, None)
        if isinstance(found, dict):
            _restore(record, found)
        return record

    def fields(self) -> dict[str, Any]:
        """The record as it is now (:meth:`read`)."""
        return self.read(self.folder)

    def get(self, key: str, default: Any = None) -> Any:
        """One field of the record (``default`` when absent)."""
        return self.fields().get(key, default)

    # -- writing ----------------------------------------------------------------------------
    def update(self, **fields: Any) -> dict[str, Any]:
        """Merge ``fields`` into the record (written atomically, strict JSON, URLs masked: see
        the module docstring); returns the merged record as Python values (NaN included)."""
        if not self.writer:
            return {}
        with _lock(self.path):  # the heartbeat thread writes too
            results = {**self.fields(), **fields}
            results.pop(NON_FINITE, None)
            written, found = strict_json(results)
            if found:
                written[NON_FINITE] = {"reason": _REASON, **found}
            self.folder.mkdir(parents=True, exist_ok=True)
            text = json.dumps(written, indent=2, allow_nan=False)
            atomic_write(self.path, text, what="run record")
        return results

    def set_aside(self) -> Path | None:
        """Rename an earlier run's record in the folder to the first free
        ``results.previous-<n>.json`` (nothing is lost, nothing is merged); its new path, or
        ``None`` when there was none."""
        if not self.path.is_file():
            return None
        n = 1
        while (kept := self.folder / f"{self.path.stem}.previous-{n}{self.path.suffix}").exists():
            n += 1
        os.replace(self.path, kept)
        return kept

    # -- the run's life ---------------------------------------------------------------------
    def start(self, settings: RecordSettings, *, fresh: bool = False) -> None:
        """Start the run whose settings, read once from its composed config, are ``settings``
        (:meth:`RecordSettings.from_config <resireg_train.record.settings.RecordSettings.from_config>`):
        its trackers are those it names (:class:`resireg_train.record.trackers.base.RunTrackers`); the writer then
        sets an earlier record aside (``fresh``: a job that never resumes), writes ``name``,
        ``status: running`` and the provenance's start (a resumed run keeps its run id), masks
        the URL passwords in the config files Hydra saved, and starts the trackers: one that
        needs a network is checked first (``tracker.<name>.check_timeout``) and refused
        (:class:`~resireg_train.record.trackers.base.TrackerUnreachable`) or, with
        ``tracker.<name>.unreachable=warn``, left out with a warning. Then the system metrics
        are sampled until :meth:`finish` (``system_metrics``: :mod:`resireg_train.record.system`)."""
        import logging

        from resireg_train.record.provenance.block import start_provenance
        from resireg_train.record.system import SystemSampler
        from resireg_train.record.trackers.base import RunTrackers

        self.trackers = RunTrackers(settings, self)
        if not self.writer:
            return
        if fresh and (kept := self.set_aside()) is not None:
            logging.getLogger(__name__).warning(
                "%s held an earlier run's record: kept as %s", self.folder, kept.name
            )
        previous = self.get("provenance")  # a resumed run keeps its run id
        beat = settings.provenance
        heartbeat = Heartbeat(self, beat["heartbeat_interval"], beat["heartbeat_stale"])
        self.update(name=settings.name, status="running", error=None,
                    output_dir=str(self.folder),
                    provenance=start_provenance(settings, self.folder, previous),
                    **{HEARTBEAT: heartbeat.beat()})  # fmt: skip
        self._heartbeat = heartbeat.start()
        mask_saved_configs(self.folder)
        enabled, interval = settings.system_metrics  # checked when the settings were read
        self.trackers.start()
        if enabled:  # system.csv and results.json's system block (record/system.py)
            self.sampler = SystemSampler(self.folder, interval).start(fresh=fresh)

    def finish(self, status: str = "completed", error: str | None = None) -> dict[str, Any]:
        """End the run: write ``status`` (``completed`` when the job body returned: a resumed
        training run with nothing left to train included), ``error``, the provenance's end and
        the system metrics' peaks (``system``), then hand the record to the trackers (a tracker that fails is a warning, never a lost
        run). A record that cannot be written (a full disk) never hides the run's own error:
        stderr and the run's log file say which status could not be recorded and which one
        the file still reads. Returns the record."""
        if not self.writer:
            return {}
        if self._heartbeat is not None:  # before the final status: no beat after it
            self._heartbeat.stop()
            self._heartbeat = None
        from resireg_train.record.provenance.block import finish_provenance
        from resireg_train.record.system import merge_blocks

        fields: dict[str, Any] = {"status": status, "error": error}
        try:
            fields["provenance"] = finish_provenance(self.get("provenance") or {}, self.folder)
        except (OSError, ValueError):
            pass  # the record cannot be read: the status is what matters
        if self.sampler is not None:  # the peaks (a resumed run: over all its processes)
            block, self.sampler = self.sampler.stop(), None
            try:
                fields["system"] = merge_blocks(self.get("system"), block)
            except (OSError, ValueError):
                fields["system"] = block
        try:
            record = self.update(**fields)
        except OSError as err:
            try:
                stale = self.get("status")
            except (OSError, ValueError):
                stale = None
            message = (
                f"could not record status {status!r} in {self.path} ({err}); it still reads "
                f"status {stale!r} although the run ended {status!r}: {flat(str(error))}"
            )
            sys.stderr.write(f"error: {mask_text(message)}\n")
            sys.stderr.flush()
            if self._report is not None:
                self._report(message)
            record = {**fields}
        if self.trackers is not None:
            self.trackers.finish(record, failed=status != "completed")
        return record


def job_records(sweep: Path) -> dict[Path, tuple[int, int]]:
    """Every job record of the sweep folder ``sweep`` (``<sweep>/<job>/results.json``), by
    job folder: (mtime ns, size), as the file system gives them."""
    records = {}
    for path in sweep.glob(f"*/{RESULTS_FILE}"):
        try:
            stat = path.stat()
        except OSError:  # removed meanwhile
            continue
        records[path.parent] = (stat.st_mtime_ns, stat.st_size)
    return records
