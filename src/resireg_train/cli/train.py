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
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from resireg_train.cli.task import hydra_entry_point, run_task
from resireg_train.results import read_results, update_results
from resireg_train.validation import check_devices, validate

if TYPE_CHECKING:
    import lightning as L

__all__ = ["build", "train", "main"]

log = logging.getLogger(__name__)

# Lightning, the models and the data load inside the task, after the config check: --help,
# --cfg job and a bad value answer without them (README, "Start-up").


def _process_rank() -> int:
    """This process's global rank from the launcher's environment (the variables Lightning's
    ``rank_zero_only`` reads), without importing Lightning; 0 for a single process."""
    for name in ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK"):
        if os.environ.get(name, "").isdigit():
            return int(os.environ[name])
    return 0


def _instantiate_all(group: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` entry of a config group (callbacks, loggers)."""
    import hydra

    if not group:
        return []
    return [hydra.utils.instantiate(c) for c in group.values() if c and "_target_" in c]


def build(cfg: DictConfig) -> tuple[L.LightningModule, L.LightningDataModule]:
    """The module and data module of a composed config (``model.init_from`` is not applied:
    it is a starting point for :func:`train`, not part of the model)."""
    import hydra

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
    out = cfg.paths.output_dir
    rank_zero = _process_rank() == 0
    if rank_zero and cfg.ckpt_path is None:
        _refuse_occupied(Path(out))
    return run_task(
        cfg,
        body,
        rank_zero=rank_zero,
        resume_hint=f"resume with ckpt_path=last hydra.run.dir={out}",
    )


def _refuse_occupied(out: Path) -> None:
    """A new run never shares a folder with another (their metrics.csv, checkpoints and
    results.json would interleave): a folder already holding a run record is refused unless
    the run resumes it. Default folders are unique (time + run id, for sweeps too); this
    guards a folder given by hand."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    previous = read_results(out)
    if not previous:
        return
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        where, unset = f"the sweep job's folder {out} (hydra.sweep.dir/subdir)", "hydra.sweep.dir"
    else:
        where, unset = f"hydra.run.dir={out}", "hydra.run.dir"
    raise FileExistsError(
        f"{where} already holds a run ({previous.get('name')!r}, status "
        f"{previous.get('status')!r}): resume it with ckpt_path=last, or give this run its "
        f"own folder (leave {unset} unset for a new, unique one)"
    )


def _fit(cfg: DictConfig, out: Path, callbacks: Sequence[L.Callback]) -> dict[str, Any]:
    validate(cfg)
    check_devices(cfg)
    import hydra
    import lightning as L

    from resireg_train.ovss.callback import ReSiRegEval
    from resireg_train.tracking import ResultsTracker, ResumableCSVLogger
    from resireg_train.training.checkpoints import AtomicCheckpointIO, resolve_checkpoint
    from resireg_train.training.console import EpochLog, quiet_library_noise

    quiet_library_noise()
    L.seed_everything(cfg.seed, workers=True)
    module, datamodule = build(cfg)
    init_from = cfg.model.get("init_from")

    resumed = resolve_checkpoint(cfg.ckpt_path, out)
    ckpt = resumed[0] if resumed else None
    if init_from and ckpt is None:
        loaded = module.load_trained(init_from)
        log.info("model.init_from: loaded %d tensors from %s", len(loaded), init_from)
    resume_step = None
    if resumed is not None:
        resume_step = int(resumed[1]["global_step"])
        log.info("resuming from %s (global step %d)", ckpt, resume_step)

    loggers = [ResumableCSVLogger(out, resume_step=resume_step), *_instantiate_all(cfg.logger)]
    trainer: L.Trainer = hydra.utils.instantiate(
        cfg.trainer,
        logger=loggers,
        callbacks=[*_instantiate_all(cfg.callbacks), ResultsTracker(out), EpochLog(), *callbacks],
        plugins=[AtomicCheckpointIO()],
        default_root_dir=str(out),
    )
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt)
    except SystemExit:
        # Lightning answers Ctrl-C by shutting down and calling sys.exit(1); say what it was.
        if trainer.interrupted:
            raise KeyboardInterrupt from None
        raise
    if not trainer.is_global_zero:
        return {}
    extra: dict[str, Any] = {}
    if cfg.export:
        export = module.vlm.save_pretrained(out / "export")
        for callback in trainer.callbacks:
            if isinstance(callback, ReSiRegEval):
                callback.save_settings(export)
        extra["export"] = str(export)
    return update_results(out, **extra)


main = hydra_entry_point("train", train)

if __name__ == "__main__":
    main()
