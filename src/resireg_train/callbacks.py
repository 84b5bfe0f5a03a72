"""``ReSiRegEval``: OVSS mIoU of BB / ReSiReg Lite / ReSiReg Full while the head trains."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import lightning as L

from resireg_train.evaluation import VARIANTS, OVSSResult, OVSSTask, build_variants
from resireg_train.segmentation import build_segmentation_set

__all__ = ["ReSiRegEval"]


class ReSiRegEval(L.Callback):
    """Open-vocabulary segmentation of every configured dataset with the current head.

    Runs at the end of every ``every_n_epochs``-th training epoch (and the last one) -
    the run's validation epoch: the caption data has no held-out split. It logs
    ``val/ovss/<dataset>/miou_<variant>`` and ``.../fmiou_<variant>`` (epoch level), which
    :class:`~resireg_train.tracking.ResultsTracker` records per epoch and keeps the best of
    in ``results.json``.

    Under DDP each rank scores a disjoint share of the batches and the confusion matrices
    are summed across ranks before the scores are computed, so every rank logs the
    single-process numbers. The text tower embeds each dataset's class prompts once per
    run; each pass applies the current text projection to them.

    Args:
        datasets: ``{name: spec}`` segmentation datasets (see
            :func:`~resireg_train.segmentation.build_segmentation_set`).
        variants: any of ``bb``, ``lite``, ``full``.
        every_n_epochs: evaluation interval in epochs.
        batch_size: images per batch (ReSiReg Full's scene; see ``OVSSTask``).
        num_workers: DataLoader workers per dataset.
        lite, full: ``ReSiRegLite`` / ``ReSiRegFull`` arguments.
        precision: ``"32"`` (default, the protocol's fp32) or ``"bf16"``.
        temperature: softmax temperature of the prediction.
    """

    def __init__(
        self,
        datasets: Mapping[str, Mapping[str, Any]],
        variants: Sequence[str] = VARIANTS,
        every_n_epochs: int = 1,
        batch_size: int = 8,
        num_workers: int = 0,
        lite: Mapping[str, Any] | None = None,
        full: Mapping[str, Any] | None = None,
        precision: str = "32",
        temperature: float = 100.0,
    ) -> None:
        key = "callbacks.resireg_eval"
        if not datasets:
            raise ValueError(f"{key}.datasets is empty: configure at least one dataset")
        if int(every_n_epochs) < 1:
            raise ValueError(f"{key}.every_n_epochs={every_n_epochs!r}: expected >= 1")
        if int(batch_size) < 1:
            raise ValueError(f"{key}.batch_size={batch_size!r}: expected >= 1")
        self.dataset_specs = {name: dict(spec) for name, spec in datasets.items()}
        self.variants = build_variants(list(variants), lite, full, key=f"{key}.variants")
        self.every_n_epochs = int(every_n_epochs)
        self.batch_size = int(batch_size)
        self.num_workers = int(num_workers)
        self.precision = str(precision)
        self.temperature = float(temperature)
        self.tasks: dict[str, OVSSTask] = {}
        self.last_results: dict[str, OVSSResult] = {}

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if self.tasks:
            return
        patch = pl_module.vlm.backbone.patch_size
        for name, spec in self.dataset_specs.items():
            dataset = build_segmentation_set(
                spec, patch, key=f"callbacks.resireg_eval.datasets.{name}", name=name
            )
            self.tasks[name] = OVSSTask(
                dataset, self.batch_size, self.num_workers, temperature=self.temperature
            )

    def due(self, trainer: L.Trainer) -> bool:
        epoch = trainer.current_epoch + 1
        return epoch % self.every_n_epochs == 0 or epoch == trainer.max_epochs

    def evaluate(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, float]:
        """Score every dataset now (sharded across ranks, then reduced); returns the scores."""
        scores: dict[str, float] = {}
        for name, task in self.tasks.items():
            result = task.run(
                pl_module.vlm,
                self.variants,
                rank=trainer.global_rank,
                world_size=trainer.world_size,
                precision=self.precision,
            )
            if trainer.world_size > 1:
                result.reduce(lambda t: trainer.strategy.reduce(t, reduce_op="sum"))
            self.last_results[name] = result
            scores.update(result.scores())
        return scores

    def idle_metric_prefixes(self, trainer: L.Trainer) -> tuple[str, ...]:
        """Metric prefixes not logged in this epoch (for ``ResultsTracker``)."""
        return () if self.due(trainer) else ("val/ovss/",)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.due(trainer):
            return
        for name, value in self.evaluate(trainer, pl_module).items():
            # Identical on every rank (the confusion matrices were summed); "max" keeps it exact.
            pl_module.log(
                name, value, on_step=False, on_epoch=True, sync_dist=True, reduce_fx="max"
            )

    @property
    def tower_calls(self) -> int:
        """Text-tower calls made for class prompts so far (once per dataset per run)."""
        return sum(task.tower_calls for task in self.tasks.values())
