"""``resireg-runs plot``: runs compared in pictures.

- **Runs** (``resireg-runs plot RUN... --metric train/loss --metric 'val/ovss/*/miou_full'``):
  one PNG with a panel per metric (a pattern, ``*`` and ``?``, is every metric the runs logged
  that it matches), one curve per run against the global step, read from each run's own
  files: ``metrics.csv`` (a training run's every step: ``<metric>_step``, else the metric's
  own column, else its epoch column) or, where it lacks the metric, the record's ``history``
  (per epoch). A run with no curve for the metric but a final value (an evaluation, a map)
  shows it as a dashed level. ``--html`` also writes the same curves as an interactive plotly
  page (plotly: the ``optuna`` extra).
- **A search folder** (an Optuna search's sweep folder): Optuna's own plots,
  :mod:`resireg_train.runs.search_plots` (the sweeps sit above the runs).

Matplotlib draws without a display (Agg).
"""

from __future__ import annotations

import csv
import fnmatch
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from resireg_train.record.run_record import target_problem
from resireg_train.runs.index import Run

__all__ = [
    "LIMIT",
    "PlotResult",
    "axes_lines",
    "runs_of",
    "expand_metrics",
    "metric_curve",
    "plot_runs",
    "run_labels",
]

METRICS_FILE = "metrics.csv"


@dataclass
class PlotResult:
    """What a plot command wrote, and the curves as the figure holds them: per metric, per
    run label, ``(x, y)`` read back from the figure's lines (a level: ``x`` is ``None``)."""

    files: list[Path]
    curves: dict[str, dict[str, tuple[list[float] | None, list[float]]]] = field(
        default_factory=dict
    )


def _csv_rows(run: Run) -> tuple[list[str], list[dict[str, str]]]:
    path = run.path / METRICS_FILE
    if not path.is_file():
        return [], []
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            return list(reader.fieldnames or []), list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        run.problems.append(f"{path}: unreadable ({err}); the record's history is used")
        return [], []


#: The largest magnitude drawn, a step's or a value's: float32's (every metric a run logs
#: passes through a float32 tensor or fits one; beyond it, matplotlib's axis arithmetic
#: overflows and the figure cannot be drawn).
LIMIT = float(np.finfo(np.float32).max)


def _number(text: Any) -> float | None:
    """``text`` as a number that can be drawn, else ``None`` (not a number, not finite, or
    beyond :data:`LIMIT`)."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) and abs(value) <= LIMIT else None


def _out_of_range(text: Any) -> bool:
    """Whether ``text`` is a number that cannot be drawn (not finite, or beyond :data:`LIMIT`),
    as opposed to an empty cell or a word."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        return False
    return _number(value) is None


def _points(
    run: Run, metric: str, source: str, pairs: list[tuple[Any, Any]]
) -> tuple[list[float], list[float]]:
    """The ``(x, y)`` pairs that can be drawn; the others whose value cell holds something (a
    word, a NaN, an infinity or a number beyond :data:`LIMIT`, in x or y) left out and named
    once in ``run.problems``. An empty value cell is no point (metrics.csv leaves the cells of
    the metrics not logged at a step empty)."""
    xs, ys, dropped = [], [], []
    for x, y in pairs:
        fx, fy = _number(x), _number(y)
        if fx is not None and fy is not None:
            xs.append(fx)
            ys.append(fy)
        elif y is not None and str(y).strip():
            dropped.append(f"step={x} value={y}")
    if dropped:
        shown = ", ".join(dropped[:3]) + (f" and {len(dropped) - 3} more" if len(dropped) > 3
                                           else "")  # fmt: skip
        problem = (f"run {run.run_id} ({run.path}): {metric}: {len(dropped)} point(s) of {source} "
                   f"left out, not a number, not finite or beyond +-{LIMIT:.3g}: {shown}")  # fmt: skip
        if problem not in run.problems:
            run.problems.append(problem)
    return xs, ys


