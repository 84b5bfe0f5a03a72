"""A search trial that trains with a strategy that re-launches the command line (Lightning's
``ddp``: ``trainer=ddp``, or ``devices`` > 1 without a spawning strategy): the worker starts
the trial's ranks itself, as ``torchrun`` would, instead of letting Lightning re-launch the
search's own command line (which is a search: every re-launched rank would run a search of
its own, ask trials of its own and join the other trials' process groups).

Each rank runs the trial's job alone (``hydra.mode=RUN`` in the trial's run folder, the
trial's overrides) with the environment Lightning reads for processes created outside it
(``LOCAL_RANK``, ``NODE_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` / ``MASTER_PORT`` on a free
port; ``RANK``), so Lightning starts no process. The ranks share one process group of their
own; the worker watches them: the first rank that exits with an error stops the others
(SIGTERM, SIGKILL after :data:`GRACE` seconds) and is named in the trial's error, ranks still
running :data:`GRACE` seconds after rank 0 ended are stopped, and whatever happens (Ctrl-C,
SIGTERM to the worker) no rank outlives the trial. Global rank 0 alone asks the study,
reports and decides pruning (:class:`~resireg_train.search.pruning.OptunaPruning`, which
broadcasts its decision to every rank).

A trial on several nodes (``trainer.num_nodes`` > 1) needs a launcher that starts the ranks
on the other nodes: the command prefix in the environment variable :data:`TRIAL_LAUNCHER_ENV`
(e.g. ``srun --nodes=2 --ntasks-per-node=4`` inside the worker's SLURM allocation; never
recorded in ``search.json``, which holds no command). The worker then runs
``<prefix> python -m resireg_train.cli.train <the trial's overrides>`` once, in a process group
of its own, with ``MASTER_PORT`` on a port free on its machine; the launcher's ranks read
their ranks from its environment (SLURM's: Lightning's SLURM environment), and a failed trial
names the launcher's exit code (which rank failed is the launcher's to say)."""

from __future__ import annotations

import contextlib
import os
import shlex
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from resireg.errors import ResiregError
from resireg_train.search.workers import sigterm_ends

__all__ = [
    "GRACE",
    "TRIAL_LAUNCHER_ENV",
    "TRIAL_RANK_ENV",
    "RankFailure",
    "TrialRankFailed",
    "local_processes",
    "relaunches",
    "run_ranks",
    "trial_nodes_problem",
]

#: Seconds the other ranks get to end after one failed or rank 0 ended, before SIGKILL.
GRACE = 10.0
#: Set in the processes of a trial's ranks: they report a pruned trial through its record and
#: exit 0 (the worker tells the study).
TRIAL_RANK_ENV = "RESIREG_SEARCH_TRIAL_RANK"
#: The command prefix that starts a trial's ranks on several nodes (``srun ...``).
TRIAL_LAUNCHER_ENV = "RESIREG_SEARCH_TRIAL_LAUNCHER"
#: Strategies whose processes Lightning starts without re-running the command line.
_IN_PROCESS = ("spawn", "fork", "notebook", "single_device", "deepspeed_stage_0_spawn")


class TrialRankFailed(ResiregError, RuntimeError):
    """A trial whose DDP run failed: the message names the first rank that failed (or says
    the run's own error), on one line."""


@dataclass(frozen=True)
class RankFailure:
    """The first rank of a trial that failed: its global rank, PID and exit code (a negative
    code: the signal that ended it)."""

    rank: int | None  # None: the launcher of TRIAL_LAUNCHER_ENV (its ranks are its own)
    pid: int
    code: int

    def describe(self) -> str:
        how = (f"was killed by {signal.Signals(-self.code).name}" if self.code < 0
               else f"exited with code {self.code}")  # fmt: skip
        if self.rank is None:
            return f"its launcher ({TRIAL_LAUNCHER_ENV}, PID {self.pid}) {how}"
        return (
            f"rank {self.rank} (PID {self.pid}) of its DDP run {how}; the other ranks were stopped"
        )


def trial_nodes_problem(trainer: Mapping[str, Any]) -> str | None:
    """Why a search cannot run trials of ``trainer`` (several nodes and no launcher of
    :data:`TRIAL_LAUNCHER_ENV`), or ``None``."""
    nodes = trainer.get("num_nodes") or 1
    if int(nodes) > 1 and not os.environ.get(TRIAL_LAUNCHER_ENV):
        return (f"trainer.num_nodes={nodes}: a trial on several nodes needs a launcher that "
                f"starts its ranks there: set {TRIAL_LAUNCHER_ENV} (e.g. 'srun "
                f"--nodes={nodes} --ntasks-per-node=<devices>' in the worker's allocation), or "
                "run each trial on one node (trainer.num_nodes=1) with one worker per node")  # fmt: skip
    launcher = os.environ.get(TRIAL_LAUNCHER_ENV)
    if launcher:
        try:
            words = shlex.split(launcher)
        except ValueError as err:
            return f"{TRIAL_LAUNCHER_ENV}={launcher!r}: not a command line ({err})"
        if not words or shutil.which(words[0]) is None:
            return (f"{TRIAL_LAUNCHER_ENV}={launcher!r}: no program "
                    f"{words[0] if words else ''!r} on PATH")  # fmt: skip
    return None


