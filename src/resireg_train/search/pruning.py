"""Pruning of an Optuna search's training trials (``hparams_search=stage1_optuna``;
resireg_train.search.loop): the trial's optimised metric is reported to the study after every
validation (the ReSiRegEval callback's, at the end of a training epoch), and when the study's
pruner says so the run stops at the end of that epoch (its metrics and checkpoint written as
for any epoch) and ends with :class:`TrialPrunedStop`: the search records the trial PRUNED (its
last epoch and value are the trial's last intermediate value) and ``results.json`` the status
``pruned``.

Under DDP (``trainer=ddp_cpu``, ``trainer=ddp``) global rank 0 alone opens the study, reports
and asks the pruner; its decision is broadcast to every rank at the end of each epoch, so all
ranks stop after the same epoch (a rank that went on alone would wait for the others in its
next collective). The decision is also noted in the trial (system attribute
:data:`ATTR_PRUNED`), so the process that ran ``Trainer.fit`` learns it where the ranks were
spawned processes (``ddp_spawn``)."""

from __future__ import annotations

import math
from typing import Any

import lightning as L
import optuna

from resireg_train.record.epochs import epoch_metrics
from resireg_train.search.storage import open_storage, quiet_optuna

__all__ = ["ATTR_PRUNED", "OptunaPruning", "TrialPrunedStop"]

#: The trial's system attribute rank 0 writes when the pruner stops it: ``[epoch, value]``.
ATTR_PRUNED = "resireg:pruned"


class TrialPrunedStop(optuna.TrialPruned):
    """The pruner stopped this trial; ``run_status`` is what ``results.json`` records."""

    run_status = "pruned"


class OptunaPruning(L.Callback):
    """Report ``monitor`` (the search's ``optimized_metric``) to trial number ``trial`` of the
    study ``study_name`` (in ``storage``, or the journal in ``sweep_dir``) after every
    validation, with the epoch as step, and ask ``pruner`` (the search's, instantiated from its
    ``_target_``; ``None``: never prune). Inactive when ``trial`` is ``None`` (not a search).
    After ``Trainer.fit``, :meth:`check_pruned` raises :class:`TrialPrunedStop` on global rank
    0 of a pruned trial."""

    def __init__(self, monitor: str, trial: int | None, study_name: str, sweep_dir: str,
                 storage: str | None = None, pruner: Any = None) -> None:  # fmt: skip
        self.monitor, self.number, self.pruner = monitor, trial, pruner
        self.study_name, self.sweep_dir, self.storage = study_name, sweep_dir, storage
        self.trial: Any = None
        self.pruned: tuple[int, float] | None = None

    def _open(self) -> Any:
        quiet_optuna()
        storage = open_storage(self.storage, self.sweep_dir)
        pruner = self.pruner or optuna.pruners.NopPruner()
        study = optuna.load_study(study_name=self.study_name, storage=storage, pruner=pruner)
        trial_id = storage.get_trial_id_from_study_id_trial_number(study._study_id, self.number)
        return optuna.trial.Trial(study, trial_id)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.number is None or not trainer.is_global_zero:
            return
        self.trial = self._open()

    def _decide(self, trainer: L.Trainer) -> tuple[str, Any] | None:
        """Rank 0's decision for this epoch: ``None`` (go on), ``("prune", (epoch, value))``
        or ``("error", message)`` (a score that is not finite)."""
        value = epoch_metrics(trainer).get(self.monitor)
        if value is None:
            return None  # an epoch without validation (every_n_epochs)
        if not math.isfinite(value):
            return ("error", f"optimized_metric={self.monitor!r} is {value} at epoch "
                             f"{trainer.current_epoch}")  # fmt: skip
        self.trial.report(value, step=trainer.current_epoch)
        if not self.trial.should_prune():
            return None
        pruned = (int(trainer.current_epoch), float(value))
        self.trial.study._storage.set_trial_system_attr(
            self.trial._trial_id, ATTR_PRUNED, list(pruned)
        )
        return ("prune", pruned)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # After ReSiRegEval's (which scores at the end of the training epoch; this callback
        # comes later in conf's callbacks) and before ResultsTracker records the epoch.
        if self.number is None:
            return
        decision = self._decide(trainer) if self.trial is not None else None
        if trainer.world_size > 1:  # every rank, every epoch: the same point for all
            decision = trainer.strategy.broadcast(decision, src=0)
        if decision is None:
            return
        kind, detail = decision
        if kind == "error":
            raise FloatingPointError(detail)
        self.pruned = tuple(detail)
        trainer.should_stop = True  # this epoch ends as usual (metrics, checkpoint)

    def check_pruned(self, trainer: L.Trainer) -> None:
        """Raise :class:`TrialPrunedStop` on global rank 0 when the pruner stopped this trial,
        after ``Trainer.fit`` in the process that called it (with spawned ranks the decision
        is read back from the trial)."""
        if self.number is None or not trainer.is_global_zero:
            return
        pruned = self.pruned
        if pruned is None and self.trial is None:  # fit ran in spawned processes
            trial = self._open()
            noted = trial.study._storage.get_trial(trial._trial_id).system_attrs.get(ATTR_PRUNED)
            pruned = tuple(noted) if noted else None
        if pruned is None:
            return
        epoch, value = pruned
        pruner = type(self.pruner or optuna.pruners.NopPruner()).__name__
        raise TrialPrunedStop(
            f"trial {self.number} pruned by {pruner} after epoch {epoch}: "
            f"{self.monitor}={value:.4f}"
        )
