"""The run index behind ``resireg-runs``: every run folder under some roots (single runs,
multirun jobs, search trials: any folder with a ``results.json``), one row each, filtered,
sorted and shown; two compared: :mod:`resireg_train.runs.diff`, one followed through its
lineage: :mod:`resireg_train.runs.lineage`.

A row reads only the run's ``results.json`` (:meth:`RunRecord.read
<resireg_train.record.run_record.RunRecord.read>`) and ``.hydra/overrides.yaml`` (the resolved
``.hydra/config.yaml`` only when a filter or a column names a config key), so a thousand runs
list in well under two seconds (``benchmarks/bench_runs.py``). A run still marked ``running``
whose process is gone is shown as ``died``: on this host, its PID is not alive; on another
host (a shared file system), its heartbeat is stale (:func:`~resireg_train.record.heartbeat.
heartbeat_stale`: older than ``provenance.heartbeat_stale`` seconds). A heartbeat that
cannot tell (a ``time`` that is no time, or more than ``provenance.heartbeat_skew`` seconds ahead
of this machine's clock, or a ``stale_after`` that is not a number > 0) is shown as ``unknown``, named once in the run's
problems (:func:`~resireg_train.record.heartbeat.heartbeat_doubt`). A file that is not what
it should be (a record that is not a run record, an overrides file that is not a YAML list) is
named once in :attr:`Run.problems` / :func:`scan`'s ``bad`` list, never a traceback: the other
runs are listed.
"""

from __future__ import annotations

import math
import operator
import os
import re
import socket
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from functools import cache, cached_property
from pathlib import Path
from typing import Any

import yaml

from resireg.specs.tree import flatten
from resireg_train.record.heartbeat import heartbeat_doubt, heartbeat_stale
from resireg_train.record.run_record import RESULTS_FILE, RecordError, RunRecord

__all__ = [
    "COLUMNS",
    "Run",
    "filter_runs",
    "find_run",
    "parse_where",
    "read_run",
    "scan",
    "sort_runs",
    "UNKNOWN",
]

_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
#: Folders a run folder holds that are never runs themselves (not walked inside a run).
_SKIP = {"checkpoints", ".hydra", "export", "map", "csv", "wandb", "mlruns", "__pycache__"}
#: ``resireg-runs ls``'s default columns.
COLUMNS = ("run_id", "cli", "name", "status", "start", "duration", "overrides", "metric", "value")
_HEADLINE = ("/miou_full", "/miou_lite", "/miou_bb", "train/loss")


#: The status of a ``running`` record of another host whose heartbeat cannot tell whether its
#: job still runs (:func:`~resireg_train.record.heartbeat.heartbeat_doubt`).
UNKNOWN = "unknown"


@cache
def _settings(key: str) -> float:
    """``provenance.heartbeat_stale`` (for a record whose heartbeat does not say its own) or
    ``provenance.heartbeat_skew`` (conf/provenance/default.yaml)."""
    from resireg_train.record.settings import provenance_settings

    return float(provenance_settings()[key])


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


