"""The OVSS field's table (``sweep=ovss8``): one row per encoder and variant (BB, Calib, Lite,
Full), one column per benchmark (VOC21, PC60, Object, VOC20, PC59, Stuff, City, ADE) and their
average, with the published peers' rows beneath (``conf/paper/ovss8.yaml``: the benchmarks, each
peer's figures with its source, tier and group, and the rows left out as unconfirmed), as
``ovss8.csv`` and ``ovss8.md`` with the protocol each job ran under.

A row's average is the mean of its eight cells, left empty unless all eight are there (a job that
did not complete leaves its cell empty and is listed under the table; a peer whose source prints
fewer benchmarks is marked by its ``benchmarks`` count). The Markdown keeps the peers that learn
a text projection (Talk2DINO, dino.txt) in a table of their own, apart from the training-free
ones beside your rows.

The data file is checked where the report reads it (:func:`peers`): a peer row with a figure
outside 0-100, a benchmark the table lacks, no source, no tier or no group is refused with one
line naming the file and the row (:class:`~resireg.errors.ConfigError`).
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from resireg.errors import ConfigError
from resireg.specs.variants import BASELINE, VARIANTS
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.report.jobs import METHOD_NAMES, Job, per_encoder

__all__ = ["GROUPS", "OVSS8_FILE", "TIERS", "benchmarks", "is_ovss8_sweep", "ovss8_section",
           "ovss8_table", "peer_rows", "peers", "unconfirmed", "write_ovss8_table"]  # fmt: skip

#: The data file: the eight benchmarks and the peers' published figures (read where the report
#: runs, so a test may point it at another file).
OVSS8_FILE = CONFIG_DIR / "paper" / "ovss8.yaml"
#: The average's column.
AVERAGE = "Avg"
PUBLISHED = "published, not rerun"
#: A peer's ``tier``: who printed its figures.
TIERS = {"primary": "the method's own authors", "peer": "another paper's quotation or re-run"}
#: A peer's ``group`` and the heading its rows go under (your rows sit with the training-free).
GROUPS = {"training-free": "training-free",
          "text projection": "learn a text projection on image-caption pairs"}  # fmt: skip
#: Your rows' group in the table.
OURS = "this run"
#: How far (points) a source's printed 8-benchmark average may be from its row's mean: each of
#: the nine printed figures is rounded to 0.05 at most.
AVERAGE_TOLERANCE = 0.1
_PEER_KEYS = {"method", "backbone", "variant", "group", "tier", "source", "miou", "printed_avg",
              "confirmed_by", "differs", "note"}  # fmt: skip
_SOURCE_KEYS = {"repository", "path", "commit", "branch", "document", "table", "row"}
_COMMIT = re.compile(r"[0-9a-f]{7,40}")


@functools.cache
def _read(path: str) -> dict[str, Any]:
    with open(path) as f:
        try:
            data = yaml.safe_load(f)
        except yaml.YAMLError as err:  # its message spans lines: the first names the place
            mark = getattr(err, "problem_mark", None)
            where = f" line {mark.line + 1}" if mark else ""
            raise ConfigError(f"{path}{where}: not YAML ({getattr(err, 'problem', err)})") from None
    if not isinstance(data, dict) or not isinstance(data.get("benchmarks"), dict):
        raise ConfigError(f"{path}: expected a mapping with benchmarks: and peers:")
    return data


def _data(path: str | Path | None = None) -> dict[str, Any]:
    return _read(str(path or OVSS8_FILE))


def benchmarks() -> dict[str, dict[str, str]]:
    """``{dataset name: {"label", "config"}}`` of the eight benchmarks, in the table's order."""
    return dict(_data()["benchmarks"])


def _text(value: Any) -> bool:
    return isinstance(value, str) and bool(value.strip())


