"""``resireg-runs gc FOLDER... --keep N --by METRIC [--dry-run]``: free the disk a sweep's
checkpoints take, keeping those of its best runs.

The runs under the folders (a multirun's or a search's sweep folder; several are ranked
together) are ranked by ``METRIC``: a run's best value when its record tracks one (training),
else its final value (``min`` for losses, ``max`` for scores, as
:func:`resireg_train.record.run_record.metric_mode` says; ``--mode`` for any other metric). The best
``N`` keep everything. Every other run loses its ``checkpoints/`` folder (what
``ckpt_path=last`` would resume from) and nothing else: its record (``results.json``,
``metrics.csv``, ``system.csv``, ``.hydra/``), its export and the export's model card stay. A
run without the metric (failed before it logged it) is outside the best N.

Never touched: a run whose record says ``running`` (from another host too; a run whose
process is gone on this host is ``died``, not running), and a run folder whose lock
(``.run.lock``, held by the job writing it: :class:`resireg_train.jobs.run_folder.RunFolderLock`)
another process holds. The lock is taken while its checkpoints are removed, so a job cannot
start resuming that folder halfway. A symbolic link is removed, never followed. ``--dry-run``
lists the same decisions and the bytes they would free, and removes nothing.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from resireg_train.record.run_record import metric_mode
from resireg_train.runs.index import Run, scan

try:  # POSIX; without it (Windows) no run is touched: its lock cannot be checked
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

__all__ = ["CHECKPOINTS", "Decision", "collect", "command", "folder_bytes", "human"]

#: The folder of a run's checkpoints (conf/callbacks/default.yaml's model_checkpoint.dirpath).
CHECKPOINTS = "checkpoints"
#: The run folder's lock (resireg_train.jobs.run_folder.LOCK_FILE; that module is a job's, above
#: runs/, so not imported here).
LOCK_FILE = ".run.lock"


@dataclass
class Decision:
    """What gc does with one run: ``keep`` (rank within the best N), ``remove`` (its
    checkpoints), ``skip`` (running or locked: ``why``), ``nothing`` (no checkpoints)."""

    run: Run
    action: str
    value: float | None
    rank: int | None
    bytes: int = 0
    why: str = ""
    done: bool = False


def folder_bytes(folder: Path) -> int:
    """The bytes of the files under ``folder`` (links counted as links, never followed)."""
    if folder.is_symlink() or not folder.is_dir():
        return folder.lstat().st_size if os.path.lexists(folder) else 0
    total = 0
    for root, _, names in os.walk(folder):  # os.walk does not follow links by default
        for name in names:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, name)).st_size
    return total


def human(size: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:.1f} {unit}" if unit != "B" else f"{int(size)} B"
        size /= 1024
    return f"{size:.1f} TiB"  # pragma: no cover


def _value(run: Run, metric: str) -> float | None:
    best = (run.results.get("best") or {}).get(metric)
    value = best.get("value") if isinstance(best, dict) else None
    if value is None:
        value = (run.results.get("final") or {}).get(metric)
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[str | None]:
    """Hold ``folder``'s run lock for the block; yields ``None``, or why it could not be had
    (another process holds it: its PID)."""
    if fcntl is None:  # pragma: no cover
        yield "run folders cannot be locked on this system"
        return
    path = folder / LOCK_FILE
    try:
        handle = open(path, "a+")
    except OSError as err:
        yield f"its lock file cannot be opened ({err.strerror or err})"
        return
    try:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            yield f"locked by PID {handle.read().strip() or 'unknown'}"
            return
        yield None
    finally:
        handle.close()  # drops the lock


def collect(
    folders: Iterable[str | os.PathLike],
    keep: int,
    metric: str,
    mode: str | None = None,
    dry_run: bool = False,
    bad: list[str] | None = None,
) -> list[Decision]:
    """Rank the runs under ``folders`` by ``metric`` and remove the checkpoints of those
    outside the best ``keep`` (module docstring); with ``dry_run`` only decide. Returns one
    :class:`Decision` per run, best first (runs without the metric last)."""
    if keep < 0:
        raise ValueError(f"--keep {keep}: expected 0 or more runs to keep")
    mode = mode or metric_mode(metric)
    if mode not in ("min", "max"):
        raise ValueError(f"--by {metric!r}: is a lower or a higher value better? give --mode "
                         "min or --mode max")  # fmt: skip
    runs = scan(folders, bad)
    if not runs:
        raise ValueError(f"no run under {[str(f) for f in folders]}")
    if not any(_value(r, metric) is not None for r in runs):
        raise ValueError(f"--by {metric!r}: no run under {[str(f) for f in folders]} logged it")
    scored = sorted((r for r in runs if _value(r, metric) is not None),
                    key=lambda r: _value(r, metric), reverse=mode == "max")  # fmt: skip
    unscored = sorted((r for r in runs if _value(r, metric) is None), key=lambda r: str(r.path))
    decisions = []
    for rank, run in enumerate([*scored, *unscored], start=1):
        value = _value(run, metric)
        checkpoints = run.path / CHECKPOINTS
        size = folder_bytes(checkpoints)
        exists = os.path.lexists(checkpoints)
        if value is not None and rank <= keep:
            decisions.append(Decision(run, "keep", value, rank, size))
        elif run.may_be_running:  # running, or a heartbeat that cannot tell
            decisions.append(Decision(run, "skip", value, rank, size, run.status))
        elif not exists:
            decisions.append(Decision(run, "nothing", value, rank, 0, "no checkpoints"))
        else:
            decisions.append(Decision(run, "remove", value, rank, size))
    for decision in decisions:
        if decision.action != "remove":
            continue
        with _locked(decision.run.path) as why:
            if why is not None:
                decision.action, decision.why = "skip", why
                continue
            if dry_run:
                continue
            target = decision.run.path / CHECKPOINTS
            if target.is_symlink() or not target.is_dir():
                target.unlink()
            else:
                shutil.rmtree(target)
            decision.done = True
    return decisions


def command(args: Any) -> None:
    """``resireg-runs gc`` (module docstring): one line per run, then what was (or would be)
    freed."""
    import sys

    from resireg.secrets import mask_text

    bad: list[str] = []
    decisions = collect(args.folders, args.keep, args.by, args.mode, args.dry_run, bad)
    for line in bad:
        sys.stderr.write(f"resireg-runs: skipped {mask_text(line)}\n")
    verb = {"keep": "keep", "remove": "would remove" if args.dry_run else "removed",
            "skip": "skip", "nothing": "nothing"}  # fmt: skip
    for d in decisions:
        value = "-" if d.value is None else f"{d.value:.6g}"
        detail = f"{CHECKPOINTS}/ {human(d.bytes)}" if d.action in ("keep", "remove") else d.why
        print(f"{verb[d.action]:<12} #{d.rank:<3} {args.by}={value:<10} [{d.run.status}] "
              f"{d.run.path} ({detail})")  # fmt: skip
    freed = [d for d in decisions if d.action == "remove"]
    total = human(sum(d.bytes for d in freed))
    if args.dry_run:
        print(f"would free {total} in {len(freed)} run(s) (--dry-run: nothing removed)")
    else:
        print(f"freed {total} in {len(freed)} run(s)")
