"""The training job's body (``resireg-train``'s door is :mod:`resireg_train.cli.train`): build
the module and data module from the config, check the run folder before Hydra writes
(:class:`RunFolderCheck`), fit with the run's record, trackers and checkpoints, export the
trained :class:`~resireg.models.ResiregVLM`; and a search trial's DDP ranks, started by the
trial itself (:func:`run_trial_ranks`).

Lightning, the models and the data load inside :func:`fit`, after the config check: --help,
--cfg job and a bad value answer without them (README, "Start-up").
"""

from __future__ import annotations

import logging
import os
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError
from resireg_train.checks.resume import check_resume, hydra_quoted, refuse_occupied
from resireg_train.checks.train import validate
from resireg_train.config.machine import (
    check_available,
    check_cluster,
    check_devices,
    config_rank,
)
from resireg_train.jobs.console import error_text
from resireg_train.jobs.overrides import added_keys, instantiate_group, top_level_keys
from resireg_train.jobs.run_folder import hold_run_folder, release_run_folder
from resireg_train.record.run_record import RunRecord, flat
from resireg_train.search.ranks import TRIAL_RANK_ENV

if TYPE_CHECKING:
    import lightning as L

__all__ = ["RunFolderCheck", "build", "fit", "run_trial_ranks", "trial_ranks_needed"]

log = logging.getLogger(__name__)


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



def trial_ranks_needed(cfg: DictConfig) -> bool:
    """Whether this job is a search trial (in the search's process) whose trainer
    re-launches the command line: its ranks are started by :func:`run_trial_ranks`."""
    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return False
    if OmegaConf.select(cfg, "hparams_search.trial", default=None) is None:
        return False
    if os.environ.get(TRIAL_RANK_ENV):
        return False
    from resireg_train.search.ranks import relaunches

    return relaunches(OmegaConf.to_container(cfg.trainer, resolve=True))


def run_trial_ranks(cfg: DictConfig, out: Path) -> dict[str, Any]:
    """Run this search trial's ranks (:func:`resireg_train.search.ranks.run_ranks`): each
    one ``resireg-train`` alone (``hydra.mode=RUN``) in the trial's folder with the trial's
    overrides, the search's ``hydra.sweeper`` settings and its sweep folder; then the trial's
    outcome from its record: its results (completed), :class:`TrialPrunedStop` (pruned), or
    an error naming the first rank that failed (recorded as the run's error) or the record's
    own error."""
    from resireg_train.search.pruning import TrialPrunedStop
    from resireg_train.search.ranks import (
        TRIAL_LAUNCHER_ENV,
        TrialRankFailed,
        local_processes,
        run_ranks,
        trial_nodes_problem,
    )

    trainer = OmegaConf.to_container(cfg.trainer, resolve=True)
    number = cfg.hparams_search.trial
    if problem := trial_nodes_problem(trainer):
        raise ConfigError(problem)  # (the search refuses it before its first trial)
    runtime = HydraConfig.get()
    sweeper = [o for o in runtime.overrides.hydra if o.lstrip("+~").startswith("hydra.sweeper.")]
    common = [sys.executable, "-m", "resireg_train.cli.train", *runtime.overrides.task, *sweeper,
              f"hydra.sweep.dir={hydra_quoted(Path(runtime.sweep.dir).resolve())}",
              f"hydra.run.dir={hydra_quoted(out.resolve())}", "hydra.mode=RUN",
              "hydra.output_subdir=null"]  # fmt: skip
    launcher = os.environ.get(TRIAL_LAUNCHER_ENV)
    if launcher:  # it starts every rank, on every node
        log.info("trial %s: its DDP run started by %s", number, launcher)
        failure = run_ranks([shlex.split(launcher) + common], os.environ, ranks=False)
    else:
        ranks = local_processes(trainer)
        commands = [common + ([f"hydra.job.name=train_ddp_process_{k}"] if k else [])
                    for k in range(ranks)]  # fmt: skip
        log.info("trial %s: %d ranks of its DDP run started by this worker", number, ranks)
        failure = run_ranks(commands, os.environ)
    record = RunRecord.read(out)
    status = record.get("status")
    if failure is not None and not (failure.rank == 0 and status == "failed"):
        error = f"trial {number}: {failure.describe()}"
        if status == "failed" and record.get("error"):  # what rank 0 met meanwhile
            error += f"; rank 0: {flat(str(record['error']))}"
        took = hold_run_folder(out)
        try:
            RunRecord(out).finish("failed", f"{TrialRankFailed.__module__}.TrialRankFailed: "
                                            f"{error}")  # fmt: skip
        finally:
            if took:
                release_run_folder(out)
        raise TrialRankFailed(error)
    if status == "completed":
        return record
    if status == "pruned":
        raise TrialPrunedStop(str(record.get("error") or f"trial {number} pruned"))
    raise TrialRankFailed(
        f"trial {number}: {flat(str(record.get('error') or f'its run ended {status!r}'))}"
    )



