"""The search's record (``<sweep>/search.json``) and the workers started from it.

A search records what its workers need: the job kind (``train`` or ``eval``), the overrides
of its command, the study's name and storage (the password masked). A worker, started by the
search itself (``hparams_search.workers`` > 1) or by ``resireg-search worker <sweep>`` (e.g.
a SLURM array task), never runs a command line read from the file: it starts one of the
project's own entry points, chosen from :data:`JOBS` by the recorded kind, with the recorded
overrides once :func:`read_record` has checked them. Sweep folders are shared between users,
so the record is data, not a program: an override is refused when it

- names a class to instantiate (a ``_target_`` key, or a value holding one), except the
  search's sampler and pruner named from Optuna's own modules (:data:`CLASS_TARGETS`);
- sets Hydra's own config (``hydra.*``, ``hydra/...``), except the search settings under
  ``hydra.sweeper`` (:data:`SWEEPER_SETTINGS`);
- sets a key absent from the job's composed config (``+key=...`` included), or chooses a
  config group option that the config search path does not list;
- deletes a key (``~key``), places a group elsewhere (``group@pkg=...``) or holds an
  interpolation (``${...}``: it can read the environment).

The recorded working folder is gone: the worker runs in its own, with the sweep folder's own
location as ``hydra.sweep.dir``. Every refusal names ``search.json`` and the entry.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from resireg.errors import ResiregError
from resireg.secrets import mask_text
from resireg_train.config.moves import current_overrides
from resireg_train.search.storage import STORAGE_ENV, recorded_storage, storage_override

__all__ = [
    "CLASS_TARGETS",
    "JOBS",
    "RECORD_FORMAT",
    "SEARCH_FILE",
    "SWEEPER_SETTINGS",
    "WORKER_ENV",
    "SearchRecord",
    "SearchRecordError",
    "check_overrides",
    "read_record",
    "recorded_overrides",
    "sigterm_ends",
    "start_workers",
    "study_location",
    "worker_command",
    "worker_env",
    "write_record",
]

log = logging.getLogger(__name__)

#: What a search records for its workers and its report.
SEARCH_FILE = "search.json"
#: The record's format; an earlier one (a command line to run) is refused.
RECORD_FORMAT = "resireg.search/2"
#: Set in the workers' processes: they start no others and leave the summary to the search.
WORKER_ENV = "RESIREG_SEARCH_WORKER"
#: The entry points a worker may start: recorded job kind (the Hydra config name) -> module of
#: the console script (``resireg-train``, ``resireg-eval``), run with this interpreter.
JOBS: dict[str, str] = {"train": "resireg_train.cli.train", "eval": "resireg_train.cli.eval"}
#: ``hydra.sweeper.<setting>`` a recorded override may set (``conf/hydra/sweeper/``).
SWEEPER_SETTINGS = frozenset({
    "sampler", "pruner", "direction", "study_name", "params", "enqueue", "heartbeat_interval",
    "grace_period", "retries", "max_failure_rate",
})  # fmt: skip
#: The only ``_target_`` keys a recorded override may set, and the module whose public classes
#: they may name (``hydra.sweeper.sampler._target_=optuna.samplers.RandomSampler``).
CLASS_TARGETS = {
    "hydra.sweeper.sampler._target_": "optuna.samplers",
    "hydra.sweeper.pruner._target_": "optuna.pruners",
}
#: Keys a worker sets itself: never taken from the record.
_OWN_KEYS = ("hparams_search.workers", "hparams_search.storage", "hparams_search.trial",
             "hydra.sweep.dir")  # fmt: skip


class SearchRecordError(ResiregError, ValueError):
    """A ``search.json`` a worker refuses; the message names the file and the entry."""


@dataclass(frozen=True)
class SearchRecord:
    """``search.json``, checked: the job kind, its overrides, the study's storage (masked;
    ``None``: the journal) and name."""

    job: str
    overrides: tuple[str, ...]
    storage: str | None
    study_name: str


# --------------------------------------------------------------------------- writing
def recorded_overrides(task: list[str], hydra: list[str]) -> list[str]:
    """What a search records of its command: the task overrides and the ``hydra.sweeper.*``
    ones (other Hydra settings, such as ``hydra.verbose``, do not change a trial), less the
    keys a worker sets itself, every URL's password masked."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    kept = []
    for text in [*task, *(h for h in hydra if h.lstrip("+~").startswith("hydra.sweeper."))]:
        (override,) = parser.parse_overrides([text])
        if override.key_or_group not in _OWN_KEYS:
            kept.append(mask_text(text))
    return kept


