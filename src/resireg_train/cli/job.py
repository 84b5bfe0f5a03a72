"""What the Hydra mains share: where the configs live, the run-folder name resolver, and
the task wrapper that gives every job its run record
(:class:`~resireg_train.record.run_record.RunRecord`: status, provenance, trackers, final status),
records a failure in it and in the run's log file, and returns the value a sweeper optimises.

How a failure is reported (docs/guide.md#run-records-and-faults): ``results.json`` gets the status and
the one-line error, the run's log file (``train.log`` / ``eval.log``) the error with its
traceback, and the console either Hydra's traceback (an unexpected crash) or, for an error
whose message says everything (a bad config value, a refused resume, a file that cannot be
written, an unavailable download, a dataset of which nothing could be scored), that message
alone. A multirun ends with one line per failed job, or, when none failed, one line naming
its sweep folder and the ``resireg-report`` command.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import sys
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import CompactHydraException
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

try:  # POSIX; where it is missing (Windows) run folders are not locked
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

from resireg.errors import ConfigError, IntegrityError, ResiregError, WriteError
from resireg.secrets import MASK, SecretFilter, mask_text
from resireg_train.config.machine import check_cluster, config_rank, process_rank
from resireg_train.config.paths import CONFIG_DIR, RUN_ID
from resireg_train.record.run_record import RecordError, RunRecord, flat, job_records
from resireg_train.record.settings import RecordSettings

__all__ = [
    "CONFIG_DIR",
    "RUN_ID",
    "LOCK_FILE",
    "JobFailed",
    "RunFolderBusy",
    "RunFolderLock",
    "SweepRecords",
    "added_keys",
    "hydra_entry_point",
    "instantiate_group",
    "hold_run_folder",
    "optimized_value",
    "process_rank",
    "register_resolvers",
    "run_task",
    "safe_dirname",
    "top_level_keys",
]

log = logging.getLogger(__name__)


def safe_dirname(text: str, max_length: int = 200) -> str:
    """``text`` as one folder name: ``/`` becomes ``_``, a URL's password becomes ``masked``
    (a sweep job's folder is named after its overrides, a tracking URI's among them), and a
    name longer than ``max_length`` is cut and given a hash so it stays unique (Hydra's
    ``override_dirname`` keeps the ``/`` of paths given as values, which would nest folders)."""
    name = mask_text(str(text)).replace(MASK, "masked")
    name = name.replace("/", "_").replace(os.sep, "_")
    if len(name) > max_length:
        digest = hashlib.sha1(name.encode()).hexdigest()[:8]
        name = f"{name[: max_length - 9]}-{digest}"
    return name


def top_level_keys(config_name: str) -> set[str]:
    """The top-level keys ``conf/<config_name>.yaml`` defines: its own fields, its groups
    (``data``, ``model``...; ``experiment`` and ``sweep`` too), and the fields of the groups
    it places at the top level (``resireg@_here_``: ``variants``, ``lite``, ``full``...)."""
    raw = OmegaConf.to_container(OmegaConf.load(CONFIG_DIR / f"{config_name}.yaml"))
    keys = {k for k in raw if k not in ("defaults", "hydra")}
    for entry in raw.get("defaults") or []:
        if not isinstance(entry, dict):
            continue  # _self_
        for spec, option in entry.items():
            group, _, package = spec.partition("@")
            if package == "_here_" and option:
                placed = OmegaConf.load(CONFIG_DIR / group / f"{option}.yaml")
                keys |= {k for k in placed if k != "defaults"}
            else:
                keys.add(package.split(".")[0] if package else group.split("/")[0])
    return keys


def added_keys() -> list[str]:
    """The config keys this job's ``+key=value`` / ``++key=value`` overrides added (command
    line or sweep; not the ``+group=option`` of a config group), ``[]`` outside Hydra. A
    ``++`` override counts only if the config would not hold its key without it."""
    if not HydraConfig.initialized():
        return []
    from hydra import compose
    from hydra.core.override_parser.overrides_parser import OverridesParser

    runtime = HydraConfig.get()
    roots = [Path(src.path) for src in runtime.runtime.config_sources
             if src.schema == "file"] or [CONFIG_DIR]  # fmt: skip
    given = list(runtime.overrides.task)
    added, forced = [], []
    for override in OverridesParser.create().parse_overrides(given):
        key = override.key_or_group
        if not (override.is_add() or override.is_force_add()) or "/" in key:
            continue
        if any((root / key.replace(".", "/")).is_dir() for root in roots):
            continue  # a config group: +prior=sam2
        (forced if override.is_force_add() else added).append(key)
    if forced:
        plain = compose(runtime.job.config_name,
                        overrides=[o for o in given if not o.startswith("+")])  # fmt: skip
        added += [k for k in forced if OmegaConf.select(plain, k, default=None) is None]
    return added


def instantiate_group(group: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a config group (callbacks, loggers)."""
    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if c and "_target_" in c]


