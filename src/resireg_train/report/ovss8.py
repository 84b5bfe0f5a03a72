"""The OVSS field's table (``sweep=ovss8``): one row per encoder and variant (BB, Calib, Lite,
Full), one column per benchmark (VOC21, PC60, Object, VOC20, PC59, Stuff, City, ADE) and their
average, with the published peers' rows beneath (``conf/paper/ovss8.yaml``: the benchmarks, and
each peer's figures with document, table and row, or "not transcribed"), as ``ovss8.csv`` and
``ovss8.md`` with the protocol each job ran under.

A row's average is the mean of its eight cells, left empty unless all eight are there (a job that
did not complete leaves its cell empty and is listed under the table).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from resireg.specs.variants import BASELINE, VARIANTS
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.report.jobs import METHOD_NAMES, Job, per_encoder

__all__ = ["OVSS8_FILE", "benchmarks", "is_ovss8_sweep", "ovss8_section", "ovss8_table", "peer_rows",
           "write_ovss8_table"]  # fmt: skip

#: The data file: the eight benchmarks and the peers' published figures.
OVSS8_FILE = CONFIG_DIR / "paper" / "ovss8.yaml"
#: The average's column.
AVERAGE = "Avg"
PUBLISHED = "published, not rerun"


@functools.cache
def _data(path: str | Path = OVSS8_FILE) -> dict[str, Any]:
    with open(path) as f:
        return yaml.safe_load(f)


def benchmarks() -> dict[str, dict[str, str]]:
    """``{dataset name: {"label", "config"}}`` of the eight benchmarks, in the table's order."""
    return dict(_data()["benchmarks"])


def _benchmark_of(job: Job) -> str | None:
    """The benchmark a job scored: its dataset's name, or (a job that failed before recording
    its parameters) the name whose conf/dataset/ entry its ``dataset=`` override is."""
    marks = benchmarks()
    params = (job.results.get("params") or {}).get("dataset") or {}
    if params.get("name") in marks:
        return str(params["name"])
    override = job.overrides.get("dataset")
    return next((n for n, b in marks.items() if b["config"] == override), None)


def is_ovss8_sweep(jobs: list[Job]) -> bool:
    """Jobs of ``sweep=ovss8``: some job ran under the ``ovss8`` protocol."""
    return any((j.results.get("protocol") or {}).get("name") == "ovss8" for j in jobs)


def _columns() -> list[str]:
    return [b["label"] for b in benchmarks().values()]


def _with_average(row: dict[str, Any]) -> dict[str, Any]:
    values = [row.get(c) for c in _columns()]
    complete = all(isinstance(v, (int, float)) and not math.isnan(v) for v in values)
    row[AVERAGE] = sum(values) / len(values) if complete else math.nan
    return row


def peer_rows() -> list[dict[str, Any]]:
    """The data file's peers as table rows (points; empty cells where not transcribed)."""
    marks = benchmarks()
    rows = []
    for peer in _data()["peers"]:
        source = peer.get("source") or {}
        if peer.get("status") == "transcribed":
            where = "; ".join(str(source[k]) for k in ("document", "table", "row") if source.get(k))
            origin = f"{PUBLISHED}: {where}"
        else:
            origin = f"not transcribed: {source.get('document', '')}"
        row = {"model": f"{peer['method']} ({peer['backbone']})", "variant": None,
               "source": origin}  # fmt: skip
        for name, value in (peer.get("miou") or {}).items():
            row[marks[name]["label"]] = float(value)
        rows.append(_with_average(row))
    return rows