def write_record(
    sweep_dir: Path, job: str, overrides: list[str], storage: str | None, study_name: str
) -> None:
    """Write ``<sweep>/search.json`` (atomically; each start of the search writes it again,
    so workers started later follow its latest command, e.g. a larger ``n_trials``)."""
    from resireg.integrity import atomic_write

    record = {
        "format": RECORD_FORMAT,
        "job": job,
        "overrides": list(overrides),
        "storage": recorded_storage(storage),
        "study_name": study_name,
    }
    atomic_write(sweep_dir / SEARCH_FILE, json.dumps(record, indent=1) + "\n", what="search record")


# --------------------------------------------------------------------------- reading
def _load(path: Path) -> dict[str, Any]:
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise SearchRecordError(
            f"{path.parent} holds no {SEARCH_FILE}: not the folder of a search started with "
            "hparams_search=<name>"
        ) from None
    except (OSError, ValueError) as err:
        raise SearchRecordError(f"{path}: cannot be read: {err}") from None
    if not isinstance(record, dict):
        raise SearchRecordError(f"{path}: not a search record (a JSON {type(record).__name__})")
    return record


def study_location(sweep_dir: str | Path) -> tuple[str | None, str | None]:
    """(storage, study name) that ``<sweep>/search.json`` records, ``(None, None)`` without
    one: what the report opens (no override is run, so none is checked)."""
    path = Path(sweep_dir) / SEARCH_FILE
    if not path.is_file():
        return None, None
    record = _load(path)
    storage, name = record.get("storage"), record.get("study_name")
    return (storage if isinstance(storage, str) else None), (
        name if isinstance(name, str) else None
    )


def read_record(sweep_dir: str | Path) -> SearchRecord:
    """``<sweep>/search.json``, every entry checked (module docstring); raises
    :class:`SearchRecordError` naming the file and the entry."""
    path = Path(sweep_dir) / SEARCH_FILE
    record = _load(path)
    if "argv" in record or record.get("format") != RECORD_FORMAT:
        raise SearchRecordError(
            f"{path}: format {record.get('format')!r} is not {RECORD_FORMAT!r} (a record of an "
            "earlier release holds a command line, which a worker never runs); run the search's "
            "command once more: it resumes the study and writes a new record"
        )
    unknown = sorted(set(record) - {"format", "job", "overrides", "storage", "study_name"})
    if unknown:  # e.g. a working folder to run in: the worker runs where it is started
        raise SearchRecordError(f"{path}: unknown entry {unknown[0]!r}: a worker takes none")
    job = record.get("job")
    if job not in JOBS:
        raise SearchRecordError(
            f"{path}: job={job!r} is not one a worker starts (one of: {', '.join(sorted(JOBS))})"
        )
    overrides = record.get("overrides")
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise SearchRecordError(f"{path}: overrides must be a list of strings, not {overrides!r}")
    storage, name = record.get("storage"), record.get("study_name")
    if storage is not None and not isinstance(storage, str):
        raise SearchRecordError(f"{path}: storage={storage!r} is not a URL or null")
    if not isinstance(name, str) or not name:
        raise SearchRecordError(f"{path}: study_name={name!r} is not a name")
    overrides = current_overrides(job, overrides)  # a renamed key's old spelling: today's
    check_overrides(path, job, overrides)
    return SearchRecord(job, tuple(overrides), storage, name)


