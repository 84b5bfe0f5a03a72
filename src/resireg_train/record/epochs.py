"""What a training run records every epoch (Lightning): :class:`ResultsTracker`, the callback
that keeps the run's :class:`~resireg_train.record.run_record.RunRecord` up to date, the epoch-level
values it takes (:func:`epoch_metrics`), and :class:`ResumableCSVLogger`, the ``metrics.csv``
that survives a resume (the ``csv`` tracker's Lightning logger, :mod:`resireg_train.record.trackers.csv`).

``results.json`` is rewritten at the end of every epoch, so an interrupted or failed run still
reports how far it got::

    {"status": "running" | "completed" | "failed", "error": null | "...",
     "epoch": 3, "global_step": 32,
     "final": {"train/loss": 1.9, ...},                    # last epoch's epoch-level values
     "best": {"train/loss": {"value": 1.9, "epoch": 3}, ...},
     "history": [{"epoch": 0, "step": 8, "train/loss": 2.7, ...}, ...]}

"Best" is the minimum for losses and the maximum for accuracies, retrieval and IoU metrics;
other values (learning rate, logit scale, skip counts) are reported as final only. The file is
strict JSON: a NaN or infinite value is written as ``null`` and listed under ``non_finite``
(:mod:`resireg_train.record.run_record`).
"""

from __future__ import annotations

import csv
import math
import os
from typing import Any

import lightning as L
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter

from resireg_train.record.run_record import RunRecord, metric_mode

__all__ = ["ResumableCSVLogger", "ResultsTracker", "epoch_metrics"]


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
    """Records every epoch's metrics in the run's record (rank 0): ``final``, ``best``,
    ``history``, ``epoch`` and ``global_step``. The record's final status is the job's
    (:meth:`RunRecord.finish <resireg_train.record.run_record.RunRecord.finish>`).

    Its history is part of the checkpoint, so a resumed run reports the best values of
    the epochs before the interruption too.
    """

    def __init__(self, record: RunRecord) -> None:
        self.record = record
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
            self.record.update(
                status="running",
                epoch=trainer.current_epoch,
                global_step=trainer.global_step,
                **self.summary(),
                **_skipped_samples(trainer),
            )

    def state_dict(self) -> dict[str, Any]:
        return {"history": self.history}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.history = list(state_dict.get("history", []))