@dataclass
class Run:
    """One run folder and what its record says."""

    path: Path
    results: dict[str, Any] = field(default_factory=dict)
    #: What could not be read of its files (each once), for the caller to name.
    problems: list[str] = field(default_factory=list)

    @property
    def provenance(self) -> dict[str, Any]:
        return self.results.get("provenance") or {}

    @property
    def run_id(self) -> str:
        return str(self.provenance.get("run_id") or self.path.name)

    @property
    def cli(self) -> str | None:
        return self.provenance.get("cli")

    @property
    def status(self) -> str:
        """The recorded status, ``died`` for a ``running`` run whose process is gone: on this
        host, its PID is not alive; on another, its heartbeat is stale (a record written
        before heartbeats keeps ``running``)."""
        status = self.results.get("status", "missing")
        if status != "running":
            return status
        machine = self.provenance.get("machine") or {}
        if machine.get("host") == socket.gethostname():
            pid = machine.get("pid")
            if isinstance(pid, int) and not _pid_alive(pid):
                return "died"
        elif doubt := heartbeat_doubt(self.results, _settings("heartbeat_skew")):
            problem = f"{self.path / RESULTS_FILE}: {doubt}: listed as {UNKNOWN!r}, not running"
            if problem not in self.problems:
                self.problems.append(problem)
            return UNKNOWN
        elif heartbeat_stale(self.results, _settings("heartbeat_stale")):
            return "died"
        return status

    @property
    def may_be_running(self) -> bool:
        """Whether its job may still run (``running``, or ``unknown``: a heartbeat that cannot
        tell): what ``gc`` and ``rerun`` leave alone."""
        return self.status in ("running", UNKNOWN)

    def _yaml(self, name: str, kind: type, what: str) -> Any:
        """``.hydra/<name>`` parsed (safe YAML), ``None`` when absent; one that cannot be read
        or is not a ``kind`` is a problem named once (:attr:`problems`) and ``None``."""
        path = self.path / ".hydra" / name
        if not path.is_file():
            return None
        try:
            with open(path) as f:
                data = yaml.load(f, Loader=_LOADER)
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
            self.problems.append(f"{path}: unreadable ({' '.join(str(err).split())}); its "
                                 f"{what} are not shown")  # fmt: skip
            return None
        if data is not None and not isinstance(data, kind):
            expected = "a YAML list" if kind is list else "a YAML mapping"
            self.problems.append(f"{path}: not {expected} (it holds {type(data).__name__}); "
                                 f"its {what} are not shown")  # fmt: skip
            return None
        return data

    @cached_property
    def overrides(self) -> list[str]:
        return [str(o) for o in self._yaml("overrides.yaml", list, "overrides") or []]

    @cached_property
    def config(self) -> dict[str, Any]:
        """The resolved config, flattened (``model.optimizer.lr``)."""
        return flatten(self._yaml("config.yaml", dict, "config keys") or {})

    @property
    def metrics(self) -> dict[str, float]:
        return {k: v for k, v in (self.results.get("final") or {}).items()
                if isinstance(v, (int, float)) and not isinstance(v, bool)}  # fmt: skip

    @property
    def headline(self) -> tuple[str | None, float | None]:
        """ReSiReg Full's mIoU (else Lite's, BB's, the training loss), as the report picks."""
        metrics = self.metrics
        for suffix in _HEADLINE:
            hits = sorted(k for k in metrics if k.split("@")[0].endswith(suffix) and "@" not in k)
            if hits:
                return hits[0], metrics[hits[0]]
        return None, None

    @property
    def start(self) -> str | None:
        return (self.provenance.get("time") or {}).get("start")

    @property
    def duration(self) -> float | None:
        return (self.provenance.get("time") or {}).get("wall_seconds")

    def value(self, key: str) -> Any:
        """A column or filter key: a row field (``status``, ``cli``, ``run_id``...), a metric
        (``final``), a ``results.json`` field, a provenance path (``provenance.code.commit``)
        or a config key (``model.optimizer.lr``)."""
        fields: dict[str, Callable[[], Any]] = {
            "run_id": lambda: self.run_id, "cli": lambda: self.cli, "status": lambda: self.status,
            "name": lambda: self.results.get("name"), "start": lambda: self.start,
            "duration": lambda: self.duration, "path": lambda: str(self.path),
            "overrides": lambda: " ".join(_short(o) for o in self.overrides
                                          if not o.lstrip("+~").startswith(_QUIET)),
            "metric": lambda: self.headline[0], "value": lambda: self.headline[1],
        }  # fmt: skip
        if key in fields:
            return fields[key]()
        if key in self.metrics:
            return self.metrics[key]
        if key.startswith("provenance"):
            return flatten(self.provenance, "provenance").get(key)
        if key in self.results and not isinstance(self.results[key], (dict, list)):
            return self.results[key]
        return self.config.get(key)


#: Overrides ``ls`` leaves out of its ``overrides`` column (where, not what, a run ran).
_QUIET = ("paths.", "hydra.", "device=", "num_workers=")


def _short(override: str, width: int = 48) -> str:
    """An override cut to ``width`` characters (a path keeps its end)."""
    if len(override) <= width:
        return override
    key, _, value = override.partition("=")
    keep = max(8, width - len(key) - 2)
    return f"{key}=…{value[-keep:]}"


def _run_folders(root: Path) -> Iterator[Path]:
    if (root / RESULTS_FILE).is_file():
        yield root
    for folder, dirs, names in os.walk(root):
        is_run = RESULTS_FILE in names
        # inside a run folder, its own outputs (checkpoints, export, map, ...) hold no runs
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and not (is_run and d in _SKIP))
        if folder != str(root) and is_run:
            yield Path(folder)


def read_run(folder: Path) -> Run:
    """The run in ``folder``; :class:`~resireg_train.record.run_record.RecordError` (a
    ``ValueError`` naming the file) when its record cannot be read or is not a run record."""
    try:
        return Run(folder, RunRecord.read(folder))
    except OSError as err:
        raise RecordError(f"{folder / RESULTS_FILE}: unreadable ({err.strerror or err})") from None


