"""The end of a multirun: one line per failed job (Hydra itself reports only the first), or,
when none failed, one line naming its sweep folder and the ``resireg-report`` command, read from
the jobs' records wherever they ran."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from resireg_train.jobs.console import mask_log_handlers
from resireg_train.record.run_record import RecordError, RunRecord, flat, job_records

__all__ = ["SWEEP", "SweepRecords", "sweep_summary"]


class SweepRecords(Callback):
    """Hydra callback (``conf/hydra/default.yaml``) that notes, in the process that launches a
    multirun, where its jobs write and which job records were already there, so that process
    can list every failed job once the sweep ends (:func:`resireg_train.cli.job.hydra_entry_point`).

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
        SWEEP.clear()
        SWEEP.update(dir=sweep, before=job_records(sweep))


#: The multirun this process launched: its folder and its job records before it started.
SWEEP: dict[str, Any] = {}


def _job_number(folder: Path) -> int:
    """A job folder's number: the ``<n>_`` its name starts with (conf/hydra/default.yaml)."""
    head = folder.name.split("_", 1)[0]
    return int(head) if head.isdigit() else -1


def sweep_summary(prog: str, sweep: Path, before: dict[Path, tuple[int, int]]) -> str:
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

