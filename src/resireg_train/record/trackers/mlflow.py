"""The four trackers of :data:`resireg_train.record.trackers.base.TRACKER_SPECS` (``logger=<name>``,
``conf/logger/<name>.yaml``): what each sends to its store. Nothing heavy is imported here:
each tracker imports its library (Lightning, MLflow, W&B, TensorBoard) when it is used.

- **csv**: ``metrics.csv``. Training always writes it (every step and epoch, continued on
  resume: :class:`~resireg_train.record.epochs.ResumableCSVLogger`); an evaluation or a map with
  ``logger=csv`` writes its final metrics as one row.
- **tensorboard**: training's curves (Lightning's ``TensorBoardLogger``); an evaluation or a
  map writes its final metrics as scalars and its provenance as text under ``<run>/tensorboard``.
- **mlflow** (default store: one SQLite database under ``paths.log_dir``, ``mlflow ui
  --backend-store-uri sqlite:///outputs/mlflow.db``; a server:
  ``logger.mlflow.tracking_uri=http://host:5000``): one MLflow run per job (a training run's is
  the one Lightning's ``MLFlowLogger`` logged its curves to), with the flattened config as
  parameters, the provenance block as ``provenance.*`` tags, every finite final metric, the
  per-class IoU as a table artifact (``per_class_iou.json``) and the run's files as artifacts
  (``results.json``, CSVs, PNGs, ``code.diff``, the log, the PLY when under 64 MiB, else its
  path as a tag; a training run's export folder with its model card under ``export/``); the
  jobs of one multirun or search are children of one parent run named after the sweep
  (MLflow's ``mlflow.parentRunId`` tag). The run ends FINISHED, FAILED or KILLED with the job.
  While it runs, MLflow's own system-metrics monitor logs ``system/...`` to it every
  ``system_metrics.interval`` seconds (an evaluation's or a map's run is opened at its start
  for that: :func:`open_mlflow_run`).
  A training run's MLflow run id is recorded (``tracking.mlflow_run_id``) as soon as the run
  exists; a resume (``ckpt_path``) logs into that run again, its curves going on from the
  resumed step.
- **wandb** (``WANDB_MODE=offline`` needs no network): one W&B run per job, named
  ``<name>-<run id>[-<job number>]`` (a multirun's jobs grouped as ``<name>-<run id>``), given
  the resolved config at the start and ``results.json``'s summary at the end, then finished
  (exit code 1 if the job failed): Lightning's ``WandbLogger`` never finishes its run, and a
  run left open takes the next job's logs in a multirun. Its system panel samples the run's
  process tree every ``system_metrics.interval`` seconds. An offline run is uploaded later with
  ``wandb sync <run>/wandb/offline-run-*``.
  run left open takes the next job's logs in a multirun. The W&B run id is recorded
  (``tracking.wandb_run_id``); a resumed training run continues that W&B run.

Every value a tracker receives has the passwords of its URLs masked
(:func:`resireg.secrets.mask_text`).
"""

from __future__ import annotations

import csv
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit, urlunsplit

from resireg.secrets import mask_text
from resireg.specs.tree import flatten
from resireg_train.record.run_record import masked_tree
from resireg_train.record.trackers.base import (
    TRACKER_SPECS,
    Tracker,
    map_counts,
    mlflow_key,
    run_metrics,
)

__all__ = [
    "ARTIFACTS_FOLDER",
    "MLFLOW_ARTIFACT_MAX_BYTES",
    "artifact_location",
    "CsvTracker",
    "MlflowTracker",
    "TensorBoardTracker",
    "WandbTracker",
    "open_mlflow_run",
    "resolved_config",
    "to_mlflow",
    "wandb_logger",
    "wandb_run_name",
    "wandb_summary",
]

log = logging.getLogger(__name__)

#: Files larger than this are recorded by path (a tag), not uploaded.
MLFLOW_ARTIFACT_MAX_BYTES = 64 << 20
_STATUS = {"completed": "FINISHED", "failed": "FAILED", "interrupted": "KILLED", "pruned": "KILLED"}
#: The run folder's files an MLflow run takes as artifacts (by suffix; dot files never).
_ARTIFACTS = (".json", ".csv", ".png", ".md", ".diff", ".ply", ".rrd", ".log")


