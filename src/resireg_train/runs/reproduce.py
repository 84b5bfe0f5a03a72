"""``resireg-runs reproduce <table>/<row> [--paper FILE] [--out DIR] [overrides...]``: the jobs
behind one row of the paper's Table 1 or Table 2, run with the paper's settings, and the
user's figures printed beside the paper's.

A row is a ``conf/paper/results.yaml`` row: ``table1/<encoder>`` (2D OVSS: one job per dataset
the paper reports for it, ``table1.datasets``) or ``table2/<encoder>`` (3D mapping on
``table2.dataset``); its name is a ``conf/encoder/`` entry. The jobs are the table's own sweep
(``resireg-eval sweep=table1`` / ``sweep=table2``: the paper's protocol, docs/protocol.md) cut
to that encoder, with the variants the paper reports for the row, run as one multirun into one
sweep folder, which ``resireg-report`` reads as well. The overrides given (``model_path=``,
``paths.data_dir=``, ``dataset.path=``...) go to every job.

Before any job starts, every job's config is composed and checked for what this machine lacks
(:func:`preflight`): a dataset that is not there (the dataset table's source check: its
folder, its scenes, its label map) and a model (``model_path``'s export, the encoder's
packages) refuse the command, naming what to download and the config key to set. Then the
jobs run, and each cell the paper reports is printed with the user's figure (x100, as the
paper prints it), the paper's and the gap, followed by the protocol settings the jobs ran
with that differ from the paper's (:func:`resireg_train.report.paper.protocol_differences`,
as ``resireg-report``'s paper columns list them).
"""

from __future__ import annotations

import datetime as _dt
import math
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from resireg.errors import ResiregError
from resireg.specs.rules import is_num

__all__ = [
    "Cell",
    "ReproduceRefused",
    "cells",
    "main",
    "paper_problems",
    "preflight",
    "reproduce",
    "row_jobs",
]

#: The tables a row can come from.
TABLES = ("table1", "table2")


class ReproduceRefused(ResiregError, ValueError):
    """A paper row that cannot be reproduced here (the message names why and what to do)."""


@dataclass(frozen=True)
class RowJobs:
    """The jobs of one paper row: the table, the encoder, the datasets (one job each) and the
    variants (every job scores them all)."""

    table: str
    encoder: str
    datasets: tuple[str, ...]
    variants: tuple[str, ...]

    def overrides(self) -> list[str]:
        """The sweep's overrides: the table's sweep file cut to this row."""
        return [f"sweep={self.table}", f"encoder={self.encoder}",
                f"dataset={','.join(self.datasets)}",
                f"variants=[{','.join(self.variants)}]"]  # fmt: skip

    def job_overrides(self, dataset: str) -> list[str]:
        """One job's overrides (its dataset)."""
        return [f"sweep={self.table}", f"encoder={self.encoder}", f"dataset={dataset}",
                f"variants=[{','.join(self.variants)}]"]  # fmt: skip


def _paper(path: str | Path) -> dict[str, Any]:
    from resireg_train.report.paper import paper_results

    try:
        paper = paper_results(str(path))
    except OSError as err:
        raise ReproduceRefused(f"--paper {path}: cannot be read ({err.strerror or err})") from None
    except Exception as err:  # not YAML (a YAML error's message spans lines: one line here)
        raise ReproduceRefused(f"--paper {path}: not a paper file ({' '.join(str(err).split())})"
                               ) from None  # fmt: skip
    if not isinstance(paper, dict):
        raise ReproduceRefused(f"--paper {path}: not a paper file (a YAML mapping)")
    if problems := paper_problems(paper):
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ReproduceRefused(f"--paper {path}: {problems[0]}{more}")
    return paper


def _kind(value: Any) -> str:
    return {dict: "a mapping", list: "a list", str: "a string", bool: "a boolean",
            type(None): "null"}.get(type(value), type(value).__name__)  # fmt: skip


def _figure(value: Any) -> bool:
    """A figure of the paper: a finite number (not a boolean), or null (not reported)."""
    return value is None or (is_num(value) and math.isfinite(value))