def _source_errors(source: Any) -> list[str]:
    """What a peer's ``source`` lacks: a repository, path and commit, or a document and table;
    and in both the row."""
    if not isinstance(source, Mapping) or not source:
        return ["no source (repository + path + commit, or document + table, and the row)"]
    errors = [f"source.{k}: not a key of a source ({', '.join(sorted(_SOURCE_KEYS))})"
              for k in source if k not in _SOURCE_KEYS]  # fmt: skip
    paths = source.get("path")
    path_ok = _text(paths) or (isinstance(paths, list) and paths and all(map(_text, paths)))
    in_repository = _text(source.get("repository")) and path_ok and _text(source.get("commit"))
    in_document = _text(source.get("document")) and _text(source.get("table"))
    if not (in_repository or in_document):
        errors.append("source names neither repository + path + commit nor document + table")
    if source.get("commit") is not None and not _COMMIT.fullmatch(str(source["commit"])):
        errors.append(f"source.commit={source['commit']!r}: expected a git commit (7-40 hex)")
    if not _text(source.get("row")):
        errors.append("source.row: missing (the table row the figures are read from)")
    return errors


def _peer_errors(peer: Any, marks: Mapping[str, Any]) -> list[str]:
    """What is wrong with one peer row (empty: nothing)."""
    if not isinstance(peer, Mapping):
        return [f"expected a mapping, got {peer!r}"]
    errors = [f"{k}: not a key of a peer row ({', '.join(sorted(_PEER_KEYS))})"
              for k in peer if k not in _PEER_KEYS]  # fmt: skip
    errors += [f"{k}: missing" for k in ("method", "backbone") if not _text(peer.get(k))]
    if peer.get("group") not in GROUPS:
        errors.append(f"group={peer.get('group')!r}: expected one of {list(GROUPS)}")
    if peer.get("tier") not in TIERS:
        errors.append(f"tier={peer.get('tier')!r}: expected one of {list(TIERS)}")
    errors += _source_errors(peer.get("source"))
    figures = peer.get("miou")
    if not isinstance(figures, Mapping) or not figures:
        return [*errors, "miou: no figures ({benchmark: mIoU in points})"]
    for key, value in figures.items():
        if key not in marks:
            errors.append(f"miou.{key}: not a benchmark of the table ({', '.join(marks)})")
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            errors.append(f"miou.{key}={value!r}: not a number")
        elif not 0 <= value <= 100:
            errors.append(f"miou.{key}={value}: outside 0-100 (mIoU in points)")
    printed = peer.get("printed_avg")
    if printed is not None and not errors:
        if len(figures) != len(marks):
            errors.append(f"printed_avg={printed}: an average over the {len(marks)} benchmarks, "
                          f"but the row has {len(figures)}")  # fmt: skip
        elif isinstance(printed, bool) or not isinstance(printed, (int, float)):
            errors.append(f"printed_avg={printed!r}: not a number")
        else:
            mean = sum(figures.values()) / len(figures)
            if abs(mean - printed) > AVERAGE_TOLERANCE:
                errors.append(f"printed_avg={printed}: the row's figures average {mean:.3f} "
                              "(a figure misread?)")  # fmt: skip
    if peer.get("note") is not None and not _text(peer["note"]):
        errors.append(f"note={peer['note']!r}: expected text")
    for key in ("confirmed_by", "differs"):
        notes = peer.get(key)
        if notes is not None and not (isinstance(notes, list) and all(map(_text, notes))):
            errors.append(f"{key}: expected a list of sources (text)")
    return errors


def _row_name(i: int, peer: Any) -> str:
    if isinstance(peer, Mapping) and (peer.get("method") or peer.get("backbone")):
        return f"peers[{i}] ({peer.get('method')}, {peer.get('backbone')})"
    return f"peers[{i}]"


def peers(path: str | Path | None = None) -> list[dict[str, Any]]:
    """The data file's peer rows (``path``: another file than :data:`OVSS8_FILE`), each checked:
    a :class:`~resireg.errors.ConfigError` names the file, the first wrong row and what is
    wrong with it, on one line."""
    where = path or OVSS8_FILE
    data = _data(where)
    rows = data.get("peers")
    if not isinstance(rows, list):
        raise ConfigError(f"{where}: peers: expected a list of rows, got {rows!r}")
    marks = data["benchmarks"]
    for i, peer in enumerate(rows):
        errors = _peer_errors(peer, marks)
        if errors:
            raise ConfigError(f"{where}: {_row_name(i, peer)}: {'; '.join(errors)}")
    return rows


