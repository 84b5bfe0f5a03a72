"""A running job's heartbeat in its record, and what a reader makes of it.

While the run runs, a background thread of the job (:class:`Heartbeat`) rewrites the record's
``heartbeat`` (``{"time": <UTC>, "host", "interval", "stale_after"}``) every
``provenance.heartbeat_interval`` seconds, so a reader on another host (a run index on a
cluster's shared file system) can tell a running job from one that died:
:func:`heartbeat_stale`; :func:`heartbeat_doubt` says when a heartbeat cannot tell (a wrong
clock, a setting that never ages). Imported by the record
(:class:`~resireg_train.record.run_record.RunRecord` starts and stops the thread) and the run
index.
"""

from __future__ import annotations

import datetime as _dt
import math
import socket
import threading
from collections.abc import Mapping
from typing import Any

__all__ = ["HEARTBEAT", "Heartbeat", "heartbeat_doubt", "heartbeat_stale", "utc_now"]

#: The record's field a running job refreshes (:class:`Heartbeat`).
HEARTBEAT = "heartbeat"


def utc_now() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc)


def heartbeat_stale(
    record: Mapping[str, Any], stale_after: float, now: _dt.datetime | None = None
) -> bool | None:
    """Whether the running job of ``record`` has stopped beating: its ``heartbeat.time`` is
    more than ``heartbeat.stale_after`` seconds old (the job's own setting; ``stale_after``
    when it recorded none). ``None`` when the record has no heartbeat (a release before it).
    Compared with this machine's clock: hosts of one cluster agree to far less than the
    minutes a heartbeat may age."""
    beat = record.get(HEARTBEAT)
    if not isinstance(beat, Mapping) or not isinstance(beat.get("time"), str):
        return None
    try:
        when = _dt.datetime.fromisoformat(beat["time"])
    except ValueError:
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.timezone.utc)
    limit = beat.get("stale_after")
    limit = limit if isinstance(limit, (int, float)) and not isinstance(limit, bool) else None
    age = ((now or utc_now()) - when).total_seconds()
    return age > float(limit if limit is not None else stale_after)


def heartbeat_doubt(
    record: Mapping[str, Any], skew: float, now: _dt.datetime | None = None
) -> str | None:
    """Why the heartbeat of ``record`` cannot tell whether its job still runs, or ``None``:
    a ``heartbeat.time`` that is not an ISO 8601 time (it would never age) or is more than
    ``skew`` seconds ahead of this machine's clock (another host's clock is wrong: the beat
    would look fresh for as long), or a ``heartbeat.stale_after`` that is not a finite number
    > 0 (never stale)."""
    beat = record.get(HEARTBEAT)
    if not isinstance(beat, Mapping):
        return None
    limit = beat.get("stale_after")
    if limit is not None and not (isinstance(limit, (int, float)) and not isinstance(limit, bool)
                                  and math.isfinite(limit) and limit > 0):  # fmt: skip
        return f"heartbeat.stale_after={limit!r} is not a number of seconds > 0"
    try:
        when = _dt.datetime.fromisoformat(beat["time"])
    except (KeyError, TypeError, ValueError):
        return f"heartbeat.time={beat.get('time')!r} is not a time (ISO 8601)"
    if when.tzinfo is None:
        when = when.replace(tzinfo=_dt.timezone.utc)
    ahead = (when - (now or utc_now())).total_seconds()
    if ahead > skew:
        return (f"heartbeat.time={beat['time']} is {_span(ahead)} ahead of this machine's clock "
                f"(more than provenance.heartbeat_skew={skew:g} s)")  # fmt: skip
    return None


def _span(seconds: float) -> str:
    for unit, size in (("days", 86400), ("hours", 3600), ("minutes", 60)):
        if seconds >= 2 * size:
            return f"{seconds / size:.1f} {unit}"
    return f"{seconds:.0f} s"


class Heartbeat:
    """A daemon thread that writes ``heartbeat.time`` into a running job's record (``record``:
    its :class:`~resireg_train.record.run_record.RunRecord`) every ``interval`` seconds until
    :meth:`stop` (module docstring). A write that fails (a full
    disk, a file system gone) is skipped: the next one tries again, the run goes on."""

    def __init__(self, record: Any, interval: float, stale_after: float) -> None:
        self.record = record
        self.interval = float(interval)
        self.fields = {"host": socket.gethostname(), "interval": self.interval,
                       "stale_after": float(stale_after)}  # fmt: skip
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="resireg-heartbeat", daemon=True)

    def beat(self) -> dict[str, Any]:
        """The heartbeat field as of now."""
        return {"time": utc_now().isoformat(timespec="milliseconds"), **self.fields}

    def start(self) -> Heartbeat:
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.record.update(**{HEARTBEAT: self.beat()})
            except (OSError, ValueError):
                continue

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
