"""``resireg-train``: the Hydra main that trains the dense VLM.

    resireg-train experiment=smoke                      # CPU, tiny models, < 1 min
    resireg-train experiment=vlm25m_stage1 trainer=ddp  # the 25M VLM, stage 1, all GPUs
    resireg-train experiment=vlm25m_stage1 ckpt_path=last hydra.run.dir=<the run's folder>

A resume takes the run's own overrides (the interrupted run prints the command, and
``results.json`` records it). :class:`RunFolderCheck` refuses, before Hydra writes anything
into the folder, a resume whose composed config differs from the run's
(``.hydra/config.yaml``), naming the keys, and a new run pointed at a folder that holds one.

The run's output folder receives the resolved config (``.hydra/``), ``metrics.csv`` (always),
the optional TensorBoard / MLflow logs (``logger=``), ``checkpoints/`` (``last.ckpt`` every
epoch), ``results.json`` (final and best metrics, status) and ``export/`` (the trained
:class:`~resireg.models.ResiregVLM`, loadable with ``ResiregVLM.from_pretrained``).
"""

from __future__ import annotations

import functools
import logging
import os
import re
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from resireg.errors import ConfigError
from resireg.secrets import mask_text
from resireg.specs.tree import differences
from resireg_train.cli.job import (
    added_keys,
    error_text,
    hold_run_folder,
    hydra_entry_point,
    instantiate_group,
    release_run_folder,
    run_task,
    top_level_keys,
)
from resireg_train.config.machine import (
    check_available,
    check_cluster,
    check_devices,
    config_rank,
)
from resireg_train.config.moves import current_keys, current_targets
from resireg_train.config.train import validate
from resireg_train.record.masking import masked_tree
from resireg_train.record.run_record import RunRecord, flat
from resireg_train.search.ranks import TRIAL_RANK_ENV

if TYPE_CHECKING:
    import lightning as L

__all__ = ["RunFolderCheck", "build", "main", "resume_command", "train"]

log = logging.getLogger(__name__)

# Lightning, the models and the data load inside the task, after the config check: --help,
# --cfg job and a bad value answer without them (README, "Start-up").