def unconfirmed(path: str | Path | None = None) -> list[dict[str, str]]:
    """The rows the data file leaves out, each with its ``method``, ``backbone`` and the
    ``reason`` its source could not be confirmed."""
    where = path or OVSS8_FILE
    rows = _data(where).get("unconfirmed") or []
    for i, row in enumerate(rows):
        if not (isinstance(row, Mapping) and _text(row.get("method")) and _text(row.get("reason"))):
            raise ConfigError(f"{where}: unconfirmed[{i}]: expected a method and the reason, "
                              f"got {row!r}")  # fmt: skip
    return rows


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
    present = [v for v in values if isinstance(v, (int, float)) and not math.isnan(v)]
    row[AVERAGE] = sum(values) / len(values) if len(present) == len(values) else math.nan
    row["benchmarks"] = len(present)
    return row


def _where(source: Mapping[str, Any]) -> str:
    """A source as one line: ``repository path at commit (branch): row``, or ``document,
    table: row``."""
    if source.get("repository"):
        paths = source["path"] if isinstance(source["path"], list) else [source["path"]]
        branch = f" (branch {source['branch']})" if source.get("branch") else ""
        head = f"{source['repository']} {' + '.join(paths)} at {source['commit']}{branch}"
    else:
        head = f"{source['document']}, {source['table']}"
    return f"{head}: {source['row']}"


def peer_rows() -> list[dict[str, Any]]:
    """The data file's peers as table rows (points; a benchmark the source does not print is an
    empty cell), each with its group, tier and source (``published, not rerun: <where>``), and
    under ``notes`` the sources that print the same figures or others."""
    marks = benchmarks()
    rows = []
    for peer in peers():
        row = {"model": f"{peer['method']} ({peer['backbone']})", "variant": peer.get("variant"),
               "group": peer["group"], "tier": peer["tier"],
               "source": f"{PUBLISHED}: {_where(peer['source'])}",
               "notes": [*([f"note: {peer['note']}"] if peer.get("note") else []),
                         *(f"also printed by {s}" for s in peer.get("confirmed_by") or []),
                         *(f"differs: {s}" for s in peer.get("differs") or [])]}  # fmt: skip
        for name, value in peer["miou"].items():
            row[marks[name]["label"]] = float(value)
        rows.append(_with_average(row))
    return rows


def _table(jobs: list[Job]) -> pd.DataFrame:
    """:func:`ovss8_table` with the peers' ``notes`` (the Markdown lists them)."""
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
                                                    "group": OURS, "source": set()})  # fmt: skip
            row[marks[benchmark]["label"]] = 100 * float(value)
            row["source"].add(protocol)
    order = {v: i for i, v in enumerate(VARIANTS)}
    ours = sorted(rows.items(), key=lambda kv: (kv[0][0], order.get(kv[0][1], len(order)),
                                                kv[0][1]))  # fmt: skip
    body = []
    for _, row in ours:
        row["source"] = "this run, protocol " + ", ".join(sorted(row["source"]))
        body.append(_with_average(row))
    return pd.DataFrame([*body, *peer_rows()]).reindex(columns=[*_table_columns(), "notes"])


def _table_columns() -> list[str]:
    return ["model", "variant", *_columns(), AVERAGE, "benchmarks", "group", "tier", "source"]


def ovss8_table(jobs: list[Job]) -> pd.DataFrame:
    """Your rows (encoder x variant, in the variant table's order; mIoU x100; group ``this
    run``) then the peers' (the data file's order), each with ``benchmarks``: how many of the
    eight it has (a peer whose source prints fewer has no average), its ``group``
    (:data:`GROUPS`) and ``tier`` (:data:`TIERS`), and its ``source``."""
    return _table(jobs).reindex(columns=_table_columns())


def _missing(jobs: list[Job]) -> list[str]:
    """One line per benchmark without a completed job, and per job that did not complete."""
    marks = benchmarks()
    done = {_benchmark_of(j) for j in jobs if j.status == "completed"}
    lines = [f"- {b['label']} (`dataset={b['config']}`): no completed job"
             for n, b in marks.items() if n not in done]  # fmt: skip
    lines += [f"- job {j.number} ({j.path.name}): **{j.status}**" for j in jobs
              if j.status != "completed"]  # fmt: skip
    return lines


