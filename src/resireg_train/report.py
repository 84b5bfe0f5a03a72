"""Sweep reports (``resireg-report SWEEP_DIR``): one table (and plots) from a Hydra multirun folder.

Reads every job folder of the sweep (``<n>_<overrides>/``): its overrides
(``.hydra/overrides.yaml``) and ``results.json``. A job that failed, was interrupted
(Ctrl-C; resumable), is still running or never wrote ``results.json`` stays in the table
with its status and error. Writes, into the sweep folder (or ``--out``):

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
- For the CLIP layer sweep (configurations ``<variant>@layer:<block>``, ``sweep=clip_layers``):
  ``layer_sweep.csv`` / ``.md`` / ``.png``, mIoU of each variant against the block index.

An explicit metric must be one the sweep's results hold (a ``final`` or ``best`` key of
some job); anything else is a :class:`ValueError` that lists them.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd
import yaml

from resireg.heuristic import PrototypeHeuristic
from resireg.variant_names import takes_prior, variant_layer
from resireg.variants import parse_variant
from resireg_train.results import RESULTS_FILE, flat, metric_mode, read_results

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "Job",
    "collect",
    "count_statuses",
    "curves_figure",
    "grid_statuses",
    "heatmap_figure",
    "is_layer_sweep",
    "known_metrics",
    "layer_sweep_figure",
    "layer_sweep_table",
    "mapping_table",
    "markdown",
    "protocol_lines",
    "plot_curves",
    "plot_heatmap",
    "prototype_grid",
    "report",
    "write_layer_sweep",
]

BATCH_KEY, PROTOTYPES_KEY = "batch_size", "full.n_prototypes"
#: Job statuses in the order they are counted (others follow alphabetically).
STATUSES = ("completed", "running", "interrupted", "failed", "missing")
DPI = 120


@dataclass
class Job:
    """One sweep job: its folder, overrides and ``results.json`` content."""

    path: Path
    number: int
    overrides: dict[str, str]
    results: dict[str, Any] = field(default_factory=dict)

    @property
    def status(self) -> str:
        return self.results.get("status", "missing") if self.results else "missing"

    @property
    def error(self) -> str | None:
        if not self.results:
            return f"no {RESULTS_FILE} (the job did not start, or crashed before writing it)"
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
        jobs.append(Job(folder, number, overrides, read_results(folder)))
    if not jobs:
        raise FileNotFoundError(
            f"{str(sweep)!r} holds no job folders (<n>_<overrides>/.hydra/overrides.yaml); "
            "pass the multirun folder, e.g. outputs/<name>/multirun/<time>"
        )
    return sorted(jobs, key=lambda j: j.number)


def markdown(frame: pd.DataFrame, floatfmt: str, index: bool = False) -> str:
    """``frame`` as a Markdown table, rendered one way in every table of the report: text on
    one line (a multi-line error would split its row) with ``|`` escaped, and a missing value
    (NaN, ``None``: a job that did not complete, a mean over nothing) as an empty cell."""

    def cell(value: Any) -> Any:
        return flat(value).replace("|", "\\|") if isinstance(value, str) else value

    shown = frame.map(cell)
    shown = shown.astype(object).where(shown.notna(), None)  # tabulate blanks None, not NaN
    return shown.to_markdown(index=index, floatfmt=floatfmt, missingval="")


def _varying(jobs: list[Job]) -> list[str]:
    keys = sorted({k for j in jobs for k in j.overrides})
    return [k for k in keys if len({j.overrides.get(k) for j in jobs}) > 1]


def _scores(results: dict[str, Any]) -> dict[str, float]:
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
    names = sorted({k.split("@")[0] for j in jobs for k in _scores(j.results)})
    for suffix in ("/miou_full", "/miou_lite", "/miou_bb", "train/loss"):
        hits = [n for n in names if n.endswith(suffix)]
        if hits:
            return hits[0]
    return names[0] if names else None


def summary_table(jobs: list[Job], metric: str | None) -> pd.DataFrame:
    """One row per job: number, varying overrides, status, scores, best metric, error."""
    varying = _varying(jobs)
    rows = []
    for job in jobs:
        row: dict[str, Any] = {"job": job.number}
        row.update({k: job.overrides.get(k) for k in varying})
        row["status"] = job.status
        row.update(_scores(job.results))
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


def _is_prototype_sweep(jobs: list[Job]) -> bool:
    """A batch size x prototype count grid: jobs vary the batch size, and the prototype
    count too (one per job) or score several counts each."""
    varying = _varying(jobs)
    return BATCH_KEY in varying and (
        PROTOTYPES_KEY in varying or any(len(_prototype_configs(j)) > 1 for j in jobs)
    )


def _prototype_configs(job: Job) -> dict[int, str]:
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


def _grid_cells(jobs: list[Job], metric: str) -> pd.DataFrame:
    """One row per (job, prototype count) of the grid: batch size, prototype count, ``metric``
    (NaN unless the job completed) and status. A job either set ``full.n_prototypes`` (one
    count per job) or scored several ``full@n_prototypes:<n>`` configurations in one pass;
    ``metric`` names Full's score (``.../miou_full``), each configuration's is
    ``.../miou_full@n_prototypes:<n>``."""
    cells = []
    for job in jobs:
        try:
            batch = int(job.overrides[BATCH_KEY])
        except (KeyError, ValueError):
            continue
        scores = _scores(job.results) if job.status == "completed" else {}
        if PROTOTYPES_KEY in job.overrides:
            try:
                counts = {int(job.overrides[PROTOTYPES_KEY]): metric}
            except ValueError:
                continue
        else:
            counts = {
                n: metric + name[len("full") :] for n, name in _prototype_configs(job).items()
            }
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


def _agg_figure(width: float, height: float) -> Figure:
    """A pyplot-free figure with constrained layout and an Agg canvas (no global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _widen_to_fit(fig: Figure, *texts: Any, margin: float = 0.5) -> None:
    """Widen ``fig`` (in steps of 1/4 in, so the pixel size stays whole) until ``texts``
    (e.g. a long title) fit across it, measured by matplotlib's renderer."""
    renderer = fig.canvas.get_renderer()
    need = max(t.get_window_extent(renderer).width for t in texts) / fig.dpi + margin
    if need > fig.get_figwidth():
        fig.set_figwidth(math.ceil(4 * need) / 4)


def heatmap_figure(grid: pd.DataFrame, metric: str, statuses: pd.DataFrame | None = None) -> Figure:
    """The batch size x prototypes heatmap of ``metric``; a cell without a value reads its
    job's status (``statuses``, aligned with ``grid``: failed / interrupted / running /
    missing). Sized to the grid (at least 5 x 3.5 in) with constrained layout, so titles,
    labels and ticks stay inside the figure for any grid size."""
    import matplotlib
    import numpy as np

    values = grid.to_numpy(dtype=float)
    rows, cols = values.shape
    fig = _agg_figure(max(5.0, 2.5 + 0.75 * cols), max(3.5, 1.75 + 0.5 * rows))
    ax = fig.add_subplot()
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.9")
    image = ax.imshow(np.ma.masked_invalid(values), cmap=cmap, aspect="auto")
    ax.set_xticks(range(cols), [str(c) for c in grid.columns])
    ax.set_yticks(range(rows), [str(i) for i in grid.index])
    ax.set_xlabel("prototypes (= PCA components)")
    ax.set_ylabel("batch size")
    title = ax.set_title(metric)
    finite = values[np.isfinite(values)]
    middle = (finite.min() + finite.max()) / 2 if finite.size else 0.0
    for (i, j), v in np.ndenumerate(values):
        if math.isnan(v):
            status = statuses.iat[i, j] if statuses is not None else "missing"
            text = "no value" if status == "completed" else status
        else:
            text = f"{100 * v:.1f}"
        colour = "black" if math.isnan(v) or v > middle else "white"
        ax.text(j, i, text, ha="center", va="center", fontsize=7, color=colour)
    label = "mIoU" if "miou" in metric.lower() else metric.rsplit("/", 1)[-1]
    fig.colorbar(image, ax=ax, label=f"{label} (cells: x100)")
    _widen_to_fit(fig, title)
    return fig


def plot_heatmap(
    grid: pd.DataFrame, metric: str, path: Path, statuses: pd.DataFrame | None = None
) -> None:
    """Save :func:`heatmap_figure` as a PNG (``DPI`` dots per inch)."""
    heatmap_figure(grid, metric, statuses).savefig(path, dpi=DPI)


def curves_figure(jobs: list[Job], metric: str) -> Figure | None:
    """``metric`` per epoch of every run with a history (``None`` when none has it). Up to
    6 runs the legend sits in the axes; with more it goes outside, to the right."""
    from matplotlib.ticker import MaxNLocator

    varying = _varying(jobs)
    curves = []
    for job in jobs:
        points = [(r["epoch"], r[metric]) for r in job.results.get("history") or [] if metric in r]
        if not points:
            continue
        label = ", ".join(f"{k}={job.overrides.get(k)}" for k in varying) or f"job {job.number}"
        if job.status != "completed":
            label += f" ({job.status})"
        curves.append((points, label))
    if not curves:
        return None
    fig = _agg_figure(7.0, 4.5)
    ax = fig.add_subplot()
    for points, label in curves:
        ax.plot(*zip(*points, strict=True), marker="o", markersize=3, label=label)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # whole epochs
    ax.set_xlabel("epoch")
    ax.set_ylabel(metric)
    ax.grid(alpha=0.3)
    if len(curves) <= 6:
        ax.legend(fontsize=7)
    else:  # constrained layout makes room for an "outside" legend
        fig.set_figwidth(10.0)
        fig.legend(fontsize=7, loc="outside right upper", ncols=math.ceil(len(curves) / 24))
    return fig


def plot_curves(jobs: list[Job], metric: str, path: Path) -> bool:
    """Save :func:`curves_figure` as a PNG; ``False`` (nothing written) when no run has it."""
    fig = curves_figure(jobs, metric)
    if fig is not None:
        fig.savefig(path, dpi=DPI)
    return fig is not None


# ---------------------------------------------------------------- encoder table (Table 1)
#: Post-hoc methods compared with the backbone alone, in the order of the paper's Table 1.
METHODS = ("calib", "lite", "full")
METHOD_NAMES = {"bb": "BB", "calib": "Calib", "lite": "Lite", "full": "Full"}


def _encoder_of(job: Job) -> tuple[str, bool | None, int | None]:
    """(name, third party?, parameter count) of a job's encoder (from its results, else its
    ``encoder=`` override when the job failed before building it)."""
    info = job.results.get("encoder") or {}
    params = (job.results.get("params") or {}).get("encoder") or {}
    name = info.get("name") or params.get("name") or job.overrides.get("encoder", "?")
    third = info.get("third_party", params.get("third_party"))
    return str(name), third, info.get("parameters")


def _dataset_of(job: Job) -> str:
    params = (job.results.get("params") or {}).get("dataset") or {}
    return str(params.get("name") or job.overrides.get("dataset", "?"))


def _per_encoder(
    jobs: list[Job],
) -> tuple[list[tuple[Job, str, bool | None, float | None, str]], list[str]]:
    """Each job with its encoder's name, third-party flag and parameters in millions (one
    decimal; ``None`` when unknown) and its dataset, and the datasets in first-seen order:
    what the encoder tables (Table 1, Table 2) read of every job."""
    out, datasets = [], []
    for job in jobs:
        name, third, parameters = _encoder_of(job)
        dataset = _dataset_of(job)
        if dataset not in datasets:
            datasets.append(dataset)
        millions = round(parameters / 1e6, 1) if parameters else None
        out.append((job, name, third, millions, dataset))
    return out, datasets


#: The sweeps (``conf/sweep/``, also their run ``name``) whose report is an encoder table.
ENCODER_SWEEPS = ("table1", "table2")


def is_encoder_sweep(jobs: list[Job]) -> bool:
    """Jobs of ``resireg-eval`` that vary the encoder, or of an encoder-table sweep
    (``sweep=table1`` / ``table2``) cut to one encoder on the command line."""
    if "encoder" in _varying(jobs):
        return True
    return any(
        j.overrides.get("sweep") in ENCODER_SWEEPS or j.results.get("name") in ENCODER_SWEEPS
        for j in jobs
    )


def encoder_table(jobs: list[Job]) -> pd.DataFrame:
    """The paper's Table 1 from an encoder x dataset sweep: one row per encoder (its name,
    third-party flag and parameter count), per dataset the BB mIoU and, per method (Calib,
    Lite, Full), its mIoU and its delta to BB, in mIoU points (x100). A job that did not
    complete leaves its cells empty and is named in ``<dataset> status``. Two rows follow:
    the mean delta per method over all encoders, and over the third-party ones only."""
    rows: dict[str, dict[str, Any]] = {}
    per_job, datasets = _per_encoder(jobs)
    for job, name, third, millions, dataset in per_job:
        row = rows.setdefault(name, {"encoder": name, "third_party": third, "parameters (M)": None})
        if third is not None:
            row["third_party"] = third
        if millions:
            row["parameters (M)"] = millions
        row[f"{dataset} status"] = job.status
        if job.status != "completed":
            continue
        final = job.results.get("final", {})
        bb = final.get(f"val/ovss/{dataset}/miou_bb")
        if bb is not None:
            row[f"{dataset} BB"] = 100 * bb
        for method in METHODS:
            value = final.get(f"val/ovss/{dataset}/miou_{method}")
            if value is None:
                continue
            row[f"{dataset} {METHOD_NAMES[method]}"] = 100 * value
            if bb is not None:
                row[f"{dataset} {METHOD_NAMES[method]} Δ"] = 100 * (value - bb)
    columns = ["encoder", "third_party", "parameters (M)"]
    for dataset in datasets:
        columns.append(f"{dataset} BB")
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


def write_encoder_table(jobs: list[Job], out: Path) -> dict[str, Path]:
    """``table1.csv`` and ``table1.md`` (the table, then the mean delta per method)."""
    table = encoder_table(jobs)
    files = {"table1_csv": out / "table1.csv", "table1_md": out / "table1.md"}
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
        "",
        *protocol_lines(jobs),
    ]
    files["table1_md"].write_text("\n".join(lines) + "\n")
    return files