def resolved_config(cfg: Any) -> dict[str, Any]:
    """The run's config as plain values (resolved where it can be), URL passwords masked:
    what a tracker is given."""
    from omegaconf import OmegaConf

    try:
        config = OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # an interpolation only Hydra's runtime resolves
        config = OmegaConf.to_container(cfg, resolve=False)
    return masked_tree(config)


def _note(record: Any, key: str, value: Any) -> None:
    """Add ``key: value`` to the record's ``tracking`` (the job's writer only)."""
    if record.writer and value is not None:
        tracking = record.get("tracking") or {}
        if tracking.get(key) != value:
            record.update(tracking={**tracking, key: value})


def _recorded(record: Any, key: str) -> str | None:
    """``tracking.<key>`` of the run's record, the id a resumed run continues."""
    value = (record.get("tracking") or {}).get(key) if record.writer else None
    return value if isinstance(value, str) and value else None


# ------------------------------------------------------------------------------------ CSV
class CsvTracker(Tracker):
    """``metrics.csv`` (module docstring)."""

    @classmethod
    def always(cls, cfg: Any, record: Any) -> CsvTracker:
        """The CSV tracker of a training run whose ``logger`` does not name ``csv``: its
        ``metrics.csv`` is written all the same."""
        return cls(TRACKER_SPECS.get("csv"), {}, cfg, record)

    def lightning_logger(self, resume_step: int | None) -> Any:
        if self._logger is None:
            from resireg_train.record.epochs import ResumableCSVLogger

            self._logger = ResumableCSVLogger(self.record.folder, resume_step=resume_step)
        return self._logger

    def end(self, record: dict[str, Any], failed: bool) -> None:
        if self.training:
            return  # Lightning wrote every step and epoch
        metrics = run_metrics(record)
        filename = str(self.settings.get("filename") or "metrics.csv")
        with open(self.record.folder / filename, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=sorted(metrics))
            writer.writeheader()
            writer.writerow(metrics)


# ---------------------------------------------------------------------------- TensorBoard
class TensorBoardTracker(Tracker):
    """``<run>/tensorboard`` (module docstring)."""

    def end(self, record: dict[str, Any], failed: bool) -> None:
        if self.training:
            return  # Lightning's TensorBoardLogger wrote the curves
        from torch.utils.tensorboard import SummaryWriter

        with SummaryWriter(str(self.record.folder / "tensorboard")) as writer:
            for key, value in run_metrics(record).items():
                writer.add_scalar(key, value, 0)
            writer.add_text("provenance", "```\n" + json.dumps(record.get("provenance") or {},
                                                               indent=2) + "\n```")  # fmt: skip