def metric_curve(run: Run, metric: str) -> tuple[list[float], list[float], str] | None:
    """``(steps, values, source)`` of ``metric`` in ``run`` (module docstring: metrics.csv,
    else the record's history); ``None`` when neither has it. A point whose step or value
    is not finite or beyond :data:`LIMIT` is left out (a gap), named in ``run.problems``."""
    columns, rows = _csv_rows(run)
    for column in (f"{metric}_step", metric, f"{metric}_epoch"):
        if column not in columns:
            continue
        source = f"{METRICS_FILE}:{column}"
        xs, ys = _points(run, metric, source, [(r.get("step"), r.get(column)) for r in rows])
        if xs:
            return xs, ys, source
    # a history row's step counts the steps done; Lightning logs an epoch's values at its
    # last step's index (metrics.csv's step), one less: the same x for both sources
    history = run.results.get("history") or []
    pairs = []
    for row in history:
        if not isinstance(row, dict):
            continue
        step = _number(row.get("step"))
        x = step - 1 if step is not None else row.get("step", row.get("epoch"))
        pairs.append((x, row.get(metric)))
    xs, ys = _points(run, metric, "results.json:history", pairs)
    if xs:
        return xs, ys, "results.json:history"
    return None


def _names(run: Run) -> set[str]:
    """Every metric name ``run`` logged: its record's final, best and history, and the
    columns of its metrics.csv (``_step`` / ``_epoch`` suffixes off)."""
    names = set(run.results.get("final") or {}) | set(run.results.get("best") or {})
    for row in run.results.get("history") or []:
        if isinstance(row, dict):
            names |= {k for k in row if k not in ("epoch", "step")}
    columns, _ = _csv_rows(run)
    for column in columns:
        if column not in ("epoch", "step"):
            names.add(column.removesuffix("_step").removesuffix("_epoch"))
    return names


def expand_metrics(runs: list[Run], patterns: list[str]) -> list[str]:
    """The metric names the patterns name, in the patterns' order (a pattern with ``*``,
    ``?`` or ``[`` is every logged name it matches, sorted); a name or pattern that no run
    logged is a :class:`ValueError` listing the names there are."""
    logged = set().union(*(_names(r) for r in runs)) if runs else set()
    out: list[str] = []
    for pattern in patterns:
        if any(c in pattern for c in "*?["):
            hits = sorted(n for n in logged if fnmatch.fnmatchcase(n, pattern))
        else:
            hits = [pattern] if pattern in logged else []
        if not hits:
            shown = ", ".join(sorted(logged)[:40]) or "none"
            raise ValueError(f"--metric {pattern!r}: no run logged it; logged: {shown}")
        out += [h for h in hits if h not in out]
    return out


def run_labels(runs: list[Run]) -> list[str]:
    """A legend label per run: its run id, its name and the overrides that set it apart from
    the other runs plotted (a sweep's swept values); two runs of one id (copied folders) are
    numbered."""
    quiet = ("paths.", "hydra.", "~callbacks.", "device=", "num_workers=")
    overrides = [[o for o in r.overrides if not o.lstrip("+~").startswith(quiet)] for r in runs]
    common = set.intersection(*(set(o) for o in overrides)) if len(runs) > 1 else set()
    labels, seen = [], {}
    for run, own in zip(runs, overrides, strict=True):
        label = " ".join([run.run_id, str(run.results.get("name") or ""),
                          *[o for o in own if o not in common]]).replace("  ", " ").strip()  # fmt: skip
        seen[label] = seen.get(label, 0) + 1
        labels.append(label if seen[label] == 1 else f"{label} ({seen[label]})")
    return labels


def _final(run: Run, metric: str) -> float | None:
    value = (run.results.get("final") or {}).get(metric)
    if _out_of_range(value):
        problem = (f"run {run.run_id} ({run.path}): {metric}: the final value {value} left out, "
                   f"not finite or beyond +-{LIMIT:.3g}")  # fmt: skip
        if problem not in run.problems:
            run.problems.append(problem)
    return _number(value)