# ------------------------------------------------------------ 3D mapping table (Table 2)
MAPPING_PREFIX = "val/scannet3d/"
#: Table 2's score columns: (key of ``final`` before ``_<variant>``, column name).
MAPPING_COLUMNS = (("miou", "mIoU"), ("fmiou", "f-mIoU"), ("pooled_miou", "mIoU (pooled)"),
                   ("pooled_fmiou", "f-mIoU (pooled)"))  # fmt: skip


def is_mapping_sweep(jobs: list[Job]) -> bool:
    """Jobs of ``resireg-eval task=scannet3d`` (3D semantic mapping)."""
    for job in jobs:
        params = job.results.get("params") or {}
        if params.get("task") == "scannet3d" or job.overrides.get("task") == "scannet3d":
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
    per_job, datasets = _per_encoder(jobs)
    for job, name, third, millions, dataset in per_job:
        variants = (job.results.get("params") or {}).get("variants") or ["full"]
        for variant in variants:
            base = variant.split("@")[0]
            label = f"{name} + {METHOD_NAMES.get(base, base)}{variant[len(base) :]}"
            row = rows.setdefault((name, variant), {"model": label, "encoder": name,
                                                    "variant": variant, "third_party": third,
                                                    "parameters (M)": None})  # fmt: skip
            if millions:
                row["parameters (M)"] = millions
            row[f"{dataset} status"] = job.status
            if job.status != "completed":
                continue
            final = job.results.get("final", {})
            for key, column in MAPPING_COLUMNS:
                value = final.get(f"{MAPPING_PREFIX}{dataset}/{key}_{variant}")
                if value is not None:
                    row[f"{dataset} {column}"] = 100 * value
    columns = ["model", "encoder", "variant", "third_party", "parameters (M)"]
    for dataset in datasets:
        columns += [f"{dataset} {column}" for _, column in MAPPING_COLUMNS]
        columns.append(f"{dataset} status")
    return pd.DataFrame(list(rows.values())).reindex(columns=columns)


