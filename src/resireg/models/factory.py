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
tabulated in docs/models.md#models-and-encoders.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import torch

from resireg.errors import ConfigError, parameters
from resireg.models.hub import WeightsUnavailableError
from resireg.models.interface import DenseEncoder
from resireg.models.vlm import ResiregVLM
from resireg.specs.encoders import ENCODER_SPECS

__all__ = [
    "ENCODERS",
    "build_encoder",
    "count_parameters",
    "encoder_arguments",
    "encoder_modules",
    "weights_fingerprint",
    "load_resireg_vlm",
    "resolve_device",
]


def resolve_device(device: torch.device | str) -> torch.device:
    """``device`` as a ``torch.device``; ``"auto"`` is CUDA where a GPU is visible, else the CPU
    (the ``device`` key of conf/eval.yaml, conf/map.yaml, the node and the playground)."""
    if isinstance(device, str) and device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def load_resireg_vlm(
    path: str, device: torch.device | str | None = None, external: Mapping | None = None
) -> ResiregVLM:
    """The ``resireg_vlm`` kind: our VLM from an export folder or a hub repo id; ``external``:
    a frozen part's file outside the export, given by the user (``{"backbone": {"weights":
    path}}``; :meth:`ResiregVLM.from_pretrained`)."""
    if not path:
        raise ConfigError("path is required: an export folder or a hub repo id")
    try:
        return ResiregVLM.from_pretrained(path, map_location=device or "cpu", external=external)
    except WeightsUnavailableError as err:  # name the argument, as every other kind does
        raise WeightsUnavailableError(f"path={path!r}: {err}") from err


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


#: ``kind`` -> builder taking the entry's keys and ``device``.
ENCODERS: Mapping[str, Callable[..., DenseEncoder]] = _Builders()


def build_encoder(
    kind: str, device: torch.device | str | None = None, **kwargs: Any
) -> DenseEncoder:
    """The encoder ``kind`` built from its keys (errors name them: ``weights=...``; an unknown
    kind is a :class:`~resireg.errors.ConfigError` naming the closest kinds)."""
    spec = ENCODER_SPECS.find(kind)
    if spec is None:
        raise ConfigError(ENCODER_SPECS.unknown(kind, setting="kind"))
    try:
        return spec.load()(device=device, **kwargs)
    except TypeError as err:
        if err.__traceback__ is not None and err.__traceback__.tb_next is None:
            # the call itself failed (a key this kind does not take), not the builder's code
            raise TypeError(f"kind={kind!r}: {err}") from err
        raise


def encoder_arguments(kind: str) -> tuple[str, ...]:
    """What the messages of ``build_encoder(kind, ...)`` may name: ``kind``, ``device`` and
    the builder's arguments (:func:`resireg.errors.parameters`; the builder is imported)."""
    spec = ENCODER_SPECS.find(kind)
    return tuple(dict.fromkeys(("kind", "device", *(parameters(spec.load()) if spec else ()))))


def encoder_modules(encoder: DenseEncoder) -> list[torch.nn.Module]:
    """The encoder and the modules it keeps outside its module tree (RADSeg holds RADIO and
    its adaptor in a plain object): everything whose weights make its outputs."""
    modules: list[torch.nn.Module] = [encoder]
    inner = getattr(encoder, "encoder", None)
    if inner is not None and not isinstance(inner, torch.nn.Module):
        modules += [m for m in vars(inner).values() if isinstance(m, torch.nn.Module)]
    return modules


def weights_fingerprint(encoder: torch.nn.Module) -> str:
    """BLAKE2b digest of every parameter and buffer of ``encoder`` (names, dtypes, shapes and
    bytes), modules kept outside the module tree included (as :func:`count_parameters` counts
    them). Two encoders share a fingerprint only if their weights are bitwise equal: a resumed
    map (``resireg-map``, ``resireg-ros2``) and the feature cache are keyed by it."""
    digest = hashlib.blake2b(digest_size=16)
    for prefix, module in enumerate(encoder_modules(encoder)):
        tensors = {**dict(module.named_parameters()), **dict(module.named_buffers())}
        for name in sorted(tensors):
            t = tensors[name].detach()
            digest.update(f"{prefix}.{name}:{t.dtype}:{tuple(t.shape)};".encode())
            # bytes of the storage as laid out in memory; view as uint8 covers bf16 too
            digest.update(t.contiguous().cpu().reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


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