def paper_problems(paper: Mapping[str, Any]) -> list[str]:
    """Where the paper's figures file (``conf/paper/results.yaml``'s schema) holds what
    reproduce cannot read, one line each naming the key and what it holds: ``table1``'s
    ``datasets`` (a list of names) and ``rows`` (name -> dataset -> variant -> figure),
    ``table2``'s ``dataset`` and ``rows`` (name -> ``variant``, ``miou``, ``fmiou``) and
    ``protocol`` (table -> setting -> value). A YAML alias (``*anchor``) is read as what it
    stands for, so one put where a list or a figure belongs is named here."""
    problems: list[str] = []

    def expect(key: str, value: Any, ok: bool, what: str) -> bool:
        if not ok:
            problems.append(f"{key}: expected {what}, got {_kind(value)} {_short(value)}")
        return ok

    scalar = (str, int, float, bool, type(None))
    for table in TABLES:
        if table not in paper:
            continue
        block = paper[table]
        if not expect(table, block, isinstance(block, Mapping), "a mapping"):
            continue
        rows = block.get("rows")
        if not expect(f"{table}.rows", rows, isinstance(rows, Mapping) and all(
                isinstance(k, str) for k in rows), "a mapping of row names"):  # fmt: skip
            continue
        if table == "table1":
            datasets = block.get("datasets")
            expect(f"{table}.datasets", datasets, isinstance(datasets, list) and all(
                isinstance(d, str) for d in datasets), "a list of dataset names")  # fmt: skip
            datasets = datasets if isinstance(datasets, list) else []
        else:
            expect(f"{table}.dataset", block.get("dataset"), isinstance(block.get("dataset"), str),
                   "a dataset name")  # fmt: skip
        for name, row in rows.items():
            key = f"{table}.rows.{name}"
            if not expect(key, row, isinstance(row, Mapping), "a mapping"):
                continue
            if "params_m" in row:
                expect(f"{key}.params_m", row["params_m"], _figure(row["params_m"]), "a number")
            if table == "table2":
                expect(f"{key}.variant", row.get("variant"), isinstance(row.get("variant"), str),
                       "a variant name")  # fmt: skip
                for metric in ("miou", "fmiou"):
                    expect(f"{key}.{metric}", row.get(metric), _figure(row.get(metric)),
                           "a number or null")  # fmt: skip
                continue
            for dataset in (d for d in datasets if isinstance(d, str) and d in row):
                cells = row[dataset]
                if expect(f"{key}.{dataset}", cells, isinstance(cells, Mapping),
                          "a mapping of variant -> figure"):  # fmt: skip
                    for variant, value in cells.items():
                        expect(f"{key}.{dataset}.{variant}", value, _figure(value),
                               "a number or null")  # fmt: skip
    protocol = paper.get("protocol")
    if protocol is not None and expect("protocol", protocol, isinstance(protocol, Mapping),
                                       "a mapping of table -> settings"):  # fmt: skip
        for table, settings in protocol.items():
            if not expect(f"protocol.{table}", settings, isinstance(settings, Mapping),
                          "a mapping of setting -> value"):  # fmt: skip
                continue
            for name, value in settings.items():
                expect(f"protocol.{table}.{name}", value, isinstance(value, scalar) or (
                    isinstance(value, list) and all(isinstance(v, scalar) for v in value)),
                    "a value or a list of values")  # fmt: skip
    return problems


