"""The paper beside your numbers: the published Table 1 / Table 2 cells (``conf/paper/
results.yaml``) matched to a report's cells by encoder, dataset and variant, the difference in
points, the cells beyond a tolerance, and the protocol settings a run changed from the paper's.

A cell the paper does not report stays empty (``NaN``), never zero, and so does its Δ.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from resireg_train.config.paths import CONFIG_DIR

__all__ = [
    "DEFAULT_TOLERANCE",
    "PAPER_FILE",
    "add_paper_columns",
    "paper_cell",
    "paper_lines",
    "paper_results",
    "protocol_differences",
]

#: The data file (the paper's figures in points, and the protocol settings it states).
PAPER_FILE = CONFIG_DIR / "paper" / "results.yaml"
#: ``resireg-report --paper-tolerance``'s default: cells further than this (points) are flagged.
DEFAULT_TOLERANCE = 1.0


@functools.cache
def paper_results(path: str | Path = PAPER_FILE) -> dict[str, Any]:
    """The paper's figures as the data file holds them."""
    with open(path) as f:
        return yaml.safe_load(f)


def paper_cell(
    table: str,
    encoder: str,
    dataset: str | None,
    variant: str,
    metric: str = "miou",
    path: str | Path = PAPER_FILE,
) -> float | None:
    """The paper's value (points) of one cell: Table 1 by ``(encoder, dataset, variant)``
    (``metric`` is mIoU there), Table 2 by ``(encoder, variant, metric)`` (``miou`` /
    ``fmiou``; the paper's Table 2 has one variant per encoder, on ScanNet alone: the data
    file's ``table2.dataset``). ``None`` where the paper reports no such cell. ``path``: the
    data file (``resireg-runs reproduce --paper``)."""
    row = paper_results(path)[table]["rows"].get(encoder)
    if row is None:
        return None
    if table == "table1":
        value = (row.get(dataset) or {}).get(variant) if metric == "miou" else None
    elif dataset == paper_results(path)[table]["dataset"] and row.get("variant") == variant:
        value = row.get(metric)
    else:
        value = None
    return None if value is None else float(value)


def add_paper_columns(
    frame: pd.DataFrame,
    table: str,
    cells: Mapping[str, tuple[str | None, str | None, str]],
    tolerance: float = DEFAULT_TOLERANCE,
    encoder_column: str = "encoder",
    label_column: str | None = None,
) -> tuple[pd.DataFrame, list[str]]:
    """``frame`` with ``<column> paper`` and ``<column> Δ paper`` after every column of
    ``cells`` (``{column: (dataset, variant, metric)}``: what the column scores; a ``None``
    variant: each row's ``variant`` column), and the
    flags: one ``"<encoder> <column>: 21.40 vs 23.30 (-1.90)"`` per cell further than
    ``tolerance`` points from the paper. Rows whose encoder the paper does not report, and the
    mean rows, get empty paper cells."""
    out = frame.copy()
    flags: list[str] = []
    order: list[str] = []
    for column in frame.columns:
        order.append(column)
        if column not in cells:
            continue
        dataset, variant, metric = cells[column]
        variants = frame["variant"] if variant is None else [variant] * len(frame)
        paper = [
            paper_cell(table, enc, dataset, var, metric) if isinstance(enc, str) else None
            for enc, var in zip(frame[encoder_column], variants, strict=True)
        ]
        ours = pd.to_numeric(frame[column], errors="coerce")
        paper_values = pd.Series([math.nan if p is None else p for p in paper], index=frame.index)
        delta = ours - paper_values
        out[f"{column} paper"] = paper_values
        out[f"{column} Δ paper"] = delta
        order += [f"{column} paper", f"{column} Δ paper"]
        labels = frame[label_column or encoder_column]
        for label, mine, theirs, d in zip(labels, ours, paper_values, delta, strict=True):
            if not math.isnan(d) and abs(d) > tolerance:
                flags.append(f"{label} {column}: {mine:.2f} vs {theirs:.2f} ({d:+.2f})")
    return out[order], flags


def protocol_differences(jobs: list[Any], table: str, path: str | Path = PAPER_FILE) -> list[str]:
    """One line per protocol setting (``results.json`` ``protocol.settings``) that a job ran
    with a value other than the paper's (``conf/paper/results.yaml`` ``protocol.<table>``;
    ``path``: another data file): ``"short_side=448 (paper: 576): jobs 0, 3"``. Jobs that
    recorded no protocol, and settings the paper does not state, are not compared."""
    stated = (paper_results(path).get("protocol") or {}).get(table) or {}
    differ: dict[tuple[str, str, str], list[int]] = {}
    for job in jobs:
        settings = (job.results.get("protocol") or {}).get("settings") or {}
        for key, paper in stated.items():
            if key in settings and not _same(settings[key], paper):
                differ.setdefault((key, _text(settings[key]), _text(paper)), []).append(job.number)
    return [
        f"{key}={value} (paper: {paper}): job{'s' if len(numbers) > 1 else ''} "
        f"{', '.join(map(str, numbers))}"
        for (key, value, paper), numbers in differ.items()
    ]


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def _text(v: Any) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_text(x) for x in v) + "]"
    return "null" if v is None else str(v)


def paper_lines(flags: list[str], differences: list[str], tolerance: float) -> list[str]:
    """The Markdown under a table: the flagged cells and the protocol differences."""
    unit = "point" if tolerance == 1 else "points"
    lines = ["", f"## Against the paper (`paper`: its published value; flagged: further than "
             f"{tolerance:g} {unit})", ""]  # fmt: skip
    lines += [f"- {flag}" for flag in flags] or ["No cell differs from the paper by more."]
    lines += ["", "Protocol settings that differ from the paper's:", ""]
    lines += [f"- {line}" for line in differences] or ["none (of the settings the paper states)."]
    return lines
