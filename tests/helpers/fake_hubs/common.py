"""What the fake hub repositories share: :func:`write_repo` writes a repository's files;
:func:`offline_hub` points torch's hub cache at a private folder (with the checkpoints' names
and, optionally, the fake RADIO as ``NVlabs_RADIO_main``) and makes any network probe fail the
test (:func:`refuse_network`); :func:`build_offline` builds an encoder under it (a
module-scoped fixture's), and :func:`token_grid` lays patch tokens out as maps.
"""

from __future__ import annotations

import textwrap
from collections.abc import Iterable
from pathlib import Path
from urllib.error import URLError

import pytest
import torch

import resireg.models.hub as hub_module


def write_repo(folder: Path, files: dict[str, str]) -> Path:
    """``files`` (relative path -> source, dedented) written under ``folder``."""
    for rel, text in files.items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return folder


def refuse_network(host, timeout):
    """A stand-in for :func:`resireg.models.hub._resolves` that fails the test calling it."""
    raise AssertionError(f"a test probed the network ({host})")


def _offline_urlopen(*args, **kwargs):
    raise URLError("no network in tests")


def offline_hub(
    monkeypatch, hub_dir: Path, checkpoints: Iterable[str] = (), radio_code: bool = False
) -> Path:
    """torch's hub cache at ``hub_dir`` holding (empty files named like) ``checkpoints`` in
    ``checkpoints/`` and, with ``radio_code``, the fake NVlabs/RADIO as ``NVlabs_RADIO_main``
    and at the pinned commit (what RADSeg loads from GitHub); GitHub unreachable for torch.hub; any network probe of
    :mod:`resireg.models.hub` fails the test."""
    (hub_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    for name in checkpoints:
        (hub_dir / "checkpoints" / name).write_bytes(b"")  # cached (the fakes never read it)
    if radio_code:  # RADSeg's own load of RADIO, pinned (PINNED_REFS) or not (main)
        from helpers.fake_hubs.radio import radio_repo  # radio.py imports write_repo from here

        radio_repo(hub_dir / "NVlabs_RADIO_main")
        radio_repo(hub_dir / f"NVlabs_RADIO_{hub_module.PINNED_REFS['NVlabs/RADIO']}")
    monkeypatch.setattr(torch.hub, "_hub_dir", str(hub_dir))
    monkeypatch.setattr(torch.hub, "urlopen", _offline_urlopen)
    monkeypatch.setattr(hub_module, "_resolves", refuse_network)
    return hub_dir


def build_offline(tmp_path_factory, checkpoints: Iterable[str], build, *args, **kwargs):
    """``build(*args, **kwargs)`` under :func:`offline_hub` (a fresh hub cache holding
    ``checkpoints``), seeded with ``torch.manual_seed(0)`` (the fakes draw their weights from
    torch's global generator); the patches are undone after, so a module-scoped fixture can
    keep the encoder."""
    with pytest.MonkeyPatch.context() as mp:
        offline_hub(mp, tmp_path_factory.mktemp("hub"), checkpoints)
        torch.manual_seed(0)
        return build(*args, **kwargs)


def token_grid(tokens: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[B, N, D]`` patch tokens of a ``size`` grid -> ``[B, D, *size]`` (the tests' own
    reshape, not the adapters')."""
    return tokens.permute(0, 2, 1).unflatten(2, size)
