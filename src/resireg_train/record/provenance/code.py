"""The code that ran: the ``code`` part of a run's provenance (:func:`code_provenance`).

The package version and, when the code runs from a git checkout of the project, its commit,
branch and a dirty flag; untracked files by name, size and SHA-256 (never their content unless
``provenance.untracked_content`` opts in); tracked files' text changes (and the opted-in files)
saved as ``code.diff`` (mode 0600) in the run folder, at most ``provenance.diff_max_bytes``, so
``git apply code.diff`` on that commit gives the code that ran; what was left out named with its
size, SHA-256 and reason; each tracked file that differs from the commit by path and SHA-256 of
its content (``changes``) and one digest over them (``diff_sha256``), which ``resireg-runs
rerun`` compares whatever ``code.diff`` could hold. Outside a checkout (an installed wheel)
only the version is recorded; nothing fails.

Imported by :mod:`resireg_train.record.provenance.block`, which joins the parts.
"""

from __future__ import annotations

import fnmatch
import hashlib
import importlib.metadata as md
import os
import re
import stat
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg_train.record.settings import provenance_settings

__all__ = ["CODE_DIFF", "code_provenance"]


#: The uncommitted change of a dirty checkout, saved in the run folder.
CODE_DIFF = "code.diff"


def _git(root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip


def _checkout_root(package_dir: Path) -> Path | None:
    """The git checkout whose ``src/`` holds ``package_dir``, else ``None`` (an installed
    package, or a virtual environment that merely lives inside some other repository)."""
    try:
        top = _git(package_dir, "rev-parse", "--show-toplevel")
    except (OSError, subprocess.SubprocessError):
        return None  # no git on this machine
    if top.returncode != 0:
        return None
    root = Path(top.stdout.strip()).resolve()
    return root if (root / "src" / package_dir.name).resolve() == package_dir.resolve() else None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _binary(path: Path) -> bool:
    """git's own test: a NUL byte in the first 8000 bytes."""
    with open(path, "rb") as f:
        return b"\0" in f.read(8000)


def _identity(root: Path, name: str, hash_max: int) -> dict[str, Any]:
    """What a file of the checkout is, without its content: ``{"path", "size", "sha256"}``
    (``sha256`` null above ``hash_max`` bytes), ``{"path", "link"}`` for a symbolic link (its
    target as written, never followed: it may dangle), ``{"path", "error"}`` if unreadable."""
    path = root / name
    try:
        st = path.lstat()
        if stat.S_ISLNK(st.st_mode):
            return {"path": name, "link": os.readlink(path)}
        if not stat.S_ISREG(st.st_mode):
            return {"path": name, "kind": "not a regular file"}
        digest = _sha256(path) if st.st_size <= hash_max else None
        return {"path": name, "size": st.st_size, "sha256": digest}
    except OSError as err:
        return {"path": name, "error": err.strerror or str(err)}


def _tracked_changes(root: Path) -> list[tuple[str, bool, str]]:
    """``(path, binary, patch)`` per tracked file that differs from ``HEAD``: ``git diff HEAD``
    as text (a binary file's patch is git's one line), split at each file's ``diff --git``."""
    plain = ("-c", "core.quotepath=off", "diff", "HEAD", "--no-color", "--no-ext-diff",
             "--no-textconv")  # fmt: skip
    text = _git(root, *plain).stdout
    stats = _git(root, *plain, "--numstat", "-z").stdout.split("\0")
    entries: list[tuple[str, bool]] = []
    i = 0
    while i < len(stats) - 1:
        added, _, rest = stats[i].partition("\t")
        _, _, path = rest.partition("\t")
        if path:  # one path
            entries.append((path, added == "-"))
            i += 1
        else:  # a rename: "added\tdeleted\t", then the old and the new path
            entries.append((stats[i + 2], added == "-"))
            i += 3
    chunks = [c for c in re.split(r"(?m)^(?=diff --git )", text) if c]
    if len(chunks) != len(entries):  # not split as expected: one piece, never lost
        return [("(tracked changes)", False, text)] if text else []
    return [(path, binary, chunk) for (path, binary), chunk in zip(entries, chunks, strict=True)]


def _changes_digest(changes: list[dict[str, Any]]) -> str:
    """SHA-256 over the tracked changes (each file's path, size and content digest, sorted;
    a deleted file by its path): with the commit, it names the tracked code exactly. Content,
    not ``git diff``'s text: a binary change is one line there."""
    lines = sorted(f"{c['path']}\t{c.get('size')}\t{c.get('sha256')}\n" for c in changes)
    return hashlib.sha256("".join(lines).encode()).hexdigest()


def _write_private(path: Path, text: str) -> Path:
    """``path`` written atomically and created 0600 (it can hold uncommitted edits)."""
    from resireg.integrity import atomic_write

    def write(tmp: Path) -> None:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(text)

    return atomic_write(path, write, what="uncommitted change", mode=0o600)


def code_provenance(
    out: Path | None,
    package_dir: Path | None = None,
    settings: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """``{"version", "git": {...} | None}`` of the code that runs (``package_dir``: this
    package's folder; ``settings``: the ``provenance`` block, :func:`provenance_settings`).

    From a git checkout, ``git`` holds the commit, branch, a dirty flag and:

    - ``untracked``: every untracked file that git does not ignore, by name, size and SHA-256
      (a symbolic link by its target, never followed), never by content: the first
      ``untracked_max_files``, their count in ``untracked_files``;
    - ``diff``: ``code.diff`` (written 0600 into ``out``) when some change was inlined:
      tracked files' text changes, and the content of untracked files matching
      ``untracked_content`` (an explicit opt-in; never a binary file or one whose name looks
      secret, :func:`resireg.secrets.looks_secret`), at most ``diff_max_bytes`` in
      all, so ``git apply code.diff`` on the commit gives the code that ran;
    - ``left_out``: each change not inlined, by path, size, SHA-256 and reason (binary, a
      secret-looking name, over ``diff_max_bytes``), and ``diff_bytes``;
    - ``changes``: every tracked file that differs from the commit, by path, size and SHA-256
      of its content now (a deleted one by path and error), and ``diff_sha256``, one digest
      over them: what ``resireg-runs rerun`` compares.

    Nothing here fails a run: a git error is recorded as ``git.error``."""
    try:
        version = md.version("resireg")
    except md.PackageNotFoundError:
        import resireg

        version = resireg.__version__
    package_dir = package_dir or Path(__file__).resolve().parents[2]  # resireg_train/
    root = _checkout_root(package_dir)
    if root is None:
        return {"version": version, "git": None}
    try:
        return {"version": version, "git": _git_record(root, out, settings or
                                                       provenance_settings())}  # fmt: skip
    except Exception as err:  # provenance never fails a run: say what could not be read
        return {"version": version, "git": {"root": str(root),
                                            "error": f"{type(err).__name__}: {err}"}}  # fmt: skip


def _git_record(root: Path, out: Path | None, settings: Mapping[str, Any]) -> dict[str, Any]:
    from resireg.secrets import looks_secret

    cap = int(settings["diff_max_bytes"])
    hash_max = int(settings["hash_max_bytes"])
    patterns = [str(p) for p in settings.get("untracked_content") or []]
    commit = _git(root, "rev-parse", "HEAD").stdout.strip() or None
    branch = _git(root, "rev-parse", "--abbrev-ref", "HEAD").stdout.strip() or None
    tracked = _tracked_changes(root)
    names = [n for n in _git(root, "ls-files", "--others", "--exclude-standard", "-z")
             .stdout.split("\0") if n]  # fmt: skip
    listed = [_identity(root, n, hash_max) for n in names[: int(settings["untracked_max_files"])]]
    inlined: list[str] = []
    left_out: list[dict[str, Any]] = []
    used = 0

    def leave(name: str, reason: str) -> None:
        known = next((e for e in listed if e["path"] == name), None) or _identity(
            root, name, hash_max)  # fmt: skip
        left_out.append({**known, "reason": reason})

    def take(name: str, patch: str, binary: bool) -> None:
        nonlocal used
        size = len(patch.encode())
        if binary:
            leave(name, "binary")
        elif looks_secret(name):
            leave(name, "a secret-looking name: never inlined")
        elif used + size > cap:
            leave(name, f"over provenance.diff_max_bytes={cap}")
        else:
            inlined.append(patch)
            used += size

    for name, binary, patch in tracked:
        take(name, patch, binary)
    for entry in listed:
        name = entry["path"]
        if not any(fnmatch.fnmatch(name, p) for p in patterns) or "size" not in entry:
            continue  # not opted in, or a link / not a regular file: recorded by name only
        if looks_secret(name):
            leave(name, "a secret-looking name: never inlined")
            continue
        if _binary(root / name):
            leave(name, "binary")
            continue
        # its diff against /dev/null: `git apply` creates it (exit code 1: they differ)
        take(name, _git(root, "diff", "--no-index", "--", os.devnull, name).stdout, False)
    changes = [_identity(root, name, hash_max) for name, _, _ in tracked]
    record: dict[str, Any] = {"commit": commit, "branch": branch,
                              "dirty": bool(tracked or names), "diff": None,
                              "root": str(root), "changes": changes,
                              "diff_sha256": _changes_digest(changes),
                              "untracked": listed}  # fmt: skip
    if len(names) > len(listed):
        record["untracked_files"] = len(names)
    if left_out:
        record["left_out"] = left_out
    if inlined and out is not None:
        _write_private(Path(out) / CODE_DIFF, "".join(inlined))
        record["diff"] = CODE_DIFF
        record["diff_bytes"] = used
    return record
