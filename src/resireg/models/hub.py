"""Fail fast, and say what to do, when pretrained weights are not reachable.

Without a network a hub request can stall for close to a minute (name look-ups are
retried) before it fails. Every loader in :mod:`resireg.models` checks, before it asks a
hub for anything, that what it needs is cached or that the host serving it can be reached,
so an offline user gets an immediate error that names the local alternative (the argument
to set). The checks, one helper per kind of source (docs/models.md#models-and-encoders):

- :func:`check_hub_source`: a ``torch.hub`` repo / source pair (a local clone, or GitHub),
- :func:`require_hub_repo`: a GitHub repo's code in torch's hub cache, or GitHub reachable
  (a hub model that itself ``torch.hub.load`` s another repo: RADSeg -> NVlabs/RADIO),
- :func:`require_hub_checkpoints`: files in torch's hub cache ``<hub>/checkpoints`` (what
  ``load_state_dict_from_url`` keeps), or their host reachable,
- :func:`require_hf_files`: a Hugging Face repo's file cached, or the hub reachable,
- :func:`require_open_clip_tag`: an open_clip pretrained tag's weights cached or reachable.

All of them end in :func:`require_online`.

**Pinned refs.** ``torch.hub.load("owner/name", ...)`` from GitHub follows the repository's
default branch, so its code could change under a run. Every hub encoder therefore takes a
``ref`` (a tag or a commit SHA; each conf/encoder/*.yaml and conf/model/teacher/radseg.yaml
names the commit its adapter was checked against) and loads ``"owner/name:<ref>"``
(:func:`hub_target`); torch.hub keeps that code in ``<hub>/owner_name_<ref>``
(:func:`hub_repo_cached`), which a later load reuses without the network. A local clone
(``source="local"``) ignores the ref. ``ref=None`` is torch.hub's own behaviour (the default
branch).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from resireg.errors import ConfigError, OfflineError
from resireg.network import reach

__all__ = [
    "PINNED_REFS",
    "WeightsUnavailableError",
    "check_hub_ref",
    "check_hub_source",
    "hf_cached",
    "hub_target",
    "hub_cache_dir",
    "hub_checkpoint_path",
    "hub_repo_cached",
    "require_hf_files",
    "require_hub_checkpoints",
    "require_hub_repo",
    "require_online",
    "require_open_clip_tag",
]

_TRUE = {"1", "true", "yes", "on"}

#: The commit of each hub repository the adapters were checked against (each repository's
#: default branch as read for the pin, with its date): the constructors' default ``ref``, and
#: the ``ref`` of conf/encoder/*.yaml and conf/model/teacher/radseg.yaml (a test holds them
#: equal). To move to a newer commit, read the adapter's module docstring against that
#: commit's code, change it here and in those files, and run the encoder tests.
PINNED_REFS = {
    "NVlabs/RADIO": "c0f37017930e9dda53f93424cf4bf39fc51f287e",  # main, 2026-05-29
    "RADSeg-OVSS/RADSeg": "05ec86fcc164ade687f8dce36f69e22278679803",  # main, 2026-01-27
    "facebookresearch/dinov2": "b8931f7bf91576930313be2c6d6af376033b35f0",  # main, 2025-08-14
}


class WeightsUnavailableError(OfflineError):
    """Pretrained weights (or a tokenizer) could not be obtained; the message says how to pass them locally."""


def _resolves(host: str, timeout: float) -> bool:
    """Whether ``host``'s HTTPS port accepts a connection within ``timeout`` seconds: the one
    connection check (:func:`resireg.network.reach`; the tests stand in for this one name)."""
    return reach(f"https://{host}", timeout) is None


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


def check_hub_ref(ref: object, name: str = "ref") -> str | None:
    """``ref`` itself when it is ``None`` or a git ref torch.hub can take after ``owner/name:``
    (a tag, a branch or a commit SHA: non-empty, no whitespace, no ``:``); else a
    :class:`~resireg.errors.ConfigError` naming the argument ``name`` (``radio_ref``)."""
    if ref is None:
        return None
    if not isinstance(ref, str) or not ref or any(c.isspace() or c == ":" for c in ref):
        raise ConfigError(
            f"{name}={ref!r}: expected a git tag or commit SHA of the hub repository (or null "
            "for its default branch)"
        )
    return ref


def hub_target(repo: str, source: str, ref: str | None) -> str:
    """The first argument of ``torch.hub.load``: ``"owner/name:<ref>"`` from GitHub with a
    ``ref``, else ``repo`` (a local clone ignores the ref). A ``repo`` that names a ref of its
    own as well as ``ref`` is an error naming both."""
    check_hub_ref(ref)
    if source != "github" or ref is None:
        return repo
    if ":" in repo:
        raise ConfigError(f"repo={repo!r} names a ref and ref={ref!r} another: keep one")
    return f"{repo}:{ref}"


def check_hub_source(repo: str, source: str, what: str, hint: str, ref: str | None = None) -> None:
    """Validate a torch.hub ``repo`` / ``source`` pair (and ``ref``) before anything is loaded.

    ``source="local"`` needs ``repo`` to be a directory; ``source="github"`` needs the repo's
    code at ``ref`` in torch's hub cache (:func:`hub_repo_cached`) or github.com, else
    :class:`~resireg.models.hub.WeightsUnavailableError` at once with ``hint`` (which should
    name ``repo=`` and ``source=local``).
    """
    if source not in ("github", "local"):
        raise ConfigError(f"source={source!r}: expected 'github' or 'local'")
    check_hub_ref(ref)
    if source == "local" and not os.path.isdir(repo):
        raise FileNotFoundError(f"repo={repo!r}: no such directory ({what} clone)")
    if source == "github":
        if ref is not None and hub_repo_cached(repo, ref) is not None:
            return  # torch.hub loads the pinned code from its cache, no network needed
        target = hub_target(repo, source, ref)
        require_online(f"{what} ({target})", "github.com", hint, hf=False)


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


def hub_cache_dir(repo: str, ref: str) -> str:
    """Where ``torch.hub.load("owner/name:<ref>", ...)`` keeps the code: ``<hub>/owner_name_<ref>``
    (a ``/`` of the ref as ``_``, as torch.hub names it)."""
    owner, name = repo.split("/", 1)
    return os.path.join(_hub_dir(), f"{owner}_{name}_{ref.replace('/', '_')}")


def hub_repo_cached(repo: str, ref: str | None = None) -> str | None:
    """torch's hub cache directory of GitHub repo ``owner/name`` at ``ref``
    (:func:`hub_cache_dir`; with ``ref=None`` branch ``main`` or ``master``:
    ``<hub>/owner_name_main``), or ``None``; ``torch.hub.load`` uses it without the network."""
    for candidate in (ref,) if ref is not None else ("main", "master"):
        path = hub_cache_dir(repo, candidate)
        if os.path.isdir(path):
            return path
    return None


def require_hub_repo(repo: str, what: str, hint: str, ref: str | None = None) -> None:
    """Raise :class:`WeightsUnavailableError` at once when ``torch.hub.load(repo, ...)`` (at
    ``ref``) could get ``repo``'s code neither from torch's hub cache (:func:`hub_repo_cached`)
    nor GitHub."""
    if hub_repo_cached(repo, ref) is None:
        require_online(what, "github.com", hint, hf=False)


def require_hf_files(repo: str, filenames: Sequence[str], what: str, hint: str) -> None:
    """Raise :class:`WeightsUnavailableError` at once unless one of ``filenames`` of Hugging
    Face repo ``repo`` is cached (:func:`hf_cached`) or the hub can be reached (and
    ``HF_HUB_OFFLINE`` is not set)."""
    if not any(hf_cached(repo, f) for f in filenames):
        require_online(what, "huggingface.co", hint)


#: open_clip's default file names in a Hugging Face repo (``open_clip.pretrained``).
_OPEN_CLIP_FILES = ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")


def require_open_clip_tag(model_name: str, tag: str, name: str, hint: str) -> None:
    """The weights of open_clip pretrained tag ``tag`` of ``model_name``: cached, or their
    host reachable, else :class:`WeightsUnavailableError` at once with ``hint``. A tag open_clip
    does not know is a ``ValueError`` naming ``name``, the caller's argument (``weights``).

    Follows open_clip's own resolution (``open_clip.pretrained.get_pretrained_cfg``, then
    ``download_pretrained``): a ``hf_hub`` entry ``org/model/`` (the default file names) or
    ``org/model/file`` is looked up in the Hugging Face cache; a ``url`` entry needs its host.
    """
    import open_clip
    from open_clip.pretrained import get_pretrained_cfg

    cfg = get_pretrained_cfg(model_name, tag)
    if not cfg:
        raise ConfigError(
            f"{name}={tag!r} is neither an existing file nor an open_clip pretrained tag of "
            f"{model_name!r} (tags: {open_clip.list_pretrained_tags_by_model(model_name)})"
        )
    what = f"open_clip weights {model_name}/{tag}"
    if cfg.get("hf_hub"):
        repo, file = os.path.split(cfg["hf_hub"])  # 'org/model/' -> ('org/model', '')
        require_hf_files(repo, (file,) if file else _OPEN_CLIP_FILES, what, hint)
    elif cfg.get("url"):
        host = cfg["url"].split("://", 1)[-1].split("/", 1)[0]
        require_online(what, host, hint, hf=False)
