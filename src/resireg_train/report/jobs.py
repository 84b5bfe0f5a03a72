"""A sweep's jobs as the report reads them: folder, overrides, ``results.json``, status, error,
and what every table takes of a job (its scores, encoder, dataset)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from resireg.specs.variants import BASELINE, VARIANT_SPECS, VARIANTS
from resireg_train.record.run_record import RecordError, RunRecord, metric_mode

__all__ = [
    "BATCH_KEY", "METHODS", "METHOD_NAMES", "PROTOTYPES_KEY", "STATUSES", "Job", "check_metric",
    "collect", "count_statuses", "dataset_of", "default_metric", "encoder_of", "known_metrics",
    "named_sections", "per_encoder", "job_scores", "varying_keys",
]  # fmt: skip

BATCH_KEY, PROTOTYPES_KEY = "batch_size", "full.n_prototypes"


#: Job statuses in the order they are counted (others follow alphabetically).
STATUSES = ("completed", "running", "interrupted", "failed", "missing")


@dataclass
class Job:
    """One sweep job: its folder, overrides and ``results.json`` content."""

    path: Path
    number: int
    overrides: dict[str, str]
    results: dict[str, Any] = field(default_factory=dict)

    @property
    def config(self) -> dict[str, Any]:
        """The job's resolved config as Hydra saved it (``.hydra/config.yaml``; empty if
        absent)."""
        path = self.path / ".hydra" / "config.yaml"
        if not path.is_file():
            return {}
        with open(path) as f:
            return yaml.safe_load(f) or {}

    @property
    def status(self) -> str:
        return self.results.get("status", "missing") if self.results else "missing"

    @property
    def error(self) -> str | None:
        if not self.results:
            return "no results.json (the job did not start, or crashed before writing it)"
        error = self.results.get("error")
        if error is None and self.status == "interrupted":
            return "interrupted before completing"
        return error


def collect(sweep_dir: str | Path) -> list[Job]:
    """Every job folder of a multirun (``.hydra/overrides.yaml`` present), by job number."""
    sweep = Path(sweep_dir)
    if not sweep.is_dir():
        raise FileNotFoundError(f"sweep folder {str(sweep)!r} does not exist")
    jobs = []
    for overrides_file in sweep.glob("*/.hydra/overrides.yaml"):
        folder = overrides_file.parent.parent
        match = re.match(r"(\d+)", folder.name)
        items = yaml.safe_load(overrides_file.read_text()) or []
        overrides = dict(item.split("=", 1) for item in items if "=" in item)
        overrides = {k.lstrip("+~"): v for k, v in overrides.items()}
        number = int(match.group(1)) if match else len(jobs)
        try:
            results = RunRecord.read(folder)
        except (OSError, RecordError) as err:  # listed as failed, with the reason
            results = {"status": "unreadable", "error": str(err)}
        jobs.append(Job(folder, number, overrides, results))
    if not jobs:
        raise FileNotFoundError(
            f"{str(sweep)!r} holds no job folders (<n>_<overrides>/.hydra/overrides.yaml); "
            "pass the multirun folder, e.g. outputs/<name>/multirun/<time>"
        )
    return sorted(jobs, key=lambda j: j.number)


def named_sections(jobs: list[Job]) -> list[str] | None:
    """The report sections the jobs' sweep config names (``report: [...]`` of a
    ``conf/sweep/`` file, in every job's saved config), or ``None`` when none names them (an ad
    hoc ``-m`` sweep: the report reads them from the overrides and results)."""
    for job in jobs:
        named = job.config.get("report")
        if named is not None:
            return [str(section) for section in named]
    return None


def varying_keys(jobs: list[Job]) -> list[str]:
    keys = sorted({k for j in jobs for k in j.overrides})
    return [k for k in keys if len({j.overrides.get(k) for j in jobs}) > 1]


def job_scores(results: dict[str, Any]) -> dict[str, float]:
    return {
        k: float(v)
        for k, v in results.get("final", {}).items()
        if isinstance(v, (int, float)) and metric_mode(k) is not None
    }


def known_metrics(jobs: list[Job]) -> list[str]:
    """Every metric some job's ``results.json`` holds (its ``final`` and ``best`` keys), and
    the variant's metric of each configuration's (``.../miou_full`` for
    ``.../miou_full@n_prototypes:24``)."""
    names = {k for j in jobs for part in ("final", "best") for k in j.results.get(part) or {}}
    return sorted(names | {k.split("@")[0] for k in names})


def check_metric(jobs: list[Job], metric: str) -> None:
    """Raise a :class:`ValueError` naming the metrics that exist if ``metric`` is not one."""
    known = known_metrics(jobs)
    if metric not in known:
        listed = ", ".join(known) if known else "none (no job has recorded a metric yet)"
        raise ValueError(f"unknown metric {metric!r}; the sweep's results hold: {listed}")


def count_statuses(statuses: pd.Series | list[str]) -> str:
    """``"1 completed, 1 interrupted, 1 failed"``: jobs per status, completed always shown."""
    counts = pd.Series(statuses, dtype=object).value_counts()
    order = [*STATUSES, *sorted(set(counts.index) - set(STATUSES))]
    return ", ".join(
        f"{counts.get(s, 0)} {s}" for s in order if s == "completed" or counts.get(s, 0)
    )


def default_metric(jobs: list[Job]) -> str | None:
    """ReSiReg Full's mIoU on the first dataset scored, else the training loss."""
    names = sorted({k.split("@")[0] for j in jobs for k in job_scores(j.results)})
    for suffix in ("/miou_full", "/miou_lite", "/miou_bb", "train/loss"):
        hits = [n for n in names if n.endswith(suffix)]
        if hits:
            return hits[0]
    return names[0] if names else None


#: Post-hoc methods compared with the backbone alone, in the order of the paper's Table 1
#: (the variant table, resireg.specs.variants, less its baseline).
METHODS = tuple(name for name in VARIANTS if name != BASELINE)
#: ``variant -> its label in tables`` (``full -> Full``; the variant table).
METHOD_NAMES = {name: spec.label for name, spec in VARIANT_SPECS.items()}


def encoder_of(job: Job) -> tuple[str, bool | None, int | None]:
    """(name, third party?, parameter count) of a job's encoder (from its results, else its
    ``encoder=`` override when the job failed before building it)."""
    info = job.results.get("encoder") or {}
    params = (job.results.get("params") or {}).get("encoder") or {}
    name = info.get("name") or params.get("name") or job.overrides.get("encoder", "?")
    third = info.get("third_party", params.get("third_party"))
    return str(name), third, info.get("parameters")


def dataset_of(job: Job) -> str:
    params = (job.results.get("params") or {}).get("dataset") or {}
    return str(params.get("name") or job.overrides.get("dataset", "?"))


def per_encoder(
    jobs: list[Job],
) -> tuple[list[tuple[Job, str, bool | None, float | None, str]], list[str]]:
    """Each job with its encoder's name, third-party flag and parameters in millions (one
    decimal; ``None`` when unknown) and its dataset, and the datasets in first-seen order:
    what the encoder tables (Table 1, Table 2) read of every job."""
    out, datasets = [], []
    for job in jobs:
        name, third, parameters = encoder_of(job)
        dataset = dataset_of(job)
        if dataset not in datasets:
            datasets.append(dataset)
        millions = round(parameters / 1e6, 1) if parameters else None
        out.append((job, name, third, millions, dataset))
    return out, datasets
