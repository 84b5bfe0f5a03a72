"""Pruning of an Optuna search's training trials (``hparams_search=stage1_optuna``;
resireg_train.sweeps.loop): the trial's optimised metric is reported to the study after every
validation (the ReSiRegEval callback's, at the end of a training epoch), and when the study's pruner says so the run stops at the end of that epoch (its
metrics and checkpoint written as for any epoch) and ends with :class:`TrialPrunedStop`:
the search records the trial PRUNED (its last epoch and value are the trial's last
intermediate value) and ``results.json`` the status ``pruned``."""

from __future__ import annotations

import math
from typing import Any

import lightning as L
import optuna

from resireg_train.runs.epochs import epoch_metrics
from resireg_train.sweeps.storage import open_storage, quiet_optuna

__all__ = ["OptunaPruning", "TrialPrunedStop"]


class TrialPrunedStop(optuna.TrialPruned):
    """The pruner stopped this trial; ``run_status`` is what ``results.json`` records."""

    run_status = "pruned"


class OptunaPruning(L.Callback):
    """Report ``monitor`` (the search's ``optimized_metric``) to trial number ``trial`` of the
    study ``study_name`` (in ``storage``, or the journal in ``sweep_dir``) after every
    validation, with the epoch as step, and ask ``pruner`` (the search's, instantiated from its
    ``_target_``; ``None``: never prune). Inactive when ``trial`` is ``None`` (not a search)."""

    def __init__(self, monitor: str, trial: int | None, study_name: str, sweep_dir: str,
                 storage: str | None = None, pruner: Any = None) -> None:  # fmt: skip
        self.monitor, self.number, self.pruner = monitor, trial, pruner
        self.study_name, self.sweep_dir, self.storage = study_name, sweep_dir, storage
        self.trial: Any = None
        self.pruned: tuple[int, float] | None = None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.number is None or not trainer.is_global_zero:
            return
        quiet_optuna()
        storage = open_storage(self.storage, self.sweep_dir)
        pruner = self.pruner or optuna.pruners.NopPruner()
        study = optuna.load_study(study_name=self.study_name, storage=storage, pruner=pruner)
        trial_id = storage.get_trial_id_from_study_id_trial_number(study._study_id, self.number)
        self.trial = optuna.trial.Trial(study, trial_id)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # After ReSiRegEval's (which scores at the end of the training epoch; this callback
        # comes later in conf's callbacks) and before ResultsTracker records the epoch.
        if self.trial is None:
            return
        value = epoch_metrics(trainer).get(self.monitor)
        if value is None:
            return  # an epoch without validation (every_n_epochs)
        if not math.isfinite(value):
            raise FloatingPointError(
                f"optimized_metric={self.monitor!r} is {value} at epoch {trainer.current_epoch}"
            )
        self.trial.report(value, step=trainer.current_epoch)
        if self.trial.should_prune():
            self.pruned = (trainer.current_epoch, value)
            trainer.should_stop = True  # this epoch ends as usual (metrics, checkpoint)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.pruned is not None:
            epoch, value = self.pruned
            pruner = type(self.trial.study.pruner).__name__
            raise TrialPrunedStop(
                f"trial {self.number} pruned by {pruner} after epoch {epoch}: "
                f"{self.monitor}={value:.4f}"
            )