def register_resolvers() -> None:
    """The OmegaConf resolvers ``conf/`` uses (``safe_dirname`` and ``run_id`` in ``conf/hydra``,
    ``if_rank_zero`` in ``conf/train.yaml``,
    ``first_key`` in ``conf/hparams_search``, ``resireg_encoders`` in the sweeps over every
    encoder)."""
    if not OmegaConf.has_resolver("safe_dirname"):
        OmegaConf.register_new_resolver("safe_dirname", safe_dirname)
    if not OmegaConf.has_resolver("run_id"):
        OmegaConf.register_new_resolver("run_id", lambda: RUN_ID, use_cache=True)
    if not OmegaConf.has_resolver("if_rank_zero"):
        # conf/train.yaml: .hydra/ is written by the global rank 0 alone (the nodes of a
        # multi-node run share its folder)
        OmegaConf.register_new_resolver(
            "if_rank_zero",
            lambda value, devices=None: value if config_rank({"trainer": {"devices": devices}})
            == 0 else None,
        )  # fmt: skip
    import resireg_train.config.eval  # noqa: F401  registers resireg_encoders (conf/sweep/table*.yaml)
    from resireg_train.search.space import register_search_resolvers

    register_search_resolvers()  # conf/hparams_search/: the metric follows val_data=


#: The lock file in a run folder: held (``flock``) by the job writing the folder, with its PID.
LOCK_FILE = ".run.lock"

#: Run folders this process holds: resolved path -> the open lock file (its lock lives with it).
_HELD: dict[Path, Any] = {}


class RunFolderBusy(ResiregError, RuntimeError):
    """Another running job holds the run folder (its PID is named)."""


def hold_run_folder(out: Path) -> bool:
    """Lock the run folder ``out`` for this process: an OS lock (``fcntl.flock``) on its
    :data:`LOCK_FILE`, into which this process's PID is written. The lock is the process's
    until :func:`release_run_folder` or its exit, a crash or ``kill -9`` included (the OS drops
    it with the process's files), so a stale lock file never blocks a later job.

    Returns ``True`` if this call took the lock, ``False`` if this process already held it.
    Raises :class:`RunFolderBusy` naming the holder's PID if another process holds it: two
    jobs writing one folder would interleave their logs, maps and records.
    """
    key = out.resolve()
    if key in _HELD or fcntl is None:
        return False
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_FILE
    handle = open(path, "a+")  # not "w": truncating would erase the holder's PID
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "unknown (it is starting)"
        handle.close()
        raise RunFolderBusy(
            f"{out} is in use by another job (PID {holder}, lock file {path}): wait for it to "
            "end, or give this run its own folder (leave hydra.run.dir unset for a new one)"
        ) from None
    except BaseException:
        handle.close()
        raise
    handle.truncate(0)
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    _HELD[key] = handle
    return True


def release_run_folder(out: Path) -> None:
    """Release this process's lock on ``out`` (the lock file stays: removing it could let two
    jobs lock two different files of the same name)."""
    handle = _HELD.pop(out.resolve(), None)
    if handle is not None:
        handle.close()  # closing the file drops the flock


