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

import functools
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from resireg_train.cli.task import hydra_entry_point, run_task
from resireg_train.tracking import ResultsTracker, ResumableCSVLogger, update_results
from resireg_train.validation import validate

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
    rule = module.vlm.input_rule
    datamodule = hydra.utils.instantiate(
        cfg.data, mean=list(rule.mean), std=list(rule.std), _convert_="all"
    )
    return module, datamodule


def train(cfg: DictConfig, callbacks: Sequence[L.Callback] = ()) -> dict[str, Any]:
    """Train from a composed config; returns the ``results.json`` content (``{}`` on ranks
    other than 0).

    Any failure, from a bad config value to a crash mid-epoch, is recorded in
    ``results.json`` (see :func:`~resireg_train.cli.task.run_task`).

    Args:
        cfg: a composed ``train.yaml`` config (``paths.output_dir`` must be resolvable).
        callbacks: extra callbacks (added to the configured ones).
    """
    body = functools.partial(_fit, callbacks=callbacks)
    return run_task(cfg, body, rank_zero=rank_zero_only.rank == 0)


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


main = hydra_entry_point("train", train)

if __name__ == "__main__":
    main()
