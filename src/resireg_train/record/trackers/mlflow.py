"""The ``mlflow`` tracker (default store: one SQLite database under ``paths.log_dir``, ``mlflow ui
--backend-store-uri sqlite:///outputs/mlflow.db``; a server:
``tracker.mlflow.tracking_uri=http://host:5000``): one MLflow run per job (a training run's is
the one Lightning's ``MLFlowLogger`` logged its curves to), with the flattened config as
parameters, the provenance block as ``provenance.*`` tags, every finite final metric, the
per-class IoU as a table artifact (``per_class_iou.json``) and the run's files as artifacts
(``results.json``, CSVs, PNGs, ``code.diff``, the log, the PLY when under 64 MiB, else its path
as a tag; a training run's export folder with its model card under ``export/``); the jobs of one
multirun or search are children of one parent run named after the sweep (MLflow's
``mlflow.parentRunId`` tag). The run ends FINISHED, FAILED or KILLED with the job. While it
runs, MLflow's own system-metrics monitor logs ``system/...`` to it every
``system_metrics.interval`` seconds (an evaluation's or a map's run is opened at its start for
that: :func:`open_mlflow_run`). A training run's MLflow run id is recorded
(``tracking.mlflow_run_id``) as soon as the run exists; a resume (``ckpt_path``) logs into that
run again, its curves going on from the resumed step.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit, urlunsplit

from resireg.secrets import mask_text
from resireg.specs.tree import flatten
from resireg_train.record.settings import RecordSettings
from resireg_train.record.trackers.base import (
    Tracker,
    mlflow_key,
    note_tracking,
    recorded_id,
    run_metrics,
)

__all__ = [
    "ARTIFACTS_FOLDER",
    "MLFLOW_ARTIFACT_MAX_BYTES",
    "MlflowTracker",
    "artifact_location",
    "open_mlflow_run",
    "to_mlflow",
]

log = logging.getLogger(__name__)


#: Files larger than this are recorded by path (a tag), not uploaded.
MLFLOW_ARTIFACT_MAX_BYTES = 64 << 20

_STATUS = {"completed": "FINISHED", "failed": "FAILED", "interrupted": "KILLED", "pruned": "KILLED"}

#: The run folder's files an MLflow run takes as artifacts (by suffix; dot files never).
_ARTIFACTS = (".json", ".csv", ".png", ".md", ".diff", ".ply", ".rrd", ".log")


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
            self._run_id = open_mlflow_run(settings, self.run)

    def running(self) -> None:
        """MLflow's own system-metrics monitor (``mlflow.system_metrics``: ``system/...``
        metrics, the run's "System metrics" tab) at ``system_metrics.interval``."""
        enabled, interval = self.run.system_metrics
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
        recorded = recorded_id(self.record, "mlflow_run_id") if resume_step is not None else None
        if recorded is not None:
            self._logger = self._continued(recorded)
        logger = super().lightning_logger(resume_step)  # a new run unless continued
        if logger is not None and self.record.writer:
            note_tracking(self.record, "mlflow_run_id", logger.run_id)
        return logger

    def _continued(self, run_id: str) -> Any:
        import hydra

        logger = hydra.utils.instantiate(self.logger_settings(), run_id=run_id)
        try:
            logger.experiment.update_run(logger.run_id, status="RUNNING")
        except Exception as err:  # deleted, or another store: a new run, said once
            log.warning("tracker.mlflow: cannot continue MLflow run %s (%s); this resume "
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
        return {"mlflow_run_id": to_mlflow(settings, self.run, self.record.folder, record,
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
    (``tracker.mlflow.artifact_location``) when set; for a SQLite store, the folder
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
            f"tracker.mlflow.artifact_location: required with the database store "
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


def open_mlflow_run(settings: dict[str, Any], run: RecordSettings) -> str:
    """A new MLflow run (status RUNNING) for the job of the settings ``run``, named after the
    run (a multirun job: ``<name>-<job>``), with the flattened config (its URL passwords
    masked) as parameters; its id."""
    from mlflow import MlflowClient
    from mlflow.entities import Param

    client = MlflowClient(tracking_uri=str(settings.get("tracking_uri")))
    job, _ = _group()
    run_name = str(settings.get("run_name") or run.name)
    run_id = client.create_run(_experiment_id(client, settings), run_name=run_name if job is None
                               else f"{run_name}-{job}").info.run_id  # fmt: skip
    config = flatten(run.masked_config)
    params = [Param(mlflow_key(k)[:250], str(v)[:6000]) for k, v in config.items()]
    for i in range(0, len(params), 100):  # log_batch takes at most 100 params per call
        client.log_batch(run_id, params=params[i : i + 100])
    return run_id


def to_mlflow(
    settings: dict[str, Any],
    run: RecordSettings,
    out: Path,
    record: dict[str, Any],
    run_id: str | None,
) -> str:
    """Log the run in ``out`` (its record ``record``) to MLflow (module docstring);
    ``settings``: the ``tracker.mlflow`` block (``tracking_uri``, ``experiment_name``,
    ``run_name``); ``run``: the run's settings (its name names the sweep's parent run);
    ``run_id``: the run Lightning logged to or the one opened at the start
    (:func:`open_mlflow_run`), if any. Returns the MLflow run id."""
    from mlflow import MlflowClient
    from mlflow.entities import Metric, RunTag

    client = MlflowClient(tracking_uri=str(settings.get("tracking_uri")))
    experiment_id = _experiment_id(client, settings)
    job, sweep = _group()
    tags = {"resireg.run_dir": str(out.resolve())}
    if sweep:
        tags["mlflow.parentRunId"] = _parent_run(client, experiment_id, sweep, str(run.name))
        tags["resireg.job"] = job
    if run_id is None:
        run_id = open_mlflow_run(settings, run)
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
