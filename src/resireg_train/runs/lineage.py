"""``resireg-runs lineage RUN_OR_EXPORT``: the chain of a run or an export, oldest first
(:func:`lineage`): its data, the training runs it descends from, itself, its export and the
evaluations and maps that used that export.

Imported by ``resireg_train.cli.runs``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from resireg_train.record.provenance.inputs import EXPORT_PROVENANCE
from resireg_train.record.run_record import RunRecord
from resireg_train.runs.index import Run, find_run, read_run, scan

__all__ = ["lineage"]


def _same_path(a: Any, b: str) -> bool:
    try:
        return a is not None and Path(str(a)).expanduser().resolve() == Path(b).resolve()
    except OSError:
        return False


def lineage(spec: str, roots: Iterable[str | os.PathLike]) -> list[str]:
    """The chain of a run or an export, oldest first: its data, the training runs it descends
    from (``model.init_from``'s run, an export's training run), itself, its export and the
    evaluations and maps under ``roots`` that used that export. One line each."""
    roots = list(roots)
    path = Path(spec).expanduser()
    if (path / EXPORT_PROVENANCE).is_file() or (path / "config.json").is_file() and not (
            RunRecord.exists(path)):  # fmt: skip
        run = read_run(path.parent) if RunRecord.exists(path.parent) else None
        export = path.resolve()
    else:
        run = find_run(spec, roots)
        export = Path(run.results["export"]).resolve() if run.results.get("export") else None
    chain: list[str] = []
    seen: set[Path] = set()

    def ancestors(r: Run) -> None:
        if r.path.resolve() in seen:
            return
        seen.add(r.path.resolve())
        models = r.provenance.get("models") or {}
        parent_ckpt = (models.get("init_from") or {}).get("path")
        parent_export = (models.get("export") or {}).get("path")
        if parent_ckpt:
            folder = Path(parent_ckpt).parent.parent  # <run>/checkpoints/<file>.ckpt
            if RunRecord.exists(folder):
                ancestors(read_run(folder))
            sha = (models.get("init_from") or {}).get("sha256")
            chain.append(f"checkpoint {parent_ckpt} (sha256 {str(sha)[:12]})")
        elif parent_export and RunRecord.exists(Path(parent_export).parent):
            folder = Path(parent_export).parent
            ancestors(read_run(folder))
            chain.append(f"export {parent_export}")
        else:
            for key, data in (r.provenance.get("data") or {}).items():
                chain.append(f"data {key}: {_data_text(data)}")
        chain.append(_run_text(r))

    if run is not None:
        ancestors(run)
    if export is not None:
        chain.append(f"export {export}")
        for other in sorted(scan(roots), key=lambda r: r.start or ""):
            used = ((other.provenance.get("models") or {}).get("export") or {}).get("path")
            if _same_path(used, str(export)) and other.path.resolve() not in seen:
                chain.append(f"  used by {_run_text(other)}")
    return chain


def _run_text(run: Run) -> str:
    metric, value = run.headline
    score = f", {metric}={value:.4f}" if metric is not None and value is not None else ""
    commit = ((run.provenance.get("code") or {}).get("git") or {}).get("commit")
    code = f", commit {commit[:10]}" if commit else ""
    return f"{run.cli or 'run'} {run.run_id} [{run.status}] {run.path}{code}{score}"


def _data_text(data: Mapping[str, Any]) -> str:
    kind = data.get("kind")
    if kind == "hub":
        return f"hub {data.get('repo')} {data.get('config')}/{data.get('split')}@{data.get('revision')}"
    if kind == "local":
        return (f"local {data.get('path')} ({data.get('files')} files, fingerprint "
                f"{str(data.get('fingerprint'))[:12]})")  # fmt: skip
    return f"{kind} {data.get('settings')}"