# --------------------------------------------------------------------------------- MLflow
class MlflowTracker(Tracker):
    """One MLflow run per job (module docstring).

    A ``tracking_uri`` with a user part (``http://user:pass@host:5000``) is given to MLflow
    without it, the user and password through MLflow's own ``MLFLOW_TRACKING_USERNAME`` /
    ``MLFLOW_TRACKING_PASSWORD`` (unless the environment sets them already) while the run
    lasts (:class:`~resireg_train.record.trackers.base.RunTrackers` puts the process's environment
    back at its end): MLflow then never prints, stores or logs the password (it prints each
    run's URL, from its tracking URI).

    Where the run's files go (``artifact_location``, MLflow's experiment setting, used when the
    experiment is created): as given, else, for a SQLite store, ``mlartifacts/`` next to the
    database (:func:`artifact_location`), never MLflow's ``./mlruns`` of the folder the command
    started from; a server store keeps its own (its ``--artifacts-destination``)."""

    def address(self) -> str | None:
        return str(self.settings.get("tracking_uri") or "") or None

    def _without_credentials(self) -> dict[str, Any]:
        """Its block as MLflow is given it: the tracking URI without its user part (moved to
        the environment), the artifact location (:func:`artifact_location`)."""
        settings = dict(self.settings)
        uri = str(settings.get("tracking_uri") or "")
        settings["artifact_location"] = artifact_location(uri, settings.get("artifact_location"))
        parts = urlsplit(uri)
        if parts.username is None and parts.password is None:
            return settings
        if parts.username:
            os.environ.setdefault("MLFLOW_TRACKING_USERNAME", unquote(parts.username))
        if parts.password is not None:
            os.environ.setdefault("MLFLOW_TRACKING_PASSWORD", unquote(parts.password))
        host = parts.netloc.rpartition("@")[2]
        settings["tracking_uri"] = urlunsplit(parts._replace(netloc=host))
        return settings

    def logger_settings(self) -> dict[str, Any]:
        own = self.spec.params
        return {k: v for k, v in self._without_credentials().items() if k not in own}

    _run_id: str | None = None  # an evaluation's or a map's run, opened at its start
    _monitor: Any = None  # MLflow's SystemMetricsMonitor of the run

    def begin(self) -> None:
        settings = self._without_credentials()  # a store without an artifact location: refused
        if not self.training:  # open the run now: it shows the run's system metrics live
            self._run_id = open_mlflow_run(settings, self.cfg)

    def running(self) -> None:
        """MLflow's own system-metrics monitor (``mlflow.system_metrics``: ``system/...``
        metrics, the run's "System metrics" tab) at ``system_metrics.interval``."""
        from resireg_train.record.system import system_settings

        enabled, interval = system_settings(self.cfg)
        run_id = getattr(self._logger, "run_id", None) or self._run_id
        if not enabled or run_id is None or self._monitor is not None:
            return
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        uri = str(self._without_credentials().get("tracking_uri"))
        self._monitor = SystemMetricsMonitor(run_id, sampling_interval=interval, tracking_uri=uri)
        self._monitor.start()

    def _stop_monitor(self) -> None:
        """Stop the monitor; the samples it took since it last logged (all of them, for a run
        shorter than the interval) are logged too."""
        monitor, self._monitor = self._monitor, None
        if monitor is None:
            return
        monitor.finish()
        if any(m._metrics for m in monitor.monitors):
            monitor.publish_metrics(monitor.aggregate_metrics())
            monitor.mlflow_logger.flush()

    def lightning_logger(self, resume_step: int | None) -> Any:
        """Lightning's ``MLFlowLogger``. A resumed training run (``resume_step`` set) logs into
        the MLflow run its record names (``tracking.mlflow_run_id``), set back to RUNNING;
        one the store no longer has is a warning and a new run. The run id is recorded as
        soon as the run exists: a run killed before its end resumes into it too."""
        if self._logger is not None:
            return self._logger
        recorded = _recorded(self.record, "mlflow_run_id") if resume_step is not None else None
        if recorded is not None:
            self._logger = self._continued(recorded)
        logger = super().lightning_logger(resume_step)  # a new run unless continued
        if logger is not None and self.record.writer:
            _note(self.record, "mlflow_run_id", logger.run_id)
        return logger

    def _continued(self, run_id: str) -> Any:
        import hydra

        logger = hydra.utils.instantiate(self.logger_settings(), run_id=run_id)
        try:
            logger.experiment.update_run(logger.run_id, status="RUNNING")
        except Exception as err:  # deleted, or another store: a new run, said once
            log.warning("logger.mlflow: cannot continue MLflow run %s (%s); this resume "
                        "logs to a new run", run_id, mask_text(str(err)).splitlines()[0])  # fmt: skip
            return None
        return logger

    def end(self, record: dict[str, Any], failed: bool) -> dict[str, Any]:
        self._stop_monitor()
        # the run Lightning logged curves to, or the one opened at the start
        run_id = getattr(self._logger, "run_id", None) or self._run_id
        if run_id is None:
            run_id = (record.get("tracking") or {}).get("mlflow_run_id")
        settings = self._without_credentials()
        return {"mlflow_run_id": to_mlflow(settings, self.cfg, self.record.folder, record,
                                           run_id)}  # fmt: skip


