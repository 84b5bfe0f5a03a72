"""A trial's life as the workers see it: who runs it (host, PID) and its heartbeat, which
RUNNING trials belong to dead workers (marked FAIL, optionally enqueued again), which trials
count towards ``n_trials``, and a finished job's outcome (COMPLETE with its value, PRUNED or
FAIL).

Written here rather than taken from Optuna: in Optuna 5.1 only RDBStorage implements
BaseHeartbeat (the journal storage has none), and an ask-and-tell loop would still have to run
Optuna's heartbeat thread itself; one mechanism serves both storages."""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
import warnings
from collections.abc import Sequence
from typing import Any

from resireg_train.search.journal import ATTR_LOST
from resireg_train.search.storage import quiet_optuna

__all__ = [
    "ATTR_HEARTBEAT",
    "ATTR_HOST",
    "ATTR_PID",
    "ATTR_STALE",
    "Heartbeat",
    "counted_trials",
    "fail_stale_trials",
    "outcome",
    "output_dir",
    "stale_reason",
]

log = logging.getLogger(__name__)

#: Trial attributes: the worker that runs it, its heartbeat, a stale trial's mark.
ATTR_HOST, ATTR_PID, ATTR_HEARTBEAT, ATTR_STALE = (
    "worker_host", "worker_pid", "resireg:heartbeat", "resireg:stale",
)  # fmt: skip


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
        log.warning("trial %d: %s: marked FAIL%s", trial.number, stale_reason(trial),
                    "; enqueued again" if retries else "")  # fmt: skip
        if retries:
            with warnings.catch_warnings():  # experimental in Optuna 5.1
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                retry = RetryHeartbeatStaleTrialCallback(max_retry=retries)
            retry(study, storage.get_trial(trial._trial_id))
    return failed


def stale_reason(trial: Any) -> str:
    """Why a RUNNING trial was failed as stale: its result lost with a journal line cut
    mid-write (:data:`~resireg_train.search.journal.ATTR_LOST`: its worker had ended it), else
    its worker died mid-trial."""
    if journal := trial.system_attrs.get(ATTR_LOST):
        return (f"its result was lost: the last line of {journal}, which held it, was cut "
                "mid-write")
    return (f"its worker (host {trial.user_attrs.get(ATTR_HOST)}, PID "
            f"{trial.user_attrs.get(ATTR_PID)}) died mid-trial")


def counted_trials(trials: Sequence[Any]) -> list[Any]:
    """The trials that count towards ``n_trials``: finished ones (COMPLETE, PRUNED, FAIL), but
    not a trial failed because its worker died (it ran no job to its end; a fresh or retried
    trial replaces it)."""
    from optuna.trial import TrialState

    done = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)
    return [t for t in trials if t.state in done and not t.system_attrs.get(ATTR_STALE)]


class Heartbeat:
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

    def __enter__(self) -> Heartbeat:
        self.storage.set_trial_system_attr(self.trial_id, ATTR_HEARTBEAT, time.time())
        self.thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop.set()
        self.thread.join()


def output_dir(ret: Any) -> str | None:
    """The run folder of a finished job (Hydra's JobReturn), if it has one."""
    try:
        return str(ret.hydra_cfg.hydra.runtime.output_dir)
    except Exception:
        return None


def outcome(ret: Any) -> tuple[Any, float | None]:
    """(state, value) of a finished job: PRUNED if the pruner stopped it, FAIL if it raised
    or scored nothing finite (a NaN score, a diverged run), else COMPLETE with its value."""
    from hydra.core.utils import JobStatus
    from optuna.trial import TrialState

    optuna = quiet_optuna()
    if ret.status != JobStatus.COMPLETED:
        if isinstance(ret._return_value, optuna.TrialPruned):
            return TrialState.PRUNED, None
        return TrialState.FAIL, None
    value = ret.return_value
    if value is None or not math.isfinite(float(value)):
        return TrialState.FAIL, None
    return TrialState.COMPLETE, float(value)