def _holds_target(value: Any) -> bool:
    """Whether a parsed override value holds a ``_target_`` key at any depth (dicts, lists,
    the choices of a sweep)."""
    if isinstance(value, dict):
        return "_target_" in value or any(_holds_target(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return any(_holds_target(v) for v in value)
    choices = getattr(value, "list", None)  # ChoiceSweep
    return _holds_target(list(choices)) if choices is not None else False


def _optuna_class(module: str, name: Any) -> bool:
    import importlib

    prefix = f"{module}."
    if not isinstance(name, str) or not name.startswith(prefix):
        return False
    return name[len(prefix) :] in getattr(importlib.import_module(module), "__all__", ())


def _options(value: Any) -> list[Any]:
    """The option(s) a group override chooses (one, or a sweep's choices)."""
    choices = getattr(value, "list", None)
    return list(choices) if choices is not None else [value]


def _refusal(
    override: Any, groups: Any, composed: Any, job: str, addable: frozenset[str] = frozenset()
) -> str | None:
    """Why a recorded override is refused (module docstring), or ``None``. ``addable``: keys
    a ``+key=value`` override may add (none for a search's record)."""
    from omegaconf import OmegaConf

    key = override.key_or_group
    text = override.input_line
    value = override.value()
    if override.is_delete():
        return "it deletes a key"
    if override.package is not None:
        return "it places a config group elsewhere (@package)"
    if "${" in text.partition("=")[2]:
        return "its value is an interpolation (${...}), which can read the environment"
    hydra = key == "hydra" or key.startswith(("hydra.", "hydra/"))
    if "_target_" in key.replace("/", ".").split("."):
        if key in CLASS_TARGETS and _optuna_class(CLASS_TARGETS[key], value):
            return None
        return "it names a class to instantiate (_target_)"
    if _holds_target(value):
        return "its value names a class to instantiate (_target_)"
    if hydra:
        parts = key.split(".")
        if len(parts) > 2 and parts[1] == "sweeper" and parts[2] in SWEEPER_SETTINGS:
            return None
        return "it sets Hydra's own config (hydra.*); only the search settings under hydra.sweeper"
    options = groups(key)
    if options:
        missing = [o for o in _options(value) if o not in options]
        return f"{missing[0]!r} is not an option of config group {key!r}" if missing else None
    if override.is_add() and key not in addable:
        return "it adds a key absent from the composed config"
    if override.is_add():
        return None
    found = OmegaConf.select(composed, key, default=_ABSENT, throw_on_resolution_failure=False)
    if found is _ABSENT and (raw := _unresolved(composed, key)) is not None:
        return (
            f"{key} is {raw}, which Hydra sets when the job starts (the run's own folder: "
            "a rerun's is --out, a search's job's is under its sweep folder)"
        )
    if found is _ABSENT and not _required(composed, key):
        return f"resireg-{job}'s config has no such key"
    return None


def _unresolved(composed: Any, key: str) -> str | None:
    """The raw value of ``key`` where it is an interpolation of Hydra's runtime
    (``${hydra:...}``, e.g. ``paths.output_dir``), which a composed config cannot resolve."""
    from omegaconf import OmegaConf

    parent, _, last = key.rpartition(".")
    node = OmegaConf.select(composed, parent, default=None) if parent else composed
    if not OmegaConf.is_dict(node) or last not in node.keys():
        return None
    raw = OmegaConf.to_container(node, resolve=False).get(last)
    return raw if isinstance(raw, str) and raw.startswith("${hydra:") else None


def _required(composed: Any, key: str) -> bool:
    """Whether ``key`` is a key of ``composed`` whose value is required (``???``: select
    answers it as absent), e.g. ``source.path`` of resireg-map."""
    from omegaconf import OmegaConf

    parent, _, last = key.rpartition(".")
    node = OmegaConf.select(composed, parent, default=None) if parent else composed
    return OmegaConf.is_dict(node) and last in node.keys() and OmegaConf.is_missing(node, last)


_ABSENT: Any = object()


def check_overrides(
    path: Path,
    job: str,
    overrides: list[str],
    addable: frozenset[str] = frozenset(),
    skip: frozenset[int] = frozenset(),
) -> None:
    """Refuse any recorded override of a ``resireg-<job>`` job (the config name: ``train``,
    ``eval``, ``map``) that a worker would refuse (module docstring), raising
    :class:`SearchRecordError` naming ``path`` and the entry; ``addable``: keys a ``+``
    override may add all the same (``resireg-runs rerun``: a run's ``+model.init_from``);
    ``skip``: the indices of entries not run (given again by the user). The rule every run
    rebuilt from a file follows: a search's workers, ``resireg-runs rerun`` (a run's
    ``.hydra/overrides.yaml``). The job's config is composed with
    Hydra's compose API from the recorded group choices."""
    from hydra import compose
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from resireg_train.config.paths import composing

    parser = OverridesParser.create()
    parsed = []
    for index, text in enumerate(overrides):
        try:
            (override,) = parser.parse_overrides([text])
        except Exception as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise SearchRecordError(
                f"{path}: overrides[{index}]={text!r} is refused: not a Hydra override ({first})"
            ) from None
        parsed.append(override)

    def compose_and_check() -> None:
        loader = GlobalHydra.instance().config_loader()
        cache: dict[str, list[str]] = {}

        def groups(key: str) -> list[str]:
            if key not in cache:
                cache[key] = list(loader.get_group_options(key)) if ".." not in key else []
            return cache[key]

        chosen = [f"{o.get_key_element()}={_options(o.value())[0]}" for o in parsed
                  if not o.is_delete() and o.package is None and groups(o.key_or_group)
                  and not o.key_or_group.startswith("hydra")
                  and all(opt in groups(o.key_or_group) for opt in _options(o.value()))]  # fmt: skip
        try:
            composed = compose(job, overrides=chosen)
        except Exception as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise SearchRecordError(
                f"{path}: its config group choices {chosen} do not compose resireg-{job}'s "
                f"config: {first}"
            ) from None
        for index, override in enumerate(parsed):
            if index in skip:
                continue
            reason = _refusal(override, groups, composed, job, frozenset(addable))
            if reason is not None:
                raise SearchRecordError(
                    f"{path}: overrides[{index}]={override.input_line!r} is refused: {reason}"
                )

    with composing():  # inside a Hydra app: its config search path; else conf/
        compose_and_check()


# --------------------------------------------------------------------------- workers
def worker_command(sweep_dir: Path, record: SearchRecord | None = None) -> list[str]:
    """The command of one more worker of the search in ``sweep_dir``: this interpreter running
    the recorded job's entry point (:data:`JOBS`) with the recorded overrides, one worker, the
    sweep folder's own location and the recorded (masked) storage."""
    record = record or read_record(sweep_dir)
    storage = [] if record.storage is None else [storage_override(record.storage)]
    return [sys.executable, "-m", JOBS[record.job], *record.overrides, *storage,
            "hparams_search.workers=1", f"hydra.sweep.dir={Path(sweep_dir).resolve()}"]  # fmt: skip


def worker_env(storage: str | None = None) -> dict[str, str]:
    """A worker's environment: this one, marked as a worker, with the storage's whole URL
    (:data:`~resireg_train.search.storage.STORAGE_ENV`) when given."""
    env = {**os.environ, WORKER_ENV: "1"}
    if storage:
        env[STORAGE_ENV] = storage
    return env


def start_workers(sweep_dir: Path, count: int) -> list[subprocess.Popen]:
    """Start ``count`` more workers of this search from its record, one device each where
    ``CUDA_VISIBLE_DEVICES`` lists several (worker i gets device i modulo their number)."""
    if count < 1:
        return []
    record = read_record(sweep_dir)
    devices = [d for d in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if d.strip()]
    procs = []
    for i in range(count):
        env = worker_env()  # the storage's URL: already in this process's environment
        if len(devices) > 1:
            env["CUDA_VISIBLE_DEVICES"] = devices[(i + 1) % len(devices)]
        procs.append(subprocess.Popen(worker_command(sweep_dir, record), env=env))
    return procs


@contextlib.contextmanager
def sigterm_ends(procs: Sequence[subprocess.Popen]) -> Iterator[None]:
    """For the block: SIGTERM to this process (``kill <pid>``, a service manager, a job's end)
    is passed on to ``procs`` (the processes it started, which would otherwise go on running,
    orphaned) before it ends this process as SIGTERM does. Ctrl-C reaches them from the
    terminal already. Blocks nest: the enclosing block's processes get it too. Outside the main
    thread (no signal handler there): nothing is set."""

    def handler(signum: int, frame: Any) -> None:
        for proc in procs:
            with contextlib.suppress(OSError):
                proc.send_signal(signum)
        if callable(previous):  # an enclosing block's (a search's workers, then a trial's ranks)
            previous(signum, frame)
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous: Any = None
    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
