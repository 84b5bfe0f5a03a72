"""Optuna searches (``hparams_search=<name>``, docs/guide.md#run-records-and-faults, Optuna searches):
the study's storage, the search space, the ask-and-tell loop that the project's Hydra sweeper
(``hydra/sweeper=resireg_optuna``) and its workers run, and the study as the report reads it.

One study, any number of workers. Each worker runs the same loop: under the sweep folder's
lock it marks the trials of dead workers failed, counts the study's trials, and asks a new
trial only while the study holds fewer than ``n_trials`` (its total across workers and
invocations: a resumed or extended search runs only what is missing and never reruns a
finished trial); the trial runs as a normal Hydra job (its own run folder and
``results.json``; job number = trial number) and is told COMPLETE, PRUNED or FAIL.

Storage: Optuna's journal (``<sweep>/optuna.journal``, JournalFileBackend with its link lock)
unless ``hparams_search.storage`` names a database URL. A worker that dies mid-trial: its trial
holds the worker's host and PID and a heartbeat (a system attribute, written every
``heartbeat_interval`` seconds); any worker or a resumed search marks it FAIL when its
process is gone (same host) or its heartbeat is older than ``grace_period`` (another host),
and optionally enqueues it again (``RetryHeartbeatStaleTrialCallback``, ``retries``). Written here
rather than taken from Optuna: in Optuna 5.1 only RDBStorage implements BaseHeartbeat (the
journal storage has none), and an ask-and-tell loop would still have to run Optuna's
heartbeat thread itself; one mechanism serves both storages. Optuna loads only when a search
runs or is reported.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shlex
import socket
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from resireg.errors import ResiregError
from resireg.specs.metrics import METRIC_SPECS

__all__ = [
    "SEARCH_FILE",
    "STUDY_FILE",
    "OptunaSearch",
    "SearchError",
    "check_metric",
    "counted_trials",
    "distributions",
    "fail_stale_trials",
    "quiet_optuna",
    "load_study",
    "open_storage",
    "register_search_resolvers",
    "worker_main",
]

log = logging.getLogger(__name__)

#: The study's journal file in the sweep folder (default storage).
STUDY_FILE = "optuna.journal"
#: The command that started the search (what ``resireg-search worker <sweep>`` runs again).
SEARCH_FILE = "search.json"
#: The lock the workers take to count trials and ask one (so the total is never exceeded).
LOCK_FILE = ".search.lock"
#: Trial attributes: the worker that runs it, its heartbeat, a stale trial's mark.
ATTR_HOST, ATTR_PID, ATTR_HEARTBEAT, ATTR_STALE = (
    "worker_host", "worker_pid", "resireg:heartbeat", "resireg:stale",
)  # fmt: skip
#: Set in the processes the search starts itself (workers > 1): they start no others.
WORKER_ENV = "RESIREG_SEARCH_WORKER"


def quiet_optuna() -> Any:
    """Optuna, its messages through the logging configuration of the process (Hydra's: the
    job's log file and console, each line once, no colour codes) instead of its own handler."""
    import optuna

    optuna.logging.disable_default_handler()
    optuna.logging.enable_propagation()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


def open_storage(storage: str | None, sweep_dir: str | Path) -> Any:
    """The study's storage: a journal file in ``sweep_dir`` (``storage`` unset or
    ``journal``), or Optuna's RDBStorage for a database URL (``postgresql+psycopg://...``,
    ``sqlite:///...``). A database that cannot be reached is a ConfigError naming the key."""
    optuna = quiet_optuna()
    from optuna.storages.journal import JournalFileBackend

    if storage in (None, "", "journal"):
        folder = Path(str(sweep_dir))
        folder.mkdir(parents=True, exist_ok=True)
        path = str(folder / STUDY_FILE)
        # Its default lock (JournalFileSymlinkLock: link(2), atomic on NFSv2 and later), the
        # one optuna-dashboard takes on the same file
        return optuna.storages.JournalStorage(JournalFileBackend(path))
    from resireg.errors import ConfigError

    try:
        return optuna.storages.RDBStorage(str(storage))
    except Exception as err:  # sqlalchemy's errors: a wrong URL, a server that is down
        raise ConfigError(
            f"hparams_search.storage={storage!r} cannot be opened: {type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''}"
        ) from None


def load_study(sweep_dir: str | Path, storage: str | None = None, study_name: str | None = None):
    """The sweep's ``optuna.Study`` (its only study unless ``study_name``), or ``None``."""
    if storage in (None, "", "journal") and not (Path(sweep_dir) / STUDY_FILE).is_file():
        return None
    optuna = quiet_optuna()
    store = open_storage(storage, sweep_dir)
    names = [s.study_name for s in optuna.get_all_study_summaries(store)]
    if study_name is None:
        if len(names) != 1:
            return None
        study_name = names[0]
    if study_name not in names:
        return None
    return optuna.load_study(study_name=study_name, storage=store)


# --------------------------------------------------------------------------- search space
def _interval(low: Any, high: Any, log_scale: bool) -> Any:
    from optuna.distributions import FloatDistribution, IntDistribution

    if isinstance(low, int) and isinstance(high, int):
        return IntDistribution(low, high, log=log_scale)
    return FloatDistribution(float(low), float(high), log=log_scale)


def distributions(params: dict[str, str]) -> dict[str, Any]:
    """Optuna distributions of Hydra sweep expressions: ``choice(a, b)`` (categorical),
    ``interval(lo, hi)`` (float, or int if both ends are), ``range(start, stop, step)``
    (Python's range: ``stop`` excluded, so the highest value is the last one the range
    reaches: no range is ever "not divisible by its step"), ``tag(log, ...)`` log scale."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, RangeSweep
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    from resireg.errors import ConfigError

    parser = OverridesParser.create()
    out = {}
    for key, expr in params.items():
        try:
            (override,) = parser.parse_overrides([f"{key}={expr}"])
        except Exception as err:
            raise ConfigError(f"hydra.sweeper.params.{key}={expr!r}: {err}") from None
        value = override.value()
        log_scale = "log" in getattr(value, "tags", set())
        if isinstance(value, ChoiceSweep):
            out[key] = CategoricalDistribution(list(value.list))
        elif isinstance(value, IntervalSweep):
            out[key] = _interval(value.start, value.end, log_scale)
        elif isinstance(value, RangeSweep):
            start, stop, step = value.start, value.stop, value.step or 1
            count = math.ceil((stop - start) / step)
            if count < 1:
                raise ConfigError(f"hydra.sweeper.params.{key}={expr!r} is an empty range")
            last = start + (count - 1) * step
            if all(isinstance(v, int) for v in (start, stop, step)):
                out[key] = IntDistribution(start, last, step=step)
            else:
                out[key] = FloatDistribution(float(start), float(last), step=float(step))
        else:
            raise ConfigError(
                f"hydra.sweeper.params.{key}={expr!r} is not choice(...), interval(...) or "
                "range(...)"
            )
    return out


def _format(value: Any) -> str:
    """A parameter value as a Hydra override value."""
    if isinstance(value, float):
        return repr(value)
    return str(value)


# --------------------------------------------------------------------------- the metric
def check_metric(cfg: DictConfig) -> None:
    """``optimized_metric`` must be one the job logs: ``val/ovss/<dataset>/(f)miou_<variant>``
    with a configured validation dataset (``resireg-train``: ``val_data=``; ``resireg-eval``:
    ``dataset=``) and variant. Checked before the first trial (a search that would train every
    trial and then find nothing to optimise is refused at once)."""
    from resireg.errors import ConfigError

    metric = cfg.get("optimized_metric")
    if not metric:
        raise ConfigError(
            "optimized_metric is not set: an Optuna search needs the metric to optimise"
        )
    parts = str(metric).split("/")
    if len(parts) != 4 or parts[:2] != ["val", "ovss"]:
        return  # another metric (train/loss...): the job checks it when it ends
    callback = OmegaConf.select(cfg, "callbacks.resireg_eval")
    if callback is not None:  # resireg-train: the ReSiRegEval callback's datasets
        datasets = {str(d.get("name", k)) for k, d in (callback.get("datasets") or {}).items()}
        variants = callback.get("variants") or []
        where = "val_data"
    else:  # resireg-eval
        datasets = {str(OmegaConf.select(cfg, "dataset.name"))}
        variants = cfg.get("variants") or []
        where = "dataset"
    variants = [str(v) for v in variants]
    names = sorted(
        f"val/ovss/{d}/{kind}_{v}"
        for d in datasets
        for v in variants
        for kind in METRIC_SPECS["pixels"].logged  # the OVSS engine logs these
    )
    if metric not in names:
        raise ConfigError(
            f"optimized_metric={metric!r} is never logged with the configured validation data "
            f"({where}: {sorted(datasets)}, variants {variants}); it logs: {names}"
        )


# --------------------------------------------------------------------------- trial states
def _is_stale(trial: Any, grace_period: float, now: float) -> bool:
    """A RUNNING trial whose worker is gone: same host and its process no longer exists, or
    its heartbeat older than ``grace_period`` seconds."""
    host, pid = trial.user_attrs.get(ATTR_HOST), trial.user_attrs.get(ATTR_PID)
    if host == socket.gethostname() and pid is not None:
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            pass  # another user's live process
    beat = trial.system_attrs.get(ATTR_HEARTBEAT, trial.datetime_start.timestamp()
                                  if trial.datetime_start else now)  # fmt: skip
    return now - float(beat) > grace_period


def fail_stale_trials(study: Any, grace_period: float, retries: int = 0) -> list[int]:
    """Mark FAIL the RUNNING trials of dead workers (:func:`_is_stale`), noting it in their
    system attributes; with ``retries`` > 0 Optuna's RetryHeartbeatStaleTrialCallback (formerly
    RetryFailedTrialCallback) enqueues each
    again (same parameters, at most ``retries`` times). Returns the trial numbers failed."""
    optuna = quiet_optuna()
    from optuna.storages import RetryHeartbeatStaleTrialCallback
    from optuna.trial import TrialState

    storage, failed = study._storage, []
    now = time.time()
    for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        if not _is_stale(trial, grace_period, now):
            continue
        try:
            storage.set_trial_system_attr(trial._trial_id, ATTR_STALE, True)
            storage.set_trial_state_values(trial._trial_id, state=TrialState.FAIL)
        except optuna.exceptions.UpdateFinishedTrialError:
            continue  # another worker got there first
        failed.append(trial.number)
        log.warning(
            "trial %d: its worker (host %s, PID %s) died mid-trial: marked FAIL%s", trial.number,
            trial.user_attrs.get(ATTR_HOST), trial.user_attrs.get(ATTR_PID),
            "; enqueued again" if retries else "",
        )  # fmt: skip
        if retries:
            with warnings.catch_warnings():  # experimental in Optuna 5.1
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                retry = RetryHeartbeatStaleTrialCallback(max_retry=retries)
            retry(study, storage.get_trial(trial._trial_id))
    return failed


def counted_trials(trials: Sequence[Any]) -> list[Any]:
    """The trials that count towards ``n_trials``: finished ones (COMPLETE, PRUNED, FAIL), but
    not a trial failed because its worker died (it ran no job to its end; a fresh or retried
    trial replaces it)."""
    from optuna.trial import TrialState

    done = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
    return [t for t in trials if t.state in done and not t.system_attrs.get(ATTR_STALE)]


class _Heartbeat:
    """Writes the trial's heartbeat every ``interval`` seconds while its job runs."""

    def __init__(self, storage: Any, trial_id: int, interval: float) -> None:
        self.storage, self.trial_id, self.interval = storage, trial_id, interval
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="search-heartbeat")

    def _run(self) -> None:
        while not self.stop.wait(self.interval):
            try:
                self.storage.set_trial_system_attr(self.trial_id, ATTR_HEARTBEAT, time.time())
            except Exception as err:  # a finished trial, a storage hiccup: the next beat retries
                log.debug("heartbeat of trial %d: %s", self.trial_id, err)

    def __enter__(self) -> _Heartbeat:
        self.storage.set_trial_system_attr(self.trial_id, ATTR_HEARTBEAT, time.time())
        self.thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop.set()
        self.thread.join()


