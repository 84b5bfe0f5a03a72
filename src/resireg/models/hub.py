"""Fail fast, and say what to do, when pretrained weights are not reachable.

Without a network a hub request can stall for close to a minute (name look-ups are
retried) before it fails. Every loader in :mod:`resireg.models` calls
:func:`require_online` before it asks a hub for files it does not have cached, so an
offline user gets an immediate error that names the local alternative.
"""

from __future__ import annotations

import os
import socket
import threading

__all__ = ["WeightsUnavailableError", "check_hub_source", "require_online", "hf_cached"]

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
