"""The prototype/batch ablation (2D or 3D): the batch size x prototype count grid of ReSiReg
Full's mIoU and the heuristic ``n(B)`` fitted to the best count of every batch size."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from resireg.method.heuristic import PrototypeHeuristic
from resireg.method.variants import parse_variant
from resireg.specs.variants import takes_prior
from resireg_train.report.figures import plot_heatmap
from resireg_train.report.jobs import BATCH_KEY, PROTOTYPES_KEY, Job, job_scores, varying_keys
from resireg_train.report.tables import markdown, protocol_lines

__all__ = [
    "ELBO", "elbo_table", "fit_heuristic", "grid_statuses", "is_prototype_sweep",
    "prototype_configs", "prototype_grid", "prototype_grid_section",
]  # fmt: skip


def is_prototype_sweep(jobs: list[Job]) -> bool:
    """A batch size x prototype count grid: jobs vary the batch size, and the prototype
    count too (one per job) or score several counts each."""
    varying = varying_keys(jobs)
    return BATCH_KEY in varying and (
        PROTOTYPES_KEY in varying or any(len(prototype_configs(j)) > 1 for j in jobs)
    )


def prototype_configs(job: Job) -> dict[int, str]:
    """``{prototype count: configuration}`` of the ``full@n_prototypes:<n>`` configurations a
    job scored in one pass (its ``params.variants``, recorded before it ran)."""
    names = (job.results.get("params") or {}).get("variants") or []
    out = {}
    for name in names:
        try:
            base, overrides = parse_variant(name)
        except ValueError:
            continue
        if takes_prior(name):  # full+prior@n_prototypes:<n> is not a cell of the grid
            continue
        n = overrides.get("n_prototypes")
        if base == "full" and isinstance(n, int) and not isinstance(n, bool):
            out[n] = name
    return out


def _batched(jobs: list[Job]) -> list[tuple[Job, int]]:
    """The jobs that set the batch size (``batch_size=<n>`` among their overrides), each with
    it: the rows of the batch size x prototype grid."""
    out = []
    for job in jobs:
        try:
            out.append((job, int(job.overrides[BATCH_KEY])))
        except (KeyError, ValueError):
            continue
    return out


def _grid_cells(jobs: list[Job], metric: str) -> pd.DataFrame:
    """One row per (job, prototype count) of the grid: batch size, prototype count, ``metric``
    (NaN unless the job completed) and status. A job either set ``full.n_prototypes`` (one
    count per job) or scored several ``full@n_prototypes:<n>`` configurations in one pass;
    ``metric`` names Full's score (``.../miou_full``), each configuration's is
    ``.../miou_full@n_prototypes:<n>``."""
    cells = []
    for job, batch in _batched(jobs):
        scores = job_scores(job.results) if job.status == "completed" else {}
        if PROTOTYPES_KEY in job.overrides:
            try:
                counts = {int(job.overrides[PROTOTYPES_KEY]): metric}
            except ValueError:
                continue
        else:
            counts = {n: metric + name[len("full") :] for n, name in prototype_configs(job).items()}
        for protos, name in counts.items():
            value = scores.get(name, math.nan)
            cells.append(
                {BATCH_KEY: batch, PROTOTYPES_KEY: protos, metric: value, "status": job.status}
            )
    return pd.DataFrame(cells, columns=[BATCH_KEY, PROTOTYPES_KEY, metric, "status"])


def prototype_grid(jobs: list[Job], metric: str) -> pd.DataFrame:
    """mIoU per (batch size, prototype count); NaN where the job did not complete."""
    return (
        _grid_cells(jobs, metric)
        .pivot_table(
            index=BATCH_KEY, columns=PROTOTYPES_KEY, values=metric, aggfunc="max", dropna=False
        )
        .sort_index()
        .sort_index(axis=1)
    )


def grid_statuses(jobs: list[Job], metric: str, grid: pd.DataFrame) -> pd.DataFrame:
    """The status of each cell of ``grid`` (``"missing"`` where no job ran that pair; the
    statuses joined by ``/`` where several jobs did)."""
    return (
        _grid_cells(jobs, metric)
        .groupby([BATCH_KEY, PROTOTYPES_KEY])["status"]
        .agg(lambda s: "/".join(sorted(set(s))))
        .unstack()
        .reindex(index=grid.index, columns=grid.columns)
        .fillna("missing")
    )


def fit_heuristic(grid: pd.DataFrame) -> tuple[PrototypeHeuristic, dict[int, int]]:
    """The best prototype count of every batch size with a result, and the fitted ``n(B)``."""
    best = {int(b): int(row.idxmax()) for b, row in grid.iterrows() if row.notna().any()}
    if not best:
        raise ValueError("no completed job in the prototype/batch grid: nothing to fit")
    return PrototypeHeuristic.fit(list(best), list(best.values())), best


ELBO = "elbo"  # full.n_prototypes=elbo / full@n_prototypes:elbo (docs/method.md#the-prototype-count-by-the-evidence-lower-bound)


def elbo_table(jobs: list[Job], metric: str, grid: pd.DataFrame,
               heuristic: PrototypeHeuristic) -> pd.DataFrame:  # fmt: skip
    """The ELBO prototype count beside the fitted heuristic, per batch size: the grid's best
    count and mIoU, the heuristic's ``n(B)`` and the grid's mIoU at it (NaN off the grid),
    and for the ``elbo`` configuration (``full@n_prototypes:elbo`` scored in the job's pass,
    or a job of ``full.n_prototypes=elbo``) the counts its batches were given
    (``results.json``'s ``elbo_prototypes``, ``count x batches``) and its mIoU. Empty when no
    job ran it."""
    rows = []
    for job, batch in _batched(jobs):
        if job.overrides.get(PROTOTYPES_KEY) == ELBO:
            config, score = "full", metric
        elif any(parse_variant(n) == ("full", {"n_prototypes": ELBO})
                 for n in (job.results.get("params") or {}).get("variants") or []):  # fmt: skip
            config, score = f"full@n_prototypes:{ELBO}", f"{metric}@n_prototypes:{ELBO}"
        else:
            continue
        counts = (job.results.get("elbo_prototypes") or {}).get(config) or {}
        scores = job_scores(job.results) if job.status == "completed" else {}
        row = grid.loc[batch] if batch in grid.index else pd.Series(dtype=float)
        n_heuristic = heuristic(batch)
        rows.append({
            BATCH_KEY: batch,
            "best n (grid)": int(row.idxmax()) if row.notna().any() else None,
            "best mIoU (grid)": row.max() if row.notna().any() else math.nan,
            "heuristic n(B)": n_heuristic,
            "heuristic mIoU (grid)": row.get(n_heuristic, math.nan),
            "ELBO n (x batches)": ", ".join(f"{n} x{c}" for n, c in counts.items()) or None,
            "ELBO mIoU": scores.get(score, math.nan),
            "status": job.status,
        })  # fmt: skip
    return pd.DataFrame(rows).sort_values(BATCH_KEY) if rows else pd.DataFrame()


def prototype_grid_section(
    jobs: list[Job], out: Path, metric: str | None
) -> tuple[dict[str, Path], list[str]]:
    """The report section ``prototype_grid`` (:mod:`resireg_train.report.specs`), for
    ``metric`` (none: nothing): ``heatmap.png`` and the grid in ``summary.md``, then, where a
    cell has a value, ``prototype_heuristic.json`` (:func:`fit_heuristic`) and the ELBO's
    counts beside it (:func:`elbo_table`)."""
    if not metric:
        return {}, []
    files: dict[str, Path] = {}
    grid = prototype_grid(jobs, metric)
    files["heatmap"] = out / "heatmap.png"
    plot_heatmap(grid, metric, files["heatmap"], grid_statuses(jobs, metric, grid))
    cells = grid.map(lambda v: f"{v:.4f}").where(grid.notna(), grid_statuses(jobs, metric, grid))
    lines = ["", f"## {metric}: batch size x prototypes", "", "A cell without a value reads "
             "its job's status.", "", markdown(cells, floatfmt=".4f", index=True),
             "", *protocol_lines(jobs)]  # fmt: skip
    if grid.notna().to_numpy().any():
        heuristic, best = fit_heuristic(grid)
        files["heuristic"] = out / "prototype_heuristic.json"
        heuristic.save(files["heuristic"])
        lines += [
            "",
            "## Prototype heuristic",
            "",
            f"Best prototype count per batch size: {best}.",
            f"Fit: n(B) = round({heuristic.intercept:.3f} + {heuristic.slope:.3f} * ln B), "
            f"clipped to [{heuristic.min_prototypes}, {heuristic.max_prototypes}] "
            f"(`{files['heuristic'].name}`; use with "
            '`ReSiRegFull(n_prototypes="auto", heuristic=PATH)`).',
        ]
        elbo = elbo_table(jobs, metric, grid, heuristic)
        if len(elbo):
            lines += ["", "## ELBO prototype count beside the heuristic (docs/method.md#the-prototype-count-by-the-evidence-lower-bound)", "",
                      markdown(elbo, floatfmt=".4f")]  # fmt: skip
    return files, lines
