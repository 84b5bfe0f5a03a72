"""Files that prove their content: atomic writes (the one writer of every file the project
records: run records, checkpoints, caches, maps, exports), SHA-256 digests recorded when a folder is
written and verified when it is read, and reads that name the damaged file.

Saved maps (:meth:`resireg.mapping.SemanticMap.save`) and model exports
(:meth:`resireg.models.ResiregVLM.save_pretrained`) record ``{file name: sha256}`` of every
tensor file in their JSON record; their loaders call :func:`verify_digests` before any tensor
is read, so a flipped bit or an overwritten block is an :class:`IntegrityError` naming the file,
never a model or map that loads with wrong numbers. A file name read from such a record goes
through :func:`resolve_inside`, the one rule for a path that a file names: it stays inside the
record's folder. Only the Python standard library and
safetensors are used (``hashlib`` streams the file in 1 MiB chunks).
"""

from __future__ import annotations

import hashlib
import json
import os
import posixpath
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path, PurePosixPath, PureWindowsPath
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
    "resolve_inside",
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


def resolve_inside(folder: str | os.PathLike, name: object, field: str) -> Path:
    """``folder / name`` for a file name ``name`` that a record in ``folder`` holds (an export's
    ``config.json``, a map's ``map.json``, an ONNX manifest), refused unless it stays inside
    ``folder``: an :class:`IntegrityError` names ``field`` (where the record holds it, e.g.
    ``"<export>/config.json: frozen_weights"``) and the value when ``name`` is not a non-empty
    string, is absolute (POSIX, or a Windows drive or share), or climbs out through ``..``.

    The one rule for every path read from a file: a record names files of its own folder (or
    below it) only; an absolute path is accepted only where the user typed it (an argument,
    never a file). The check is on the name, not on the file system: symbolic links inside
    the folder are followed as the folder's owner made them (a Hugging Face snapshot is made of
    links into the cache's blobs), so its cost does not grow with the folder's depth.
    """
    if not isinstance(name, str) or not name or "\0" in name:
        raise IntegrityError(f"{field}={name!r}: expected the name of a file in {folder}")
    if PurePosixPath(name).is_absolute() or PureWindowsPath(name).anchor:
        raise IntegrityError(
            f"{field}={name!r}: an absolute path, refused (a record may name only files inside "
            f"its own folder, {folder})"
        )
    # a name that climbs out, e.g. "../x" or "a/../../x": ``normpath`` folds "a/.." by the
    # name (the rule is on names, see above); a backslash counts as a separator on every OS,
    # so a record is judged the same wherever it is read
    parts = PurePosixPath(posixpath.normpath(name.replace("\\", "/"))).parts
    if not parts or parts[0] in (".", ".."):
        raise IntegrityError(
            f"{field}={name!r}: leaves the folder, refused (a record may name only files inside "
            f"its own folder, {folder})"
        )
    return Path(folder).joinpath(*parts)


def verify_digests(
    folder: str | os.PathLike, recorded: Mapping[str, str], what: str, field: str | None = None
) -> None:
    """Check every file of ``recorded`` (``{name: sha256}``, as :func:`digests` returns) in
    ``folder``; an :class:`IntegrityError` names the first file that is missing or differs,
    and ``what`` (e.g. ``"saved map"``) says whose file it is. Every name is checked to stay
    inside ``folder`` (:func:`resolve_inside`) before any file is read; ``field`` says where
    the record holds them (default ``"<what> digests"``)."""
    folder = Path(folder)
    field = field or f"{what} digests"
    if not isinstance(recorded, Mapping):
        raise IntegrityError(f"{field}={recorded!r}: expected {{file name: sha256}}")
    paths = {name: resolve_inside(folder, name, field) for name in recorded}
    for name, expected in recorded.items():
        path = paths[name]
        if not path.is_file():
            raise IntegrityError(f"{path}: missing ({what} records it)")
        if not isinstance(expected, str):
            raise IntegrityError(f"{field}: {name}={expected!r}: expected a SHA-256 hex digest")
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
