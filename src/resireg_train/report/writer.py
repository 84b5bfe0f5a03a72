"""One sweep's report (``resireg-report SWEEP_DIR``): the summary, then each section of the
section table (:data:`resireg_train.report.specs.SECTION_SPECS`) the sweep names or shows,
then the jobs that did not complete (module docstring of :mod:`resireg_train.report`)."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

from resireg_train.record.run_record import flat
from resireg_train.report.jobs import (
    Job,
    check_metric,
    collect,
    count_statuses,
    default_metric,
    named_sections,
    varying_keys,
)
from resireg_train.report.paper import DEFAULT_TOLERANCE
from resireg_train.report.specs import SECTION_INPUTS, SECTION_SPECS
from resireg_train.report.summary import summary_table
from resireg_train.report.tables import markdown

__all__ = ["call_section", "report", "report_sections"]


def call_section(function: Callable[..., Any], inputs: dict[str, Any]) -> Any:
    """``function`` called with the report's ``inputs`` (:data:`SECTION_INPUTS`) its signature
    names, by name: each section's writer and detector takes what it reads."""
    names = inspect.signature(function).parameters
    unknown = [n for n in names if n not in SECTION_INPUTS]
    if unknown:
        raise TypeError(f"{function.__qualname__} takes {unknown}: a report section takes only "
                        f"{list(SECTION_INPUTS)}")  # fmt: skip
    return function(**{n: inputs[n] for n in names})


def report_sections(jobs: list[Job]) -> list[str]:
    """The sections the report writes beyond the summary and the ``always`` ones: those the
    sweep config names (``report: [...]``, :func:`~resireg_train.report.jobs.named_sections`),
    else those whose detector finds them in the jobs (an encoder axis: Table 1, or Table 2 for
    3D jobs; a batch size x prototype grid; blocks)."""
    named = named_sections(jobs)
    if named is not None:
        return named
    return [name for name, spec in SECTION_SPECS.items()
            if not spec.always and spec.detect and call_section(spec.detector(), {"jobs": jobs})]  # fmt: skip


def report(
    sweep_dir: str | Path,
    out: str | Path | None = None,
    metric: str | None = None,
    paper_tolerance: float = DEFAULT_TOLERANCE,
) -> dict[str, Path]:
    """Write the sweep's summary and its sections (tables, plots, heuristic where they apply);
    returns the files. Table 1 / Table 2 cells further than ``paper_tolerance`` points from the
    paper's are flagged (:mod:`resireg_train.report.paper`).

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
    inputs = {"jobs": jobs, "out": out, "sweep_dir": sweep_dir, "metric": metric,
              "paper_tolerance": paper_tolerance}  # fmt: skip
    chosen = report_sections(jobs)
    for name, spec in SECTION_SPECS.items():
        if name in chosen or (spec.always and call_section(spec.detector(), inputs)):
            written, added = call_section(spec.load(), inputs)
            files.update(written)
            lines += added
    failed = [j for j in jobs if j.status != "completed"]
    if failed:
        lines += ["", "## Jobs that did not complete", ""]
        lines += [f"- job {j.number} ({j.path.name}): **{j.status}**: {flat(j.error or '')}"
                  for j in failed]  # fmt: skip
    files["md"].write_text("\n".join(lines) + "\n")
    return files
