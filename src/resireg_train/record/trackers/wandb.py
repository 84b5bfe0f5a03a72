"""The ``wandb`` tracker (``WANDB_MODE=offline`` needs no network): one W&B run per job, named
``<name>-<run id>[-<job number>]`` (a multirun's jobs grouped as ``<name>-<run id>``), given the
resolved config at the start and ``results.json``'s summary at the end, then finished (exit code
1 if the job failed): Lightning's ``WandbLogger`` never finishes its run, and a run left open
takes the next job's logs in a multirun. Its system panel samples the run's process tree every
``system_metrics.interval`` seconds. An offline run is uploaded later with ``wandb sync
<run>/wandb/offline-run-*``. The W&B run id is recorded (``tracking.wandb_run_id``); a resumed
training run continues that W&B run.
"""

from __future__ import annotations

import os
import sys
from typing import Any

from resireg.secrets import mask_text
from resireg_train.record.trackers.base import (
    Tracker,
    map_counts,
    note_tracking,
    recorded_id,
)

__all__ = ["WandbTracker", "wandb_logger", "wandb_run_name", "wandb_summary"]


def _wandb_offline(settings: dict[str, Any]) -> bool:
    mode = os.environ.get("WANDB_MODE", "").lower()
    return bool(settings.get("offline")) or mode in ("offline", "dryrun", "disabled")


class WandbTracker(Tracker):
    """One W&B run per job (module docstring)."""

    def address(self) -> str | None:
        if _wandb_offline(self.settings):
            return None
        return os.environ.get("WANDB_BASE_URL") or "https://api.wandb.ai"

    def begin(self) -> None:
        recorded = recorded_id(self.record, "wandb_run_id")
        if self.training and self.run.resuming and recorded is not None:
            # a resumed training run continues its W&B run (WandbLogger resumes an id it is
            # given: wandb.init(id=..., resume="allow")); Lightning logs trainer/global_step
            import hydra

            self._logger = hydra.utils.instantiate(self.logger_settings(), id=recorded)
        logger = self.lightning_logger(None)
        _stats_settings(logger, self.run.system_metrics)
        # W&B records the command line (its run metadata's "args"): give it masked URLs
        argv, sys.argv = sys.argv, [mask_text(a) for a in sys.argv]
        try:
            experiment = logger.experiment  # rank 0: the wandb run (created here)
        finally:
            sys.argv = argv
        note_tracking(self.record, "wandb_run_id", getattr(experiment, "id", None))
        if hasattr(experiment, "config"):
            experiment.config.update(self.run.masked_config, allow_val_change=True)

    def end(self, record: dict[str, Any], failed: bool) -> None:
        experiment = getattr(self._logger, "experiment", None)
        if not hasattr(experiment, "finish"):
            return
        experiment.summary.update(wandb_summary(record))
        experiment.finish(exit_code=1 if failed else 0)


def _stats_settings(logger: Any, system_metrics: tuple[bool, float]) -> None:
    """W&B's own system panel (its ``wandb-core`` process samples the run's process tree) at
    ``system_metrics.interval``, or off with ``system_metrics.enabled=false``: settings of the
    ``wandb.init`` the logger's first use calls (``system_metrics``: the run's
    ``(enabled, interval)``)."""
    init = getattr(logger, "_wandb_init", None)
    if not isinstance(init, dict) or "settings" in init:
        return  # not Lightning's WandbLogger, or settings given in conf/tracker/wandb.yaml
    import wandb

    enabled, interval = system_metrics
    init["settings"] = (wandb.Settings(x_stats_sampling_interval=interval,
                                       x_stats_track_process_tree=True)
                        if enabled else wandb.Settings(x_disable_stats=True))  # fmt: skip


def wandb_run_name(name: str) -> tuple[str, str | None]:
    """``(run name, group)`` of this job's W&B run: ``<name>-<run id>`` (the run id of the
    output folder, :data:`resireg_train.config.paths.RUN_ID`), with ``-<job number>`` and the
    group ``<name>-<run id>`` (the sweep) for a job of a multirun."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from resireg_train.config.paths import RUN_ID

    base = f"{name}-{RUN_ID}"
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        return f"{base}-{HydraConfig.get().job.num}", base
    return base, None


def wandb_logger(name: str, project: str = "resireg", **kwargs: Any) -> Any:
    """Lightning's ``WandbLogger`` (``conf/tracker/wandb.yaml``'s ``_target_``) with this job's
    run name and group (:func:`wandb_run_name`); ``WANDB_MODE=offline`` logs without a
    network."""
    from lightning.pytorch.loggers import WandbLogger

    run_name, group = wandb_run_name(name)
    logger = WandbLogger(name=run_name, project=project, group=group, **kwargs)
    # Lightning passes anonymous=None to wandb.init unless asked for it, and wandb warns "The
    # anonymous setting has no effect" for any value given: leave the key out when unset.
    init = getattr(logger, "_wandb_init", {})
    if init.get("anonymous") is None:
        init.pop("anonymous", None)
    return logger


def wandb_summary(record: dict[str, Any]) -> dict[str, Any]:
    """``results.json``'s summary as W&B summary values: status, epoch, step, the final values
    (``final/<metric>``) and the best ones (``best/<metric>``, ``best/<metric>/epoch``);
    non-finite values (``null`` in the file) are left out."""
    out: dict[str, Any] = {k: record[k] for k in ("status", "epoch", "global_step", "error")
                           if record.get(k) is not None}  # fmt: skip
    out.update({f"final/{k}": v for k, v in (record.get("final") or {}).items() if v is not None})
    out.update(map_counts(record))  # a resireg-map run's voxels and frames
    for key, best in (record.get("best") or {}).items():
        if isinstance(best, dict) and best.get("value") is not None:
            out[f"best/{key}"] = best["value"]
            out[f"best/{key}/epoch"] = best["epoch"]
    return out
