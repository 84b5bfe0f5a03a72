"""The study's journal file (``<sweep>/optuna.journal``, Optuna's JournalFileBackend): opened
so that a crash's damage is repaired or named, never built upon.

Optuna appends one JSON line per operation under its link lock, in one write each. A process
killed mid-write leaves a last line without its newline: Optuna's reader skips it, but the
next append lands after it, merging both into a line that is not JSON, and every later open
fails with a bare ``JSONDecodeError`` (or, while it is the last line, silently drops it).

:func:`open_journal` therefore, under the journal's own lock (Optuna's
``JournalFileSymlinkLock``, so that no writer appends meanwhile):

- a torn last line is cut off (or, if it is a whole entry that lost only its newline, given
  it back), with a warning naming the journal: every complete entry, so every finished trial,
  is kept; a trial whose last entry was lost stays RUNNING and the search marks it failed
  (its worker is gone) and runs a new one in its place. The warning, on the console whatever
  the logging setup (:func:`_say`), names what the cut line held as far as its bytes tell
  (:func:`_lost`): the trial by its number, and whether it was the trial's result; a trial
  whose result was lost is marked so (:data:`ATTR_LOST`, the journal's path), and the search,
  failing it, says that its result was lost, not that its worker died mid-trial;
- a last complete line that is not a journal entry is refused, as Optuna would skip it;
- then Optuna replays the file; a damaged line inside makes that fail, and the error names the
  journal and the line (:class:`JournalError`).

Checking costs a read of the file's tail on every open; the whole file is scanned only to
name a damaged line (Optuna's reader reports neither the line nor a damaged last line).
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
from pathlib import Path
from typing import Any

from resireg.errors import DataError

__all__ = ["ATTR_LOST", "JournalError", "open_journal"]

log = logging.getLogger(__name__)

#: The system attribute of a trial whose result was in a journal line cut mid-write: the
#: journal's path.
ATTR_LOST = "resireg:lost_result"

#: Bytes read at a time when looking for the last newline from the end.
_CHUNK = 1 << 16


class JournalError(DataError):
    """A journal with a damaged line the search cannot replay; the message names the file and
    the line."""


def _entry(line: bytes) -> bool:
    """Whether ``line`` is a journal entry: a JSON object with Optuna's ``op_code``."""
    try:
        value = json.loads(line)
    except ValueError:  # JSONDecodeError, UnicodeDecodeError
        return False
    return isinstance(value, dict) and isinstance(value.get("op_code"), int)


def _last_lines(f: Any, size: int) -> tuple[int, bytes, int, bytes]:
    """(offset, bytes) of the text after the file's last newline (empty when it ends with
    one), and of the last complete line before it; read backwards from the end."""
    end, data = size, b""
    while True:
        start = max(0, end - _CHUNK)
        f.seek(start)
        data = f.read(end - start) + data
        end = start
        cut = data.rfind(b"\n")
        before = data.rfind(b"\n", 0, cut) if cut >= 0 else -1
        if before >= 0 or start == 0:
            tail_at = start + cut + 1
            line_at = start + before + 1
            return tail_at, data[cut + 1 :], line_at, data[before + 1 : cut + 1]


def _line_number(path: Path, offset: int) -> int:
    """The 1-based number of the line that starts at byte ``offset``."""
    with open(path, "rb") as f:
        return f.read(offset).count(b"\n") + 1


def _first_damaged_line(path: Path) -> int | None:
    with open(path, "rb") as f:
        for number, line in enumerate(f, start=1):
            if not _entry(line):
                return number
    return None


def _damaged(path: Path, number: int | None, why: str = "") -> JournalError:
    where = f"line {number} is not an Optuna journal entry" if number is not None else why
    return JournalError(
        f"{path}: {where}: the study cannot be read past it; restore the file from a copy, or "
        "remove that line and the trials it held"
    )


def _say(message: str) -> None:
    """``message`` as a warning of this module's logger and, when none of the handlers of the
    logger's chain writes to a console (a search's logging set up for its log file only), on
    stderr too: what a repair lost must be seen where the search was started."""
    enabled = log.isEnabledFor(logging.WARNING)
    log.warning("%s", message)
    logger: logging.Logger | None = log
    handlers: list[logging.Handler] = []
    while logger is not None:
        handlers += logger.handlers
        logger = logger.parent if logger.propagate else None
    console = not handlers or any(  # (no handler at all: logging's last resort, on stderr)
        isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)
        and h.level <= logging.WARNING for h in handlers)  # fmt: skip
    if not (enabled and console):
        sys.stderr.write(f"{message}\n")
        sys.stderr.flush()


#: Optuna's journal operations that concern one trial (``JournalOperation``), what each held.
_TRIAL_OPS = {
    5: "a parameter of {trial}",
    6: "{trial}'s result (its state and value), now lost: {trial} reads RUNNING until the "
       "search marks it failed",
    7: "a value {trial} reported",
    8: "an attribute of {trial}",
    9: "an attribute of {trial}",
}  # fmt: skip


def _field(tail: bytes, name: str, pattern: bytes = rb"(\d+)") -> bytes | None:
    found = re.search(rb'"' + name.encode() + rb'"\s*:\s*' + pattern, tail)
    return found.group(1) if found else None


