"""``resireg-eval task=ovss``: 2D open-vocabulary segmentation as an evaluation task
(:class:`resireg_train.evaluation.base.EvalTask`; the entry ``ovss`` of
:data:`resireg_train.evaluation.specs.TASK_SPECS`) over the engine :class:`~resireg_train.evaluation.ovss.engine.OVSSEngine`,
with the feature cache (``feature_cache``) and the segmentation prior (``+prior``
configurations, ``prior=``) that only this task takes."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from torch import nn

from resireg.models import DenseEncoder
from resireg.specs.variants import takes_prior
from resireg_train.config.errors import config_path
from resireg_train.data.segmentation import build_segmentation_set, check_segmentation_source
from resireg_train.evaluation.base import EvalTask
from resireg_train.evaluation.engine import StageTimer
from resireg_train.evaluation.ovss.engine import OVSSEngine, OVSSResult, requested_layers
from resireg_train.evaluation.protocol import protocol_record

__all__ = ["OVSSTask"]

log = logging.getLogger(__name__)


class OVSSTask(EvalTask):
    """2D OVSS of one segmentation dataset (module docstring)."""

    def check(self, variants: Mapping[str, nn.Module]) -> None:
        check_segmentation_source(self.params["dataset"], "dataset")
        super().check(variants)

    def build(self, encoder: DenseEncoder, variants: Mapping[str, nn.Module]) -> dict[str, Any]:
        cfg, params = self.cfg, self.params
        patch = encoder.input_rule.patch_size
        self.dataset = build_segmentation_set(params["dataset"], patch, key="dataset")
        self.classes = self.dataset.classes
        self.engine = OVSSEngine(self.dataset, cfg.batch_size, cfg.num_workers,
                               temperature=cfg.temperature)  # fmt: skip
        self.check_batches(self.engine, variants)
        self.cache = None
        if cfg.get("feature_cache"):
            from resireg_train.evaluation.cache import FeatureCache

            key = FeatureCache.key_for(encoder, params["encoder"], params["dataset"], patch,
                                       str(cfg.precision), requested_layers(encoder, variants))  # fmt: skip
            self.cache = FeatureCache(cfg.feature_cache, key, self.dataset.describe)
            log.info("feature cache %s: %d images stored", self.cache.folder, len(self.cache))
        self.prior = None
        if any(takes_prior(v) for v in variants):  # SAM loads only for a +prior configuration
            from resireg.priors import build_prior

            with config_path("prior", {"spec": "prior"}):
                self.prior = build_prior(params["prior"], device=encoder.device)
        return {"protocol": protocol_record(params, self.dataset)}

    def run(self, encoder: DenseEncoder, variants: Mapping[str, nn.Module],
            timer: StageTimer) -> OVSSResult:  # fmt: skip
        return self.engine.run(encoder, variants, precision=str(self.cfg.precision), timer=timer,
                               cache=self.cache, prior=self.prior)  # fmt: skip

    def results(self, result: OVSSResult) -> dict[str, Any]:
        """``skipped``, ``skipped_samples``, the histogram of scored batch sizes
        (``batch_sizes``) and the feature cache's summary where one was used."""
        if result.skipped:
            log.warning(result.skip_report())
        return {
            "skipped": result.skipped,
            "skipped_samples": [s.as_dict() for s in result.skipped_samples],
            "batch_sizes": {str(k): v for k, v in result.batch_sizes.items()},
            **({"feature_cache": self.cache.summary()} if self.cache is not None else {}),
        }
