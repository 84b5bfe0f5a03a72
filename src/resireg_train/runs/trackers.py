"""One tracker for every run: what ``logger=mlflow`` / ``tensorboard`` / ``csv`` record of a
``resireg-train``, ``resireg-eval`` or ``resireg-map`` run when it ends (``logger=wandb``:
:func:`resireg_train.runs.tracking.wandb_runs`, around the job).

:func:`record_run` is called by the job wrapper (:func:`resireg_train.cli.job.run_task`) at
the end of every run, completed or not, and reads everything from the run folder:

- **MLflow** (``conf/logger/mlflow.yaml``; default store: one SQLite database under
  ``paths.log_dir``, ``mlflow ui --backend-store-uri sqlite:///outputs/mlflow.db``; a server:
  ``logger.mlflow.tracking_uri=http://host:5000``): one MLflow run per job (a training run
  reuses the run Lightning's ``MLFlowLogger`` logged its curves to), with the flattened config
  as parameters, the provenance block as ``provenance.*`` tags, every finite final metric, the
  per-class IoU as a table artifact (``per_class_iou.json``) and the run's files as artifacts
  (``results.json``, CSVs, PNGs, ``code.diff``, the PLY when under 64 MiB, else its path as a
  tag; a training run's export folder with its model card under ``export/``); the jobs of one multirun or search are children of one parent run named after the sweep
  (MLflow's ``mlflow.parentRunId`` tag). The run ends FINISHED, FAILED or KILLED with the job.
- **TensorBoard** (evaluations and maps; training logs its own curves): the final metrics as
  scalars and the provenance as text, under ``<run>/tensorboard``.
- **CSV**: ``metrics.csv`` is training's; an evaluation or a map writes its final metrics as
  one row of ``<run>/metrics.csv``.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg.specs.tree import flatten
from resireg_train.runs.record import RESULTS_FILE, read_results

__all__ = [
    "MLFLOW_ARTIFACT_MAX_BYTES",
    "map_counts",
    "mlflow_key",
    "record_run",
    "run_metrics",
    "to_mlflow",
]

log = logging.getLogger(__name__)

#: Files larger than this are recorded by path (a tag), not uploaded.
MLFLOW_ARTIFACT_MAX_BYTES = 64 << 20
_STATUS = {"completed": "FINISHED", "failed": "FAILED", "interrupted": "KILLED", "pruned": "KILLED"}
_KEY = re.compile(r"[^A-Za-z0-9_\-. /]")  # what MLflow accepts in a metric or param name


def mlflow_key(name: str) -> str:
    """``name`` with the characters MLflow refuses in a key replaced by ``_``
    (``val/ovss/x/miou_full@n_prototypes:24`` -> ``val/ovss/x/miou_full_n_prototypes_24``)."""
    return _KEY.sub("_", name)


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


def map_counts(record: Mapping[str, Any]) -> dict[str, float]:
    """A ``resireg-map`` record's counts (``map/voxels``, ``map/frames``, ``frames/used``,
    ...): what a map run has for metrics. Empty for other runs."""
    counts = {}
    for part in ("map", "frames"):
        section = record.get(part)
        if isinstance(section, Mapping):
            counts.update({f"{part}/{k}": float(v) for k, v in section.items() if _number(v)})
    return counts


def run_metrics(record: Mapping[str, Any]) -> dict[str, float]:
    """A run record's metrics as a tracker shows them: every finite final value and, for a
    map, its counts (:func:`map_counts`)."""
    metrics = {k: float(v) for k, v in (record.get("final") or {}).items() if _number(v)}
    return {**metrics, **map_counts(record)}


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


def to_mlflow(settings: Mapping[str, Any], cfg: Any, out: Path) -> str:
    """Log the run in ``out`` to MLflow (module docstring); ``settings``: the
    ``logger.mlflow`` entry (``tracking_uri``, ``experiment_name``, ``run_name``). Returns the
    MLflow run id."""
    from mlflow import MlflowClient
    from mlflow.entities import Metric, Param, RunTag
    from omegaconf import OmegaConf

    record = read_results(out)
    client = MlflowClient(tracking_uri=str(settings.get("tracking_uri")))
    name = str(settings.get("experiment_name") or "resireg")
    experiment = client.get_experiment_by_name(name)
    experiment_id = experiment.experiment_id if experiment else client.create_experiment(name)
    tracking = record.get("tracking") or {}
    run_id = tracking.get("mlflow_run_id")  # the training run Lightning's logger made
    job, sweep = _group()
    tags = {"resireg.run_dir": str(out.resolve())}
    if sweep:
        tags["mlflow.parentRunId"] = _parent_run(client, experiment_id, sweep, str(cfg.name))
        tags["resireg.job"] = job
    if run_id is None:
        run_name = str(settings.get("run_name") or cfg.name)
        run_id = client.create_run(experiment_id, run_name=run_name if job is None
                                   else f"{run_name}-{job}").info.run_id  # fmt: skip
        try:
            config = OmegaConf.to_container(cfg, resolve=True)
        except Exception:  # an interpolation only Hydra's runtime resolves
            config = OmegaConf.to_container(cfg, resolve=False)
        params = [Param(mlflow_key(k)[:250], str(v)[:6000]) for k, v in flatten(config).items()]
        for i in range(0, len(params), 100):  # log_batch takes at most 100 params per call
            client.log_batch(run_id, params=params[i : i + 100])
    tags.update({mlflow_key(k)[:250]: str(v)[:5000]
                 for k, v in flatten(record.get("provenance") or {}, "provenance").items()})  # fmt: skip
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
        if not path.is_file() or path.name.startswith("."):
            continue
        if path.suffix in (".json", ".csv", ".png", ".md", ".diff", ".ply", ".rrd", ".log"):
            if path.stat().st_size <= MLFLOW_ARTIFACT_MAX_BYTES:
                client.log_artifact(run_id, str(path))
            else:
                client.set_tag(run_id, f"resireg.file.{path.name}", str(path.resolve()))
    export = Path(str(record["export"])) if record.get("export") else None
    if export is not None and export.is_dir():  # a training run's export, with its model card
        for path in sorted(export.iterdir()):
            if path.is_file() and path.stat().st_size <= MLFLOW_ARTIFACT_MAX_BYTES:
                client.log_artifact(run_id, str(path), artifact_path="export")
    client.set_terminated(run_id, _STATUS.get(str(record.get("status")), "FINISHED"))
    return run_id


def _to_tensorboard(out: Path) -> None:
    from torch.utils.tensorboard import SummaryWriter

    record = read_results(out)
    with SummaryWriter(str(out / "tensorboard")) as writer:
        for key, value in run_metrics(record).items():
            writer.add_scalar(key, value, 0)
        writer.add_text("provenance", "```\n" + json.dumps(record.get("provenance") or {},
                                                           indent=2) + "\n```")  # fmt: skip


def _to_csv(out: Path, filename: str) -> None:
    metrics = run_metrics(read_results(out))
    with open(out / filename, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=sorted(metrics))
        writer.writeheader()
        writer.writerow(metrics)


def record_run(cfg: Any, out: Path, training: bool) -> None:
    """Send the finished run in ``out`` to the trackers of ``cfg.logger`` (module docstring;
    training logs its own curves and CSV through Lightning). A tracker that cannot be reached
    is a warning, never a lost run: ``results.json`` keeps everything."""
    loggers = cfg.get("logger") or {}
    if not (out / RESULTS_FILE).is_file():
        return
    for kind, settings in loggers.items():
        if not settings:
            continue
        try:
            if kind == "mlflow":
                run_id = to_mlflow(settings, cfg, out)
                from resireg_train.runs.record import update_results

                update_results(out, tracking={**(read_results(out).get("tracking") or {}),
                                              "mlflow_run_id": run_id})  # fmt: skip
            elif kind == "tensorboard" and not training:
                _to_tensorboard(out)
            elif kind == "csv" and not training:
                _to_csv(out, str(settings.get("filename") or "metrics.csv"))
        except Exception as err:  # a tracker down must not fail a finished run
            log.warning("logger.%s: could not record the run in %s: %s", kind, out, err)