def protocol_lines(jobs: list[Job]) -> list[str]:
    """The evaluation protocol of the jobs (``results.json``'s ``protocol``, docs/protocol.md):
    one line when they share it, else one per protocol with its jobs; nothing when no job
    recorded one."""
    from resireg_train.protocol import protocol_text

    seen: dict[str, list[int]] = {}
    for job in jobs:
        record = job.results.get("protocol")
        if record:
            seen.setdefault(protocol_text(record), []).append(job.number)
    if len(seen) == 1:
        return [f"Protocol: {next(iter(seen))}"]
    return [f"Protocol (jobs {', '.join(map(str, n))}): {text}" for text, n in seen.items()]


def write_mapping_table(jobs: list[Job], out: Path) -> dict[str, Path]:
    """``table2.csv`` and ``table2.md`` (the table, then the protocol)."""
    table = mapping_table(jobs)
    files = {"table2_csv": out / "table2.csv", "table2_md": out / "table2.md"}
    table.to_csv(files["table2_csv"], index=False)
    shown = table.drop(columns=["encoder", "variant", "third_party"])
    lines = [
        "# 3D semantic mapping on ScanNet (x100; mIoU / f-mIoU: mean over scenes; pooled: one "
        "confusion over the voxels of all scenes)",
        "",
        markdown(shown, floatfmt=".1f"),
        "",
        *protocol_lines(jobs),
    ]
    files["table2_md"].write_text("\n".join(lines) + "\n")
    return files