def _group() -> tuple[str | None, str | None]:
    """``(job label, sweep folder)`` of a multirun job, ``(None, None)`` for a single run."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        runtime = HydraConfig.get()
        return str(runtime.job.num), str(runtime.sweep.dir)
    return None, None


def _parent_run(client: Any, experiment_id: str, sweep: str, name: str) -> str:
    """The MLflow run that stands for the sweep folder ``sweep`` (created on first use; the
    jobs of a sweep find it by its ``resireg.sweep`` tag)."""
    quoted = sweep.replace("'", "\\'")
    found = client.search_runs([experiment_id], f"tags.`resireg.sweep` = '{quoted}' and "
                               "tags.`resireg.parent` = 'true'", max_results=1)  # fmt: skip
    if found:
        return found[0].info.run_id
    run = client.create_run(experiment_id, run_name=f"{name} sweep {Path(sweep).name}",
                            tags={"resireg.sweep": sweep, "resireg.parent": "true"})  # fmt: skip
    return run.info.run_id


#: The folder of a SQLite store's artifacts, next to its database (MLflow server's own
#: default name for its ``--artifacts-destination``).
ARTIFACTS_FOLDER = "mlartifacts"


def artifact_location(tracking_uri: str, given: Any = None) -> str | None:
    """Where a new experiment of the store ``tracking_uri`` keeps its runs' files: ``given``
    (``logger.mlflow.artifact_location``) when set; for a SQLite store, the folder
    :data:`ARTIFACTS_FOLDER` next to its database (a ``file:`` URI); else ``None``: a server
    store (``http(s)://``) chooses its own. Another database store (``postgresql://``,
    ``mysql://``...) needs one given: MLflow would write into ``./mlruns`` of whatever folder
    the command started from (a :class:`~resireg.errors.ConfigError` naming the key)."""
    if given:
        return str(given)
    from resireg.network import local_store

    scheme = urlsplit(tracking_uri).scheme.lower().split("+")[0]
    if scheme == "sqlite":
        folder = local_store(tracking_uri)
        return None if folder is None else (folder / ARTIFACTS_FOLDER).resolve().as_uri()
    if scheme in ("postgresql", "mysql", "mssql", "oracle"):
        from resireg.errors import ConfigError

        raise ConfigError(
            f"logger.mlflow.artifact_location: required with the database store "
            f"{mask_text(tracking_uri)!r} (where the runs' files go: a folder, or an s3:// ... "
            "URI); MLflow would otherwise write them into ./mlruns of the current folder"
        )
    return None


def _experiment_id(client: Any, settings: dict[str, Any]) -> str:
    name = str(settings.get("experiment_name") or "resireg")
    experiment = client.get_experiment_by_name(name)
    if experiment:
        return experiment.experiment_id
    return client.create_experiment(name, artifact_location=settings.get("artifact_location"))


def open_mlflow_run(settings: dict[str, Any], cfg: Any) -> str:
    """A new MLflow run (status RUNNING) for the job of ``cfg``, named after the run (a
    multirun job: ``<name>-<job>``), with the flattened config as parameters; its id."""
    from mlflow import MlflowClient
    from mlflow.entities import Param

    client = MlflowClient(tracking_uri=str(settings.get("tracking_uri")))
    job, _ = _group()
    run_name = str(settings.get("run_name") or cfg.name)
    run_id = client.create_run(_experiment_id(client, settings), run_name=run_name if job is None
                               else f"{run_name}-{job}").info.run_id  # fmt: skip
    config = flatten(resolved_config(cfg))
    params = [Param(mlflow_key(k)[:250], str(v)[:6000]) for k, v in config.items()]
    for i in range(0, len(params), 100):  # log_batch takes at most 100 params per call
        client.log_batch(run_id, params=params[i : i + 100])
    return run_id


def to_mlflow(
    settings: dict[str, Any], cfg: Any, out: Path, record: dict[str, Any], run_id: str | None
) -> str:
    """Log the run in ``out`` (its record ``record``) to MLflow (module docstring);
    ``settings``: the ``logger.mlflow`` block (``tracking_uri``, ``experiment_name``,
    ``run_name``); ``run_id``: the run Lightning logged to or the one opened at the start
    (:func:`open_mlflow_run`), if any. Returns the MLflow run id."""
    from mlflow import MlflowClient
    from mlflow.entities import Metric, RunTag

    client = MlflowClient(tracking_uri=str(settings.get("tracking_uri")))
    experiment_id = _experiment_id(client, settings)
    job, sweep = _group()
    tags = {"resireg.run_dir": str(out.resolve())}
    if sweep:
        tags["mlflow.parentRunId"] = _parent_run(client, experiment_id, sweep, str(cfg.name))
        tags["resireg.job"] = job
    if run_id is None:
        run_id = open_mlflow_run(settings, cfg)
    provenance = flatten(record.get("provenance") or {}, "provenance")
    tags.update({mlflow_key(k)[:250]: mask_text(str(v))[:5000] for k, v in provenance.items()})
    tags["resireg.status"] = str(record.get("status"))
    metrics = [Metric(mlflow_key(k), v, 0, 0) for k, v in run_metrics(record).items()]
    tag_list = [RunTag(k, v) for k, v in tags.items()]
    for i in range(0, max(len(metrics), len(tag_list)), 100):
        client.log_batch(run_id, metrics=metrics[i : i + 100], tags=tag_list[i : i + 100])
    per_class = record.get("per_class_iou")
    if per_class:
        classes = sorted({c for ious in per_class.values() for c in ious})
        table = {"class": classes, **{v: [ious.get(c) for c in classes]
                                      for v, ious in per_class.items()}}  # fmt: skip
        client.log_table(run_id, data=table, artifact_file="per_class_iou.json")
    for path in sorted(out.iterdir()):
        if not path.is_file() or path.name.startswith(".") or path.suffix not in _ARTIFACTS:
            continue
        if path.stat().st_size <= MLFLOW_ARTIFACT_MAX_BYTES:
            client.log_artifact(run_id, str(path))
        else:
            client.set_tag(run_id, f"resireg.file.{path.name}", str(path.resolve()))
    export = Path(str(record["export"])) if record.get("export") else None
    if export is not None and export.is_dir():  # a training run's export, with its model card
        for path in sorted(export.iterdir()):
            if (path.is_file() and not path.name.startswith(".")
                    and path.stat().st_size <= MLFLOW_ARTIFACT_MAX_BYTES):  # fmt: skip
                client.log_artifact(run_id, str(path), artifact_path="export")
    client.set_terminated(run_id, _STATUS.get(str(record.get("status")), "FINISHED"))
    return run_id


# ------------------------------------------------------------------------------------ W&B
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
        recorded = _recorded(self.record, "wandb_run_id")
        if self.training and self.cfg.get("ckpt_path") is not None and recorded is not None:
            # a resumed training run continues its W&B run (WandbLogger resumes an id it is
            # given: wandb.init(id=..., resume="allow")); Lightning logs trainer/global_step
            import hydra

            self._logger = hydra.utils.instantiate(self.logger_settings(), id=recorded)
        logger = self.lightning_logger(None)
        _stats_settings(logger, self.cfg)
        # W&B records the command line (its run metadata's "args"): give it masked URLs
        argv, sys.argv = sys.argv, [mask_text(a) for a in sys.argv]
        try:
            experiment = logger.experiment  # rank 0: the wandb run (created here)
        finally:
            sys.argv = argv
        _note(self.record, "wandb_run_id", getattr(experiment, "id", None))
        if hasattr(experiment, "config"):
            experiment.config.update(resolved_config(self.cfg), allow_val_change=True)

    def end(self, record: dict[str, Any], failed: bool) -> None:
        experiment = getattr(self._logger, "experiment", None)
        if not hasattr(experiment, "finish"):
            return
        experiment.summary.update(wandb_summary(record))
        experiment.finish(exit_code=1 if failed else 0)


def _stats_settings(logger: Any, cfg: Any) -> None:
    """W&B's own system panel (its ``wandb-core`` process samples the run's process tree) at
    ``system_metrics.interval``, or off with ``system_metrics.enabled=false``: settings of the
    ``wandb.init`` the logger's first use calls."""
    from resireg_train.record.system import system_settings

    init = getattr(logger, "_wandb_init", None)
    if not isinstance(init, dict) or "settings" in init:
        return  # not Lightning's WandbLogger, or settings given in conf/logger/wandb.yaml
    import wandb

    enabled, interval = system_settings(cfg)
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
    """Lightning's ``WandbLogger`` (``conf/logger/wandb.yaml``'s ``_target_``) with this job's
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
