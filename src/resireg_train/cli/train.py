"""``resireg-train``: the Hydra main that trains the dense VLM.

    resireg-train experiment=smoke                      # CPU, tiny models, < 1 min
    resireg-train experiment=vlm25m_stage1 trainer=ddp  # the 25M VLM, stage 1, all GPUs
    resireg-train experiment=vlm25m_stage1 ckpt_path=last hydra.run.dir=<the run's folder>

A resume takes the run's own overrides (the interrupted run prints the command, and
``results.json`` records it). :class:`~resireg_train.jobs.train.RunFolderCheck` refuses, before Hydra writes anything
into the folder, a resume whose composed config differs from the run's
(``.hydra/config.yaml``), naming the keys, and a new run pointed at a folder that holds one.

The run's output folder receives the resolved config (``.hydra/``), ``metrics.csv`` (always),
the optional TensorBoard / MLflow logs (``tracker=``), ``checkpoints/`` (``last.ckpt`` every
epoch), ``results.json`` (final and best metrics, status) and ``export/`` (the trained
:class:`~resireg.models.ResiregVLM`, loadable with ``ResiregVLM.from_pretrained``).

This module is the door: the job's body is :mod:`resireg_train.jobs.train`, the checks of a
resume :mod:`resireg_train.checks.resume`.
"""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from resireg_train.checks.resume import refuse_occupied, resume_command
from resireg_train.cli.job import hydra_entry_point, run_task
from resireg_train.config.machine import config_rank
from resireg_train.jobs.train import fit, run_trial_ranks, trial_ranks_needed
from resireg_train.search.ranks import TRIAL_RANK_ENV

if TYPE_CHECKING:
    import lightning as L

__all__ = ["main", "train"]

log = logging.getLogger(__name__)


def train(cfg: DictConfig, callbacks: Sequence[L.Callback] = ()) -> dict[str, Any]:
    """Train from a composed config; returns the ``results.json`` content (``{}`` on ranks
    other than 0).

    Any failure, from a bad config value to a crash mid-epoch, is recorded in
    ``results.json`` (see :func:`~resireg_train.cli.job.run_task`).

    Args:
        cfg: a composed ``train.yaml`` config (``paths.output_dir`` must be resolvable).
        callbacks: extra callbacks (added to the configured ones).
    """
    body = functools.partial(fit, callbacks=callbacks)
    out = Path(cfg.paths.output_dir)
    if trial_ranks_needed(cfg):
        return run_trial_ranks(cfg, out)
    rank_zero = config_rank(cfg) == 0
    if rank_zero and cfg.ckpt_path is None:
        refuse_occupied(out)  # (a single run's folder was checked before Hydra wrote to it)
    if HydraConfig.initialized():
        runtime = HydraConfig.get()
        multirun = runtime.mode == RunMode.MULTIRUN
        command = resume_command(runtime.overrides.task, runtime.overrides.hydra, out, multirun)
    else:  # called from Python: the caller knows its config
        command = f"ckpt_path=last and paths.output_dir={out} (with this run's config)"
    try:
        return run_task(cfg, body, rank_zero=rank_zero, resume_hint=f"resume with {command}")
    except Exception as exc:
        # A rank of a search trial started by its worker (resireg_train.search.ranks): a
        # pruned trial is recorded (run_task) and the worker tells the study; exit 0
        if getattr(exc, "run_status", None) == "pruned" and os.environ.get(TRIAL_RANK_ENV):
            log.info("%s", exc)
            return {}
        raise



main = hydra_entry_point("train", train)

if __name__ == "__main__":
    main()
