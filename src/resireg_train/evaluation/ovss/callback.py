"""``ReSiRegEval``: OVSS mIoU of the ReSiReg variants while the head trains."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from typing import Any

import lightning as L
import torch.distributed as dist
from omegaconf import OmegaConf

from resireg.method.variants import build_variants
from resireg.specs.rules import check_batch_size
from resireg_train.config.errors import config_path
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.evaluation.ovss.engine import METRIC_PREFIX, OVSSEngine, OVSSResult
from resireg_train.evaluation.ovss.settings import VARIANT_PARAM_KEYS, save_settings

__all__ = ["ReSiRegEval"]

log = logging.getLogger(__name__)

_KEY = "callbacks.resireg_eval"


class ReSiRegEval(L.Callback):
    """Open-vocabulary segmentation of every configured dataset with the current head.

    Runs at the end of every ``every_n_epochs``-th training epoch (and the last one) -
    the run's validation epoch: the caption data has no held-out split. It logs
    ``val/ovss/<dataset>/miou_<variant>`` and ``.../fmiou_<variant>`` (epoch level), which
    :class:`~resireg_train.record.epochs.ResultsTracker` records per epoch and keeps the best of
    in ``results.json``.

    Under DDP each rank scores a disjoint share of the batches and the confusion matrices
    are summed across ranks, on the module's device, by one explicit reduce that every
    rank issues at the same point; the scores are then identical on every rank and are
    logged without ``sync_dist`` (a lazy sync would be issued by whichever rank first reads
    the metric, e.g. rank 0's progress bar, and the ranks' collectives would interleave).
    Images that cannot be scored (unreadable, or a label that is not a valid single-channel
    map of the image's size) are skipped: ``val/ovss/<dataset>/skipped`` counts them, the
    log names each the first time it is skipped, and :attr:`skipped_samples` (written to
    ``results.json`` by ``ResultsTracker``) names them all with their reasons.
    The text tower embeds each dataset's class prompts once per run; each pass applies the
    current text projection to them.

    Args:
        datasets: ``{name: spec}`` segmentation datasets (see
            :func:`~resireg_train.data.segmentation.build_segmentation_set`).
        variants: names of :func:`resireg.method.variants.build_variant` (``bb``, ``calib``, ``lite``,
            ``full``); no default: ``conf/resireg/default.yaml``'s ``variants`` is the one.
        every_n_epochs: evaluation interval in epochs.
        batch_size: images per batch (ReSiReg Full's scene; see ``OVSSEngine``).
        num_workers: DataLoader workers per dataset.
        **variant_params: each variant's arguments by its name (``calib``, ``lite``, ``full``:
            the ``resireg`` config group; the variant table names them,
            :data:`~resireg_train.evaluation.ovss.settings.VARIANT_PARAM_KEYS`).
        precision: ``"32"`` (default, the protocol's fp32) or ``"bf16"``.
        temperature: softmax temperature of the prediction.
    """

    def __init__(
        self,
        datasets: Mapping[str, Mapping[str, Any]],
        variants: Sequence[str],
        every_n_epochs: int = 1,
        batch_size: int = 8,
        num_workers: int = 2,
        precision: str = "32",
        temperature: float = 100.0,
        **variant_params: Mapping[str, Any] | None,
    ) -> None:
        if not datasets:
            raise ValueError(f"{_KEY}.datasets is empty: configure at least one dataset")
        if int(every_n_epochs) < 1:
            raise ValueError(f"{_KEY}.every_n_epochs={every_n_epochs!r}: expected >= 1")
        check_batch_size(batch_size, f"{_KEY}.batch_size")
        self.dataset_specs = {name: dict(spec) for name, spec in datasets.items()}
        self.variant_names = list(variants)
        unknown = sorted(set(variant_params) - set(VARIANT_PARAM_KEYS))
        if unknown:
            raise TypeError(f"{_KEY}: unknown arguments {unknown}; the variants' parameters are "
                            f"{list(VARIANT_PARAM_KEYS)}")  # fmt: skip
        # plain values (full.elbo_candidates is a list), so that the settings are JSON
        self.variant_params = {
            k: OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else dict(v or {})
            for k, v in ((k, variant_params.get(k)) for k in VARIANT_PARAM_KEYS)
        }
        with config_path(f"{_KEY}.variants", {"names": f"{_KEY}.variants"}):
            self.variants = build_variants(self.variant_names, self.variant_params)
        self.every_n_epochs = int(every_n_epochs)
        self.batch_size = int(batch_size)
        self.num_workers = int(num_workers)
        self.precision = str(precision)
        self.temperature = float(temperature)
        self.engines: dict[str, OVSSEngine] = {}
        #: ``{dataset: [{"file", "reason"}, ...]}`` of the last pass (the same on every rank).
        self.skipped_samples: dict[str, list[dict[str, str]]] = {}

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        """Build each dataset's engine and check every variant against its batches now, so a
        bad setting fails before training rather than at the first evaluation."""
        if self.engines:
            return
        patch = pl_module.vlm.input_rule.patch_size
        for name, spec in self.dataset_specs.items():
            dataset = build_segmentation_set(spec, patch, key=f"{_KEY}.datasets.{name}", name=name)
            engine = OVSSEngine(
                dataset, self.batch_size, self.num_workers, temperature=self.temperature
            )
            engine.check_variants(self.variants, key=_KEY)
            self.engines[name] = engine

    def due(self, trainer: L.Trainer) -> bool:
        epoch = trainer.current_epoch + 1
        return epoch % self.every_n_epochs == 0 or epoch == trainer.max_epochs

    def evaluate(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, float]:
        """Score every dataset now (sharded across ranks, then reduced); returns the scores
        and the skipped counts (``val/ovss/<dataset>/skipped``)."""
        scores: dict[str, float] = {}
        for engine in self.engines.values():
            result = engine.run(
                pl_module.vlm,
                self.variants,
                rank=trainer.global_rank,
                world_size=trainer.world_size,
                precision=self.precision,
            )
            if trainer.world_size > 1:
                result.reduce(
                    lambda t: trainer.strategy.reduce(t, reduce_op="sum"),
                    _all_gather_object,
                    pl_module.device,
                )
            scores.update(result.scores())
            scores[f"{METRIC_PREFIX}{result.dataset}/skipped"] = float(result.skipped)
            self._report_skipped(trainer, result)
        return scores

    def _report_skipped(self, trainer: L.Trainer, result: OVSSResult) -> None:
        """Keep the pass's skipped samples; warn (rank 0) about the ones not reported yet."""
        known = {s["file"] for s in self.skipped_samples.get(result.dataset, [])}
        self.skipped_samples[result.dataset] = [s.as_dict() for s in result.skipped_samples]
        new = [s for s in result.skipped_samples if s.file not in known]
        if new and trainer.is_global_zero:
            log.warning(result.skip_report())

    def idle_metric_prefixes(self, trainer: L.Trainer) -> tuple[str, ...]:
        """Metric prefixes not logged in this epoch (for ``ResultsTracker``)."""
        return () if self.due(trainer) else (METRIC_PREFIX,)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.due(trainer):
            return
        for name, value in self.evaluate(trainer, pl_module).items():
            # Already identical on every rank: no sync_dist (see the class docstring).
            pl_module.log(name, value, on_step=False, on_epoch=True, sync_dist=False)

    @property
    def settings(self) -> dict[str, Any]:
        """What ``resireg-eval`` needs to score the exported model the same way."""
        return {
            "variants": self.variant_names, **self.variant_params,
            "batch_size": self.batch_size, "precision": self.precision,
            "temperature": self.temperature,
        }  # fmt: skip

    def save_settings(self, export: str | os.PathLike) -> None:
        """Record this callback's evaluation settings in an export folder, so ``resireg-eval``
        on the export reproduces the scores of training by default."""
        save_settings(export, self.settings)

    @property
    def tower_calls(self) -> int:
        """Text-feature calls made for class prompts so far (once per dataset per run)."""
        return sum(engine.tower_calls for engine in self.engines.values())


def _all_gather_object(obj: Any) -> list[Any]:
    """Every rank's ``obj`` (a collective: all ranks call it at the same point). With NCCL,
    ``all_gather_object`` pickles through the current CUDA device, which Lightning sets to
    the rank's own before training starts."""
    gathered: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(gathered, obj)
    return gathered
