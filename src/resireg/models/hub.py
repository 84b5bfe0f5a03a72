"""Fail fast, and say what to do, when pretrained weights are not reachable.

Without a network a hub request can stall for close to a minute (name look-ups are
retried) before it fails. Every loader in :mod:`resireg.models` checks, before it asks a
hub for anything, that what it needs is cached or that the host serving it can be reached,
so an offline user gets an immediate error that names the local alternative (the config key
to set). The checks, one helper per kind of source (docs/design.md section 6):

- :func:`check_hub_source`: a ``torch.hub`` repo / source pair (a local clone, or GitHub),
- :func:`require_hub_repo`: a GitHub repo's code in torch's hub cache, or GitHub reachable
  (a hub model that itself ``torch.hub.load`` s another repo: RADSeg -> NVlabs/RADIO),
- :func:`require_hub_checkpoints`: files in torch's hub cache ``<hub>/checkpoints`` (what
  ``load_state_dict_from_url`` keeps), or their host reachable,
- :func:`require_hf_files`: a Hugging Face repo's file cached, or the hub reachable,
- :func:`require_open_clip_tag`: an open_clip pretrained tag's weights cached or reachable.

All of them end in :func:`require_online`.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Sequence

__all__ = [
    "WeightsUnavailableError",
    "check_hub_source",
    "hf_cached",
    "hub_checkpoint_path",
    "hub_repo_cached",
    "require_hf_files",
    "require_hub_checkpoints",
    "require_hub_repo",
    "require_online",
    "require_open_clip_tag",
]

_TRUE = {"1", "true", "yes", "on"}


class WeightsUnavailableError(RuntimeError):
    """Pretrained weights (or a tokenizer) could not be obtained; the message says how to pass them locally."""


def _resolves(host: str, timeout: float) -> bool:
    result: list[bool] = []

    def probe() -> None:
        try:
            with socket.create_connection((host, 443), timeout=timeout):
                result.append(True)
        except OSError:
            result.append(False)

    thread = threading.Thread(target=probe, daemon=True)
    thread.start()
    thread.join(timeout)
    return bool(result and result[0])


def hf_cached(repo_id: str, filename: str) -> bool:
    """Whether ``filename`` of Hugging Face repo ``repo_id`` is already in the local cache."""
    from huggingface_hub import try_to_load_from_cache

    path = try_to_load_from_cache(repo_id, filename)
    return isinstance(path, str) and os.path.exists(path)


def require_online(
    what: str, host: str, hint: str, *, hf: bool = True, timeout: float = 5.0
) -> None:
    """Raise :class:`WeightsUnavailableError` at once if ``host`` cannot be reached.

    Args:
        what: what was being fetched (for the message).
        host: the host that serves it (``huggingface.co``, ``github.com``).
        hint: how to pass the files locally instead.
        hf: honour ``HF_HUB_OFFLINE`` (Hugging Face hub downloads).
        timeout: seconds allowed for one connection attempt.
    """
    offline = hf and os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in _TRUE
    if offline:
        raise WeightsUnavailableError(f"{what} is not cached and HF_HUB_OFFLINE is set. {hint}")
    if not _resolves(host, timeout):
        raise WeightsUnavailableError(
            f"{what} needs {host}, which cannot be reached from this machine. {hint}"
        )


def check_hub_source(repo: str, source: str, what: str, hint: str, key: str = "model") -> None:
    """Validate a torch.hub ``repo`` / ``source`` pair before anything is loaded.

    ``source="local"`` needs ``repo`` to be a directory; ``source="github"`` needs
    github.com, else :class:`~resireg.models.hub.WeightsUnavailableError` at once with
    ``hint`` (which should name ``{key}.repo`` and ``{key}.source=local``).
    """
    if source not in ("github", "local"):
        raise ValueError(f"{key}.source={source!r}: expected 'github' or 'local'")
    if source == "local" and not os.path.isdir(repo):
        raise FileNotFoundError(f"{key}.repo={repo!r}: no such directory ({what} clone)")
    if source == "github":
        require_online(f"{what} ({repo})", "github.com", hint, hf=False)


def _hub_dir() -> str:
    import torch.hub  # here, so that importing this module stays light

    return torch.hub.get_dir()


def hub_checkpoint_path(filename: str) -> str:
    """Where ``torch.hub.load_state_dict_from_url`` keeps ``filename``:
    ``<torch.hub.get_dir()>/checkpoints/<filename>``."""
    return os.path.join(_hub_dir(), "checkpoints", filename)


def require_hub_checkpoints(files: Sequence[str], what: str, host: str, hint: str) -> None:
    """Raise :class:`WeightsUnavailableError` at once unless every one of ``files`` is in
    torch's hub cache (:func:`hub_checkpoint_path`) or ``host``, which serves them, can be
    reached. ``what`` names them in the message, ``hint`` says how to pass them locally."""
    missing = [f for f in files if not os.path.isfile(hub_checkpoint_path(f))]
    if missing:
        names = repr(missing[0]) if len(missing) == 1 else repr(missing)
        require_online(f"{what} {names}", host, hint, hf=False)


def hub_repo_cached(repo: str) -> str | None:
    """torch's hub cache directory of GitHub repo ``owner/name`` (branch ``main`` or
    ``master``: ``<hub>/owner_name_main``), or ``None``; ``torch.hub.load(repo, ...)`` uses
    it when GitHub is unreachable."""
    owner, name = repo.split("/", 1)
    for ref in ("main", "master"):
        path = os.path.join(_hub_dir(), f"{owner}_{name}_{ref}")
        if os.path.isdir(path):
            return path
    return None


def require_hub_repo(repo: str, what: str, hint: str) -> None:
    """Raise :class:`WeightsUnavailableError` at once when ``torch.hub.load(repo, ...)`` could
    get ``repo``'s code neither from torch's hub cache (:func:`hub_repo_cached`) nor GitHub."""
    if hub_repo_cached(repo) is None:
        require_online(what, "github.com", hint, hf=False)


def require_hf_files(repo: str, filenames: Sequence[str], what: str, hint: str) -> None:
    """Raise :class:`WeightsUnavailableError` at once unless one of ``filenames`` of Hugging
    Face repo ``repo`` is cached (:func:`hf_cached`) or the hub can be reached (and
    ``HF_HUB_OFFLINE`` is not set)."""
    if not any(hf_cached(repo, f) for f in filenames):
        require_online(what, "huggingface.co", hint)


#: open_clip's default file names in a Hugging Face repo (``open_clip.pretrained``).
_OPEN_CLIP_FILES = ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")


def require_open_clip_tag(model_name: str, tag: str, key: str, hint: str) -> None:
    """The weights of open_clip pretrained tag ``tag`` of ``model_name``: cached, or their
    host reachable, else :class:`WeightsUnavailableError` at once with ``hint``. A tag open_clip
    does not know is a ``ValueError`` naming ``key`` (e.g. ``model.weights``).

    Follows open_clip's own resolution (``open_clip.pretrained.get_pretrained_cfg``, then
    ``download_pretrained``): a ``hf_hub`` entry ``org/model/`` (the default file names) or
    ``org/model/file`` is looked up in the Hugging Face cache; a ``url`` entry needs its host.
    """
    import open_clip
    from open_clip.pretrained import get_pretrained_cfg

    cfg = get_pretrained_cfg(model_name, tag)
    if not cfg:
        raise ValueError(
            f"{key}={tag!r} is neither an existing file nor an open_clip pretrained tag of "
            f"{model_name!r} (tags: {open_clip.list_pretrained_tags_by_model(model_name)})"
        )
    what = f"open_clip weights {model_name}/{tag}"
    if cfg.get("hf_hub"):
        repo, name = os.path.split(cfg["hf_hub"])  # 'org/model/' -> ('org/model', '')
        require_hf_files(repo, (name,) if name else _OPEN_CLIP_FILES, what, hint)
    elif cfg.get("url"):
        host = cfg["url"].split("://", 1)[-1].split("/", 1)[0]
        require_online(what, host, hint, hf=False)