class RunFolderCheck(Callback):
    """Hydra callback (``conf/train.yaml``, ``hydra.callbacks``): checks a single run's
    folder before Hydra writes anything into it (``.hydra/``, the log file), so a refused
    command leaves an existing run exactly as it was. A resume (``ckpt_path`` set) must
    compose the run's config (:func:`~resireg_train.checks.resume.check_resume`); a new run must not be pointed at a
    folder holding another (:func:`~resireg_train.checks.resume.refuse_occupied`). Sweep jobs get fresh folders (time
    and run id); ranks > 0 of a DDP run re-launched by Lightning skip the check."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        if config_rank(config) != 0:
            return
        out = Path(str(config.hydra.run.dir))
        try:
            if config.get("ckpt_path") is None:
                refuse_occupied(out, multirun=False)
            elif RunRecord.exists(out):
                check_resume(out, config)
        except (ConfigError, FileExistsError) as err:
            # Hydra turns a callback's exception into a warning and runs the job anyway: exit.
            sys.stderr.write(f"resireg-train: refused: {error_text(err)}\n")
            raise SystemExit(1) from None



def fit(cfg: DictConfig, record: RunRecord, callbacks: Sequence[L.Callback]) -> dict[str, Any]:
    out = record.folder
    validate(cfg, added_keys(), top_level_keys("train") if HydraConfig.initialized() else None)
    check_available(cfg)
    check_devices(cfg)
    check_cluster(cfg)
    import hydra
    import lightning as L
    from lightning.pytorch.callbacks import ProgressBar

    from resireg_train.evaluation.ovss.callback import ReSiRegEval
    from resireg_train.record.cards import write_export_card
    from resireg_train.record.epochs import ResultsTracker
    from resireg_train.record.provenance.block import write_export_provenance
    from resireg_train.training.checkpoints import AtomicCheckpointIO, resolve_checkpoint
    from resireg_train.training.console import (
        EpochLog,
        ModelSummary,
        on_terminal,
        quiet_library_noise,
    )

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

    # metrics.csv and the trackers' Lightning loggers (tracker=...), from the run's record
    loggers = record.trackers.lightning_loggers(resume_step)
    configured = instantiate_group(cfg.callbacks)
    # The model summary without an unmeasured "Total Flops: 0" (a configured one is kept); the
    # Trainer's own is off, else it would say that it skips its default for this one.
    summary = []
    if cfg.trainer.get("enable_model_summary", True) and not any(
        isinstance(c, L.pytorch.callbacks.ModelSummary) for c in configured
    ):
        summary = [ModelSummary()]
    bar: dict[str, Any] = {"enable_model_summary": False}
    if not on_terminal():  # a batch job, a pipe: the epoch lines, no progress bar redraws
        configured = [c for c in configured if not isinstance(c, ProgressBar)]
        bar["enable_progress_bar"] = False
    trainer: L.Trainer = hydra.utils.instantiate(
        cfg.trainer,
        logger=loggers,
        callbacks=[*configured, ResultsTracker(record), EpochLog(), *summary, *callbacks],
        plugins=[AtomicCheckpointIO()],
        default_root_dir=str(out),
        **bar,
    )
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt)
    except SystemExit:
        # Lightning answers Ctrl-C by shutting down and calling sys.exit(1); say what it was.
        if trainer.interrupted:
            raise KeyboardInterrupt from None
        raise
    for callback in trainer.callbacks:  # a search's pruning (sweeps.pruning.OptunaPruning)
        if hasattr(callback, "check_pruned"):
            callback.check_pruned(trainer)
    if not trainer.is_global_zero:
        return {}
    if not cfg.export:
        return record.fields()
    export = module.vlm.save_pretrained(out / "export")
    # the run that made it (its provenance, the last checkpoint's SHA-256)
    write_export_provenance(export, out, record.get("provenance") or {})
    write_export_card(export, record)  # README.md: a Hugging Face model card
    for callback in trainer.callbacks:
        if isinstance(callback, ReSiRegEval):
            callback.save_settings(export)
    return record.update(export=str(export))

