"""``resireg-train``: the Hydra main that trains the dense VLM.

    resireg-train experiment=smoke                      # CPU, tiny models, < 1 min
    resireg-train experiment=vlm25m_stage1 trainer=ddp  # the 25M VLM, stage 1, all GPUs
    resireg-train experiment=vlm25m_stage1 ckpt_path=last hydra.run.dir=<the run's folder>

The run's output folder receives the resolved config (``.hydra/``), ``metrics.csv`` (always),
the optional TensorBoard / MLflow logs (``logger=``), ``checkpoints/`` (``last.ckpt`` every
epoch), ``results.json`` (final and best metrics, status) and ``export/`` (the trained
:class:`~resireg.models.ResiregVLM`, loadable with ``ResiregVLM.from_pretrained``).
"""

from __future__ import annotations

import logging
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from hydra.core.hydra_config import HydraConfig
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from resireg_train.config import CONFIG_DIR, validate
from resireg_train.tracking import ResultsTracker, ResumableCSVLogger, update_results

__all__ = ["build", "train", "main"]

log = logging.getLogger(__name__)


def _resolve_checkpoint(ckpt_path: str | None, output_dir: Path) -> str | None:
    """``"last"`` -> ``<output_dir>/checkpoints/last.ckpt`` when it exists (else start fresh)."""
    if ckpt_path is None:
        return None
    if ckpt_path == "last":
        last = output_dir / "checkpoints" / "last.ckpt"
        if last.is_file():
            return str(last)
        log.warning("ckpt_path=last: no %s yet, starting from scratch", last)
        return None
    if not Path(ckpt_path).is_file():
        raise FileNotFoundError(f"ckpt_path={ckpt_path!r}: no such checkpoint file")
    return ckpt_path


def _instantiate_all(group: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a config group (callbacks, loggers)."""
    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if c and "_target_" in c]


def build(cfg: DictConfig) -> tuple[L.LightningModule, L.LightningDataModule]:
    """The module and data module of a composed config (``model.init_from`` is not applied:
    it is a starting point for :func:`train`, not part of the model)."""
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    model_cfg.pop("init_from", None)
    module = hydra.utils.instantiate(model_cfg, _convert_="all")
    backbone = module.vlm.backbone
    datamodule = hydra.utils.instantiate(
        cfg.data, mean=list(backbone.mean), std=list(backbone.std), _convert_="all"
    )
    return module, datamodule


def train(cfg: DictConfig, callbacks: Sequence[L.Callback] = ()) -> dict[str, Any]:
    """Train from a composed config; returns the ``results.json`` content.

    Any failure, from a bad config value to a crash mid-epoch, is recorded in
    ``results.json`` (``"status": "failed"`` and the error) before it is re-raised, so a
    sweep report lists the job with its reason.

    Args:
        cfg: a composed ``train.yaml`` config (``paths.output_dir`` must be resolvable).
        callbacks: extra callbacks (added to the configured ones).
    """
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    if rank_zero_only.rank == 0:
        update_results(out, name=cfg.name, status="running", error=None, output_dir=str(out))
    try:
        return _fit(cfg, out, callbacks)
    except BaseException as exc:
        if rank_zero_only.rank == 0:
            error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            update_results(out, status="failed", error=error)
        raise


def _fit(cfg: DictConfig, out: Path, callbacks: Sequence[L.Callback]) -> dict[str, Any]:
    validate(cfg)
    L.seed_everything(cfg.seed, workers=True)
    module, datamodule = build(cfg)
    init_from = cfg.model.get("init_from")

    ckpt = _resolve_checkpoint(cfg.ckpt_path, out)
    if init_from and ckpt is None:
        loaded = module.load_trained(init_from)
        log.info("model.init_from: loaded %d tensors from %s", len(loaded), init_from)
    resume_step = None
    if ckpt is not None:
        resume_step = int(torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"])
        log.info("resuming from %s (global step %d)", ckpt, resume_step)

    loggers = [ResumableCSVLogger(out, resume_step=resume_step), *_instantiate_all(cfg.logger)]
    trainer: L.Trainer = hydra.utils.instantiate(
        cfg.trainer,
        logger=loggers,
        callbacks=[*_instantiate_all(cfg.callbacks), ResultsTracker(out), *callbacks],
        default_root_dir=str(out),
    )
    trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt)
    if not trainer.is_global_zero:
        return {}
    if trainer.interrupted:
        return update_results(out, status="interrupted")
    extra: dict[str, Any] = {}
    if cfg.export:
        module.vlm.save_pretrained(out / "export")
        extra["export"] = str(out / "export")
    return update_results(out, **extra)


def _optimized_value(cfg: DictConfig, results: dict[str, Any]) -> float | None:
    """The value a sweeper (e.g. Optuna) optimises: ``optimized_metric``'s best or final."""
    name = cfg.get("optimized_metric")
    if not name or not results:  # unset, or a rank other than 0
        return None
    for section in ("best", "final"):
        value = results.get(section, {}).get(name)
        if value is not None:
            return float(value["value"] if isinstance(value, dict) else value)
    raise KeyError(f"optimized_metric={name!r} was not logged; logged: {sorted(results['final'])}")


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="train")
def main(cfg: DictConfig) -> float | None:
    """Console entry point ``resireg-train`` (Hydra command-line overrides)."""
    log.info("output dir: %s", HydraConfig.get().runtime.output_dir)
    return _optimized_value(cfg, train(cfg))


if __name__ == "__main__":
    main()