class RunFolderLock(Callback):
    """Hydra callback (``conf/train.yaml``, ``eval.yaml``, ``map.yaml``; in ``train.yaml`` after
    ``RunFolderCheck``, so a refused resume leaves even the lock file as it was): locks a single
    run's folder (:func:`hold_run_folder`) before Hydra writes anything into it (``.hydra/``,
    the log file), so a second job given the same ``hydra.run.dir`` (or a ``resume=true`` while the
    first still runs) is refused and leaves the first one's files as they were. Sweep jobs are
    locked by :func:`run_task`; ranks > 0 of a DDP run (re-launched by Lightning into rank 0's
    folder) take no lock, nor do the processes of other nodes, even given the same folder
    (every process knows its global rank from its cluster's environment,
    :func:`~resireg_train.config.machine.process_rank`). A process whose environment
    contradicts its trainer (a node rank not below ``trainer.num_nodes``) is refused first,
    before anything is written (:func:`~resireg_train.config.machine.check_cluster`)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            check_cluster(config)
            if config_rank(config) != 0:
                return
            hold_run_folder(Path(str(config.hydra.run.dir)))
        except (RunFolderBusy, ConfigError) as err:
            # Hydra turns a callback's exception into a warning and runs the job anyway: exit.
            sys.stderr.write(f"resireg-{config.hydra.job.name}: refused: {err}\n")
            raise SystemExit(1) from None


def run_task(
    cfg: DictConfig,
    body: Callable[[DictConfig, RunRecord], dict[str, Any]],
    rank_zero: bool = True,
    resume_hint: str | None = None,
    fresh: bool = False,
) -> dict[str, Any]:
    """Run ``body(cfg, record)`` with the run's record (a
    :class:`~resireg_train.record.run_record.RunRecord` of ``paths.output_dir``), which the body
    adds its fields to; returns the final record (on ranks other than 0: the body's result).

    The record starts the run (:meth:`RunRecord.start`: ``running``, provenance, trackers;
    with ``fresh``, a job that never resumes such as ``resireg-eval``, an earlier record in the
    folder is kept as ``results.previous-<n>.json`` instead of having its fields merged into
    this run's) and finishes it (:meth:`RunRecord.finish`): ``completed`` whenever the body
    returns. Ctrl-C (``KeyboardInterrupt``) is recorded as ``"status": "interrupted"`` and the
    process exits with status 130 (what a shell reports for Ctrl-C) after saying how to
    resume (``resume_hint``). Any other failure, from a bad config value or an unreachable
    tracker to a crash mid-epoch, is recorded as ``"status": "failed"`` with its error before
    it is re-raised, so a sweep report lists the job with its reason. Only rank 0
    (``rank_zero``) writes.
    """
    check_model_registry(cfg)  # before anything is written, as a busy folder below
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    # Before anything is written: a folder another job writes is refused (its PID named). A
    # lock taken here (a sweep job, a call from Python) is released when the job ends; a
    # single run's, taken before Hydra wrote (RunFolderLock), lasts as long as the process.
    took = rank_zero and hold_run_folder(out)
    try:
        record = RunRecord(out, writer=rank_zero, report=lambda m: _to_log_files(m, None))
        return _run_recorded(cfg, body, record, resume_hint, fresh)
    finally:
        if took:
            release_run_folder(out)


def check_model_registry(cfg: DictConfig) -> None:
    """A ``model_path`` in MLflow's model registry (``models:/NAME@ALIAS``), checked before
    the run starts: one that is not of the registry's two forms is a :class:`ConfigError`,
    a registry that does not answer within ``logger.mlflow.check_timeout`` seconds a
    :class:`~resireg.models.vlm.registry.RegistryError` (:func:`resireg.models.vlm.registry.
    check_registry`): one line each, instead of a traceback or minutes of MLflow's retries."""
    from resireg.specs.exports import REGISTRY_PREFIX, registry_model

    try:
        model_path = OmegaConf.select(cfg, "model_path", default=None)
    except Exception:  # an interpolation only the job resolves: its own check names it
        return
    if not isinstance(model_path, str) or not model_path.startswith(REGISTRY_PREFIX):
        return
    try:
        registry_model(model_path)
    except ValueError as err:
        raise ConfigError(f"model_path: {err}") from None
    from resireg.models.vlm.registry import check_registry, registry_timeout

    check_registry(timeout=registry_timeout(cfg), what=f"model_path={model_path!r}")


def _run_recorded(
    cfg: DictConfig,
    body: Callable[[DictConfig, RunRecord], dict[str, Any]],
    record: RunRecord,
    resume_hint: str | None,
    fresh: bool,
) -> dict[str, Any]:
    try:
        record.start(RecordSettings.from_config(cfg), fresh=fresh)
        result = body(cfg, record)
    except KeyboardInterrupt:
        error = "KeyboardInterrupt: interrupted by the user (Ctrl-C)"
        if resume_hint:
            error += f"; {resume_hint}"
        record.finish("interrupted", error)
        if record.writer:
            log.warning("%s", mask_text(error))
        raise SystemExit(130) from None
    except BaseException as exc:
        if record.writer:
            error = error_text(exc)
            status = getattr(exc, "run_status", "failed")  # "pruned": an Optuna search's pruner
            record.finish(status, error)
            _to_log_files(f"run {status}: {error}", exc)
        raise
    return record.finish() if record.writer else result


def error_text(exc: BaseException) -> str:
    """``module.Type: message`` of an exception and its notes, one per line (the config path
    of a library error: ``config: encoder``; what ``results.json`` records), every URL's
    password masked."""
    text = "".join(traceback.format_exception_only(type(exc), exc)).strip()
    if sys.version_info < (3, 11):  # from 3.11 on, traceback prints the notes itself
        text = "\n".join([text, *map(str, getattr(exc, "__notes__", None) or ())])
    return mask_text(text)


def _to_log_files(message: str, exc: BaseException | None) -> None:
    """Write ``message`` to this process's log files only (Hydra's ``<output dir>/<job
    name>.log``; the console gets the error from Hydra, once), with ``exc``'s traceback
    unless its message is the whole report (a config error)."""
    trace = None
    if exc is not None and not isinstance(exc, _reported_types()):
        trace = (type(exc), exc, exc.__traceback__)
    record = logging.LogRecord(log.name, logging.ERROR, __file__, 0, message, None, trace)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)  # (a handler that cannot write reports it on stderr)


def optimized_value(cfg: DictConfig, results: dict[str, Any]) -> float | None:
    """The value a sweeper (e.g. Optuna) optimises: ``optimized_metric``'s best value if the
    run tracked one, else its final value; ``None`` when unset or on ranks other than 0.

    A metric that was logged but is not finite (NaN, stored as ``null`` in ``results.json``)
    raises: the job is failed, and an Optuna search records its trial FAIL and goes on."""
    name = cfg.get("optimized_metric")
    if not name or not results:
        return None
    for section in ("best", "final"):
        if name not in results.get(section, {}):
            continue
        value = results[section][name]
        value = value["value"] if isinstance(value, dict) else value
        if value is None or not math.isfinite(float(value)):
            raise ValueError(
                f"optimized_metric={name!r} is {value!r}: not finite, so this job scores nothing"
            )
        return float(value)
    logged = sorted(results.get("final", {}))
    raise KeyError(f"optimized_metric={name!r} was not logged; logged: {logged}")


class JobFailed(ResiregError, CompactHydraException):
    """A job failed with an error whose message says what to do: Hydra prints the message
    alone, not a traceback (the run's log file keeps it; ``HYDRA_FULL_ERROR=1`` shows it)."""


def _reported_types() -> tuple[type[BaseException], ...]:
    """The errors whose message is the whole report (see the module docstring). The classes
    of modules not loaded yet cannot have been raised, so nothing heavy is imported here."""
    types: list[type[BaseException]] = [ConfigError, WriteError, FileExistsError, RunFolderBusy,
                                        IntegrityError]  # fmt: skip
    for module, name in (
        ("resireg_train.record.trackers.base", "TrackerUnreachable"),
        ("resireg_train.training.checkpoints", "CheckpointError"),
        ("resireg_train.evaluation.base", "NothingScoredError"),
        ("resireg_train.search.ranks", "TrialRankFailed"),
        ("resireg.models.hub", "WeightsUnavailableError"),
        ("resireg.models.vlm.registry", "RegistryError"),
    ):
        cls = getattr(sys.modules.get(module), name, None)
        if cls is not None:
            types.append(cls)
    return tuple(types)


class SweepRecords(Callback):
    """Hydra callback (``conf/hydra/default.yaml``) that notes, in the process that launches a
    multirun, where its jobs write and which job records were already there, so that process
    can list every failed job once the sweep ends (:func:`hydra_entry_point`).

    The list comes from the jobs' ``results.json`` files, not from this process's memory: with
    a launcher that runs jobs elsewhere (``hydra/launcher=submitit_slurm``, ``submitit_local``)
    no job runs in this process, and Hydra itself reports only the first failure. A record is
    this sweep's when it is new or changed since the sweep started (a resumed Optuna search
    keeps its earlier trials' folders); changes are found by file size and modification time
    as the file system gives them, never compared with this machine's clock (a cluster's
    shared file system may run on another)."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        mask_log_handlers()  # the launcher logs each job's overrides
        sweep = Path(str(config.hydra.sweep.dir))
        _SWEEP.clear()
        _SWEEP.update(dir=sweep, before=job_records(sweep))


#: The multirun this process launched: its folder and its job records before it started.
_SWEEP: dict[str, Any] = {}


def _job_number(folder: Path) -> int:
    """A job folder's number: the ``<n>_`` its name starts with (conf/hydra/default.yaml)."""
    head = folder.name.split("_", 1)[0]
    return int(head) if head.isdigit() else -1


def _sweep_summary(prog: str, sweep: Path, before: dict[Path, tuple[int, int]]) -> str:
    """One line per failed job of the multirun in ``sweep`` (Hydra itself reports only the
    first): its number, folder and its error (on one line), from the job records written
    since ``before`` (:class:`SweepRecords`); when none failed, one line with the number of
    jobs (and pruned trials), the folder and the report command."""
    now = job_records(sweep)
    jobs = sorted((p for p, stat in now.items() if before.get(p) != stat),
                  key=lambda p: (_job_number(p), p.name))  # fmt: skip
    failures, pruned = [], 0
    for folder in jobs:
        try:
            record = RunRecord.read(folder)
        except (OSError, RecordError) as err:
            failures.append((folder, f"unreadable record: {err}"))
            continue
        if record.get("status") == "failed":
            failures.append((folder, str(record.get("error") or "no error recorded")))
        pruned += record.get("status") == "pruned"
    if not jobs:
        return ""
    if not failures:
        stopped = f", {pruned} pruned" if pruned else ""
        return (f"{prog}: {len(jobs)} jobs ran{stopped}, none failed (sweep {sweep}; "
                f"resireg-report {sweep} lists every job)\n")  # fmt: skip
    lines = [f"{prog}: {len(failures)} of {len(jobs)} jobs failed (sweep {sweep}; "
             f"resireg-report {sweep} lists every job):"]  # fmt: skip
    lines += [f"  job {_job_number(out)} ({out.name}): {flat(error)}" for out, error in failures]
    return "\n".join(lines) + "\n"


class _MaskedStream:
    """``sys.stdout`` / ``sys.stderr`` with every URL's password masked in what is written
    through it (Hydra prints a failed job's overrides, libraries print their server's URL);
    everything else is the stream's own."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        self._stream.write(mask_text(text) if isinstance(text, str) else text)
        return len(text)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


@contextlib.contextmanager
def masked_console() -> Iterator[None]:
    """Within: ``sys.stdout`` and ``sys.stderr`` mask URL passwords (:class:`_MaskedStream`)."""
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _MaskedStream(sys.stdout), _MaskedStream(sys.stderr)
    try:
        yield
    finally:
        sys.stdout, sys.stderr = saved


def mask_log_handlers() -> None:
    """Give every handler of the root logger (Hydra's console and the run's log file) the
    filter that masks URL passwords (:class:`~resireg.secrets.SecretFilter`),
    once."""
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, SecretFilter) for f in handler.filters):
            handler.addFilter(SecretFilter())


def hydra_entry_point(
    config_name: str, task: Callable[[DictConfig], dict[str, Any]]
) -> Callable[[], float | None]:
    """A console entry point: Hydra composes ``conf/<config_name>.yaml`` with the command
    line's overrides, ``task`` runs, and :func:`optimized_value` goes back to the sweeper.

    A failing job is listed; a multirun ends with one line per failed job (on stderr),
    after Hydra's report of the first one, wherever its jobs ran (:class:`SweepRecords`)."""
    register_resolvers()
    prog = f"resireg-{config_name}"

    @hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=config_name)
    def main(cfg: DictConfig) -> float | None:
        mask_log_handlers()  # the console and the run's log file: no URL's password
        log.info("output dir: %s", HydraConfig.get().runtime.output_dir)
        try:
            return optimized_value(cfg, task(cfg))
        except Exception as exc:
            if isinstance(exc, _reported_types()):
                raise JobFailed(error_text(exc)) from exc
            raise

    def entry() -> float | None:
        _SWEEP.clear()
        with masked_console():  # no URL's password on the console, whoever prints it
            try:
                return main()
            finally:
                # (a worker an Optuna search started itself leaves the summary to the search)
                if _SWEEP and os.environ.get("RESIREG_SEARCH_WORKER") != "1":
                    sys.stderr.write(_sweep_summary(prog, _SWEEP["dir"], _SWEEP["before"]))

    return entry