# --------------------------------------------------------------------------- the loop
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
            overrides = [*fixed, *(f"{k}={_format(v)}" for k, v in trial.params.items()),
                         f"hparams_search.trial={trial.number}"]  # fmt: skip
            log.info("trial %d: %s", trial.number, " ".join(overrides[len(fixed) :]))
            with _Heartbeat(study._storage, trial._trial_id, float(self.s.heartbeat_interval)):
                ret = run_job(overrides, trial.number)
            ran += 1
            out = _output_dir(ret)
            if out:
                trial.set_user_attr("run_dir", out)
            state, value = _outcome(ret, optuna)
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


class SearchError(ResiregError, RuntimeError):
    """A search that cannot go on (too many failed trials); the message says why."""


def _output_dir(ret: Any) -> str | None:
    try:
        return str(ret.hydra_cfg.hydra.runtime.output_dir)
    except Exception:
        return None


def _outcome(ret: Any, optuna: Any) -> tuple[Any, float | None]:
    """(state, value) of a finished job: PRUNED if the pruner stopped it, FAIL if it raised
    or scored nothing finite (a NaN score, a diverged run), else COMPLETE with its value."""
    from hydra.core.utils import JobStatus
    from optuna.trial import TrialState

    if ret.status != JobStatus.COMPLETED:
        if isinstance(ret._return_value, optuna.TrialPruned):
            return TrialState.PRUNED, None
        return TrialState.FAIL, None
    value = ret.return_value
    if value is None or not math.isfinite(float(value)):
        return TrialState.FAIL, None
    return TrialState.COMPLETE, float(value)