def _process_rank(cfg: DictConfig) -> int:
    """This process's global rank (:func:`~resireg_train.config.machine.config_rank`)."""
    return config_rank(cfg)


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
    ``results.json`` (see :func:`~resireg_train.cli.job.run_task`).

    Args:
        cfg: a composed ``train.yaml`` config (``paths.output_dir`` must be resolvable).
        callbacks: extra callbacks (added to the configured ones).
    """
    body = functools.partial(_fit, callbacks=callbacks)
    out = Path(cfg.paths.output_dir)
    if _trial_ranks_needed(cfg):
        return _run_trial_ranks(cfg, out)
    rank_zero = _process_rank(cfg) == 0
    if rank_zero and cfg.ckpt_path is None:
        _refuse_occupied(out)  # (a single run's folder was checked before Hydra wrote to it)
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


def _trial_ranks_needed(cfg: DictConfig) -> bool:
    """Whether this job is a search trial (in the search's process) whose trainer
    re-launches the command line: its ranks are started by :func:`_run_trial_ranks`."""
    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return False
    if OmegaConf.select(cfg, "hparams_search.trial", default=None) is None:
        return False
    if os.environ.get(TRIAL_RANK_ENV):
        return False
    from resireg_train.search.ranks import relaunches

    return relaunches(OmegaConf.to_container(cfg.trainer, resolve=True))


def _run_trial_ranks(cfg: DictConfig, out: Path) -> dict[str, Any]:
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
              f"hydra.sweep.dir={_hydra_quoted(Path(runtime.sweep.dir).resolve())}",
              f"hydra.run.dir={_hydra_quoted(out.resolve())}", "hydra.mode=RUN",
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


def _hydra_quoted(folder: Path | str) -> str:
    """A folder as a Hydra override's value: double-quoted where it holds what Hydra parses
    (a sweep job's folder holds ``=`` and ``,``)."""
    folder = str(folder)
    if re.fullmatch(r"[\w/.\-:~+@%]+", folder):
        return folder
    return '"' + folder.replace("\\", "\\\\").replace('"', '\\"') + '"'


#: Keys a resume may change: the resume itself, and what is recorded of the run without
#: changing what it computes (its trackers, what provenance keeps of the code, the system
#: metrics' interval).
_RESUME_FREE = ("ckpt_path", "logger", "provenance", "system_metrics")
#: Overrides a resume command sets itself (or must not repeat: the sweep's own folders).
_RESUME_SET = ("ckpt_path", "hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir",
               "hydra.mode", "hydra.output_subdir", "hydra.job.name")  # fmt: skip


def resume_command(
    task: Sequence[str], hydra: Sequence[str], out: Path, multirun: bool = False
) -> str:
    """The command that resumes the run in ``out``: ``resireg-train`` with the run's own
    overrides (``task``: the command line's, a sweep job's swept values included; ``hydra``:
    Hydra's), ``ckpt_path=last hydra.run.dir=<out>``, and for a sweep job ``hydra.mode=RUN``
    (it resumes that job alone), shell-quoted, URL passwords masked (a tracking URI's password
    is given again, or through the tracker's own environment variables)."""

    def kept(items: Sequence[str]) -> list[str]:
        return [o for o in items if o.split("=", 1)[0].lstrip("+~") not in _RESUME_SET]

    folder = _hydra_quoted(out)  # a sweep job's folder: "=" and ","
    words = [
        "resireg-train",
        *kept(task),
        *kept(hydra),
        "ckpt_path=last",
        f"hydra.run.dir={folder}",
    ]
    if multirun:
        words.append("hydra.mode=RUN")
    return mask_text(" ".join(shlex.quote(str(w)) for w in words))


def _differences(run: dict[str, Any], this: dict[str, Any]) -> list[str]:
    """``key=<this value> (the run: <its value>)`` of every leaf that differs, the shallowest
    keys first (``trainer.max_epochs`` before a dataset's ``split``)."""
    return [
        f"{key}={now!r} (the run: {then!r})"
        for key, then, now in differences(run, this, skip=_RESUME_FREE)
    ]


def check_resume(out: Path, composed: DictConfig) -> None:
    """Refuse a resume of the run in ``out`` whose config (``composed``, without its
    ``hydra`` node) differs from the run's ``.hydra/config.yaml``: ``ConfigError`` naming the
    differing keys (up to 8, and how many more), the run's overrides and this command's, the
    command that resumes the run with its own overrides, and the way to train on with other
    settings. A folder without a stored config (a run started from Python) is not checked."""
    stored = out / ".hydra" / "config.yaml"
    if not stored.is_file():
        return
    # a run written before a class moved names its old path, and one written before a key
    # existed lacks it: compare with today's; the saved config has its URL passwords masked
    # (RunRecord.start): compare masked values
    run = current_keys(
        current_targets(OmegaConf.to_container(OmegaConf.load(stored), resolve=False))
    )
    this = OmegaConf.to_container(composed, resolve=False)
    this.pop("hydra", None)
    run, this = masked_tree(run), masked_tree(this)
    differences = _differences(run, this)
    if not differences:
        return
    shown = "; ".join(differences[:8])
    if len(differences) > 8:
        shown += f"; and {len(differences) - 8} more"
    hydra_file = out / ".hydra" / "hydra.yaml"
    recorded = yaml.safe_load(hydra_file.read_text())["hydra"] if hydra_file.is_file() else {}
    overrides = recorded.get("overrides") or {}
    task = yaml.safe_load((out / ".hydra" / "overrides.yaml").read_text()) or []
    command = resume_command(task, overrides.get("hydra") or [], out,
                             recorded.get("mode") == "MULTIRUN")  # fmt: skip
    given = list(composed.hydra.overrides.task) if "hydra" in composed else []
    raise ConfigError(
        f"ckpt_path={composed.get('ckpt_path')}: this command's config differs from the run's "
        f"({stored}) in {len(differences)} key(s): {shown}. The run's overrides: "
        f"{' '.join(task) or 'none'}; this command's: {' '.join(given) or 'none'}. Nothing under "
        f"{out} was changed. Resume with the run's own overrides: {command}; to train on with "
        f"other settings, start a new run from its weights: "
        f"model.init_from={out / 'checkpoints' / 'last.ckpt'}"
    )


class RunFolderCheck(Callback):
    """Hydra callback (``conf/train.yaml``, ``hydra.callbacks``): checks a single run's
    folder before Hydra writes anything into it (``.hydra/``, the log file), so a refused
    command leaves an existing run exactly as it was. A resume (``ckpt_path`` set) must
    compose the run's config (:func:`check_resume`); a new run must not be pointed at a
    folder holding another (:func:`_refuse_occupied`). Sweep jobs get fresh folders (time
    and run id); ranks > 0 of a DDP run re-launched by Lightning skip the check."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        if _process_rank(config) != 0:
            return
        out = Path(str(config.hydra.run.dir))
        try:
            if config.get("ckpt_path") is None:
                _refuse_occupied(out, multirun=False)
            elif RunRecord.exists(out):
                check_resume(out, config)
        except (ConfigError, FileExistsError) as err:
            # Hydra turns a callback's exception into a warning and runs the job anyway: exit.
            sys.stderr.write(f"resireg-train: refused: {error_text(err)}\n")
            raise SystemExit(1) from None


def _refuse_occupied(out: Path, multirun: bool | None = None) -> None:
    """A new run never shares a folder with another (their metrics.csv, checkpoints and
    results.json would interleave): a folder already holding a run record is refused unless
    the run resumes it. Default folders are unique (time + run id, for sweeps too); this
    guards a folder given by hand."""
    previous = RunRecord.read(out)
    if not previous:
        return
    if multirun is None:
        multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    if multirun:
        where, unset = f"the sweep job's folder {out} (hydra.sweep.dir/subdir)", "hydra.sweep.dir"
    else:
        where, unset = f"hydra.run.dir={out}", "hydra.run.dir"
    raise FileExistsError(
        f"{where} already holds a run ({previous.get('name')!r}, status "
        f"{previous.get('status')!r}): resume it with ckpt_path=last, or give this run its "
        f"own folder (leave {unset} unset for a new, unique one)"
    )


def _fit(cfg: DictConfig, record: RunRecord, callbacks: Sequence[L.Callback]) -> dict[str, Any]:
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

    # metrics.csv and the trackers' Lightning loggers (logger=...), from the run's record
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


main = hydra_entry_point("train", train)

if __name__ == "__main__":
    main()