def local_processes(trainer: Mapping[str, Any]) -> int:
    """How many processes Lightning runs on this machine for ``trainer`` (its accelerator and
    ``devices`` as Lightning parses them; 1 when they cannot be parsed here)."""
    from lightning.pytorch.accelerators import CPUAccelerator, CUDAAccelerator

    accelerator = str(trainer.get("accelerator") or "auto")
    devices = trainer.get("devices", "auto")
    try:
        if accelerator in ("gpu", "cuda") or (accelerator == "auto"
                                              and CUDAAccelerator.is_available()):  # fmt: skip
            return len(CUDAAccelerator.parse_devices(devices) or [0])
        if accelerator in ("cpu", "auto"):
            return int(CPUAccelerator.parse_devices(devices))
    except Exception:
        return 1
    return 1


def relaunches(trainer: Mapping[str, Any]) -> bool:
    """Whether Lightning would run ``trainer`` by re-launching the command line (its
    subprocess-script launcher): several processes or nodes, and a strategy that neither
    spawns nor forks them."""
    strategy = trainer.get("strategy") or "auto"
    if isinstance(strategy, Mapping):
        strategy = str(strategy.get("start_method") or strategy.get("_target_") or "")
    if any(word in str(strategy) for word in _IN_PROCESS):
        return False
    nodes = trainer.get("num_nodes") or 1
    return int(nodes) > 1 or local_processes(trainer) > 1


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _stop(procs: Sequence[subprocess.Popen], group: int) -> None:
    """SIGTERM to the ranks still running, SIGKILL to the whole group after :data:`GRACE`."""
    for proc in procs:
        if proc.poll() is None:
            with contextlib.suppress(OSError):
                proc.terminate()
    deadline = time.monotonic() + GRACE
    while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
        time.sleep(0.1)
    with contextlib.suppress(OSError):
        os.killpg(group, signal.SIGKILL)  # data loader workers and the like, too
    for proc in procs:
        proc.wait()


def run_ranks(
    commands: Sequence[Sequence[str]], env: Mapping[str, str], ranks: bool = True
) -> RankFailure | None:
    """Run a trial's ranks, ``commands[k]`` as local (and global) rank ``k``, in ``env`` with
    each rank's variables, in one process group of their own; returns the first rank that
    failed (``None`` when all ended with 0). ``ranks=False``: one command, a launcher that
    starts the ranks itself (:data:`TRIAL_LAUNCHER_ENV`; only ``MASTER_PORT`` is set). Every
    process has ended when this returns or raises."""
    port, world = _free_port(), len(commands)
    procs: list[subprocess.Popen] = []
    group = 0
    try:
        for rank, command in enumerate(commands):
            if ranks:
                rank_env = {**env, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port),
                            "WORLD_SIZE": str(world), "NODE_RANK": "0",
                            "LOCAL_RANK": str(rank), "RANK": str(rank),
                            TRIAL_RANK_ENV: "1"}  # fmt: skip
                rank_env.pop("GROUP_RANK", None)
            else:
                rank_env = {**env, "MASTER_PORT": str(port), TRIAL_RANK_ENV: "1"}
            procs.append(subprocess.Popen(list(command), env=rank_env, process_group=group))
            group = group or procs[0].pid
        with sigterm_ends(procs):  # kill <pid> of the worker ends the trial's ranks too
            failure, ended = None, None
            while True:
                codes = [p.poll() for p in procs]
                bad = [(k, c) for k, c in enumerate(codes) if c not in (None, 0)]
                if bad:
                    rank, code = bad[0]
                    failure = RankFailure(rank if ranks else None, procs[rank].pid, code)
                    break
                if all(c == 0 for c in codes):
                    break
                if codes[0] == 0:  # rank 0 ended: the others follow within the grace period
                    ended = ended or time.monotonic()
                    if time.monotonic() - ended > GRACE:
                        break
                time.sleep(0.1)
    except BaseException:
        if procs:
            for proc in procs:  # Ctrl-C: as a terminal's would, then the grace period
                with contextlib.suppress(OSError):
                    proc.send_signal(signal.SIGINT)
            _stop(procs, group)
        raise
    _stop(procs, group)
    return failure