def plot_runs(
    runs: list[Run], patterns: list[str], out: str | Path, html: str | Path | None = None
) -> PlotResult:
    """The curves of ``patterns``' metrics for ``runs`` into the PNG ``out`` (and the plotly
    page ``html``); see the module docstring."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    if not runs:
        raise ValueError("no run to plot")
    out = Path(out)
    for option, path in (("--out", out), ("--html", html)):
        if path is not None and (problem := target_problem(Path(path), folder=False)):
            raise ValueError(f"{option} {path}: {problem}")
    metrics = expand_metrics(runs, patterns)
    labels = run_labels(runs)
    fig, axes = plt.subplots(len(metrics), 1, figsize=(9, 3.2 * len(metrics)), squeeze=False)
    result = PlotResult(files=[out])
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, metric in zip(axes[:, 0], metrics, strict=True):
        for i, (run, label) in enumerate(zip(runs, labels, strict=True)):
            colour = colours[i % len(colours)]
            curve = metric_curve(run, metric)
            if curve is not None:
                x, y, _ = curve
                ax.plot(x, y, label=label, color=colour, marker="o" if len(x) < 30 else None,
                        markersize=3, linewidth=1.2)  # fmt: skip
            elif (level := _final(run, metric)) is not None:
                ax.axhline(level, label=f"{label} (final)", color=colour, linestyle="--",
                           linewidth=1.2)  # fmt: skip
        ax.set_title(metric, fontsize=10)
        ax.set_xlabel("global step")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(True, alpha=0.3)
        handles = ax.get_legend_handles_labels()[0]
        if handles:
            ax.legend(fontsize=8, loc="best", ncol=1 if len(handles) <= 6 else 2)
        result.curves[metric] = axes_lines(ax)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    if html is not None:
        result.files.append(_runs_html(result.curves, Path(html)))
    return result


def axes_lines(ax: Any) -> dict[str, tuple[list[float] | None, list[float]]]:
    """The axes' curves as drawn: label -> (x, y); a level (``axhline``) -> (None, [y]); a
    scatter (Optuna's trials) -> its points."""
    drawn: dict[str, tuple[list[float] | None, list[float]]] = {}
    for collection in ax.collections:
        offsets = collection.get_offsets()
        if len(offsets) and not str(collection.get_label()).startswith("_"):
            drawn[str(collection.get_label())] = ([float(p[0]) for p in offsets],
                                                  [float(p[1]) for p in offsets])  # fmt: skip
    for line in ax.get_lines():
        label = str(line.get_label())
        x = [float(v) for v in line.get_xdata()]
        y = [float(v) for v in line.get_ydata()]
        if line.get_linestyle() == "--" and label.endswith(" (final)"):
            drawn[label.removesuffix(" (final)")] = (None, [y[0]])
        else:
            drawn[label] = (x, y)
    return drawn


def _runs_html(curves: dict[str, dict[str, Any]], path: Path) -> Path:
    """The curves as one interactive plotly page (a panel per metric)."""
    try:
        import plotly.graph_objects as go
        from plotly.subplots import make_subplots
    except ImportError:
        raise ValueError("--html needs plotly: pip install 'resireg[optuna]'") from None
    fig = make_subplots(rows=len(curves), cols=1, subplot_titles=list(curves))
    for row, runs in enumerate(curves.values(), start=1):
        for label, (x, y) in runs.items():
            if x is None:
                fig.add_hline(y=y[0], line_dash="dash", row=row, col=1,
                              annotation_text=f"{label} (final)")  # fmt: skip
            else:
                fig.add_trace(go.Scatter(x=x, y=y, mode="lines", name=label, legendgroup=label,
                                         showlegend=row == 1), row=row, col=1)  # fmt: skip
    fig.update_layout(height=320 * len(curves), width=1000)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.write_html(str(path), include_plotlyjs=True)
    return path


def runs_of(specs: list[str], roots: list[str]) -> list[Run]:
    """The runs the command line names: a run folder or run id (:func:`index.find_run`), or a
    folder holding runs (a sweep: each of its runs, in folder order)."""
    from resireg_train.record.run_record import RunRecord
    from resireg_train.runs import index

    runs: list[Run] = []
    for spec in specs:
        path = Path(spec).expanduser()
        if path.is_dir() and not RunRecord.exists(path):
            found = sorted(index.scan([path]), key=lambda r: str(r.path))
            if not found:
                raise ValueError(f"{spec}: no run folder under it")
            runs += found
        else:
            runs.append(index.find_run(spec, roots))
    return runs
