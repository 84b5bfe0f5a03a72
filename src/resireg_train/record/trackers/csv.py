"""The ``csv`` tracker: ``metrics.csv``. Training always writes it (every step and epoch, continued
on resume: :class:`~resireg_train.record.epochs.ResumableCSVLogger`); an evaluation or a map
with ``tracker=csv`` writes its final metrics as one row.
"""

from __future__ import annotations

import csv
from typing import Any

from resireg_train.record.settings import RecordSettings
from resireg_train.record.trackers.base import Tracker, run_metrics
from resireg_train.record.trackers.specs import TRACKER_SPECS

__all__ = ["CsvTracker"]


class CsvTracker(Tracker):
    """``metrics.csv`` (module docstring)."""

    @classmethod
    def always(cls, run: RecordSettings, record: Any) -> CsvTracker:
        """The CSV tracker of a training run whose ``tracker`` does not name ``csv``: its
        ``metrics.csv`` is written all the same."""
        return cls(TRACKER_SPECS.get("csv"), {}, run, record)

    def lightning_logger(self, resume_step: int | None) -> Any:
        if self._logger is None:
            from resireg_train.record.epochs import ResumableCSVLogger

            self._logger = ResumableCSVLogger(self.record.folder, resume_step=resume_step)
        return self._logger

    def end(self, record: dict[str, Any], failed: bool) -> None:
        if self.training:
            return  # Lightning wrote every step and epoch
        metrics = run_metrics(record)
        filename = str(self.settings.get("filename") or "metrics.csv")
        with open(self.record.folder / filename, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=sorted(metrics))
            writer.writeheader()
            writer.writerow(metrics)
