"""The dense-encoder interface: what any backbone gives ReSiReg and the evaluation.

A :class:`DenseEncoder` declares how its input is prepared (:class:`InputRule`) and
produces, from one forward pass,

- ``intermediates`` ``[B, Dv, h, w]``: features that carry the image's spatial structure
  (ReSiReg clusters / attends over them),
- ``language`` ``[B, Dl, h', w']``: language-aligned dense tokens,
- ``embedding`` ``[B, De]`` or ``None``: a global image embedding, when the model has one,
- ``layers`` ``{block: [B, Dv, h, w]}`` or ``None``: the intermediates of several blocks from
  the same pass, only from an encoder's ``encode_layers(images, layers)`` (the CLIP layer
  sweep; ``None`` from ``encode``),

and embeds text queries into the language space (``encode_text -> [K, Dl]``, unit norm).
Text goes through two steps so an evaluation can run a frozen text tower once and still
follow a trainable projection: ``text_features`` (frozen, cacheable) then ``dense_text``
(the current projection and normalisation). A frozen encoder's ``dense_text`` only
normalises.

``preprocess``, ``encode_image`` and ``similarity`` are shared by every encoder, so a new
backbone implements ``input_rule``, ``encode``, ``encode_text`` and ``spec`` (its
construction config: ``build_encoder(**encoder.spec())`` rebuilds it; docs/method.md#the-dense-encoder-interface).

An encoder that takes a block index (CLIP's ``intermediate_layer`` and its layer sweep, the
EUPE backbone's ``intermediate_layer``) reads it with :func:`block_indices`, the one rule:
timm's ``feature_take_indices``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor, nn

from resireg.models.images import pil_to_tensor, resize_to_patch_grid
from resireg.specs.variants import build_variant

__all__ = ["InputRule", "DenseOutput", "DenseEncoder", "block_index", "block_indices"]


def block_indices(
    depth: int, indices: int | Sequence[int], name: str = "layer", owner: str = "the model"
) -> tuple[int, ...]:
    """Block indices of a ``depth``-block model as 0-based indices, in the given order.

    The rule is timm's (``timm.models._features.feature_take_indices``, which timm's
    ``forward_intermediates`` applies): a sequence lists blocks, a negative index counts from
    the end (``-1`` = the last block); an int ``n`` means the last ``n`` blocks. A block that
    does not exist, or a value that is not an int, is an error naming ``name`` and the value
    (``owner`` says whose blocks: ``ViT-B-16``). Used by every encoder that takes a block.
    """
    from timm.models._features import feature_take_indices

    def is_int(value: Any) -> bool:
        return isinstance(value, int) and not isinstance(value, bool)

    listed = isinstance(indices, Sequence) and not isinstance(indices, str)
    if not (is_int(indices) or (listed and all(map(is_int, indices)))):
        raise TypeError(f"{name}={indices!r}: expected an int or a list of ints (block indices)")
    span = f"{owner} ({depth} blocks: 0..{depth - 1}, or negative from the end)"
    if isinstance(indices, int):  # timm: the last n blocks
        try:
            return tuple(feature_take_indices(depth, indices)[0])
        except AssertionError:  # timm's _assert
            raise ValueError(
                f"{name}={indices}: the last {indices} blocks, but {owner} has {depth} "
                f"(expected 1..{depth}, or a list of block indices)"
            ) from None
    taken = []
    for index in indices:  # one at a time, so that the message names the wrong one
        try:
            taken += feature_take_indices(depth, [index])[0]
        except AssertionError:
            raise ValueError(f"{name}={index} is out of range for {span}") from None
    return tuple(taken)


def block_index(depth: int, index: int, name: str = "layer", owner: str = "the model") -> int:
    """One block (:func:`block_indices` of ``[index]``) as a 0-based index."""
    if isinstance(index, bool) or not isinstance(index, int):
        raise TypeError(f"{name}={index!r}: expected an int (a block index)")
    (taken,) = block_indices(depth, [index], name, owner)
    return taken


@dataclass(frozen=True)
class InputRule:
    """How an encoder's images are prepared.

    Attributes:
        patch_size: sides of the model input are multiples of it.
        mean, std: per-channel normalisation of RGB in [0, 1].
    """

    patch_size: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]

    def check_size(self, images: Tensor, unit: str = "the patch size") -> None:
        """Raise ``ValueError`` unless both sides of ``images`` are multiples of the patch size
        (what :meth:`DenseEncoder.encode` accepts); ``unit`` names it in the message."""
        h, w = images.shape[-2:]
        if h % self.patch_size or w % self.patch_size:
            raise ValueError(f"image size {(h, w)} is not a multiple of {unit} {self.patch_size}")

    def resize(self, image: Tensor, short_side: int | None) -> Tensor:
        """RGB ``[3, H, W]`` (uint8 or float in [0, 1]) -> float ``[3, h, w]`` in [0, 1]."""
        return resize_to_patch_grid(image, short_side, self.patch_size)

    def normalize(self, images: Tensor) -> Tensor:
        """``[B, 3, H, W]`` in [0, 1] -> normalised with ``mean`` / ``std``."""
        mean = torch.tensor(self.mean, device=images.device).view(1, 3, 1, 1)
        std = torch.tensor(self.std, device=images.device).view(1, 3, 1, 1)
        return (images - mean) / std


class DenseOutput(NamedTuple):
    """One encoder pass (see the module docstring). ``layers`` defaults to ``None``, so the
    three-field form ``DenseOutput(intermediates, language, embedding)`` is unchanged."""

    intermediates: Tensor
    language: Tensor
    embedding: Tensor | None
    layers: dict[int, Tensor] | None = None


class DenseEncoder(nn.Module, ABC):
    """Base class of every dense vision-language encoder ReSiReg runs on."""

    @property
    @abstractmethod
    def input_rule(self) -> InputRule:
        """Patch size and normalisation of this encoder's input."""

    @abstractmethod
    def encode(self, images: Tensor) -> DenseOutput:
        """Normalised images ``[B, 3, H, W]`` (sides multiples of the patch size) -> features."""

    @abstractmethod
    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """Unit-norm text queries ``[K, Dl]`` in the language tokens' space."""

    def spec(self) -> dict[str, Any]:
        """The JSON-able construction config: ``{"kind": <encoder kind>, <parameter>: ...}``
        (``device`` aside), such that ``resireg.models.build_encoder(**spec)`` builds the same
        encoder (same architecture, weights source and settings). Every encoder of the registry
        implements it; an encoder outside it (a test double, a benchmark oracle, your own
        backbone) has none: a ValueError, as for a ResiregVLM not loaded from an export."""
        raise ValueError(
            f"{type(self).__name__} has no construction config (spec): only the encoder kinds "
            "of resireg.specs.encoders are rebuilt from one"
        )

    # Text in two steps; the defaults suit an encoder with no trainable text part.
    def text_features(self, texts: Sequence[str]) -> Tensor:
        """The frozen part of :meth:`encode_text` (safe to compute once and reuse)."""
        return self.encode_text(texts)

    def dense_text(self, features: Tensor) -> Tensor:
        """:meth:`text_features` output -> unit-norm queries ``[K, Dl]`` (current weights)."""
        return F.normalize(features.float(), dim=-1)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    # ------------------------------------------------------------- shared helpers
    def preprocess(self, images: Any, short_side: int | None = None) -> Tensor:
        """PIL images, or RGB tensors (uint8, or float in [0, 1]), -> normalised ``[B, 3, H, W]``.

        Each image is resized by :meth:`InputRule.resize` (shorter side to ``short_side``
        if given; sides rounded to the patch size); the images of one call must share the
        resulting size.
        """
        return self.input_rule.normalize(self.resized(images, short_side))

    def resized(self, images: Any, short_side: int | None = None) -> Tensor:
        """:meth:`preprocess` before normalisation: float ``[B, 3, H, W]`` in [0, 1]."""
        if isinstance(images, (Image.Image, Tensor)) and not (
            isinstance(images, Tensor) and images.ndim == 4
        ):
            images = [images]
        rule = self.input_rule
        tensors = [pil_to_tensor(im) if isinstance(im, Image.Image) else im for im in images]
        out = [rule.resize(t, short_side) for t in tensors]
        if len({tuple(t.shape) for t in out}) != 1:
            raise ValueError(
                "images of one batch must share a size after resizing, got "
                f"{[tuple(t.shape[-2:]) for t in out]}"
            )
        return torch.stack(out).to(self.device)

    def encode_image(
        self,
        images: Any,
        resireg: str | nn.Module | None = None,
        *,
        normalized: bool = False,
        short_side: int | None = None,
        prior: Tensor | Callable[[Tensor], Tensor] | None = None,
        **resireg_kwargs: Any,
    ) -> Tensor:
        """Dense language features ``[B, Dl, h, w]`` (unit norm over channels).

        Args:
            images: PIL images / RGB tensors, or (``normalized=True``) a normalised batch.
            resireg: ``None`` or ``"bb"`` (the language tokens), a variant name of
                :func:`resireg.specs.variants.build_variant` (``"lite"``, ``"full"``), or a
                variant module. ReSiReg's grid is ``upscale`` times finer.
            short_side: resize for PIL/tensor input (see :meth:`preprocess`).
            prior: optional segmentation prior for ReSiReg: instance ids ``[B, H', W']``
                (0 = none), or a provider (e.g. :class:`resireg.priors.SamPrior`) called on
                the resized images before normalisation (float ``[B, 3, H, W]`` in [0, 1])
                that returns them; a provider needs ``normalized=False``.
            **resireg_kwargs: the variant's arguments (with a name).
        """
        if normalized and prior is not None and not isinstance(prior, Tensor):
            raise ValueError("a prior provider needs the images: pass normalized=False")
        raw = None if normalized else self.resized(images, short_side)
        x = images if raw is None else self.input_rule.normalize(raw)
        if prior is not None and not isinstance(prior, Tensor):
            prior = prior(raw)
        variant = (
            resireg
            if isinstance(resireg, nn.Module)
            else build_variant(resireg or "bb", **resireg_kwargs)
        )
        with torch.no_grad():
            out = self.encode(x)
            if prior is not None:
                prior = prior.to(out.intermediates.device)
            return variant(out.intermediates, out.language, prior)

    def similarity(
        self,
        images: Any,
        texts: Sequence[str],
        resireg: str | nn.Module | None = None,
        **kwargs: Any,
    ) -> Tensor:
        """Per-pixel cosine similarity maps ``[B, K, h, w]`` of images with text queries."""
        dense = self.encode_image(images, resireg, **kwargs)
        with torch.no_grad():
            queries = self.encode_text(texts).to(dense.device)
        return torch.einsum("bdhw,kd->bkhw", dense.float(), queries.float())
