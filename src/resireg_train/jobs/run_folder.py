"""The run folder's lock: one job writes a folder at a time (``fcntl.flock`` on its lock file,
with the holder's PID), taken before Hydra writes into a single run's folder
(:class:`RunFolderLock`) or by the task wrapper for a sweep job."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

try:  # POSIX; where it is missing (Windows) run folders are not locked
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

from resireg.errors import ConfigError, ResiregError
from resireg_train.config.machine import check_cluster, config_rank

__all__ = ["LOCK_FILE", "RunFolderBusy", "RunFolderLock", "hold_run_folder", "release_run_folder"]


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
        holder = _holder(handle)
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


def _holder(handle: Any, wait: float = 2.0) -> str:
    """The PID the lock file's holder wrote. It writes it just after taking the lock: a job
    started at the same moment can find the lock taken and the file still empty, so the file
    is read again for up to ``wait`` seconds before the holder is said to be starting."""
    deadline = time.monotonic() + wait
    while True:
        handle.seek(0)
        holder = handle.read().strip()
        if holder or time.monotonic() >= deadline:
            return holder or "unknown (it is starting)"
        time.sleep(0.02)


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
    locked by :func:`resireg_train.cli.job.run_task`; ranks > 0 of a DDP run (re-launched by Lightning into rank 0's
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

