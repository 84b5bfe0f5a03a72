"""``summary.csv`` / ``summary.md``: one row per job of any sweep."""

from __future__ import annotations

from typing import Any

import pandas as pd

from resireg_train.report.jobs import Job, job_scores, varying_keys

__all__ = ["summary_table"]


def summary_table(jobs: list[Job], metric: str | None) -> pd.DataFrame:
    """One row per job: number, varying overrides, status, scores, best metric, error."""
    varying = varying_keys(jobs)
    rows = []
    for job in jobs:
        row: dict[str, Any] = {"job": job.number}
        row.update({k: job.overrides.get(k) for k in varying})
        row["status"] = job.status
        row.update(job_scores(job.results))
        history = job.results.get("history") or []
        best = job.results.get("best", {}).get(metric) if metric else None
        if history and best is not None:
            row[f"best {metric}"] = best["value"]
            row["best epoch"] = best["epoch"]
        row["error"] = job.error if job.status != "completed" else None
        rows.append(row)
    table = pd.DataFrame(rows)
    front = ["job", *varying, "status"]
    back = ["error"]
    middle = [c for c in table.columns if c not in front and c not in back]
    return table[front + middle + back]