def _short(value: Any, width: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= width else f"{text[: width - 1]}…"


def row_jobs(spec: str, path: str | Path) -> RowJobs:
    """The jobs behind the row ``spec`` (``table1/<encoder>``) of the paper file ``path``."""
    from resireg.specs.variants import VARIANTS
    from resireg_train.config.paths import CONFIG_DIR

    table, _, encoder = spec.partition("/")
    if table not in TABLES or not encoder:
        raise ReproduceRefused(f"{spec!r}: expected <table>/<row> with a table of {TABLES}, "
                               "e.g. table1/radseg")  # fmt: skip
    block = _paper(path).get(table)
    rows = (block or {}).get("rows") if isinstance(block, Mapping) else None
    if not isinstance(rows, Mapping) or encoder not in rows:
        known = ", ".join(f"{table}/{r}" for r in rows or {}) or "none"
        raise ReproduceRefused(f"{spec!r}: no such row in {path} (its rows: {known})")
    if not (CONFIG_DIR / "encoder" / f"{encoder}.yaml").is_file():
        raise ReproduceRefused(f"{spec!r}: the row has no encoder config (conf/encoder/"
                               f"{encoder}.yaml), so nothing here can run it")  # fmt: skip
    row = rows[encoder]
    if table == "table1":
        datasets = tuple(d for d in block.get("datasets") or [] if isinstance(row.get(d), Mapping))
        named = {v for d in datasets for v in row[d]}
        variants = tuple(v for v in VARIANTS if v in named)
    else:
        datasets = (str(block.get("dataset")),)
        variants = (str(row.get("variant")),)
    if not datasets or not variants:
        raise ReproduceRefused(f"{spec!r}: {path} reports no figure of this row")
    return RowJobs(table, encoder, datasets, variants)


def preflight(jobs: RowJobs, given: Sequence[str]) -> list[str]:
    """What this machine lacks for the jobs (each job's config composed, as its
    ``resireg-eval`` would): a dataset's source (its kind's check), the model (``model_path``'s
    export, the encoder's packages) and the devices; one line each, naming what to download
    and the config key to set. ``[]`` when every job can start."""
    from omegaconf import OmegaConf

    from resireg.errors import ConfigError
    from resireg_train.config.machine import check_available, check_devices
    from resireg_train.data.specs import DATASET_SPECS
    from resireg_train.runs.rerun.plan import compose_job

    problems: list[str] = []
    for dataset in jobs.datasets:
        try:
            cfg = compose_job("eval", [*jobs.job_overrides(dataset), *given])
        except Exception as err:  # an override Hydra refuses
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ReproduceRefused(f"the overrides do not compose resireg-eval's config: "
                                   f"{first}") from None  # fmt: skip
        entry = OmegaConf.to_container(cfg.dataset, resolve=True)
        spec = DATASET_SPECS.find(str(entry.get("kind")))
        check = spec.load_check() if spec is not None else None
        if check is not None:
            try:
                check(entry, "dataset")
            except (OSError, ValueError, ResiregError) as err:
                problems.append(f"dataset={dataset}: {err} (download {spec.summary}; set "
                                "dataset.path, or paths.data_dir for the default layout)")  # fmt: skip
        for checker, what in ((check_available, "the model"), (check_devices, "the device")):
            try:
                checker(cfg)
            except ConfigError as err:
                lines = [line.strip() for line in str(err).splitlines()[1:] if line.strip()]
                for line in lines:
                    hint = ""
                    if line.startswith("model_path="):
                        hint = (" (download the export, or train one with resireg-train; set "
                                "model_path to its folder or hub repo id)")  # fmt: skip
                    problems.append(f"{what}: {line}{hint}")
    return list(dict.fromkeys(problems))  # each once, in order


@dataclass(frozen=True)
class Cell:
    """One cell of the row: the paper's figure, the user's (``None``: its job did not
    complete), in points."""

    dataset: str
    variant: str
    metric: str
    yours: float | None
    paper: float

    @property
    def gap(self) -> float | None:
        return None if self.yours is None else self.yours - self.paper


def cells(jobs: RowJobs, sweep: Path, paper: str | Path) -> tuple[list[Cell], list[Any]]:
    """Every cell the paper reports for the row, with the user's figure read from the jobs'
    records (x100), and the jobs (``resireg_train.report.jobs.Job``)."""
    from resireg_train.report.jobs import collect, dataset_of
    from resireg_train.report.paper import paper_cell
    from resireg_train.report.tables import metric_prefix

    found = collect(sweep)
    prefix = metric_prefix(jobs.table)
    metrics = ("miou",) if jobs.table == "table1" else ("miou", "fmiou")
    out = []
    for job in found:
        dataset = job.overrides.get("dataset", "?")  # the conf/dataset/ name: the paper's key
        final = job.results.get("final") or {} if job.status == "completed" else {}
        for variant in jobs.variants:
            for metric in metrics:
                theirs = paper_cell(jobs.table, jobs.encoder, dataset, variant, metric, paper)
                if theirs is None:
                    continue
                value = final.get(f"{prefix}{dataset_of(job)}/{metric}_{variant}")
                yours = 100 * float(value) if isinstance(value, (int, float)) else None
                out.append(Cell(dataset, variant, metric, yours, theirs))
    return out, found


def _text(value: float | None, signed: bool = False) -> str:
    if value is None:
        return "-"
    return f"{value:+.2f}" if signed else f"{value:.2f}"


def default_out(jobs: RowJobs) -> Path:
    stamp = _dt.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    return Path("outputs") / "reproduce" / f"{jobs.table}_{jobs.encoder}" / stamp


def reproduce(
    spec: str,
    given: Sequence[str] = (),
    paper: str | Path | None = None,
    out: str | Path | None = None,
    stream: TextIO = sys.stdout,
) -> list[Cell]:
    """Run the jobs of the paper row ``spec`` (module docstring) and print the row: the
    user's figure, the paper's and the gap per cell, then the protocol settings that differ.
    Raises :class:`ReproduceRefused` before any job starts when something is missing."""
    from tabulate import tabulate

    from resireg.specs.metrics import SCORE_SPECS
    from resireg_train.report.paper import PAPER_FILE, protocol_differences
    from resireg_train.runs.rerun.plan import hydra_value

    path = Path(paper) if paper else PAPER_FILE
    jobs = row_jobs(spec, path)
    problems = preflight(jobs, given)
    if problems:
        raise ReproduceRefused(
            f"{spec}: this machine lacks what its {len(jobs.datasets)} job(s) need; no job "
            "was started:\n  " + "\n  ".join(problems)
        )
    sweep = (Path(out) if out else default_out(jobs)).resolve()
    if sweep.exists() and any(sweep.iterdir()):
        raise ReproduceRefused(f"--out {sweep}: not empty; give the jobs a new folder")
    stream.write(f"reproduce {spec} ({len(jobs.datasets)} job(s), paper: {path}) into {sweep}\n")
    stream.flush()
    command = [sys.executable, "-m", "resireg_train.cli.eval", *jobs.overrides(), *given,
               f"hydra.sweep.dir={hydra_value(str(sweep))}"]  # fmt: skip
    code = subprocess.run(command, check=False).returncode
    found_cells, found_jobs = cells(jobs, sweep, path)
    rows = [[f"{c.dataset} {c.variant}" + ("" if c.metric == "miou" else f" {c.metric}"),
             _text(c.yours), _text(c.paper), _text(c.gap, signed=True)]
            for c in found_cells]  # fmt: skip
    label = SCORE_SPECS["miou"].label
    stream.write(f"\n{spec}: {label} x100 (yours: {sweep})\n")
    stream.write(tabulate(rows, headers=["cell", "yours", "paper", "gap"],
                          disable_numparse=True) + "\n")  # fmt: skip
    for job in found_jobs:
        if job.status != "completed":
            stream.write(f"job {job.number} ({job.path.name}): {job.status}: {job.error}\n")
    differ = protocol_differences(found_jobs, jobs.table, path)
    head = "protocol settings that differ from the paper's:"
    lines = [f"  {line}" for line in differ] or ["  none (of the settings it states)"]
    stream.write("\n".join([head, *lines]) + "\n")
    if code != 0 and all(j.status == "completed" for j in found_jobs):
        stream.write(f"resireg-eval exited with status {code}\n")
    return found_cells


def main(args: Any) -> int:
    """``resireg-runs reproduce``'s parsed arguments run (:func:`reproduce`); the exit status:
    0 when every job completed, else 1."""
    found = reproduce(args.row, args.overrides, args.paper, args.out)
    return 0 if found and all(c.yours is not None for c in found) else 1
