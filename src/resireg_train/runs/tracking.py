"""Run records: a CSV logger that survives resume, ``results.json`` (final + best metrics), and
the W&B runs of ``logger=wandb`` (one per job, named by the project's run id, finished at the
job's end with the config and ``results.json``'s summary: :func:`wandb_logger`, :func:`wandb_runs`).

``results.json`` is what sweeps are summarised from (``resireg-report``). It is rewritten
at the end of every epoch, so an interrupted or failed run still reports how far it got::

    {"status": "running" | "completed" | "failed", "error": null | "...",
     "epoch": 3, "global_step": 32,
     "final": {"train/loss": 1.9, ...},                    # last epoch's epoch-level values
     "best": {"train/loss": {"value": 1.9, "epoch": 3}, ...},
     "history": [{"epoch": 0, "step": 8, "train/loss": 2.7, ...}, ...]}

"Best" is the minimum for losses and the maximum for accuracies, retrieval and IoU metrics;
other values (learning rate, logit scale, skip counts) are reported as final only. The file is
strict JSON: a NaN or infinite value is written as ``null`` and listed under ``non_finite``
(:mod:`resireg_train.runs.record`).
"""

from __future__ import annotations

import contextlib
import csv
import math
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter

from resireg_train.runs.record import metric_mode, read_results, update_results

__all__ = [
    "ResumableCSVLogger",
    "ResultsTracker",
    "epoch_metrics",
    "wandb_logger",
    "wandb_loggers",
    "wandb_run_name",
    "wandb_runs",
    "wandb_summary",
]


# ------------------------------------------------------------------------- CSV logger
class _ResumingWriter(ExperimentWriter):
    """Keeps ``metrics.csv`` rows logged before ``keep_before_step`` instead of deleting the file."""

    def __init__(self, log_dir: str, keep_before_step: int | None) -> None:
        self._keep_before = keep_before_step
        super().__init__(log_dir)

    def _check_log_dir_exists(self) -> None:
        if self._keep_before is None or not os.path.isfile(self.metrics_file_path):
            if os.path.isfile(self.metrics_file_path):
                os.remove(self.metrics_file_path)  # a fresh run: no stale rows
            return
        with open(self.metrics_file_path, newline="") as f:
            reader = csv.DictReader(f)
            keys = list(reader.fieldnames or [])
            rows = [r for r in reader if r.get("step") and int(r["step"]) < self._keep_before]
        # Rows logged after the checkpoint were computed by steps that are now re-run.
        with open(self.metrics_file_path, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=keys)
            writer.writeheader()
            writer.writerows(rows)
        self.metrics_keys = keys


class ResumableCSVLogger(CSVLogger):
    """``CSVLogger`` writing ``<save_dir>/metrics.csv`` that continues the file on resume.

    Lightning's own ``CSVLogger`` deletes an existing ``metrics.csv``. With
    ``resume_step`` (the global step of the checkpoint being resumed) the rows logged
    before that step are kept and the later ones (from the interrupted epoch) dropped.
    """

    def __init__(self, save_dir: str | os.PathLike, resume_step: int | None = None) -> None:
        super().__init__(save_dir=str(save_dir), name="", version="")
        self._resume_step = resume_step

    @property
    def experiment(self) -> ExperimentWriter:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _ResumingWriter(self.log_dir, self._resume_step)
        return self._experiment


def epoch_metrics(trainer: L.Trainer) -> dict[str, float]:
    """This epoch's epoch-level values from ``trainer.callback_metrics`` (``x_epoch`` -> ``x``;
    no ``x_step``).

    ``callback_metrics`` keeps a metric's last value in later epochs. A callback that logs
    only in some epochs (``ReSiRegEval`` every n epochs) names, through
    ``idle_metric_prefixes(trainer)``, what it did not log in this one; those are left out.
    """
    idle = tuple(
        prefix
        for callback in trainer.callbacks
        for prefix in getattr(callback, "idle_metric_prefixes", lambda _: ())(trainer)
    )
    out = {}
    for key, value in trainer.callback_metrics.items():
        if key.endswith("_step") or key.startswith(idle):
            continue
        try:
            number = float(value)
        except (TypeError, ValueError):
            continue
        out[key.removesuffix("_epoch")] = number
    return out


def _skipped_samples(trainer: L.Trainer) -> dict[str, Any]:
    """``{"skipped_samples": {dataset: [{"file", "reason"}]}}`` from the callbacks that skip
    evaluation samples (``ReSiRegEval.skipped_samples``); ``{}`` when none does."""
    merged: dict[str, Any] = {}
    for callback in trainer.callbacks:
        merged.update(getattr(callback, "skipped_samples", None) or {})
    return {"skipped_samples": merged} if merged else {}