def ovss8_table(jobs: list[Job]) -> pd.DataFrame:
    """Your rows (encoder x variant, in the variant table's order; mIoU x100) then the peers'."""
    marks = benchmarks()
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    per_job, _ = per_encoder(jobs)
    for job, name, _, _, _ in per_job:
        benchmark = _benchmark_of(job)
        if benchmark is None or job.status != "completed":
            continue
        protocol = (job.results.get("protocol") or {}).get("name", "?")
        final = job.results.get("final") or {}
        for variant in (job.results.get("params") or {}).get("variants") or []:
            value = final.get(f"val/ovss/{benchmark}/miou_{variant}")
            if value is None:
                continue
            base = variant.split("@")[0].split("+")[0]
            label = METHOD_NAMES.get(base, base) + variant[len(base) :]
            row = rows.setdefault((name, variant), {"model": name, "variant": label,
                                                    "source": set()})  # fmt: skip
            row[marks[benchmark]["label"]] = 100 * float(value)
            row["source"].add(protocol)
    order = {v: i for i, v in enumerate(VARIANTS)}
    ours = sorted(rows.items(), key=lambda kv: (kv[0][0], order.get(kv[0][1], len(order)),
                                                kv[0][1]))  # fmt: skip
    body = []
    for _, row in ours:
        row["source"] = "this run, protocol " + ", ".join(sorted(row["source"]))
        body.append(_with_average(row))
    columns = ["model", "variant", *_columns(), AVERAGE, "source"]
    return pd.DataFrame([*body, *peer_rows()]).reindex(columns=columns)


def _missing(jobs: list[Job]) -> list[str]:
    """One line per benchmark without a completed job, and per job that did not complete."""
    marks = benchmarks()
    done = {_benchmark_of(j) for j in jobs if j.status == "completed"}
    lines = [f"- {b['label']} (`dataset={b['config']}`): no completed job"
             for n, b in marks.items() if n not in done]  # fmt: skip
    lines += [f"- job {j.number} ({j.path.name}): **{j.status}**" for j in jobs
              if j.status != "completed"]  # fmt: skip
    return lines


def write_ovss8_table(jobs: list[Job], out: Path) -> dict[str, Path]:
    """``ovss8.csv`` (:func:`ovss8_table`) and ``ovss8.md`` (the table, what is missing, the
    protocol of every job)."""
    from resireg_train.report.tables import markdown, protocol_lines

    table = ovss8_table(jobs)
    files = {"ovss8_csv": out / "ovss8.csv", "ovss8_md": out / "ovss8.md"}
    table.to_csv(files["ovss8_csv"], index=False)
    base = METHOD_NAMES[BASELINE]
    other = [
        j for j in jobs if (j.results.get("protocol") or {}).get("name") not in (None, "ovss8")
    ]
    # the Markdown names each peer's source by number, listed under the table (the CSV keeps
    # the whole source in its column)
    shown, sources = table.copy(), []
    for i, origin in shown["source"].items():
        kind, sep, where = str(origin).partition(": ")
        if sep and not str(origin).startswith("this run"):
            sources.append(where)
            shown.loc[i, "source"] = f"{kind} [{len(sources)}]"
    lines = [
        "# The eight OVSS benchmarks (mIoU x100)",
        "",
        f"Your rows: each encoder with {base} and the post-hoc variants, scored by this sweep. The "
        f"peers' rows are {PUBLISHED}; a peer's empty row is one whose paper was not transcribed "
        "(conf/paper/ovss8.yaml). Avg: the mean of the eight cells (empty unless all eight are "
        "there).",
        "",
        markdown(shown, floatfmt=".2f"),
        "",
        "## Sources",
        "",
        *(f"{n}. {where}" for n, where in enumerate(sources, 1)),
    ]
    missing = _missing(jobs)
    if missing:
        lines += ["", "## Not scored", "", *missing]
    if other:
        lines += ["", f"Jobs {', '.join(str(j.number) for j in other)} ran under another protocol "
                  "than ovss8: their cells do not compare with the peers'."]  # fmt: skip
    lines += ["", *protocol_lines(jobs)]
    files["ovss8_md"].write_text("\n".join(lines) + "\n")
    return files


def ovss8_section(jobs: list[Job], out: Path) -> tuple[dict[str, Path], list[str]]:
    """The report section ``ovss8`` (:mod:`resireg_train.report.sections`):
    :func:`write_ovss8_table` and the line of ``summary.md`` naming its table."""
    files = write_ovss8_table(jobs, out)
    return files, ["", f"The eight OVSS benchmarks, beside the published peers: "
                       f"`{files['ovss8_md'].name}`."]  # fmt: skip
