"""Sweep reports (``resireg-report SWEEP_DIR``): one table (and plots) from a Hydra multirun folder.

Reads every job folder of the sweep (``<n>_<overrides>/``): its overrides
(``.hydra/overrides.yaml``) and ``results.json``. A job that failed, was interrupted
(Ctrl-C; resumable), is still running or never wrote ``results.json`` stays in the table
with its status and error. Which sections beyond the summary it writes, the sweep config names
(``report: [table1]`` etc. in ``conf/sweep/``, saved in every job's ``.hydra/config.yaml``); an
ad hoc ``-m`` sweep, which names none, gets those its jobs show (:func:`report_sections`).
Writes, into the sweep folder (or ``--out``):

- ``summary.csv`` and ``summary.md``: one row per job; the overrides that vary across
  jobs, status, the scores (final values; for training runs also the best of the chosen
  metric) and the error.
- For the prototype/batch ablation (jobs varying ``batch_size`` and ``full.n_prototypes``,
  2D or 3D: the metric is whichever ``.../miou_full`` the jobs recorded, ``val/ovss/...`` or
  ``val/scannet3d/...``): ``heatmap.png`` (batch size x prototype count, mIoU of ReSiReg Full) and
  ``prototype_heuristic.json``: ``n(B)`` fitted to the best prototype count of every
  batch size, loadable by ``ReSiRegFull(n_prototypes="auto", heuristic=PATH)``.
- For encoder sweeps (the encoder varies, or ``sweep=table1`` / ``table2`` cut to one
  encoder): ``table1.md`` / ``.csv`` (2D OVSS, the paper's Table 1) or, for
  ``task=scannet3d`` jobs, ``table2.md`` / ``.csv`` (3D mapping, the paper's Table 2).
- For training sweeps (jobs with a per-epoch history): ``curves.png``, the chosen metric
  per epoch for every run.
- For an Optuna search (``hparams_search=...``: ``optuna.journal`` or ``search.json``):
  ``optuna_trials.csv`` (every trial's state, value, parameters, job and error), the best
  trial in ``summary.md``, and ``optuna_history.png`` / ``optuna_intermediate.png`` / ``optuna_importance.png``.
- For the CLIP layer sweep (configurations ``<variant>@layer:<block>``, ``sweep=clip_layers``):
  ``layer_sweep.csv`` / ``.md`` / ``.png``, mIoU of each variant against the block index.
- For the OVSS field's eight benchmarks (``sweep=ovss8``): ``ovss8.csv`` / ``.md``, encoder x
  variant against VOC21 ... ADE and their average, beside the published peers
  (:mod:`resireg_train.report.ovss8`).

An explicit metric must be one the sweep's results hold (a ``final`` or ``best`` key of
some job); anything else is a :class:`ValueError` that lists them.
"""

from __future__ import annotations

from pathlib import Path

from resireg_train.report.figures import (
    DPI,
    curves_figure,
    heatmap_figure,
    layer_sweep_figure,
    plot_curves,
    plot_heatmap,
)
from resireg_train.report.jobs import (
    STATUSES,
    Job,
    check_metric,
    collect,
    count_statuses,
    default_metric,
    known_metrics,
    named_sections,
    varying_keys,
)
from resireg_train.report.ovss8 import is_ovss8_sweep, ovss8_table, write_ovss8_table
from resireg_train.report.paper import DEFAULT_TOLERANCE
from resireg_train.report.prototypes import (
    elbo_table,
    fit_heuristic,
    grid_statuses,
    is_prototype_sweep,
    prototype_grid,
)
from resireg_train.report.summary import summary_table
from resireg_train.report.tables import (
    LAYER_SWEEP_FILES,
    encoder_table,
    is_encoder_sweep,
    is_layer_sweep,
    is_mapping_sweep,
    layer_sweep_table,
    mapping_table,
    markdown,
    method_means,
    protocol_lines,
    write_encoder_table,
    write_layer_sweep,
    write_mapping_table,
)
from resireg_train.runs.record import flat
from resireg_train.sweeps.report import is_optuna_sweep

__all__ = [
    "DPI", "STATUSES", "Job", "check_metric", "collect", "count_statuses", "curves_figure",
    "default_metric", "encoder_table", "fit_heuristic", "grid_statuses", "heatmap_figure",
    "is_encoder_sweep", "is_layer_sweep", "is_mapping_sweep", "known_metrics",
    "is_ovss8_sweep", "layer_sweep_figure", "layer_sweep_table", "mapping_table", "markdown",
    "method_means", "ovss8_table", "write_ovss8_table",
    "plot_curves", "plot_heatmap", "protocol_lines", "prototype_grid", "report", "report_sections",
    "summary_table",
    "write_encoder_table", "write_layer_sweep", "write_mapping_table",
]  # fmt: skip


