"""An export folder of :class:`~resireg.models.ResiregVLM` as a reader finds it: where it is (a
local folder, or a Hugging Face snapshot of a repo id) and its ``config.json``, verified.

Both the model (:meth:`ResiregVLM.from_pretrained`) and the Hub folder
(:func:`resireg.models.vlm.card.hub_folder`) read exports through this module, so neither
imports the other to do so (it was an import circle, hidden inside functions).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

from resireg.integrity import IntegrityError, read_json, resolve_inside, verify_digests
from resireg.models.hub import require_online
from resireg.specs.exports import is_repo_id

__all__ = ["EXPORT_FORMAT", "EXPORT_WHAT", "export_dir", "read_config"]

#: ``config.json``'s ``format``.
EXPORT_FORMAT = "resireg-vlm"
#: Whose files an :class:`~resireg.integrity.IntegrityError` names.
EXPORT_WHAT = "ResiregVLM export"


def read_config(directory: str | os.PathLike) -> dict[str, Any]:
    """An export's ``config.json``, with the SHA-256 of every tensor file it records verified
    (:func:`~resireg.integrity.verify_digests`); an export written before digests were
    recorded loads with a warning. A missing, truncated or altered file is an
    :class:`~resireg.integrity.IntegrityError` naming it; so is a file name in it
    (``digests``, ``frozen_weights``) that leaves the folder
    (:func:`~resireg.integrity.resolve_inside`), before any file is read."""
    path = Path(directory)
    cfg_file = path / "config.json"
    if not cfg_file.is_file():
        raise FileNotFoundError(f"{str(path)!r} holds no config.json (not a ResiregVLM export)")
    cfg = read_json(cfg_file, f"{EXPORT_WHAT} config")
    if not isinstance(cfg, dict) or cfg.get("format") != EXPORT_FORMAT:
        found = cfg.get("format") if isinstance(cfg, dict) else type(cfg).__name__
        raise IntegrityError(
            f"{str(cfg_file)!r} is not a {EXPORT_FORMAT} config (format={found!r})"
        )
    for key in ("backbone", "head", "text"):
        if not isinstance(cfg.get(key), dict):
            raise IntegrityError(
                f"{cfg_file}: {key}={cfg.get(key)!r}: expected the part's settings"
            )
    if "frozen_weights" in cfg:
        resolve_inside(path, cfg["frozen_weights"], f"{cfg_file}: frozen_weights")
    recorded = cfg.get("digests")
    if recorded is None:
        warnings.warn(
            f"{cfg_file}: this export records no file digests (written before they were "
            "recorded): its tensor files are loaded unverified; save_pretrained again to add them",
            stacklevel=3,
        )
    else:
        verify_digests(path, recorded, EXPORT_WHAT, f"{cfg_file}: digests")
    return cfg


def export_dir(source: str | os.PathLike) -> Path:
    """The local folder of an export: ``source`` itself, or a Hugging Face snapshot (a
    ``models:/`` source of MLflow's registry goes through :func:`local_export` of
    :mod:`resireg.models.vlm.model`, since the registry reads exports with this module).

    A source that is not an existing folder is a repo id only if it has the form
    ``owner/name`` and names no existing file; the local cache is tried first and only a
    cache miss (``LocalEntryNotFoundError``) leads to a download.
    """
    path = Path(source)
    if path.is_dir():
        return path
    text = os.fspath(source)
    if path.exists() or not is_repo_id(text):  # (resireg.specs.exports: the checks' rule too)
        raise FileNotFoundError(
            f"{text!r} is not an export folder (and not a Hugging Face repo id 'owner/name')"
        )
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import LocalEntryNotFoundError

    try:
        return Path(snapshot_download(text, local_files_only=True))
    except LocalEntryNotFoundError:
        require_online(
            f"ResiregVLM {text!r} (no such local folder; as a Hugging Face repo id it is not cached)",
            "huggingface.co",
            "Pass the export directory instead (resireg-eval: model_path=/path/to/export).",
        )
    return Path(snapshot_download(text))
