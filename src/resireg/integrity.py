"""Files that prove their content: atomic writes (the one writer of every file the project
records: run records, checkpoints, caches, maps, exports), SHA-256 digests recorded when a folder is
written and verified when it is read, and reads that name the damaged file.

Saved maps (:meth:`resireg.mapping.SemanticMap.save`) and model exports
(:meth:`resireg.models.ResiregVLM.save_pretrained`) record ``{file name: sha256}`` of every
tensor file in their JSON record; their loaders call :func:`verify_digests` before any tensor
is read, so a flipped bit or an overwritten block is an :class:`IntegrityError` naming the file,
never a model or map that loads with wrong numbers. Only the Python standard library and
safetensors are used (``hashlib`` streams the file in 1 MiB chunks).
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from resireg.errors import IntegrityError, WriteError

__all__ = [
    "IntegrityError",
    "WriteError",
    "atomic_write",
    "digests",
    "file_mode",
    "load_safetensors",
    "read_json",
    "sha256_file",
    "verify_digests",
]

_CHUNK = 1 << 20


def sha256_file(path: str | os.PathLike) -> str:
    """SHA-256 hex digest of a file's bytes, streamed in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def digests(folder: str | os.PathLike, names: Iterable[str]) -> dict[str, str]:
    """``{name: sha256}`` of the files ``names`` in ``folder``."""
    folder = Path(folder)
    return {name: sha256_file(folder / name) for name in sorted(names)}


def verify_digests(folder: str | os.PathLike, recorded: Mapping[str, str], what: str) -> None:
    """Check every file of ``recorded`` (``{name: sha256}``, as :func:`digests` returns) in
    ``folder``; an :class:`IntegrityError` names the first file that is missing or differs,
    and ``what`` (e.g. ``"saved map"``) says whose file it is."""
    folder = Path(folder)
    for name, expected in recorded.items():
        path = folder / name
        if not path.is_file():
            raise IntegrityError(f"{path}: missing ({what} records it)")
        actual = sha256_file(path)
        if actual != expected:
            raise IntegrityError(
                f"{path}: SHA-256 {actual[:16]}... does not match the {expected[:16]}... "
                f"that the {what} recorded when it was written (the file was changed or damaged)"
            )


def read_json(path: str | os.PathLike, what: str) -> Any:
    """The JSON document in ``path``; a missing, unreadable or malformed (e.g. truncated) file
    is an :class:`IntegrityError` naming it, never a raw ``JSONDecodeError``."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as err:
        raise IntegrityError(f"{path}: missing ({what})") from err
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise IntegrityError(f"{path}: not a readable {what} ({err})") from err


def load_safetensors(path: str | os.PathLike, what: str, device: str = "cpu") -> dict[str, Any]:
    """``safetensors.torch.load_file`` with a truncated or malformed file reported as an
    :class:`IntegrityError` naming it (safetensors raises ``SafetensorError`` naming none)."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise IntegrityError(f"{path}: missing ({what})")
    try:
        return load_file(str(path), device=device)
    except (SafetensorError, OSError, ValueError) as err:
        raise IntegrityError(f"{path}: not a readable safetensors file ({what}): {err}") from err


def file_mode() -> int:
    """The mode a new regular file gets from this process's umask (``0o666 & ~umask``)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def atomic_write(
    path: str | os.PathLike,
    data: str | bytes | memoryview | Callable[[Path], None],
    what: str = "file",
    mode: int | None = None,
) -> Path:
    """Write ``path`` so that a reader, or a crash, never sees it half-written: the content goes
    to a temporary file beside it (same folder: ``os.replace`` is atomic only within one file
    system), is flushed to disk, gets its mode and replaces ``path`` in one rename.

    ``data``: text or bytes, or ``write(tmp)``, a function that writes the temporary file (a
    library's own writer: safetensors, ONNX). ``mode``: the file's permission bits; default
    the umask's (``0o666 & ~umask``, as ``open()`` gives; some writers, safetensors among them,
    create files 0600). On any failure (a full disk, Ctrl-C) the temporary file is removed and
    the old ``path``, if any, is left as it was; an ``OSError`` becomes a :class:`WriteError`
    (an ``OSError`` too, same ``errno``) saying what (``what``) was being written where."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        if callable(data):
            data(tmp)
        else:
            with open(tmp, "wb") as f:
                f.write(data.encode() if isinstance(data, str) else data)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, file_mode() if mode is None else mode)
        os.replace(tmp, path)
    except OSError as err:
        if isinstance(err, WriteError):
            raise
        failure = WriteError(f"could not write the {what} {path}: {err.strerror or err}")
        failure.errno = err.errno
        raise failure from err
    finally:
        tmp.unlink(missing_ok=True)
    return path