def _owned(path: Path, worker: str) -> int | None:
    """The trial id the last complete entry of a worker whose id starts with ``worker`` names
    (a worker writes for one trial at a time), ``None`` if none does."""
    trial = None
    with open(path, "rb") as f:
        for line in f:
            try:
                entry = json.loads(line)
            except ValueError:
                continue
            if (isinstance(entry, dict) and str(entry.get("worker_id", "")).startswith(worker)
                    and isinstance(entry.get("trial_id"), int)):  # fmt: skip
                trial = entry["trial_id"]
    return trial


def _lost(storage: Any, path: Path, tail: bytes) -> tuple[str, int | None]:
    """What the cut-off ``tail`` of the journal ``path`` held, as far as its bytes tell: the
    trial (by its number, found by its ``trial_id``, else by its worker's last trial, else
    among the trials still RUNNING) and, by its operation code, what of it; ``""`` when it
    names no trial. Second: the id of the one trial whose result it held, else ``None``."""
    from optuna.trial import TrialState

    code = _field(tail, "op_code")
    op = int(code) if code is not None else None
    if op == 4:
        return ", which held a new trial's start (no trial had it yet)", None
    if op is not None and op not in _TRIAL_OPS:
        return "", None
    trial_id = _field(tail, "trial_id")
    worker = _field(tail, "worker_id", rb'"([^"]*)')
    if trial_id is None and worker:
        found = _owned(path, worker.decode("utf-8", "replace"))
        trial_id = None if found is None else str(found).encode()
    held = _TRIAL_OPS.get(op, "an entry of {trial}") if op is not None else "an entry of {trial}"
    try:
        if trial_id is not None:
            number = storage.get_trial(int(trial_id)).number
            return (", which held " + held.format(trial=f"trial {number}"),
                    int(trial_id) if op == 6 else None)  # fmt: skip
        running = sorted((t.number, t._trial_id) for study in storage.get_all_studies()
                         for t in storage.get_all_trials(study._study_id, deepcopy=False,
                                                         states=(TrialState.RUNNING,)))  # fmt: skip
    except Exception:  # (a trial id the study does not hold: the bytes tell no more)
        return "", None
    if not running:
        return "", None
    which = f"trial {running[0][0]}" if len(running) == 1 else (
        "one of trials " + ", ".join(str(number) for number, _ in running))  # fmt: skip
    return (", which held " + held.format(trial=which) + " (told from the trials still "
            "RUNNING: the cut came before the entry named its trial)",
            running[0][1] if op == 6 and len(running) == 1 else None)  # fmt: skip


def _repair(path: Path) -> bytes | None:
    """Under the journal's lock: cut a torn last line, refuse a damaged last complete one.
    Returns the bytes cut off (``None`` when nothing was)."""
    from optuna.storages.journal import JournalFileSymlinkLock

    lock = JournalFileSymlinkLock(str(path))
    lock.acquire()
    try:
        size = path.stat().st_size
        if size == 0:
            return None
        cut = None
        with open(path, "rb+") as f:
            tail_at, tail, line_at, line = _last_lines(f, size)
            if tail:
                if _entry(tail):  # a whole entry that lost only its newline
                    f.seek(size)
                    f.write(b"\n")
                else:
                    f.truncate(tail_at)
                    cut = tail
                f.flush()
                os.fsync(f.fileno())
                if cut is None:
                    _say(f"{path}: its last line was cut mid-write (a process stopped while "
                         "writing): completed with its newline; every complete entry is kept")  # fmt: skip
            if line and not _entry(line):
                raise _damaged(path, _line_number(path, line_at))
        return cut
    finally:
        lock.release()


def _needs_repair(path: Path) -> bool:
    """Cheap test outside the lock: the file does not end with a newline, or its last line is
    not an entry."""
    size = path.stat().st_size
    if size == 0:
        return False
    with open(path, "rb") as f:
        _, tail, _, line = _last_lines(f, size)
    return bool(tail) or (bool(line) and not _entry(line))


def open_journal(path: str | os.PathLike) -> Any:
    """Optuna's ``JournalStorage`` over the journal file ``path`` (created if missing; its
    default link lock, the one optuna-dashboard takes on the same file, atomic on NFS), after
    the repairs and checks of the module docstring. Raises :class:`JournalError`."""
    import optuna
    from optuna.storages.journal import JournalFileBackend

    path = Path(path)
    cut = None
    if path.is_file() and _needs_repair(path):
        try:
            cut = _repair(path)
        except PermissionError as err:  # a folder the reader may not write: read what is whole
            log.warning("%s: its last line is damaged and cannot be repaired here: %s", path, err)
    backend = JournalFileBackend(str(path))
    try:
        storage = optuna.storages.JournalStorage(backend)
    except (ValueError, KeyError, TypeError, AssertionError) as err:  # Optuna's replay
        why = f"Optuna cannot replay it ({type(err).__name__}: {err})"
        raise _damaged(path, _first_damaged_line(path), why) from None
    if cut is not None:
        held, result_of = _lost(storage, path, cut)
        _say(f"{path}: its last line was cut mid-write (a process stopped while writing): "
             f"removed ({len(cut)} bytes){held}; every complete entry is kept")  # fmt: skip
        if result_of is not None:  # so that failing it says why (resireg_train.search.trials)
            try:
                storage.set_trial_system_attr(result_of, ATTR_LOST, str(path))
            except Exception as err:  # (finished meanwhile by another process: nothing to say)
                log.debug("trial id %d: %s", result_of, err)
    return storage