def _shown(frame: pd.DataFrame, sources: list[str], notes: list[list[str]]) -> pd.DataFrame:
    """The rows as the Markdown shows them: a peer's source by its number under the tables
    (appended to ``sources`` with its tier, its notes to ``notes``), a row with fewer than the
    eight benchmarks marked ``n of 8``."""
    shown = frame.drop(columns=["group", "notes"]).astype(object)
    total = len(benchmarks())
    for i, row in frame.iterrows():
        kind, sep, where = str(row["source"]).partition(": ")
        if sep and row["group"] != OURS:
            sources.append(f"({row['tier']}) {where}")
            notes.append(list(row["notes"]) if isinstance(row["notes"], list) else [])
            shown.loc[i, "source"] = f"{kind} [{len(sources)}]"
        count = int(row["benchmarks"])
        shown.loc[i, "benchmarks"] = str(count) if count == total else f"{count} of {total}"
    return shown


def write_ovss8_table(jobs: list[Job], out: Path) -> dict[str, Path]:
    """``ovss8.csv`` (:func:`ovss8_table`) and ``ovss8.md``: your rows beside the training-free
    peers, the peers that learn a text projection in a table of their own, the sources (with
    tier, and the sources that agree or differ), the rows left out as unconfirmed, what is
    missing and the protocol of every job. The data file is checked before anything is
    written."""
    from resireg_train.report.tables import markdown, protocol_lines

    full = _table(jobs)
    missing_rows = unconfirmed()
    table = full.reindex(columns=_table_columns())
    files = {"ovss8_csv": out / "ovss8.csv", "ovss8_md": out / "ovss8.md"}
    table.to_csv(files["ovss8_csv"], index=False)
    base = METHOD_NAMES[BASELINE]
    other = [
        j for j in jobs if (j.results.get("protocol") or {}).get("name") not in (None, "ovss8")
    ]
    sources: list[str] = []
    notes: list[list[str]] = []
    projection = full["group"] == "text projection"
    first = _shown(full[~projection], sources, notes)
    second = _shown(full[projection], sources, notes)
    tiers = "; ".join(f"{k}: {v}" for k, v in TIERS.items())
    lines = [
        "# The eight OVSS benchmarks (mIoU x100)",
        "",
        f"Your rows: each encoder with {base} and the post-hoc variants, scored by this sweep, "
        f"beside the training-free peers. The peers' rows are {PUBLISHED} "
        f"(conf/paper/ovss8.yaml), each with its tier ({tiers}) and its source, listed under "
        "the tables. Avg: the mean of the eight cells (empty unless all eight are there); "
        "benchmarks: how many of the eight a row has (`5 of 8`: its source prints five).",
        "",
        markdown(first, floatfmt=".2f"),
    ]
    if len(second):
        lines += ["", f"## Peers that {GROUPS['text projection']}", "",
                  "Zero-shot on these benchmarks, but not training-free: kept apart from the "
                  "rows above.", "", markdown(second, floatfmt=".2f")]  # fmt: skip
    lines += ["", "## Sources", ""]
    for n, (where, extra) in enumerate(zip(sources, notes, strict=True), 1):
        lines += [f"{n}. {where}", *(f"    - {note}" for note in extra)]
    if missing_rows:
        lines += ["", "## Not confirmed (left out of the tables)", ""]
        lines += [f"- {r['method']}" + (f" ({r['backbone']})" if r.get("backbone") else "")
                  + f": {r['reason']}" for r in missing_rows]  # fmt: skip
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
    """The report section ``ovss8`` (:mod:`resireg_train.report.specs`):
    :func:`write_ovss8_table` and the line of ``summary.md`` naming its table."""
    files = write_ovss8_table(jobs, out)
    return files, ["", f"The eight OVSS benchmarks, beside the published peers: "
                       f"`{files['ovss8_md'].name}`."]  # fmt: skip
