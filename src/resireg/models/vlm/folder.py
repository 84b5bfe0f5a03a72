"""An export folder of :class:`~resireg.models.ResiregVLM` as a reader finds it: where it is (a
local folder, or a Hugging Face snapshot of a repo id) and its ``config.json``, verified.

Both the model (:meth:`ResiregVLM.from_pretrained`) and the Hub folder
(:func:`resireg.models.vlm.card.hub_folder`) read exports through this module, so neither
imports the other to do so (it was an import circle, hidden inside functions).
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from resireg.integrity import IntegrityError, read_json, resolve_inside, verify_digests
from resireg.models.hub import require_online
from resireg.specs.exports import is_repo_id

__all__ = ["EXPORT_FORMAT", "EXPORT_FILES", "EXPORT_WHAT", "export_dir", "frozen_sources",
           "read_config"]

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


#: The fields of an export's ``config.json`` that may name a file (or folder) of a frozen part's
#: weights: ``(part, key)``. ``backbone.weights`` may also be ``"hub"`` (timm's hub copy) or
#: null (random init, or the weights in ``frozen_weights``); ``text.weights`` an open_clip tag.
EXPORT_FILES = (("backbone", "weights"), ("text", "weights"), ("text", "tokenizer"))


def frozen_sources(
    directory: str | os.PathLike,
    cfg: Mapping[str, Any],
    external: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """``cfg`` (an export's ``config.json`` as :func:`read_config` read it) with every file its
    frozen parts name (:data:`EXPORT_FILES`) resolved inside the export folder ``directory``:
    the one rule for paths read from a file (:func:`~resireg.integrity.resolve_inside`) holds
    here as for ``frozen_weights`` and ``digests``. A file the config names must be covered by
    its ``digests`` too (a folder, ``text.tokenizer``, by the name alone). An absolute path, one
    that climbs out, or a file the digests do not cover is an
    :class:`~resireg.integrity.IntegrityError` naming the field and the value.

    ``external`` (``{part: {key: path}}``, e.g. ``{"backbone": {"weights": "/ckpt/eupe.pt"}}``)
    is what the caller passes as an argument: a file outside the export that replaces the
    field (it must exist); the caller records it (a run's provenance records it with its
    SHA-256). A text ``weights`` that is neither a path nor the name of a file of the export is
    an open_clip tag and is left as it is."""
    folder = Path(directory)
    cfg_file = folder / "config.json"
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in cfg.items()}
    given = {(part, key): value for part, keys in (external or {}).items()
             for key, value in (keys or {}).items() if value is not None}  # fmt: skip
    unknown = sorted(f"{p}.{k}" for p, k in given if (p, k) not in EXPORT_FILES)
    if unknown:
        raise ValueError(f"external: {unknown} are not files of an export's frozen parts "
                         f"(those are {[f'{p}.{k}' for p, k in EXPORT_FILES]})")  # fmt: skip
    recorded = cfg.get("digests") or {}
    for part, key in EXPORT_FILES:
        field = f"{cfg_file}: {part}.{key}"
        if (part, key) in given:
            path = Path(os.fspath(given[(part, key)])).expanduser()
            if not path.exists():
                raise FileNotFoundError(f"external {part}.{key}={str(path)!r} does not exist")
            out[part][key] = str(path.resolve())
            continue
        value = out[part].get(key)
        if value is None or (part, key) == ("backbone", "weights") and value == "hub":
            continue
        if not isinstance(value, str):
            raise IntegrityError(f"{field}={value!r}: expected a file name of {folder}")
        is_path = "/" in value or "\\" in value or os.path.isabs(value)
        if part == "text" and key == "weights" and not is_path and not (folder / value).is_file():
            continue  # an open_clip tag ("webli")
        try:
            path = resolve_inside(folder, value, field)
        except IntegrityError as err:
            raise IntegrityError(
                f"{err}; a weights file outside the export is taken only as an argument: "
                f"from_pretrained(..., external={{{part!r}: {{{key!r}: <path>}}}}) "
                f"(resireg-eval, resireg-map: encoder.external.{part}.{key}=<path>)"
            ) from None
        covered = value in recorded or os.path.normpath(value) in recorded
        if "digests" in cfg and path.is_file() and not covered:
            raise IntegrityError(f"{field}={value!r}: not covered by the export's digests "
                                 "(a file of the export that was never verified)")  # fmt: skip
        if not path.exists():
            raise IntegrityError(f"{field}={value!r}: {path} is missing")
        out[part][key] = str(path)
    return out


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