# ------------------------------------------------------------- CLIP layer sweep
LAYER_SWEEP_FILES = ("layer_sweep.csv", "layer_sweep.md", "layer_sweep.png")
VARIANT_ORDER = ("bb", *METHODS)


def _layer_configs(job: Job) -> list[tuple[str, str, int]]:
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


def _variant_order(label: str) -> tuple[int, str]:
    """Sort key of a variant label: the paper's order (BB, Calib, Lite, Full), then the rest."""
    base = label.removesuffix("+prior")
    return (VARIANT_ORDER.index(base) if base in VARIANT_ORDER else len(VARIANT_ORDER), label)


def is_layer_sweep(jobs: list[Job]) -> bool:
    """Some job scored configurations on other encoder blocks (``sweep=clip_layers``)."""
    return any(_layer_configs(job) for job in jobs)


def layer_sweep_table(jobs: list[Job]) -> pd.DataFrame:
    """One row per (encoder, dataset, variant, block) of a layer sweep: mIoU and f-mIoU (x100;
    empty unless the job completed) and the job's status. The backbone alone (``bb``, no
    intermediates) of the same jobs follows each (encoder, dataset) with an empty block: the
    reference the blocks are compared with. Negative blocks are the jobs' own spelling; the
    rows are sorted by encoder, dataset, variant (the paper's order) and block."""
    rows = []
    per_job, _ = _per_encoder(jobs)
    for job, name, _, _, dataset in per_job:
        configs = _layer_configs(job)
        if not configs:
            continue
        final = job.results.get("final", {}) if job.status == "completed" else {}
        names = (job.results.get("params") or {}).get("variants") or []
        entries = [*configs, *(("bb", "bb", None) for n in names if n == "bb")]
        for config, variant, block in entries:
            row = {"encoder": name, "dataset": dataset, "variant": variant, "block": block}
            for key in ("miou", "fmiou"):
                value = final.get(f"val/ovss/{dataset}/{key}_{config}")
                row[key] = 100 * value if value is not None else math.nan
            row["status"] = job.status
            rows.append(row)
    columns = ["encoder", "dataset", "variant", "block", "miou", "fmiou", "status"]
    table = pd.DataFrame(rows, columns=columns)
    table["block"] = table["block"].astype("Int64")
    order = table["variant"].map(lambda v: _variant_order(v)[0])
    return (
        table.assign(_order=order)
        .sort_values(["encoder", "dataset", "_order", "variant", "block"], ignore_index=True)
        .drop(columns="_order")
    )


