"""Checkpoints that a crash cannot truncate, and resuming that survives a corrupt one.

:class:`AtomicCheckpointIO` replaces Lightning's file writer. Lightning's own writes the
checkpoint into the system temp folder and *moves* it to the run folder; across file
systems a move is a copy, so a full disk leaves a truncated ``epochNNN.ckpt`` (and a temp
file) behind. Here the checkpoint is written next to its final name and renamed
(:func:`resireg.integrity.atomic_write`).

:func:`resolve_checkpoint` turns ``ckpt_path`` into the checkpoint to resume and checks it
can be read; an unreadable ``last.ckpt`` falls back to the newest readable checkpoint of
the run, and says so.

Every checkpoint a user passes (``ckpt_path=``, ``model.init_from=``) and every checkpoint
Lightning restores is read with ``torch.load(weights_only=True)`` (:func:`load_weights_only`):
a pickle may name any Python callable, so a crafted file would run code while it is read.
The project's own checkpoints hold only tensors and plain values (dicts, lists, numbers,
strings; the module's hyperparameters are plain dicts, the optimizer partial is left out),
checked by loading a smoke run's ``last.ckpt`` with ``weights_only=True``: no global needs
allow-listing with ``torch.serialization.add_safe_globals`` (:data:`SAFE_GLOBALS` is empty).
A checkpoint that needs one is refused, naming the global.
"""

from __future__ import annotations

import io
import logging
import os
import pickle
import re
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

from resireg.errors import ResiregError
from resireg.integrity import atomic_write

__all__ = [
    "SAFE_GLOBALS",
    "AtomicCheckpointIO",
    "CheckpointError",
    "UnsafeCheckpointError",
    "load_weights_only",
    "read_checkpoint",
    "resolve_checkpoint",
]

log = logging.getLogger(__name__)


class CheckpointError(ResiregError, RuntimeError):
    """No readable checkpoint to resume from; the message names the files and the options."""


class UnsafeCheckpointError(ResiregError, pickle.UnpicklingError):
    """A checkpoint holds Python objects that weights-only loading refuses (running their
    pickle could execute code); the message names the file and the refused global."""


#: Globals a checkpoint of this project may hold beyond torch's weights-only defaults, passed
#: to ``torch.serialization.safe_globals`` at every load. Empty: a smoke run's ``last.ckpt``
#: (Lightning's loops, callbacks, optimizer and LR-scheduler states, RNG states, the module's
#: hyperparameters) loads with ``weights_only=True`` as it is. Add a class here only if a
#: checkpoint of the project's own needs it, never a callable.
SAFE_GLOBALS: list[Any] = []


def load_weights_only(path: str | os.PathLike | io.IOBase, what: str, **kwargs: Any) -> Any:
    """``torch.load(path, weights_only=True)`` with :data:`SAFE_GLOBALS` allowed; a file
    whose pickle names any other global raises :class:`UnsafeCheckpointError` naming ``what``
    (e.g. ``"ckpt_path='x.ckpt'"``) and the global, before anything of it runs. ``kwargs``
    go to ``torch.load`` (``map_location``)."""
    kwargs.pop("weights_only", None)  # never anything else
    try:
        with torch.serialization.safe_globals(SAFE_GLOBALS):
            return torch.load(path, weights_only=True, **kwargs)
    except pickle.UnpicklingError as err:
        found = re.search(r"Unsupported global: GLOBAL (\S+)", str(err))
        named = f"global {found.group(1)}" if found else str(err).splitlines()[0]
        raise UnsafeCheckpointError(
            f"{what} holds Python objects that are not weights ({named}); checkpoints are "
            "read weights-only, since unpickling such objects can run code. Only load "
            "checkpoints of this project's own runs"
        ) from None


class AtomicCheckpointIO(TorchCheckpointIO):
    """The checkpoint written to a temporary file beside it, then renamed.

    ``torch.save`` serialises into memory first (as Lightning's own writer does): its zip
    writer would turn a failed file write into an internal "unexpected pos" error, where a
    write from memory fails with the system's reason (e.g. "No space left on device").
    """

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: str | os.PathLike, storage_options: Any = None
    ) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        atomic_write(path, buffer.getbuffer(), what="checkpoint")

    def load_checkpoint(
        self, path: str | os.PathLike, map_location: Any = None, weights_only: bool | None = None
    ) -> dict[str, Any]:
        """Lightning's restore (``trainer.fit(ckpt_path=...)``): weights-only whatever the
        caller asks (:func:`load_weights_only`)."""
        if not Path(path).is_file():
            raise FileNotFoundError(f"checkpoint file not found: {path}")
        location = map_location if map_location is not None else (lambda storage, loc: storage)
        return load_weights_only(path, f"checkpoint {str(path)!r}", map_location=location)


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any] | str:
    """The checkpoint at ``path`` (on the CPU, weights-only: :func:`load_weights_only`), or
    why it cannot be read (a refused global is named)."""
    try:
        checkpoint = load_weights_only(path, str(path), map_location="cpu")
    except UnsafeCheckpointError as err:
        return str(err)
    except Exception as err:  # noqa: BLE001 - zip, pickle and I/O errors all mean "unreadable"
        return f"{type(err).__name__}: {err}".splitlines()[0]
    if not isinstance(checkpoint, dict) or "global_step" not in checkpoint:
        return "not a Lightning training checkpoint (no global_step)"
    return checkpoint


def _candidates(folder: Path) -> list[Path]:
    """``last.ckpt`` first, then the other checkpoints of ``folder``, newest first."""
    others = sorted(
        (p for p in folder.glob("*.ckpt") if p.name != "last.ckpt"),
        key=lambda p: p.stat().st_mtime,
        reverse=True,
    )
    last = folder / "last.ckpt"
    return ([last] if last.is_file() else []) + others


def resolve_checkpoint(
    ckpt_path: str | None, output_dir: Path
) -> tuple[str, dict[str, Any]] | None:
    """The checkpoint to resume and its content, or ``None`` to start from scratch.

    Args:
        ckpt_path: ``None`` (start from scratch), ``"last"`` (``<output_dir>/checkpoints/
            last.ckpt``, or the newest readable checkpoint there when it is corrupt; from
            scratch when there is none) or a checkpoint file (must be readable).
        output_dir: the run's folder.
    """
    if ckpt_path is None:
        return None
    if ckpt_path != "last":
        if not Path(ckpt_path).is_file():
            raise FileNotFoundError(f"ckpt_path={ckpt_path!r}: no such checkpoint file")
        content = read_checkpoint(ckpt_path)
        if isinstance(content, str):
            raise CheckpointError(f"ckpt_path={ckpt_path!r} cannot be read ({content})")
        return ckpt_path, content
    folder = output_dir / "checkpoints"
    candidates = _candidates(folder) if folder.is_dir() else []
    if not candidates:
        log.warning("ckpt_path=last: no checkpoint in %s yet, starting from scratch", folder)
        return None
    problems = []
    for path in candidates:
        content = read_checkpoint(path)
        if isinstance(content, str):
            problems.append(f"{path.name} ({content})")
            continue
        if problems:
            log.warning(
                "ckpt_path=last: %s unreadable; resuming from %s (global step %d) instead",
                "; ".join(problems), path, content["global_step"],
            )  # fmt: skip
        return str(path), content
    raise CheckpointError(
        f"ckpt_path=last: no readable checkpoint in {folder}: {'; '.join(problems)}. Remove the "
        "unreadable files to start this run again from scratch, or set ckpt_path to a readable "
        "checkpoint (e.g. of another run)"
    )
