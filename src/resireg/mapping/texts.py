"""The text side of a map's queries: each text's embedding and each class list's prototypes,
computed once by the encoder and kept (:class:`TextEmbeddings`)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["TextEmbeddings"]

#: Texts whose embeddings a map keeps.
TEXT_CACHE = 1024
#: Class lists (with their templates) whose prototypes a map keeps.
PROTOTYPE_CACHE = 64


class TextEmbeddings:
    """The embeddings of texts and prototypes of class lists by a map's encoder (its
    ``text_features`` then ``dense_text``), the last :data:`TEXT_CACHE` texts and
    :data:`PROTOTYPE_CACHE` class lists kept."""

    def __init__(self) -> None:
        self._texts: OrderedDict[str, Tensor] = OrderedDict()
        self._prototypes: OrderedDict[Any, Tensor] = OrderedDict()

    @torch.no_grad()
    def queries(self, encoder: Any, texts: Sequence[str]) -> Tensor:
        """``[K, D]`` unit-norm queries of the raw texts (the encoder's text path, no template),
        each text embedded once per map (the last 1,024 kept)."""
        if encoder is None:
            raise ValueError("this map has no encoder to embed text: pass one to load()")
        texts = [str(t) for t in texts]
        missing = [t for t in dict.fromkeys(texts) if t not in self._texts]
        if missing:
            feats = encoder.text_features(missing)
            queries = F.normalize(encoder.dense_text(feats).float(), dim=-1)
            for text, q in zip(missing, queries, strict=True):
                self._texts[text] = q
        for text in texts:
            self._texts.move_to_end(text)
        while len(self._texts) > TEXT_CACHE:
            self._texts.popitem(last=False)
        return torch.stack([self._texts[t] for t in texts]) if texts else torch.empty(0, 0)

    @torch.no_grad()
    def prototypes(
        self,
        encoder: Any,
        device: torch.device,
        classes: Sequence[str],
        templates: Sequence[Callable[[str], str]] | None = None,
    ) -> Tensor:
        """``[K, D]`` class prototypes as the protocol builds them: every template (default:
        the 80 OpenAI ImageNet templates) per class through ``text_features`` then
        ``dense_text``, averaged (:func:`resireg.ovss.text_prototypes`); kept per class list
        and templates; ``device``: the map's, where autocast is off."""
        from resireg.ovss import TEMPLATES, text_prototypes

        if encoder is None:
            raise ValueError("this map has no encoder to embed text: pass one to load()")
        key = (tuple(classes), None if templates is None else tuple(map(id, templates)))
        if key in self._prototypes:
            self._prototypes.move_to_end(key)
            return self._prototypes[key]
        enc = encoder

        def embed(texts: list[str]) -> Tensor:
            return enc.dense_text(enc.text_features(texts))

        with torch.autocast(device.type, enabled=False):
            protos = text_prototypes(embed, list(classes), templates or TEMPLATES)
        self._prototypes[key] = protos
        while len(self._prototypes) > PROTOTYPE_CACHE:
            self._prototypes.popitem(last=False)
        return protos
