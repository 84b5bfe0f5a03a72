"""Every dense encoder ReSiReg is evaluated on, built by one factory from a config entry.

The kinds and their classes are one table, :data:`resireg.specs.encoders.ENCODER_SPECS`
(installed packages may add kinds through entry points, ``resireg.encoders``);
``build_encoder(kind, **kwargs)`` with ``kind``:

- ``resireg_vlm``: our 25M VLM from an export (``path``; :meth:`ResiregVLM.from_pretrained`),
- ``clip``: OpenAI CLIP through open_clip, the last block's value path (or, with
  ``dense_path="maskclip"``, the official MaskCLIP's tokens) as language tokens
  (:class:`ClipEncoder`),
- ``radio``: C-RADIO through ``torch.hub`` with a language adaptor (:class:`RadioEncoder`),
- ``radseg``: RADSeg through ``torch.hub``, one pass (:class:`RadSegEncoder`),
- ``dinotxt``: dino.txt through ``torch.hub`` (:class:`DinoTxtEncoder`),
- ``tips``: TIPSv2 from the release's ``.npz`` files (:class:`TipsEncoder`),
- ``otas``: OTAS, DINOv2 clusters pooling CLIP value-path tokens (:class:`OtasEncoder`); these two
  are the backbone-only references of the paper's Table 1.

What each gives ReSiReg (intermediates, language tokens, resolution, text path, source) is
tabulated in docs/design.md section 6.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

import torch

from resireg.models.encoder import DenseEncoder
from resireg.models.hub import WeightsUnavailableError
from resireg.models.vlm import ResiregVLM
from resireg.specs.encoders import ENCODER_SPECS

__all__ = ["ENCODERS", "build_encoder", "count_parameters", "encoder_modules", "load_resireg_vlm"]


def load_resireg_vlm(
    path: str, device: torch.device | str | None = None, config_key: str = "model"
) -> ResiregVLM:
    """The ``resireg_vlm`` kind: our VLM from an export folder or a hub repo id."""
    if not path:
        raise ValueError(f"{config_key}.path is required: an export folder or a hub repo id")
    try:
        return ResiregVLM.from_pretrained(path, map_location=device or "cpu")
    except WeightsUnavailableError as err:  # name the key, as every other kind does
        raise WeightsUnavailableError(f"{config_key}.path={path!r}: {err}") from err


class _Builders(Mapping[str, Callable[..., DenseEncoder]]):
    """``kind -> builder`` read from the encoder table (resireg.specs.encoders, the one list of
    kinds; installed packages' kinds included), each builder imported on first access."""

    def __getitem__(self, kind: str) -> Callable[..., DenseEncoder]:
        spec = ENCODER_SPECS.find(kind)
        if spec is None:
            raise KeyError(kind)
        return spec.load()

    def __iter__(self) -> Iterator[str]:
        return iter(ENCODER_SPECS.everything())

    def __len__(self) -> int:
        return len(ENCODER_SPECS.everything())


#: ``kind`` -> builder taking the entry's keys, ``device`` and ``config_key``.
ENCODERS: Mapping[str, Callable[..., DenseEncoder]] = _Builders()


def build_encoder(
    kind: str,
    device: torch.device | str | None = None,
    config_key: str = "model",
    **kwargs: Any,
) -> DenseEncoder:
    """The encoder ``kind`` built from its config keys (errors name ``<config_key>.<key>``)."""
    spec = ENCODER_SPECS.find(kind)
    if spec is None:
        known = sorted(ENCODER_SPECS.everything())
        raise ValueError(f"{config_key}.kind={kind!r}: expected one of {known}")
    try:
        return spec.load()(device=device, config_key=config_key, **kwargs)
    except TypeError as err:  # an unknown key for this kind
        raise TypeError(f"{config_key} (kind {kind!r}): {err}") from err


def encoder_modules(encoder: DenseEncoder) -> list[torch.nn.Module]:
    """The encoder and the modules it keeps outside its module tree (RADSeg holds RADIO and
    its adaptor in a plain object): everything whose weights make its outputs."""
    modules: list[torch.nn.Module] = [encoder]
    inner = getattr(encoder, "encoder", None)
    if inner is not None and not isinstance(inner, torch.nn.Module):
        modules += [m for m in vars(inner).values() if isinstance(m, torch.nn.Module)]
    return modules


def count_parameters(encoder: DenseEncoder) -> int:
    """All parameters of the encoder, frozen ones included (those of
    :func:`encoder_modules`), each shared tensor once."""
    seen: set[int] = set()
    total = 0
    for module in encoder_modules(encoder):
        for p in module.parameters():
            if id(p) not in seen:
                seen.add(id(p))
                total += p.numel()
    return total
