"""The paper's tables from encoder sweeps (Table 1: 2D OVSS; Table 2: 3D mapping) and the CLIP
layer sweep's table, each as CSV and Markdown with the protocol beneath; the one Markdown
renderer every table of the report uses."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd

from resireg.method.variants import parse_variant
from resireg.specs.metrics import SCORE_SPECS
from resireg.specs.variants import BASELINE, VARIANTS, takes_prior, variant_layer
from resireg_train.evaluation.specs import TASK_SPECS
from resireg_train.record.run_record import flat
from resireg_train.report.figures import DPI, layer_sweep_figure
from resireg_train.report.jobs import METHOD_NAMES, METHODS, Job, per_encoder, varying_keys
from resireg_train.report.paper import (
    DEFAULT_TOLERANCE,
    add_paper_columns,
    paper_lines,
    protocol_differences,
)
from resireg_train.report.specs import ENCODER_SWEEPS

__all__ = [
    "ENCODER_SWEEPS", "LAYER_SWEEP_FILES", "MAPPING_COLUMNS", "MAPPING_PREFIX", "OVSS_PREFIX",
    "encoder_table", "metric_prefix", "table_tasks",
    "is_encoder_sweep", "is_layer_sweep", "is_mapping_sweep", "is_table1", "is_table2",
    "layer_configs", "layer_sweep_section", "layer_sweep_table", "mapping_table", "markdown",
    "method_means", "protocol_lines", "table1_section", "table2_section", "variant_order",
    "write_encoder_table", "write_layer_sweep", "write_mapping_table",
]  # fmt: skip


def markdown(frame: pd.DataFrame, floatfmt: str | list[str], index: bool = False) -> str:
    """``frame`` as a Markdown table, rendered one way in every table of the report: text on
    one line (a multi-line error would split its row) with ``|`` escaped, and a missing value
    (NaN, ``None``: a job that did not complete, a mean over nothing) as an empty cell.
    ``floatfmt``: one format for every column, or one per column (tabulate's)."""

    def cell(value: Any) -> Any:
        return flat(value).replace("|", "\\|") if isinstance(value, str) else value

    shown = frame.map(cell)
    shown = shown.astype(object).where(shown.notna(), None)  # tabulate blanks None, not NaN
    return shown.to_markdown(index=index, floatfmt=floatfmt, missingval="")


def protocol_lines(jobs: list[Job]) -> list[str]:
    """The evaluation protocol of the jobs (``results.json``'s ``protocol``, docs/protocol.md):
    one line when they share it, else one per protocol with its jobs; nothing when no job
    recorded one."""
    from resireg_train.evaluation.protocol import protocol_text

    seen: dict[str, list[int]] = {}
    for job in jobs:
        record = job.results.get("protocol")
        if record:
            seen.setdefault(protocol_text(record), []).append(job.number)
    if len(seen) == 1:
        return [f"Protocol: {next(iter(seen))}"]
    return [f"Protocol (jobs {', '.join(map(str, n))}): {text}" for text, n in seen.items()]


def table_tasks(table: str) -> list[str]:
    """The tasks whose sweeps feed report table ``table`` (``table1``, ``table2``: the task
    table's :attr:`~resireg_train.evaluation.specs.TaskSpec.report`)."""
    return [t.name for t in TASK_SPECS.values() if t.report == table]


def metric_prefix(table: str) -> str:
    """What the scores of report table ``table`` start with: the metric prefix of the task that
    feeds it (``val/ovss/`` for Table 1, ``val/scannet3d/`` for Table 2)."""
    return TASK_SPECS[table_tasks(table)[0]].metric_prefix


#: The prefix of Table 1's scores and the layer sweep's (:func:`metric_prefix`).
OVSS_PREFIX = metric_prefix("table1")


def is_encoder_sweep(jobs: list[Job]) -> bool:
    """Jobs of ``resireg-eval`` that vary the encoder, or of an encoder-table sweep
    (``sweep=table1`` / ``table2``) cut to one encoder on the command line."""
    if "encoder" in varying_keys(jobs):
        return True
    return any(
        j.overrides.get("sweep") in ENCODER_SWEEPS or j.results.get("name") in ENCODER_SWEEPS
        for j in jobs
    )


def _encoder_row(
    rows: dict[Any, dict[str, Any]], key: Any, first: dict[str, Any], job: Job,
    third: bool | None, millions: float | None, dataset: str,
) -> tuple[dict[str, Any], dict[str, Any] | None]:  # fmt: skip
    """Row ``key`` of an encoder table (Table 1: one per encoder; Table 2: per encoder and
    variant), made with the cells ``first`` when new, with the job's encoder facts (its
    third-party flag where known, its parameters in millions) and its status in
    ``<dataset> status``; and the job's final scores, ``None`` when it did not complete (its
    cells stay empty)."""
    row = rows.setdefault(key, {**first, "third_party": third, "parameters (M)": None})
    if third is not None:
        row["third_party"] = third
    if millions:
        row["parameters (M)"] = millions
    row[f"{dataset} status"] = job.status
    return row, (job.results.get("final", {}) if job.status == "completed" else None)


def encoder_table(jobs: list[Job]) -> pd.DataFrame:
    """The paper's Table 1 from an encoder x dataset sweep: one row per encoder (its name,
    third-party flag and parameter count), per dataset the BB mIoU and, per method (Calib,
    Lite, Full), its mIoU and its delta to BB, in mIoU points (x100). A job that did not
    complete leaves its cells empty and is named in ``<dataset> status``. Two rows follow:
    the mean delta per method over all encoders, and over the third-party ones only."""
    rows: dict[str, dict[str, Any]] = {}
    per_job, datasets = per_encoder(jobs)
    for job, name, third, millions, dataset in per_job:
        row, final = _encoder_row(rows, name, {"encoder": name}, job, third, millions, dataset)
        if final is None:
            continue
        bb = final.get(f"{OVSS_PREFIX}{dataset}/miou_{BASELINE}")
        if bb is not None:
            row[f"{dataset} {METHOD_NAMES[BASELINE]}"] = 100 * bb
        for method in METHODS:
            value = final.get(f"{OVSS_PREFIX}{dataset}/miou_{method}")
            if value is None:
                continue
            row[f"{dataset} {METHOD_NAMES[method]}"] = 100 * value
            if bb is not None:
                row[f"{dataset} {METHOD_NAMES[method]} Δ"] = 100 * (value - bb)
    columns = ["encoder", "third_party", "parameters (M)"]
    for dataset in datasets:
        columns.append(f"{dataset} {METHOD_NAMES[BASELINE]}")
        for method in METHODS:
            columns += [f"{dataset} {METHOD_NAMES[method]}", f"{dataset} {METHOD_NAMES[method]} Δ"]
        columns.append(f"{dataset} status")
    table = pd.DataFrame(list(rows.values())).reindex(columns=columns)
    deltas = [c for c in columns if c.endswith(" Δ")]
    third_party = table["third_party"].fillna(False).astype(bool)
    averages = []
    for label, mask in (("mean Δ, all encoders", pd.Series(True, index=table.index)),
                        ("mean Δ, third-party encoders", third_party)):  # fmt: skip
        row = {"encoder": label, **table.loc[mask, deltas].astype(float).mean().to_dict()}
        for dataset in datasets:  # which encoders the means of this dataset cover
            row[f"{dataset} status"] = _covered(table.loc[mask], dataset)
        averages.append(row)
    return pd.concat([table, pd.DataFrame(averages)], ignore_index=True).reindex(columns=columns)


def _covered(rows: pd.DataFrame, dataset: str) -> str:
    """``"over 2 of 3 (not x: failed)"``: the encoders of ``rows`` whose ``dataset`` job
    completed (only they have deltas), and those left out with their status."""
    statuses = rows[f"{dataset} status"].fillna("missing")
    left = [f"{e}: {s}" for e, s in zip(rows["encoder"], statuses, strict=True) if s != "completed"]
    done = len(rows) - len(left)
    if not left:
        return f"over all {done}" if done else "no encoder"
    return f"over {done} of {len(rows)} (not {', '.join(left)})"


def method_means(table: pd.DataFrame) -> pd.DataFrame:
    """Mean delta per method over every encoder and dataset of :func:`encoder_table` (all
    encoders, and third-party ones only)."""
    body = table[~table["encoder"].str.startswith("mean Δ")]
    third = body["third_party"].fillna(False).astype(bool)
    out = {}
    for method in METHODS:
        cols = [c for c in table.columns if c.endswith(f" {METHOD_NAMES[method]} Δ")]
        values = body[cols].astype(float)
        out[METHOD_NAMES[method]] = {
            "all encoders": values.stack().mean(),
            "third-party encoders": values[third].stack().mean(),
        }
    return pd.DataFrame(out)


def encoder_paper_cells(table: pd.DataFrame) -> dict[str, tuple[str, str, str]]:
    """``{column: (dataset, variant, "miou")}`` of Table 1's score columns (not its Δ)."""
    labels = {f" {METHOD_NAMES[v]}": v for v in (BASELINE, *METHODS)}
    cells = {}
    for column in table.columns:
        for suffix, variant in labels.items():
            if column.endswith(suffix):
                cells[column] = (column[: -len(suffix)], variant, "miou")
    return cells


def write_encoder_table(
    jobs: list[Job], out: Path, paper_tolerance: float = DEFAULT_TOLERANCE
) -> dict[str, Path]:
    """``table1.csv`` and ``table1.md`` (the table with the paper's value and the difference
    to it beside each cell the paper reports, then the mean delta per method, the cells
    further than ``paper_tolerance`` points from the paper and the protocol settings that
    differ from the paper's)."""
    table = encoder_table(jobs)
    files = {"table1_csv": out / "table1.csv", "table1_md": out / "table1.md"}
    table, flags = add_paper_columns(table, "table1", encoder_paper_cells(table), paper_tolerance)
    table.to_csv(files["table1_csv"], index=False)
    shown = table.copy()
    shown["third_party"] = shown["third_party"].map({True: "yes", False: "no (ours)"})
    body = table[~table["encoder"].str.startswith("mean Δ")]
    statuses = body[[c for c in body.columns if c.endswith(" status")]].stack()
    lines = [
        "# ReSiReg across encoders (mIoU x100; Δ = method - BB)",
        "",
        "Deltas and their means are over the jobs that completed; a mean row's status column "
        "says which encoders it covers.",
        "",
        markdown(shown, floatfmt=".1f"),
        "",
        "## Mean Δ per method (over encoders and datasets)",
        "",
        f"Over the {int((statuses == 'completed').sum())} of {len(statuses)} encoder x dataset "
        "jobs that completed.",
        "",
        markdown(method_means(table), floatfmt="+.2f", index=True),
        *paper_lines(flags, protocol_differences(jobs, "table1"), paper_tolerance),
        "",
        *protocol_lines(jobs),
    ]
    files["table1_md"].write_text("\n".join(lines) + "\n")
    return files


def is_table1(jobs: list[Job]) -> bool:
    """The 2D encoder sweep (Table 1's report section): an encoder sweep of 2D jobs."""
    return is_encoder_sweep(jobs) and not is_mapping_sweep(jobs)


def is_table2(jobs: list[Job]) -> bool:
    """The 3D encoder sweep (Table 2's report section): an encoder sweep of 3D mapping jobs."""
    return is_encoder_sweep(jobs) and is_mapping_sweep(jobs)


def _named(files: dict[str, Path], what: str, key: str) -> tuple[dict[str, Path], list[str]]:
    """A report section's result (:mod:`resireg_train.report.specs`): its ``files`` and the
    line of ``summary.md`` that names its Markdown file ``files[key]``."""
    return files, ["", f"{what}: `{files[key].name}`."]


def table1_section(
    jobs: list[Job], out: Path, paper_tolerance: float = DEFAULT_TOLERANCE
) -> tuple[dict[str, Path], list[str]]:
    """The report section ``table1``: :func:`write_encoder_table`."""
    files = write_encoder_table(jobs, out, paper_tolerance)
    return _named(files, "Encoder table (the paper's Table 1)", "table1_md")


def table2_section(
    jobs: list[Job], out: Path, paper_tolerance: float = DEFAULT_TOLERANCE
) -> tuple[dict[str, Path], list[str]]:
    """The report section ``table2``: :func:`write_mapping_table`."""
    files = write_mapping_table(jobs, out, paper_tolerance)
    return _named(files, "3D mapping table (the paper's Table 2)", "table2_md")


#: The prefix of Table 2's scores (the task table's, :func:`metric_prefix`).
MAPPING_PREFIX = metric_prefix("table2")


#: Table 2's score columns: (key of ``final`` before ``_<variant>``, column name).
MAPPING_COLUMNS = (
    *((n, SCORE_SPECS[n].label) for n in ("miou", "fmiou")),
    *((f"pooled_{n}", f"{SCORE_SPECS[n].label} (pooled)") for n in ("miou", "fmiou")),
)


def is_mapping_sweep(jobs: list[Job]) -> bool:
    """Jobs of ``resireg-eval task=scannet3d`` (3D semantic mapping: the tasks of Table 2)."""
    tasks = table_tasks("table2")
    for job in jobs:
        params = job.results.get("params") or {}
        if params.get("task") in tasks or job.overrides.get("task") in tasks:
            return True
        if any(k.startswith(MAPPING_PREFIX) for k in job.results.get("final") or {}):
            return True
    return False


def mapping_table(jobs: list[Job]) -> pd.DataFrame:
    """The paper's Table 2 from a 3D mapping sweep: one row per encoder and variant scored
    (``encoder + Full``), its parameter count, and per dataset the mIoU and f-mIoU as the mean
    of the scenes' values (the table's figure, RayFronts' per-scene evaluation), the same two
    pooled over the voxels of all scenes (x100) and the job's status (a job that did not
    complete leaves its cells empty)."""
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    per_job, datasets = per_encoder(jobs)
    for job, name, third, millions, dataset in per_job:
        variants = (job.results.get("params") or {}).get("variants") or ["full"]
        for variant in variants:
            base = variant.split("@")[0]
            label = f"{name} + {METHOD_NAMES.get(base, base)}{variant[len(base) :]}"
            first = {"model": label, "encoder": name, "variant": variant}
            row, final = _encoder_row(rows, (name, variant), first, job, third, millions, dataset)
            if final is None:
                continue
            for key, column in MAPPING_COLUMNS:
                value = final.get(f"{MAPPING_PREFIX}{dataset}/{key}_{variant}")
                if value is not None:
                    row[f"{dataset} {column}"] = 100 * value
    columns = ["model", "encoder", "variant", "third_party", "parameters (M)"]
    for dataset in datasets:
        columns += [f"{dataset} {column}" for _, column in MAPPING_COLUMNS]
        columns.append(f"{dataset} status")
    return pd.DataFrame(list(rows.values())).reindex(columns=columns)


def write_mapping_table(
    jobs: list[Job], out: Path, paper_tolerance: float = DEFAULT_TOLERANCE
) -> dict[str, Path]:
    """``table2.csv`` and ``table2.md`` (the table with the paper's value and the difference to
    it beside each mean-over-scenes cell the paper reports, the cells further than
    ``paper_tolerance`` points, the protocol settings that differ from the paper's, then the
    protocol)."""
    table = mapping_table(jobs)
    files = {"table2_csv": out / "table2.csv", "table2_md": out / "table2.md"}
    cells = {}  # the per-scene means (the paper's figures), not the pooled columns
    for key, name in MAPPING_COLUMNS[:2]:
        for column in table.columns:
            if column.endswith(f" {name}"):
                cells[column] = (column.removesuffix(f" {name}"), None, key)
    table, flags = add_paper_columns(table, "table2", cells, paper_tolerance, label_column="model")
    table.to_csv(files["table2_csv"], index=False)
    shown = table.drop(columns=["encoder", "variant", "third_party"])
    lines = [
        "# 3D semantic mapping on ScanNet (x100; mIoU / f-mIoU: mean over scenes; pooled: one "
        "confusion over the voxels of all scenes)",
        "",
        markdown(shown, floatfmt=".1f"),
        *paper_lines(flags, protocol_differences(jobs, "table2"), paper_tolerance),
        "",
        *protocol_lines(jobs),
    ]
    files["table2_md"].write_text("\n".join(lines) + "\n")
    return files


LAYER_SWEEP_FILES = ("layer_sweep.csv", "layer_sweep.md", "layer_sweep.png")


VARIANT_ORDER = VARIANTS  # the variant table's order


def layer_configs(job: Job) -> list[tuple[str, str, int]]:
    """``(configuration, variant label, block)`` of every ``<variant>@layer:<block>``
    configuration a job scored (its ``params.variants``); the label keeps ``+prior``."""
    out = []
    for name in (job.results.get("params") or {}).get("variants") or []:
        try:
            block = variant_layer(name)
            base = parse_variant(name)[0]
        except ValueError:
            continue
        if block is not None:
            out.append((name, base + ("+prior" if takes_prior(name) else ""), block))
    return out


def variant_order(label: str) -> tuple[int, str]:
    """Sort key of a variant label: the paper's order (BB, Calib, Lite, Full), then the rest."""
    base = label.removesuffix("+prior")
    return (VARIANT_ORDER.index(base) if base in VARIANT_ORDER else len(VARIANT_ORDER), label)


def is_layer_sweep(jobs: list[Job]) -> bool:
    """Some job scored configurations on other encoder blocks (``sweep=clip_layers``)."""
    return any(layer_configs(job) for job in jobs)


def layer_sweep_table(jobs: list[Job]) -> pd.DataFrame:
    """One row per (encoder, dataset, variant, block) of a layer sweep: mIoU and f-mIoU (x100;
    empty unless the job completed) and the job's status. The backbone alone (``bb``, no
    intermediates) of the same jobs follows each (encoder, dataset) with an empty block: the
    reference the blocks are compared with. Negative blocks are the jobs' own spelling; the
    rows are sorted by encoder, dataset, variant (the paper's order) and block."""
    rows = []
    per_job, _ = per_encoder(jobs)
    for job, name, _, _, dataset in per_job:
        configs = layer_configs(job)
        if not configs:
            continue
        final = job.results.get("final", {}) if job.status == "completed" else {}
        names = (job.results.get("params") or {}).get("variants") or []
        entries = [*configs, *((BASELINE, BASELINE, None) for n in names if n == BASELINE)]
        for config, variant, block in entries:
            row = {"encoder": name, "dataset": dataset, "variant": variant, "block": block}
            for key in ("miou", "fmiou"):
                value = final.get(f"{OVSS_PREFIX}{dataset}/{key}_{config}")
                row[key] = 100 * value if value is not None else math.nan
            row["status"] = job.status
            rows.append(row)
    columns = ["encoder", "dataset", "variant", "block", "miou", "fmiou", "status"]
    table = pd.DataFrame(rows, columns=columns)
    table["block"] = table["block"].astype("Int64")
    order = table["variant"].map(lambda v: variant_order(v)[0])
    return (
        table.assign(_order=order)
        .sort_values(["encoder", "dataset", "_order", "variant", "block"], ignore_index=True)
        .drop(columns="_order")
    )


def write_layer_sweep(jobs: list[Job], out: Path) -> dict[str, Path]:
    """``layer_sweep.csv`` (:func:`layer_sweep_table`), ``layer_sweep.md`` (per encoder and
    dataset: mIoU per block and variant, the backbone alone, the best block of each variant)
    and ``layer_sweep.png`` (:func:`layer_sweep_figure`)."""
    table = layer_sweep_table(jobs)
    files = {f"layer_sweep_{f.rsplit('.', 1)[1]}": out / f for f in LAYER_SWEEP_FILES}
    table.to_csv(files["layer_sweep_csv"], index=False)
    lines = ["# CLIP intermediate-layer sweep (mIoU x100 per intermediate block)"]
    for (encoder, dataset), part in table.groupby(["encoder", "dataset"], sort=False):
        blocks = part.dropna(subset=["block"])
        grid = blocks.pivot_table(index="block", columns="variant", values="miou",
                                  aggfunc="max", dropna=False)  # fmt: skip
        grid = grid[sorted(grid.columns, key=variant_order)]
        grid = grid.rename(columns=lambda v: METHOD_NAMES.get(v, v))
        lines += ["", f"## {encoder} / {dataset}", "", markdown(grid, floatfmt=".1f", index=True)]
        bb = part.loc[part["block"].isna() & (part["variant"] == BASELINE), "miou"].dropna()
        if not bb.empty:
            lines += ["", f"BB (no intermediates): {float(bb.iloc[0]):.1f}."]
        best = [f"{column}: block {int(grid[column].idxmax())} ({grid[column].max():.1f})"
                for column in grid.columns if grid[column].notna().any()]  # fmt: skip
        if best:
            lines += ["", "Best block: " + "; ".join(best) + "."]
    files["layer_sweep_md"].write_text("\n".join(lines) + "\n")
    layer_sweep_figure(table).savefig(files["layer_sweep_png"], dpi=DPI)
    return files


def layer_sweep_section(jobs: list[Job], out: Path) -> tuple[dict[str, Path], list[str]]:
    """The report section ``layer_sweep``: :func:`write_layer_sweep`."""
    files = write_layer_sweep(jobs, out)
    return _named(files, "CLIP layer sweep (mIoU per intermediate block)", "layer_sweep_md")