def report_sections(jobs: list[Job]) -> list[str]:
    """What the report writes beyond the summary (``REPORT_SECTIONS``): the sections the sweep
    config names (``report: [...]``, :func:`named_sections`), else those the jobs show: an
    encoder axis (Table 1, or Table 2 for 3D jobs), a batch size x prototype grid, blocks."""
    named = named_sections(jobs)
    if named is not None:
        return named
    found = []
    if is_encoder_sweep(jobs):
        found.append("table2" if is_mapping_sweep(jobs) else "table1")
    if is_prototype_sweep(jobs):
        found.append("prototype_grid")
    if is_layer_sweep(jobs):
        found.append("layer_sweep")
    if is_ovss8_sweep(jobs):
        found.append("ovss8")
    return found


def report(
    sweep_dir: str | Path,
    out: str | Path | None = None,
    metric: str | None = None,
    paper_tolerance: float = DEFAULT_TOLERANCE,
) -> dict[str, Path]:
    """Write the sweep's summary (and plots / heuristic where they apply); returns the files.
    Table 1 / Table 2 cells further than ``paper_tolerance`` points from the paper's are
    flagged (:mod:`resireg_train.report.paper`).

    Raises :class:`ValueError` (before writing anything) when ``metric`` is given and no
    job's results hold it."""
    jobs = collect(sweep_dir)
    if metric:
        check_metric(jobs, metric)
    out = Path(out) if out else Path(sweep_dir)
    out.mkdir(parents=True, exist_ok=True)
    metric = metric or default_metric(jobs)
    table = summary_table(jobs, metric)
    files = {"csv": out / "summary.csv", "md": out / "summary.md"}
    table.to_csv(files["csv"], index=False)

    constant = {k: v for k, v in jobs[0].overrides.items() if k not in varying_keys(jobs)}
    lines = [
        f"# Sweep {Path(sweep_dir).resolve()}",
        "",
        f"{len(jobs)} jobs: {count_statuses(table['status'])}",
        "",
        "Common overrides: " + (", ".join(f"`{k}={v}`" for k, v in constant.items()) or "none"),
        "",
        # scores to 4 decimals; the overrides that vary in significant digits (a learning
        # rate of 0.0006466 would read 0.0006)
        markdown(table, floatfmt=[".4g" if c in varying_keys(jobs) else ".4f" for c in table]),
    ]
    sections = report_sections(jobs)
    if "table2" in sections:
        files.update(write_mapping_table(jobs, out, paper_tolerance))
        lines += ["", f"3D mapping table (the paper's Table 2): `{files['table2_md'].name}`."]
    elif "table1" in sections:
        files.update(write_encoder_table(jobs, out, paper_tolerance))
        lines += ["", f"Encoder table (the paper's Table 1): `{files['table1_md'].name}`."]
    if metric and "prototype_grid" in sections:
        grid = prototype_grid(jobs, metric)
        files["heatmap"] = out / "heatmap.png"
        plot_heatmap(grid, metric, files["heatmap"], grid_statuses(jobs, metric, grid))
        cells = grid.map(lambda v: f"{v:.4f}").where(
            grid.notna(), grid_statuses(jobs, metric, grid)
        )
        lines += ["", f"## {metric}: batch size x prototypes", "", "A cell without a value reads "
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
    if metric and any(j.results.get("history") for j in jobs):
        curves = out / "curves.png"
        if plot_curves(jobs, metric, curves):
            files["curves"] = curves
    if "ovss8" in sections:  # sweep=ovss8: the field's eight benchmarks beside the peers
        files.update(write_ovss8_table(jobs, out))
        lines += ["", f"The eight OVSS benchmarks, beside the published peers: "
                  f"`{files['ovss8_md'].name}`."]  # fmt: skip
    if "layer_sweep" in sections:  # sweep=clip_layers
        files.update(write_layer_sweep(jobs, out))
        lines += ["", f"CLIP layer sweep (mIoU per intermediate block): `{LAYER_SWEEP_FILES[1]}`."]
    if is_optuna_sweep(sweep_dir):  # hparams_search=...: the study's trials, best, plots
        from resireg_train.sweeps.report import write_optuna_report

        optuna_files, optuna_lines = write_optuna_report(sweep_dir, jobs, out)
        files.update(optuna_files)
        lines += optuna_lines
    failed = [j for j in jobs if j.status != "completed"]
    if failed:
        lines += ["", "## Jobs that did not complete", ""]
        lines += [f"- job {j.number} ({j.path.name}): **{j.status}**: {flat(j.error or '')}"
                  for j in failed]  # fmt: skip
    files["md"].write_text("\n".join(lines) + "\n")
    return files