def scan(roots: Iterable[str | os.PathLike], bad: list[str] | None = None) -> list[Run]:
    """Every run folder under ``roots`` (a root may itself be a run folder) whose record can
    be read; each other one is named in ``bad`` (when given) with why."""
    runs, seen = [], set()
    for root in roots:
        for folder in _run_folders(Path(root).expanduser()):
            try:
                key = folder.resolve()
            except (OSError, RuntimeError) as err:  # a symbolic link loop
                if bad is not None:
                    bad.append(f"{folder}: {err}")
                continue
            if key in seen:
                continue
            seen.add(key)
            try:
                runs.append(read_run(folder))
            except RecordError as err:
                if bad is not None:
                    bad.append(str(err))
    return runs


_OPS: dict[str, Callable[[Any, Any], bool]] = {
    ">=": operator.ge, "<=": operator.le, "!=": operator.ne, "=": operator.eq,
    ">": operator.gt, "<": operator.lt,
}  # fmt: skip
_WHERE = re.compile(r"^(?P<key>[^<>=!]+?)\s*(?P<op>>=|<=|!=|=|>|<)\s*(?P<value>.*)$")


def parse_where(text: str) -> tuple[str, str, Any]:
    """``key=value`` / ``key>0.25`` / ... -> ``(key, op, value)`` (the value parsed as YAML:
    numbers, booleans, null, strings). A malformed filter is a :class:`ValueError`."""
    match = _WHERE.match(text.strip())
    if not match:
        raise ValueError(f"--where {text!r}: expected KEY=VALUE or KEY OP VALUE (>, <, >=, <=, !=)")
    try:  # safe YAML: a tag naming a Python object is refused, never built
        value = yaml.load(match["value"], Loader=_LOADER) if match["value"] else None
    except yaml.YAMLError as err:
        reason = " ".join(str(getattr(err, "problem", None) or err).split())
        raise ValueError(f"--where {text!r}: the value is not a plain YAML value ({reason}); "
                         "quote it as text, e.g. status='[x'") from None  # fmt: skip
    if isinstance(value, (dict, list)):
        raise ValueError(f"--where {text!r}: expected one value (a number, a word), got a "
                         f"{type(value).__name__}")  # fmt: skip
    return match["key"].strip(), match["op"], value


def _matches(actual: Any, op: str, wanted: Any) -> bool:
    if actual is None:
        return op == "!=" if wanted is not None else op == "="
    if isinstance(wanted, (int, float)) and not isinstance(wanted, bool):
        try:
            actual = float(actual)
        except (TypeError, ValueError):
            return False
        if math.isnan(actual):
            return False
    elif op in ("=", "!="):
        actual, wanted = str(actual), str(wanted)
    try:
        return bool(_OPS[op](actual, wanted))
    except TypeError:
        return False


def filter_runs(runs: list[Run], where: Iterable[str]) -> list[Run]:
    """The runs matching every ``--where`` filter."""
    filters = [parse_where(w) for w in where]
    return [r for r in runs if all(_matches(r.value(k), op, v) for k, op, v in filters)]


def sort_runs(runs: list[Run], key: str | None) -> list[Run]:
    """Sorted by ``key`` (``-key``: descending); runs without a value last. Default: start."""
    key = key or "start"
    descending = key.startswith("-")
    key = key.lstrip("-")

    def order(run: Run) -> tuple[int, int, Any]:
        value = run.value(key)
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return (1, 0, 0)
        if isinstance(value, (int, float)):  # numbers first, by value; then text, by text
            return (0, 0, float(value))
        return (0, 1, str(value))

    keys = {id(r): order(r) for r in runs}
    present = [r for r in runs if keys[id(r)][0] == 0]
    missing = [r for r in runs if keys[id(r)][0] == 1]
    return sorted(present, key=lambda r: keys[id(r)], reverse=descending) + missing


def find_run(spec: str, roots: Iterable[str | os.PathLike]) -> Run:
    """A run by folder path or by run id (a unique prefix) under ``roots``."""
    path = Path(spec).expanduser()
    if RunRecord.exists(path):
        return read_run(path)
    hits = [r for r in scan(roots) if r.run_id.startswith(spec)]
    if len(hits) == 1:
        return hits[0]
    if not hits:
        raise ValueError(f"no run {spec!r}: not a run folder, nor a run id under {list(roots)}")
    raise ValueError(f"run id {spec!r} is ambiguous: {', '.join(r.run_id for r in hits)}")


