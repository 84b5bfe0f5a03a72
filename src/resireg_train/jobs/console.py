"""What a job shows on the console and in its log files: every URL's password masked (the
streams and the log handlers), an error as one line (``module.Type: message``), and which errors
are the whole report (their message says what to do: no traceback on the console).

How a failure is reported (docs/runs.md#run-records-and-faults): ``results.json`` gets the
status and the one-line error, the run's log file (``train.log`` / ``eval.log``) the error with
its traceback, and the console either Hydra's traceback (an unexpected crash) or, for an error
whose message says everything (a bad config value, a refused resume, a file that cannot be
written, an unavailable download, a dataset of which nothing could be scored), that message
alone.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import traceback
from collections.abc import Iterator
from typing import Any

from resireg.errors import ConfigError, IntegrityError, WriteError
from resireg.secrets import SecretFilter, mask_text
from resireg_train.jobs.run_folder import RunFolderBusy

__all__ = ["error_text", "mask_log_handlers", "masked_console", "reported_types", "to_log_files"]

log = logging.getLogger(__name__)


def error_text(exc: BaseException) -> str:
    """``module.Type: message`` of an exception and its notes, one per line (the config path
    of a library error: ``config: encoder``; what ``results.json`` records), every URL's
    password masked."""
    text = "".join(traceback.format_exception_only(type(exc), exc)).strip()
    if sys.version_info < (3, 11):  # from 3.11 on, traceback prints the notes itself
        text = "\n".join([text, *map(str, getattr(exc, "__notes__", None) or ())])
    return mask_text(text)


def to_log_files(message: str, exc: BaseException | None) -> None:
    """Write ``message`` to this process's log files only (Hydra's ``<output dir>/<job
    name>.log``; the console gets the error from Hydra, once), with ``exc``'s traceback
    unless its message is the whole report (a config error)."""
    trace = None
    if exc is not None and not isinstance(exc, reported_types()):
        trace = (type(exc), exc, exc.__traceback__)
    record = logging.LogRecord(log.name, logging.ERROR, __file__, 0, message, None, trace)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)  # (a handler that cannot write reports it on stderr)



def reported_types() -> tuple[type[BaseException], ...]:
    """The errors whose message is the whole report (see the module docstring). The classes
    of modules not loaded yet cannot have been raised, so nothing heavy is imported here."""
    types: list[type[BaseException]] = [ConfigError, WriteError, FileExistsError, RunFolderBusy,
                                        IntegrityError]  # fmt: skip
    for module, name in (
        ("resireg_train.record.trackers.base", "TrackerUnreachable"),
        ("resireg_train.training.checkpoints", "CheckpointError"),
        ("resireg_train.evaluation.base", "NothingScoredError"),
        ("resireg_train.search.ranks", "TrialRankFailed"),
        ("resireg.models.hub", "WeightsUnavailableError"),
        ("resireg.models.vlm.registry", "RegistryError"),
    ):
        cls = getattr(sys.modules.get(module), name, None)
        if cls is not None:
            types.append(cls)
    return tuple(types)



class _MaskedStream:
    """``sys.stdout`` / ``sys.stderr`` with every URL's password masked in what is written
    through it (Hydra prints a failed job's overrides, libraries print their server's URL);
    everything else is the stream's own."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        self._stream.write(mask_text(text) if isinstance(text, str) else text)
        return len(text)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


@contextlib.contextmanager
def masked_console() -> Iterator[None]:
    """Within: ``sys.stdout`` and ``sys.stderr`` mask URL passwords (:class:`_MaskedStream`)."""
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _MaskedStream(sys.stdout), _MaskedStream(sys.stderr)
    try:
        yield
    finally:
        sys.stdout, sys.stderr = saved


def mask_log_handlers() -> None:
    """Give every handler of the root logger (Hydra's console and the run's log file) the
    filter that masks URL passwords (:class:`~resireg.secrets.SecretFilter`),
    once."""
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, SecretFilter) for f in handler.filters):
            handler.addFilter(SecretFilter())

