"""The report section ``table3d``: 3D semantic mapping on the field's benchmarks beyond ScanNet
(``sweep=replica3d``, ``sweep=tartanair3d``; any ``task=scannet3d`` sweep), the user's rows
beside RayFronts' published figures.

The published figures live in ``conf/paper/rayfronts3d.yaml``: each row names its source (the
document and table, or the repository, path and commit), its tier (``primary``: the method's
authors; ``peer``: another paper's quote) and its figures per benchmark (mIoU / f-mIoU in
points). A row is shown only when its source was opened and each figure confirmed; the rows
that could not be are listed in the file's ``unconfirmed`` block with the reason, and the
report names them ("not transcribed") instead of showing a number. A row with a figure outside
0-100, a benchmark the table lacks or no source is refused when the report reads the file,
naming the row.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from resireg_train.config.paths import CONFIG_DIR
from resireg_train.report.jobs import Job
from resireg_train.report.tables import is_mapping_sweep, mapping_table, markdown, protocol_lines

__all__ = [
    "PUBLISHED_FILE",
    "TIERS",
    "is_table3d",
    "published_figures",
    "table3d_section",
    "write_table3d",
]

#: RayFronts' published 3D figures (module docstring).
PUBLISHED_FILE = CONFIG_DIR / "paper" / "rayfronts3d.yaml"
#: Who reported a row: the method's own authors, or another paper quoting or re-running it.
TIERS = ("primary", "peer")
_METRICS = ("miou", "fmiou")


def published_figures(path: str | Path = PUBLISHED_FILE) -> dict[str, Any]:
    """The checked contents of the published-figures file: ``benchmarks`` (dataset names),
    ``rows`` (``{method: {source, tier, <benchmark>: {miou, fmiou}}}``) and ``unconfirmed``
    (``[{rows, reason}]``). A ValueError naming the file and the row on a row without a
    source, with an unknown tier, a benchmark the file's list lacks or a figure outside
    0-100."""
    path = Path(path)
    data = yaml.safe_load(path.read_text()) or {}
    benchmarks = list(data.get("benchmarks") or [])
    rows = data.get("rows") or {}
    for method, row in rows.items():
        where = f"{path.name}: row {method!r}"
        if not isinstance(row, dict) or not str(row.get("source") or "").strip():
            raise ValueError(f"{where}: no source (the document and table, or the repository, "
                             "path and commit, that was opened to confirm it)")  # fmt: skip
        if row.get("tier") not in TIERS:
            raise ValueError(f"{where}: tier={row.get('tier')!r}, expected one of {list(TIERS)}")
        for key, cell in row.items():
            if key in ("source", "tier", "excerpt", "note"):
                continue
            if key not in benchmarks:
                raise ValueError(f"{where}: benchmark {key!r} is not in the table's "
                                 f"benchmarks {benchmarks}")  # fmt: skip
            for metric, value in (cell or {}).items():
                ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                if metric not in _METRICS or not ok or not 0 <= value <= 100:
                    raise ValueError(f"{where}: {key}.{metric}={value!r}, expected mIoU / "
                                     "f-mIoU points in 0-100")  # fmt: skip
    return {"benchmarks": benchmarks, "rows": rows,
            "unconfirmed": list(data.get("unconfirmed") or []),
            "source": str(data.get("source") or "")}  # fmt: skip


def is_table3d(jobs: list[Job]) -> bool:
    """3D mapping jobs on a benchmark of the published-figures file other than ScanNet (whose
    table is ``table2``)."""
    if not is_mapping_sweep(jobs):
        return False
    benchmarks = set(published_figures()["benchmarks"]) - {"scannet"}
    _, datasets = _datasets(jobs)
    return bool(benchmarks & set(datasets))


def _datasets(jobs: list[Job]) -> tuple[pd.DataFrame, list[str]]:
    table = mapping_table(jobs)
    datasets = sorted({c.rsplit(" ", 1)[0] for c in table.columns if c.endswith(" status")})
    return table, datasets


def write_table3d(jobs: list[Job], out: Path,
                  path: str | Path = PUBLISHED_FILE) -> dict[str, Path]:  # fmt: skip
    """``table3d.csv`` (the user's rows: :func:`resireg_train.report.tables.mapping_table`) and
    ``table3d.md`` (those rows, then RayFronts' published rows of the same benchmarks with
    their source and tier, or the line naming what is not transcribed and why, then the
    protocol)."""
    published = published_figures(path)
    table, datasets = _datasets(jobs)
    files = {"table3d_csv": out / "table3d.csv", "table3d_md": out / "table3d.md"}
    table.to_csv(files["table3d_csv"], index=False)
    shown = table.drop(columns=["encoder", "variant", "third_party"], errors="ignore")
    names = " / ".join(datasets) or "no benchmark"
    lines = [f"# 3D semantic mapping on {names} (x100; mIoU / f-mIoU: mean over scenes, "
             "RayFronts' figure; pooled: one confusion over the voxels of all scenes)", "",
             markdown(shown, floatfmt=".1f"), "", "## Published figures (RayFronts' protocol)",
             ""]  # fmt: skip
    rows = []
    for method, row in published["rows"].items():
        cells = {f"{d} {m}": (row.get(d) or {}).get(m, math.nan)
                 for d in datasets for m in _METRICS}  # fmt: skip
        if any(not math.isnan(v) for v in cells.values()):
            rows.append({"method": method, **cells, "tier": row["tier"], "source": row["source"]})
    if rows:
        lines += [markdown(pd.DataFrame(rows), floatfmt=".1f"), ""]
    for item in published["unconfirmed"]:
        lines.append(f"- not transcribed: {item.get('rows')}: {item.get('reason')}")
    if not rows and not published["unconfirmed"]:
        lines.append(f"- no published figure of {names} in {Path(path).name}")
    lines += ["", *protocol_lines(jobs)]
    files["table3d_md"].write_text("\n".join(lines) + "\n")
    return files


def table3d_section(jobs: list[Job], out: Path) -> tuple[dict[str, Path], list[str]]:
    """The report section ``table3d``: :func:`write_table3d`."""
    files = write_table3d(jobs, out)
    return files, ["", f"3D mapping beyond ScanNet, beside RayFronts' figures: "
                       f"`{files['table3d_md'].name}`."]  # fmt: skip