# --------------------------------------------------------------------------- workers
def save_command(sweep_dir: Path, argv: Sequence[str], storage: str | None, study: str) -> None:
    """Record the command of a search in ``<sweep>/search.json`` (what its workers run), its
    storage and study (what the report opens). A resumed search keeps the first record."""
    from resireg.integrity import atomic_write

    if (sweep_dir / SEARCH_FILE).is_file():
        return
    record = {"argv": list(argv), "cwd": os.getcwd(), "storage": storage, "study_name": study}
    text = json.dumps(record, indent=1)
    atomic_write(sweep_dir / SEARCH_FILE, lambda tmp: tmp.write_text(text))


def worker_command(sweep_dir: Path) -> list[str]:
    """The command of one more worker of the search in ``sweep_dir``: its first command with
    one worker and the sweep folder fixed (``hydra.sweep.dir``)."""
    record = search_record(sweep_dir)
    argv = [a for a in record["argv"] if not a.startswith(("hparams_search.workers=",
                                                           "hydra.sweep.dir="))]  # fmt: skip
    return [*argv, "hparams_search.workers=1", f"hydra.sweep.dir={sweep_dir.resolve()}"]


def search_record(sweep_dir: str | Path) -> dict[str, Any]:
    """``<sweep>/search.json`` (empty if absent)."""
    path = Path(sweep_dir) / SEARCH_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def _search_cwd(sweep_dir: Path) -> str:
    """The first command's working folder (its relative paths), if it still exists here."""
    cwd = search_record(sweep_dir).get("cwd")
    return cwd if cwd and Path(cwd).is_dir() else os.getcwd()


