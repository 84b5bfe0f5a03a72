"""Small file helpers shared by the data, evaluation, tracking and checkpoint code."""

from __future__ import annotations

import os
from pathlib import Path

from resireg.errors import ResiregError
from resireg.sources.frames import DECODE_ERRORS

__all__ = ["DECODE_ERRORS", "WriteError", "write_atomic"]


class WriteError(ResiregError, OSError):
    """A file could not be written (disk full, quota, permissions); one line naming it."""


def write_atomic(
    path: str | os.PathLike,
    data: str | bytes | memoryview,
    what: str = "file",
) -> Path:
    """Write ``data`` (text or bytes) to ``path`` through a temporary file in the same
    folder, flushed to disk, and one rename.

    A reader, or a crash, never sees a half-written file under the final name: if the write
    fails (a full disk) the temporary file is removed, the old ``path`` (if any) is left as
    it was, and a :class:`WriteError` says what was being written where.
    """
    path = Path(path)
    # Same folder: os.replace is atomic only within one file system.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OSError) and not isinstance(err, WriteError):
            failure = WriteError(f"could not write the {what} {path}: {err.strerror or err}")
            failure.errno = err.errno
            raise failure from err
        raise
    return path
