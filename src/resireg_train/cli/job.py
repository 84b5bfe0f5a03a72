"""The door every Hydra main of ``resireg_train`` goes through: :func:`hydra_entry_point`
(Hydra composes ``conf/<name>.yaml``, the task runs, the sweeper gets its value) and
:func:`run_task`, the wrapper that gives every job its run record
(:class:`~resireg_train.record.run_record.RunRecord`: status, provenance, trackers, final status),
records a failure in it and in the run's log file, and returns the value a sweeper optimises.

What a job shows of a failure is :mod:`resireg_train.jobs.console`'s; a multirun ends with one
line per failed job, or, when none failed, one line naming its sweep folder and the
``resireg-report`` command (:mod:`resireg_train.jobs.summary`).
"""

from __future__ import annotations

import logging
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import CompactHydraException
from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError, ResiregError
from resireg.secrets import mask_text
from resireg_train.config.moves import current_argv
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.jobs.console import (
    error_text,
    mask_log_handlers,
    masked_console,
    reported_types,
    to_log_files,
)
from resireg_train.jobs.resolvers import register_resolvers
from resireg_train.jobs.run_folder import hold_run_folder, release_run_folder
from resireg_train.jobs.summary import SWEEP, sweep_summary
from resireg_train.record.run_record import RunRecord
from resireg_train.record.settings import RecordSettings

__all__ = [
    "CONFIG_DIR",
    "JobFailed",
    "check_model_registry",
    "hydra_entry_point",
    "optimized_value",
    "run_task",
]

log = logging.getLogger(__name__)


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
        record = RunRecord(out, writer=rank_zero, report=lambda m: to_log_files(m, None))
        return _run_recorded(cfg, body, record, resume_hint, fresh)
    finally:
        if took:
            release_run_folder(out)


def check_model_registry(cfg: DictConfig) -> None:
    """A ``model_path`` in MLflow's model registry (``models:/NAME@ALIAS``), checked before
    the run starts: one that is not of the registry's two forms is a :class:`ConfigError`,
    a registry that does not answer within ``tracker.mlflow.check_timeout`` seconds a
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
            to_log_files(f"run {status}: {error}", exc)
        raise
    return record.finish() if record.writer else result



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



def hydra_entry_point(
    config_name: str, task: Callable[[DictConfig], dict[str, Any]]
) -> Callable[[], float | None]:
    """A console entry point: Hydra composes ``conf/<config_name>.yaml`` with the command
    line's overrides, ``task`` runs, and :func:`optimized_value` goes back to the sweeper.

    Before Hydra parses the command line, an override in a renamed key's old spelling
    (``logger=mlflow``) is rewritten to the new one with one warning line, and one given in
    both spellings is refused in one line (exit 1; :func:`resireg_train.config.moves.current_argv`).
    A failing job is listed; a multirun ends with one line per failed job (on stderr), after
    Hydra's report of the first one, wherever its jobs ran
    (:class:`~resireg_train.jobs.summary.SweepRecords`)."""
    register_resolvers()
    prog = f"resireg-{config_name}"

    @hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=config_name)
    def main(cfg: DictConfig) -> float | None:
        mask_log_handlers()  # the console and the run's log file: no URL's password
        log.info("output dir: %s", HydraConfig.get().runtime.output_dir)
        try:
            return optimized_value(cfg, task(cfg))
        except Exception as exc:
            if isinstance(exc, reported_types()):
                raise JobFailed(error_text(exc)) from exc
            raise

    def entry() -> float | None:
        SWEEP.clear()
        with masked_console():  # (the warning names the overrides: a URL's password too)
            try:
                sys.argv[1:] = current_argv(
                    config_name, sys.argv[1:], lambda line: print(f"{prog}: warning: {line}",
                                                                  file=sys.stderr)
                )  # fmt: skip
            except ConfigError as err:
                sys.stderr.write(f"{prog}: error: {err}\n")
                raise SystemExit(1) from None
        with masked_console():  # no URL's password on the console, whoever prints it
            try:
                return main()
            finally:
                # (a worker an Optuna search started itself leaves the summary to the search)
                if SWEEP and os.environ.get("RESIREG_SEARCH_WORKER") != "1":
                    sys.stderr.write(sweep_summary(prog, SWEEP["dir"], SWEEP["before"]))

    return entry