def layer_sweep_figure(table: pd.DataFrame) -> Figure:
    """mIoU (x100) against the block index: one panel per (encoder, dataset), one line per
    variant, the backbone alone as a dashed horizontal line; a block without a value (the
    job did not complete) is a gap in its line."""
    from matplotlib.ticker import MaxNLocator

    panels = list(table.groupby(["encoder", "dataset"], sort=False))
    fig = _agg_figure(6.5 * len(panels), 4.5)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, ((encoder, dataset), part) in zip(axes, panels, strict=True):
        blocks = part.dropna(subset=["block"])
        for variant, line in blocks.groupby("variant", sort=False):
            label = METHOD_NAMES.get(variant, variant)
            ax.plot(line["block"].astype(int), line["miou"], marker="o", markersize=4, label=label)
        bb = part.loc[part["block"].isna() & (part["variant"] == "bb"), "miou"].dropna()
        if not bb.empty:
            ax.axhline(
                float(bb.iloc[0]), color="0.4", linestyle="--", label="BB (no intermediates)"
            )
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("intermediate block (0-based)")
        ax.set_ylabel("mIoU (x100)")
        ax.set_title(f"{encoder} / {dataset}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return fig


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
        grid = grid[sorted(grid.columns, key=_variant_order)]
        grid = grid.rename(columns=lambda v: METHOD_NAMES.get(v, v))
        lines += ["", f"## {encoder} / {dataset}", "", markdown(grid, floatfmt=".1f", index=True)]
        bb = part.loc[part["block"].isna() & (part["variant"] == "bb"), "miou"].dropna()
        if not bb.empty:
            lines += ["", f"BB (no intermediates): {float(bb.iloc[0]):.1f}."]
        best = [f"{column}: block {int(grid[column].idxmax())} ({grid[column].max():.1f})"
                for column in grid.columns if grid[column].notna().any()]  # fmt: skip
        if best:
            lines += ["", "Best block: " + "; ".join(best) + "."]
    files["layer_sweep_md"].write_text("\n".join(lines) + "\n")
    layer_sweep_figure(table).savefig(files["layer_sweep_png"], dpi=DPI)
    return files


def report(
    sweep_dir: str | Path, out: str | Path | None = None, metric: str | None = None
) -> dict[str, Path]:
    """Write the sweep's summary (and plots / heuristic where they apply); returns the files.

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

    constant = {k: v for k, v in jobs[0].overrides.items() if k not in _varying(jobs)}
    lines = [
        f"# Sweep {Path(sweep_dir).resolve()}",
        "",
        f"{len(jobs)} jobs: {count_statuses(table['status'])}",
        "",
        "Common overrides: " + (", ".join(f"`{k}={v}`" for k, v in constant.items()) or "none"),
        "",
        markdown(table, floatfmt=".4f"),
    ]
    if is_encoder_sweep(jobs) and is_mapping_sweep(jobs):
        files.update(write_mapping_table(jobs, out))
        lines += ["", f"3D mapping table (the paper's Table 2): `{files['table2_md'].name}`."]
    elif is_encoder_sweep(jobs):
        files.update(write_encoder_table(jobs, out))
        lines += ["", f"Encoder table (the paper's Table 1): `{files['table1_md'].name}`."]
    if metric and _is_prototype_sweep(jobs):
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
    if metric and any(j.results.get("history") for j in jobs):
        curves = out / "curves.png"
        if plot_curves(jobs, metric, curves):
            files["curves"] = curves
    if is_layer_sweep(jobs):  # sweep=clip_layers
        files.update(write_layer_sweep(jobs, out))
        lines += ["", f"CLIP layer sweep (mIoU per intermediate block): `{LAYER_SWEEP_FILES[1]}`."]
    failed = [j for j in jobs if j.status != "completed"]
    if failed:
        lines += ["", "## Jobs that did not complete", ""]
        lines += [f"- job {j.number} ({j.path.name}): **{j.status}**: {flat(j.error or '')}"
                  for j in failed]  # fmt: skip
    files["md"].write_text("\n".join(lines) + "\n")
    return files