class ResultsTracker(L.Callback):
    """Records every epoch's metrics and keeps ``results.json`` up to date (rank 0).

    Its history is part of the checkpoint, so a resumed run reports the best values of
    the epochs before the interruption too.
    """

    def __init__(self, directory: str | os.PathLike) -> None:
        self.directory = Path(directory)
        self.history: list[dict[str, float]] = []

    def summary(self) -> dict[str, Any]:
        best: dict[str, dict[str, float]] = {}
        for row in self.history:
            for key, value in row.items():
                mode = metric_mode(key)
                if mode is None or math.isnan(value):
                    continue
                current = best.get(key, {}).get("value")
                if current is None or (value < current if mode == "min" else value > current):
                    best[key] = {"value": value, "epoch": int(row["epoch"])}
        last = self.history[-1] if self.history else {}
        final = {k: v for k, v in last.items() if k not in ("epoch", "step")}
        return {"final": final, "best": best, "history": self.history}

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        row = {"epoch": trainer.current_epoch, "step": trainer.global_step}
        row.update(epoch_metrics(trainer))
        self.history = [r for r in self.history if r["epoch"] < row["epoch"]] + [row]
        if trainer.is_global_zero:
            update_results(
                self.directory,
                status="running",
                epoch=trainer.current_epoch,
                global_step=trainer.global_step,
                **self.summary(),
                **_skipped_samples(trainer),
            )

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.is_global_zero and self.history:
            update_results(self.directory, status="completed", error=None, **self.summary())

    def state_dict(self) -> dict[str, Any]:
        return {"history": self.history}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.history = list(state_dict.get("history", []))


# ------------------------------------------------------------------------- W&B
def wandb_run_name(name: str) -> tuple[str, str | None]:
    """``(run name, group)`` of this job's W&B run: ``<name>-<run id>`` (the run id of the
    output folder, :data:`resireg_train.config.paths.RUN_ID`), with ``-<job number>`` and the
    group ``<name>-<run id>`` (the sweep) for a job of a multirun."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from resireg_train.config.paths import RUN_ID

    base = f"{name}-{RUN_ID}"
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        return f"{base}-{HydraConfig.get().job.num}", base
    return base, None


def wandb_logger(name: str, project: str = "resireg", **kwargs: Any) -> Any:
    """Lightning's ``WandbLogger`` (``conf/logger/wandb.yaml``) with this job's run name and
    group (:func:`wandb_run_name`); ``WANDB_MODE=offline`` logs without a network."""
    from lightning.pytorch.loggers import WandbLogger

    run_name, group = wandb_run_name(name)
    logger = WandbLogger(name=run_name, project=project, group=group, **kwargs)
    # Lightning passes anonymous=None to wandb.init unless asked for it, and wandb warns "The
    # anonymous setting has no effect" for any value given: leave the key out when unset.
    init = getattr(logger, "_wandb_init", {})
    if init.get("anonymous") is None:
        init.pop("anonymous", None)
    return logger


def wandb_loggers(cfg: Any) -> list[Any]:
    """The W&B logger of ``cfg.logger`` (``logger=wandb``) for a job without Lightning's
    trainer (``resireg-eval``, ``resireg-map``); ``[]`` without one. The other trackers record
    such a job when it ends (:mod:`resireg_train.runs.trackers`)."""
    settings = (cfg.get("logger") or {}).get("wandb")
    if not settings:
        return []
    import hydra

    return [hydra.utils.instantiate(settings)]


def wandb_summary(record: dict[str, Any]) -> dict[str, Any]:
    """``results.json``'s summary as W&B summary values: status, epoch, step, the final values
    (``final/<metric>``) and the best ones (``best/<metric>``, ``best/<metric>/epoch``);
    non-finite values (``null`` in the file) are left out."""
    from resireg_train.runs.trackers import map_counts

    out: dict[str, Any] = {k: record[k] for k in ("status", "epoch", "global_step", "error")
                           if record.get(k) is not None}  # fmt: skip
    out.update({f"final/{k}": v for k, v in (record.get("final") or {}).items() if v is not None})
    out.update(map_counts(record))  # a resireg-map run's voxels and frames
    for key, best in (record.get("best") or {}).items():
        if best.get("value") is not None:
            out[f"best/{key}"] = best["value"]
            out[f"best/{key}/epoch"] = best["epoch"]
    return out


@contextlib.contextmanager
def wandb_runs(loggers: Sequence[Any], cfg: Any, directory: str | os.PathLike) -> Iterator[None]:
    """Around a job's training: the W&B runs among ``loggers`` get the job's resolved config
    first and, at the end (failed or not), ``results.json``'s summary (:func:`wandb_summary`),
    then are finished (exit code 1 if the job raised). Lightning's ``WandbLogger`` never
    finishes its run, and a run left open takes the next job's logs in a multirun. Without a
    W&B logger this does nothing (wandb is not imported)."""
    runs = [lg for lg in loggers if type(lg).__name__ == "WandbLogger"]
    if not runs:
        yield
        return
    from omegaconf import OmegaConf

    config = OmegaConf.to_container(cfg, resolve=True)
    experiments = [lg.experiment for lg in runs]  # rank 0: the wandb runs (created here)
    experiments = [e for e in experiments if hasattr(e, "finish")]  # other ranks: no run
    for experiment in experiments:
        experiment.config.update(config, allow_val_change=True)
    failed = True
    try:
        yield
        failed = False
    finally:
        summary = wandb_summary(read_results(directory))
        for experiment in experiments:
            experiment.summary.update(summary)
            experiment.finish(exit_code=1 if failed else 0)
