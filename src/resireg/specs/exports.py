"""Where a model comes from, decided without torch: the rule of
:meth:`resireg.models.ResiregVLM.from_pretrained` for its ``source`` (an export folder or a
Hugging Face repo id), shared with the config checks of ``resireg-eval`` and
``resireg-playground``, which run it before torch and the models load. (This was
``resireg.sources`` before that name became the map's frame sources.)"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["export_source_problem", "is_repo_id"]


def is_repo_id(text: str) -> bool:
    """Whether ``text`` has the form of a Hugging Face repo id ``owner/name`` (one ``/``, not a
    path that starts at ``/``, ``.`` or ``~``)."""
    return text.count("/") == 1 and not text.startswith(("/", ".", "~"))


def export_source_problem(source: str | os.PathLike) -> str | None:
    """Why ``source`` cannot be a ``ResiregVLM`` export (``None`` when it may be one): an
    existing folder must hold ``config.json``; anything else must be a repo id, looked up in
    the Hugging Face cache (then the hub) only when the model loads."""
    path, text = Path(source), os.fspath(source)
    if path.is_dir():
        if (path / "config.json").is_file():
            return None
        return f"{text!r} holds no config.json (not a ResiregVLM export)"
    if path.exists() or not is_repo_id(text):
        return f"{text!r} is not an export folder (and not a Hugging Face repo id 'owner/name')"
    return None
