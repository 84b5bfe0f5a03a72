"""The search loop (``hparams_search=<name>``, docs/runs.md#run-records-and-faults, Optuna
searches): what the project's Hydra sweeper (``hydra/sweeper=resireg_optuna``) runs in every
process of a search, the first one and each worker.

One study, any number of workers. Each worker runs the same ask-and-tell loop: under the sweep
folder's lock it marks the trials of dead workers failed (:mod:`.trials`), counts the study's
trials, and asks a new trial only while the study holds fewer than ``n_trials`` (its total
across workers and invocations: a resumed or extended search runs only what is missing and
never reruns a finished trial); the trial runs as a normal Hydra job (its own run folder and
``results.json``; job number = trial number) and is told COMPLETE, PRUNED or FAIL. The first
process also records the search for its workers (:mod:`.workers`) and starts
``hparams_search.workers - 1`` of them. Optuna loads only when a search runs or is reported.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError, ResiregError
from resireg.secrets import mask_url
from resireg_train.search.journal import JournalError
from resireg_train.search.space import check_metric, distributions, format_value
from resireg_train.search.storage import (
    STORAGE_ENV,
    open_storage,
    quiet_optuna,
    storage_override,
    storage_url,
)
from resireg_train.search.trials import (
    ATTR_HOST,
    ATTR_PID,
    Heartbeat,
    counted_trials,
    fail_stale_trials,
    outcome,
    output_dir,
)
from resireg_train.search.workers import (
    WORKER_ENV,
    SearchRecordError,
    read_record,
    recorded_overrides,
    sigterm_ends,
    start_workers,
    write_record,
)

__all__ = ["ATTR_TRAINER", "LOCK_FILE", "REFUSALS", "OptunaSearch", "SearchError", "run_search"]

log = logging.getLogger(__name__)

#: The lock the workers take to count trials and ask one (so the total is never exceeded).
LOCK_FILE = ".search.lock"
#: The study's user attribute holding the ``trainer`` config every worker trains with.
ATTR_TRAINER = "resireg:trainer"


class SearchError(ResiregError, RuntimeError):
    """A search that cannot go on (too many failed trials, a failed worker); the message says
    why."""


#: The errors a search stops with in one line (the sweeper prints them without a traceback).
REFUSALS = (ConfigError, SearchError, SearchRecordError, JournalError)


class OptunaSearch:
    """One worker's ask-and-tell loop over a study (see the module docstring). ``run_job``
    runs one trial's job from its overrides and job number and returns Hydra's JobReturn."""

    def __init__(self, cfg: DictConfig, sweep_dir: Path, settings: DictConfig) -> None:
        self.cfg, self.sweep_dir, self.s = cfg, Path(sweep_dir), settings

    def study(self) -> Any:
        import hydra

        optuna = quiet_optuna()
        sampler = self._sampler(0)
        pruner_cfg = self.s.get("pruner")
        pruner = hydra.utils.instantiate(pruner_cfg) if pruner_cfg else optuna.pruners.NopPruner()
        storage = open_storage(self.s.get("storage"), self.sweep_dir)
        study = optuna.create_study(
            storage=storage, sampler=sampler, pruner=pruner, study_name=self.s.study_name,
            direction=self.s.direction, load_if_exists=True,
        )  # fmt: skip
        return study

    def _sampler(self, number: int) -> Any:
        """The configured sampler, its ``seed`` moved on by ``number`` (the trial about to be
        asked): Optuna's samplers keep their random state in the process, so two workers, or
        a resumed search, seeded alike would draw the same parameters again (TPE's startup
        trials are random draws); seeded per trial number, each trial's draw is new and a
        one-worker search is reproducible."""
        import hydra

        conf = self.s.get("sampler")
        if not conf:
            return None
        seed = conf.get("seed")
        if seed is None:
            return hydra.utils.instantiate(conf)
        return hydra.utils.instantiate(conf, seed=int(seed) + int(number))

    def _reserve(self, study: Any, space: dict[str, Any]) -> Any | None:
        """Under the sweep folder's lock: fail dead workers' trials, then ask a trial if the
        study still holds fewer than ``n_trials`` counted and running ones (else ``None``)."""
        from filelock import FileLock
        from optuna.trial import TrialState

        with FileLock(str(self.sweep_dir / LOCK_FILE)):
            fail_stale_trials(study, float(self.s.grace_period), int(self.s.retries or 0))
            trials = study.get_trials(deepcopy=False)
            counted = counted_trials(trials)
            running = [t for t in trials if t.state == TrialState.RUNNING]
            self._check_failures(counted)
            if len(counted) >= int(self.s.n_trials):
                return None  # the study is complete
            if len(counted) + len(running) >= int(self.s.n_trials):
                return _WAIT  # the last trials run elsewhere: wait, take over if one dies
            # (enqueued, WAITING trials are not drawn by the sampler: not counted)
            study.sampler = self._sampler(sum(t.state != TrialState.WAITING for t in trials))
            trial = study.ask(space)
            trial.set_user_attr(ATTR_HOST, socket.gethostname())
            trial.set_user_attr(ATTR_PID, os.getpid())
            return trial

    def _check_trainer(self, study: Any) -> None:
        """Every worker of a training search trains its trials alike: the first to run notes
        its resolved ``trainer`` config in the study (user attribute :data:`ATTR_TRAINER`);
        a worker whose ``trainer`` differs (another machine's ``trainer.devices``, another
        strategy) is refused naming each differing key, before it asks a trial (its scores
        would not be comparable with the study's)."""
        from filelock import FileLock

        from resireg.specs.tree import MISSING, differences

        if "trainer" not in self.cfg:
            return  # an evaluation's search
        mine = OmegaConf.to_container(self.cfg.trainer, resolve=True)
        with FileLock(str(self.sweep_dir / LOCK_FILE)):
            noted = study.user_attrs.get(ATTR_TRAINER)
            if noted is None:
                study.set_user_attr(ATTR_TRAINER, mine)
                return
        found = differences({"trainer": noted}, {"trainer": mine})
        if found:
            shown = "; ".join(
                f"{key}={'(unset)' if now is MISSING else repr(now)} (the study's: "
                f"{'(unset)' if then is MISSING else repr(then)})"
                for key, then, now in found
            )
            raise ConfigError(
                f"this worker's trainer differs from the one study {study.study_name!r} "
                f"trains its trials with: {shown}; every worker of a search trains alike: "
                "start it with the search's trainer settings, or start a new search "
                "(another hydra.sweep.dir or study)"
            )

    def _check_failures(self, counted: list[Any]) -> None:
        from optuna.trial import TrialState

        failed = sum(t.state == TrialState.FAIL for t in counted)
        rate = float(self.s.max_failure_rate)
        if counted and failed > 1 and failed / len(counted) > rate:
            raise SearchError(
                f"{failed} of {len(counted)} trials failed, more than "
                f"hydra.sweeper.max_failure_rate={rate}: the search stops (resireg-report "
                f"{self.sweep_dir} lists why each failed)"
            )

    def run(self, fixed: list[str], space: dict[str, Any], run_job: Any) -> int:
        """Run trials until the study holds ``n_trials`` finished ones (waiting while other
        workers run the last ones, taking over a dead one's); returns how many this ran."""
        optuna = quiet_optuna()
        from optuna.trial import TrialState

        study = self.study()
        self._check_trainer(study)
        enqueue = self.s.get("enqueue") or []
        if enqueue:
            from filelock import FileLock

            with FileLock(str(self.sweep_dir / LOCK_FILE)):
                if not study.get_trials(deepcopy=False):  # a new study: these first
                    for params in enqueue:
                        study.enqueue_trial(OmegaConf.to_container(params), skip_if_exists=True)
        ran = 0
        poll = min(5.0, float(self.s.heartbeat_interval))
        while (trial := self._reserve(study, space)) is not None:
            if trial is _WAIT:
                time.sleep(poll)
                continue
            overrides = [*fixed, *(f"{k}={format_value(v)}" for k, v in trial.params.items()),
                         f"hparams_search.trial={trial.number}"]  # fmt: skip
            log.info("trial %d: %s", trial.number, " ".join(overrides[len(fixed) :]))
            with Heartbeat(study._storage, trial._trial_id, float(self.s.heartbeat_interval)):
                ret = run_job(overrides, trial.number)
            ran += 1
            out = output_dir(ret)
            if out:
                trial.set_user_attr("run_dir", out)
            state, value = outcome(ret)
            try:
                if state == TrialState.COMPLETE:
                    study.tell(trial, value)
                else:
                    study.tell(trial, state=state)
            except optuna.exceptions.UpdateFinishedTrialError:
                # marked FAIL meanwhile by another worker (a missed heartbeat): keep its verdict
                log.warning("trial %d was marked finished by another worker", trial.number)
            log.info("trial %d: %s %s", trial.number, state.name, "" if value is None else value)
        return ran


#: :meth:`OptunaSearch._reserve`'s answer while other workers run the study's last trials.
_WAIT: Any = object()


def _split(arguments: list[str], params: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """The command line's task overrides as the fixed overrides of every trial and the search
    axes: a sweep override adds or replaces an axis, a fixed value takes its key out of the
    search."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    fixed = []
    for override in OverridesParser.create().parse_overrides(arguments):
        if override.is_sweep_override():  # a search axis given on the command line
            params[override.key_or_group] = override.input_line.split("=", 1)[1]
        else:
            fixed.append(override.input_line)
            params.pop(override.key_or_group, None)
    return fixed, params


def run_search(config: DictConfig, settings: DictConfig, arguments: list[str], run_job: Any) -> int:
    """One process of a search: check the settings, the space and the metric before the first
    trial; in the first process record the search (``search.json``) and start its other
    workers; run the loop; wait for the workers. ``run_job(overrides, number)`` runs one
    trial's job (Hydra's launcher). Returns how many trials this process ran; raises one of
    :data:`REFUSALS` with a one-line message."""
    sweep_dir = Path(str(config.hydra.sweep.dir)).resolve()
    sweep_dir.mkdir(parents=True, exist_ok=True)
    fixed, params = _split(list(arguments), dict(settings.get("params") or {}))
    try:
        for key in ("workers", "n_trials"):
            value = settings.get(key)
            least = 1 if key == "workers" else 0
            if not isinstance(value, int) or value < least:
                raise ConfigError(f"hparams_search.{key}={value!r}: expected an integer >= {least}")
        space = distributions(params)
        check_metric(config)
        if "trainer" in config:
            from resireg_train.search.ranks import trial_nodes_problem

            problem = trial_nodes_problem(OmegaConf.to_container(config.trainer, resolve=True))
            if problem:
                raise ConfigError(problem)
        url = storage_url(settings.get("storage"))
    except ConfigError as err:
        raise ConfigError(f"refused before the first trial: {err}") from None
    if url is not None and mask_url(url) != url:
        # The password reaches this process's jobs and its workers through the environment,
        # never a trial's config (Hydra writes it into the trial's folder)
        os.environ[STORAGE_ENV] = url
        fixed = [o for o in fixed if not o.lstrip("+").startswith("hparams_search.storage=")]
        fixed.append(storage_override(url))
    procs = []
    if os.environ.get(WORKER_ENV) != "1":
        if url is not None:  # the database's tables, made before any worker opens it
            open_storage(settings.get("storage"), sweep_dir)
        hydra = OmegaConf.to_container(config.hydra.overrides.hydra)
        task = OmegaConf.to_container(config.hydra.overrides.task)
        write_record(sweep_dir, str(config.hydra.job.config_name),
                     recorded_overrides(task, hydra), settings.get("storage"),
                     str(settings.study_name))  # fmt: skip
        if int(settings.workers) > 1:
            procs = start_workers(sweep_dir, int(settings.workers) - 1)
        else:
            try:
                read_record(sweep_dir)
            except SearchRecordError as err:
                log.warning("resireg-search worker would refuse this search: %s", err)
    try:
        with sigterm_ends(procs):  # kill <pid> of the search ends the workers it started too
            ran = OptunaSearch(config, sweep_dir, settings).run(fixed, space, run_job)
    except BaseException:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            proc.wait()
        raise
    codes = [proc.wait() for proc in procs]
    log.info("this worker ran %d trials; %d other workers ended with %s", ran, len(procs),
             codes)  # fmt: skip
    if any(codes):
        raise SearchError(f"a worker of the search in {sweep_dir} failed (exit codes {codes})")
    return ran