def start_workers(sweep_dir: Path, count: int) -> list[subprocess.Popen]:
    """Start ``count`` more workers of this search, one device each where
    ``CUDA_VISIBLE_DEVICES`` lists several (worker i gets device i modulo their number)."""
    devices = [d for d in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if d.strip()]
    procs = []
    for i in range(count):
        env = {**os.environ, WORKER_ENV: "1"}
        if len(devices) > 1:
            env["CUDA_VISIBLE_DEVICES"] = devices[(i + 1) % len(devices)]
        cmd = [sys.executable, *worker_command(sweep_dir)]
        procs.append(subprocess.Popen(cmd, env=env, cwd=_search_cwd(sweep_dir)))
    return procs


def worker_main(argv: Sequence[str] | None = None) -> int:
    """``resireg-search worker <sweep>``: one more worker of the search in ``<sweep>`` (e.g.
    one per SLURM array task; the sweep folder on a shared file system, or the study in a
    database given by the first command's ``hparams_search.storage``)."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="resireg-search",
        description="Run one more worker of an Optuna search (hparams_search=...): it pulls "
        "trials from the search's study until the study holds hparams_search.n_trials.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    worker = sub.add_parser("worker", help="run one worker of the search in SWEEP")
    worker.add_argument("sweep", type=Path, help="the search's sweep folder (hydra.sweep.dir)")
    worker.add_argument("overrides", nargs="*", help="extra overrides (e.g. device=cuda:0)")
    args = parser.parse_args(argv)
    if not (args.sweep / SEARCH_FILE).is_file():
        parser.error(f"{args.sweep} holds no {SEARCH_FILE}: not the folder of a search started "
                     "with hparams_search=<name>")  # fmt: skip
    cmd = [sys.executable, *worker_command(args.sweep), *args.overrides]
    log.info("%s", shlex.join(cmd))
    return subprocess.call(cmd, env={**os.environ, WORKER_ENV: "1"}, cwd=_search_cwd(args.sweep))


def main() -> None:
    sys.exit(worker_main())


def _first_key(node: Any) -> str:
    """``${first_key:${callbacks.resireg_eval.datasets}}``: the name of the first configured
    validation dataset (the metric a training search optimises follows ``val_data=``)."""
    if not node:
        return "<no validation dataset: val_data= is empty>"
    key = next(iter(node))
    return str(node[key].get("name", key)) if hasattr(node[key], "get") else str(key)


def register_search_resolvers() -> None:
    """``first_key`` for ``conf/hparams_search/``."""
    if not OmegaConf.has_resolver("first_key"):
        OmegaConf.register_new_resolver("first_key", _first_key)


if __name__ == "__main__":  # python -m resireg_train.sweeps.search worker <sweep>
    main()
