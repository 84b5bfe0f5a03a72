"""``resireg-eval``: OVSS of an exported :class:`~resireg.models.ResiregVLM` (Hydra main).

    resireg-eval model_path=outputs/smoke/<time>/export dataset=synthetic
    resireg-eval model_path=<export> dataset=ade20k variants=[full] batch_size=16 \
        full.n_prototypes=60
    resireg-eval model_path=<export> dataset=ade20k sweep=prototype_batch      # the ablation grid

The scores use the engine of the training callback (:mod:`resireg_train.ovss.engine`), so a
model's ``val/ovss/...`` numbers from training are recomputed exactly from its export.
ReSiReg's parameters (``variants``, ``lite.*``, ``full.*``) come from the ``resireg``
config group, which the training callback shares.
``results.json`` in the output dir holds the status (and the error of a failed run), the
scores under ``final``, per-class IoU, the parameters, image counts, the batch-size
histogram and seconds per stage.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from resireg.models import ResiregVLM
from resireg.variants import build_variants
from resireg_train.cli.task import hydra_entry_point, run_task
from resireg_train.ovss.datasets import build_segmentation_set
from resireg_train.ovss.engine import OVSSTask, StageTimer
from resireg_train.tracking import update_results
from resireg_train.validation import validate_eval

__all__ = ["evaluate", "main"]

log = logging.getLogger(__name__)


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate from a composed ``eval.yaml`` config; returns the ``results.json`` content.

    A failure (bad value, missing model or dataset, too many prototypes for a batch) is
    recorded in ``results.json`` as ``"status": "failed"`` with its error, then re-raised.
    """
    return run_task(cfg, _evaluate)


def _evaluate(cfg: DictConfig, out: Path) -> dict[str, Any]:
    validate_eval(cfg)
    params = OmegaConf.to_container(cfg, resolve=True)
    params = {k: params[k] for k in ("model_path", "dataset", "variants", "batch_size", "precision",
                                     "temperature", "lite", "full")}  # fmt: skip
    update_results(out, params=params)
    torch.manual_seed(cfg.seed)
    variants = build_variants(list(cfg.variants), params)
    encoder = ResiregVLM.from_pretrained(cfg.model_path, map_location=_device(cfg.device))
    patch = encoder.input_rule.patch_size
    dataset = build_segmentation_set(params["dataset"], patch, key="dataset")
    task = OVSSTask(dataset, cfg.batch_size, cfg.num_workers, temperature=cfg.temperature)
    task.check_variants(variants)
    timer = StageTimer()
    result = task.run(encoder, variants, precision=str(cfg.precision), timer=timer)
    scores = result.scores()
    for name, value in scores.items():
        log.info("%s = %.4f", name, value)
    classes = dataset.classes
    return update_results(
        out,
        status="completed",
        final=scores,
        per_class_iou={
            v: dict(zip(classes, ious, strict=True)) for v, ious in result.per_class_iou().items()
        },  # fmt: skip
        images=result.images,
        skipped=result.skipped,
        batch_sizes={str(k): v for k, v in result.batch_sizes.items()},
        seconds={k: round(v, 4) for k, v in sorted(timer.seconds.items())},
    )


main = hydra_entry_point("eval", evaluate)

if __name__ == "__main__":
    main()
