"""``resireg-eval``: OVSS of an exported :class:`~resireg.models.ResiregVLM` (Hydra main).

    resireg-eval model_path=outputs/smoke/<time>/export dataset=synthetic
    resireg-eval model_path=<export> dataset=ade20k variants=[full] batch_size=16 \
        full.n_prototypes=60
    resireg-eval model_path=<export> dataset=ade20k sweep=prototype_batch      # the ablation grid

The scores use the engine of the training callback (:mod:`resireg_train.evaluation`), so a
model's ``val/ovss/...`` numbers from training are recomputed exactly from its export.
``results.json`` in the output dir holds the status (and the error of a failed run), the
scores under ``final``, per-class IoU, the parameters, image counts, the batch-size
histogram and seconds per stage.
"""

from __future__ import annotations

import logging
import traceback
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from resireg.models import ResiregVLM
from resireg_train.config import CONFIG_DIR, validate_eval
from resireg_train.evaluation import OVSSTask, StageTimer, build_variants
from resireg_train.segmentation import build_segmentation_set
from resireg_train.tracking import update_results

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
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    update_results(out, name=cfg.name, status="running", error=None, output_dir=str(out))
    try:
        return _evaluate(cfg, out)
    except BaseException as exc:
        error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        update_results(out, status="failed", error=error)
        raise


def _evaluate(cfg: DictConfig, out: Path) -> dict[str, Any]:
    validate_eval(cfg)
    params = OmegaConf.to_container(cfg, resolve=True)
    params = {k: params[k] for k in ("model_path", "dataset", "variants", "batch_size", "precision",
                                     "temperature", "lite", "full")}  # fmt: skip
    update_results(out, params=params)
    torch.manual_seed(cfg.seed)
    variants = build_variants(list(cfg.variants), params["lite"], params["full"])
    vlm = ResiregVLM.from_pretrained(cfg.model_path, map_location=_device(cfg.device))
    dataset = build_segmentation_set(params["dataset"], vlm.backbone.patch_size, key="dataset")
    task = OVSSTask(dataset, cfg.batch_size, cfg.num_workers, temperature=cfg.temperature)
    timer = StageTimer()
    result = task.run(vlm, variants, precision=str(cfg.precision), timer=timer)
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


def _optimized_value(cfg: DictConfig, results: dict[str, Any]) -> float | None:
    name = cfg.get("optimized_metric")
    if not name:
        return None
    if name not in results.get("final", {}):
        raise KeyError(
            f"optimized_metric={name!r} was not computed; computed: {sorted(results['final'])}"
        )
    return float(results["final"][name])


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="eval")
def main(cfg: DictConfig) -> float | None:
    """Console entry point ``resireg-eval`` (Hydra command-line overrides)."""
    log.info("output dir: %s", HydraConfig.get().runtime.output_dir)
    return _optimized_value(cfg, evaluate(cfg))


if __name__ == "__main__":
    main()
