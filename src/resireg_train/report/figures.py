"""The report's figures: the batch size x prototypes heatmap, training curves, the layer sweep's
mIoU per block. Pyplot-free (an Agg canvas per figure, no global state)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd

from resireg.specs.variants import BASELINE
from resireg_train.report.jobs import METHOD_NAMES, Job, varying_keys

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "DPI", "agg_figure", "curves_figure", "curves_section", "has_history", "heatmap_figure",
    "layer_sweep_figure", "plot_curves", "plot_heatmap", "short_keys", "short_value",
    "widen_to_fit",
]  # fmt: skip

DPI = 120


def agg_figure(width: float, height: float) -> Figure:
    """A pyplot-free figure with constrained layout and an Agg canvas (no global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def widen_to_fit(fig: Figure, *texts: Any, margin: float = 0.5) -> None:
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
    fig = agg_figure(max(5.0, 2.5 + 0.75 * cols), max(3.5, 1.75 + 0.5 * rows))
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
    widen_to_fit(fig, title)
    return fig


def plot_heatmap(
    grid: pd.DataFrame, metric: str, path: Path, statuses: pd.DataFrame | None = None
) -> None:
    """Save :func:`heatmap_figure` as a PNG (``DPI`` dots per inch)."""
    heatmap_figure(grid, metric, statuses).savefig(path, dpi=DPI)


def short_keys(keys: list[str]) -> dict[str, str]:
    """Each dotted key by its shortest unambiguous ending (``model.optimizer.lr`` -> ``lr``;
    ``model.loss.distill.scale`` and ``model.loss.contrastive.scale`` keep one more part)."""
    out = {}
    for key in keys:
        parts = key.lstrip("+~").split(".")
        for n in range(1, len(parts) + 1):
            tail = ".".join(parts[-n:])
            others = [k for k in keys if k != key and k.lstrip("+~").split(".")[-n:] == parts[-n:]]
            if not others:
                out[key] = tail
                break
        else:
            out[key] = key
    return out


def short_value(value: object) -> str:
    """A number in three significant digits (``0.000646628`` -> ``0.000647``), else as is."""
    try:
        number = float(str(value))
    except ValueError:
        return str(value)
    return f"{number:.3g}"


def curves_figure(jobs: list[Job], metric: str) -> Figure | None:
    """``metric`` per epoch of every run with a history (``None`` when none has it). Up to
    6 runs the legend sits in the axes; with more it goes outside, to the right."""
    from matplotlib.ticker import MaxNLocator

    varying = varying_keys(jobs)
    names = short_keys(varying)
    curves = []
    for job in jobs:
        points = [(r["epoch"], r[metric]) for r in job.results.get("history") or [] if metric in r]
        if not points:
            continue
        label = ", ".join(f"{names[k]}={short_value(job.overrides.get(k))}"
                          for k in varying) or f"job {job.number}"  # fmt: skip
        if job.status != "completed":
            label += f" ({job.status})"
        curves.append((points, label))
    if not curves:
        return None
    fig = agg_figure(7.0, 4.5)
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


def layer_sweep_figure(table: pd.DataFrame) -> Figure:
    """mIoU (x100) against the block index: one panel per (encoder, dataset), one line per
    variant, the backbone alone as a dashed horizontal line; a block without a value (the
    job did not complete) is a gap in its line."""
    from matplotlib.ticker import MaxNLocator

    panels = list(table.groupby(["encoder", "dataset"], sort=False))
    fig = agg_figure(6.5 * len(panels), 4.5)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, ((encoder, dataset), part) in zip(axes, panels, strict=True):
        blocks = part.dropna(subset=["block"])
        for variant, line in blocks.groupby("variant", sort=False):
            label = METHOD_NAMES.get(variant, variant)
            ax.plot(line["block"].astype(int), line["miou"], marker="o", markersize=4, label=label)
        bb = part.loc[part["block"].isna() & (part["variant"] == BASELINE), "miou"].dropna()
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


def has_history(jobs: list[Job]) -> bool:
    """Some job recorded a per-epoch history (a training sweep): the ``curves`` section."""
    return any(j.results.get("history") for j in jobs)


def curves_section(
    jobs: list[Job], out: Path, metric: str | None
) -> tuple[dict[str, Path], list[str]]:
    """The report section ``curves`` (:mod:`resireg_train.report.specs`): ``curves.png``,
    ``metric`` per epoch of every run (:func:`plot_curves`), when there is a metric and a run
    has it."""
    curves = out / "curves.png"
    if metric and plot_curves(jobs, metric, curves):
        return {"curves": curves}, []
    return {}, []
