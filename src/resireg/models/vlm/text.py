"""Frozen SigLIP 2 text tower (open_clip) with a caption cache, and the learned projection.
The kinds of tower (``pretrained``, ``tiny``) are the entries of the text tower table,
:data:`resireg.specs.text.TEXT_SPECS`.

The tower is open_clip's ``ViT-B-16-SigLIP2`` (pretrained ``webli``): only its text
transformer is kept, frozen, pooled output 768-d. The trainable model owns
:class:`TextProjection` (Linear 768 -> 1024); dense retrieval uses the second half (512)
of the projected embedding, L2-normalised, matching the mean-patch half of the image
embedding.

The tower never changes, so its outputs are cached by caption text: repeated captions
and the evaluation's class prompts never run it twice.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import open_clip
import torch
import torch.nn.functional as F
from open_clip.transformer import TextTransformer
from torch import Tensor, nn

from resireg.models.frozen import FrozenModule
from resireg.models.hub import WeightsUnavailableError, require_hf_files, require_open_clip_tag
from resireg.specs.text import CACHE_SIZE, TEXT_SPECS

__all__ = ["CAPTION_CACHE_SIZE", "FrozenTextTower", "TextProjection", "dense_text_half"]

#: Captions whose tower outputs a :class:`FrozenTextTower` keeps (LRU) unless told otherwise:
#: ``cache_size`` of ``conf/model/text/*.yaml`` (tests/resireg/specs/test_specs.py holds the two equal).
CAPTION_CACHE_SIZE = 200_000

_OFFLINE_HINT = (
    "Pass local files instead: model.text.weights=/path/to/open_clip_model.safetensors (the "
    "ViT-B-16-SigLIP2 checkpoint) and model.text.tokenizer=/path/to/tokenizer_dir (a Hugging Face "
    "tokenizer directory for timm/ViT-B-16-SigLIP2; needs `transformers`), or use the tiny tower."
)


class FrozenTextTower(FrozenModule):
    """A frozen open_clip text transformer with a caption -> embedding cache.

    Build with :meth:`pretrained` (SigLIP 2) or :meth:`tiny` (random 2-layer tower with
    open_clip's bundled BPE tokenizer, offline).

    Args:
        tower: an open_clip text tower (``encode`` = ``tower(tokens)`` -> ``[B, out_dim]``).
        tokenizer: callable ``list[str] -> LongTensor [B, context]``.
        out_dim: pooled output width.
        spec: JSON-serialisable description used to rebuild it.
        cache_size: most captions kept (least recently used dropped); ``None`` = unbounded.
    """

    def __init__(
        self,
        tower: nn.Module,
        tokenizer: Any,
        out_dim: int,
        spec: dict,
        cache_size: int | None = CAPTION_CACHE_SIZE,
    ) -> None:
        super().__init__()
        self.tower = tower
        self.tokenizer = tokenizer
        self.out_dim = out_dim
        self._spec = spec
        self.cache_size = cache_size
        self._cache: OrderedDict[str, Tensor] = OrderedDict()
        self.hits = 0
        self.misses = 0
        self.freeze()

    @classmethod
    def pretrained(
        cls,
        model_name: str = "ViT-B-16-SigLIP2",
        weights: str = "webli",
        tokenizer: str | None = None,
        cache_size: int | None = CAPTION_CACHE_SIZE,
    ) -> FrozenTextTower:
        """The SigLIP 2 text tower; ``weights`` is an open_clip tag or a local checkpoint file."""
        spec = {
            "kind": "pretrained",
            "model_name": model_name,
            "weights": weights,
            "tokenizer": tokenizer,
        }
        local = os.path.isfile(os.fspath(weights))
        if not local:
            require_open_clip_tag(model_name, weights, "model.text.weights", _OFFLINE_HINT)
        model = open_clip.create_model(model_name, pretrained=weights)
        tower = model.text
        tok = cls._tokenizer(model_name, tokenizer)
        out_dim = int(open_clip.get_model_config(model_name)["embed_dim"])
        return cls(tower, tok, out_dim, spec, cache_size)

    @staticmethod
    def _tokenizer(model_name: str, tokenizer: str | None) -> Any:
        cfg = open_clip.get_model_config(model_name)["text_cfg"]
        if tokenizer is not None:
            if not os.path.isdir(tokenizer):
                raise FileNotFoundError(f"tokenizer directory {tokenizer!r} does not exist")
            from open_clip.tokenizer import HFTokenizer

            return HFTokenizer(
                tokenizer, context_length=cfg["context_length"], **cfg.get("tokenizer_kwargs", {})
            )
        hf_name = cfg.get("hf_tokenizer_name")
        if hf_name:
            require_hf_files(
                hf_name, ["tokenizer_config.json"], f"tokenizer {hf_name!r}", _OFFLINE_HINT
            )
        try:
            return open_clip.get_tokenizer(model_name)
        except Exception as err:  # HF tokenizer could not be fetched or built
            raise WeightsUnavailableError(
                f"could not load the tokenizer of {model_name}: {err}. {_OFFLINE_HINT}"
            ) from err

    @classmethod
    def tiny(
        cls,
        width: int = 64,
        layers: int = 2,
        heads: int = 2,
        out_dim: int = 96,
        context_length: int = 32,
        seed: int = 0,
        cache_size: int | None = CAPTION_CACHE_SIZE,
    ) -> FrozenTextTower:
        """A random open_clip text transformer with the bundled CLIP BPE tokenizer (offline)."""
        spec = {"kind": "tiny", "width": width, "layers": layers, "heads": heads, "out_dim": out_dim,
                "context_length": context_length, "seed": seed}  # fmt: skip
        tok = open_clip.SimpleTokenizer(context_length=context_length)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            tower = TextTransformer(
                context_length=context_length, vocab_size=tok.vocab_size, width=width, heads=heads,
                layers=layers, output_dim=out_dim, no_causal_mask=True, proj_bias=True,
                pool_type="argmax",
            )  # fmt: skip
        return cls(tower, tok, out_dim, spec, cache_size)

    @classmethod
    def from_spec(cls, spec: dict) -> FrozenTextTower:
        """Build from :meth:`spec` output or a config (``model.text``): ``kind`` selects the
        builder of the text tower table (:data:`resireg.specs.text.TEXT_SPECS`: ``pretrained``,
        :meth:`pretrained`; ``tiny``, :meth:`tiny`), called with the other keys;
        ``cache_size`` (optional) bounds the caption cache."""
        spec = dict(spec)
        builder = TEXT_SPECS.load(spec.pop("kind"))
        cache_size = spec.pop("cache_size", CAPTION_CACHE_SIZE)
        check, expected = CACHE_SIZE
        if not check(cache_size):
            raise ValueError(f"model.text.cache_size={cache_size!r}: expected {expected}")
        return builder(**spec, cache_size=cache_size)

    def spec(self) -> dict:
        return {**self._spec, "cache_size": self.cache_size}

    @property
    def device(self) -> torch.device:
        return next(self.tower.parameters()).device

    @torch.no_grad()
    def forward(self, texts: Sequence[str], cache: bool = True) -> Tensor:
        """Pooled embeddings ``[K, out_dim]`` (float32) of ``texts``.

        With ``cache`` (default) known texts come from the cache and new ones are added.
        ``cache=False`` runs the tower on exactly ``texts`` in one batch, reading and
        writing no cache: the result then does not depend on what was cached before
        (a text embedded within a different batch can differ in the last float bits).
        """
        texts = list(texts)
        if not cache:
            return self.tower(self.tokenizer(texts).to(self.device)).float()
        missing = list(dict.fromkeys(t for t in texts if t not in self._cache))
        self.misses += len(missing)
        self.hits += len(texts) - len(missing)
        if missing:
            tokens = self.tokenizer(missing).to(self.device)
            out = self.tower(tokens).float()
            for text, emb in zip(missing, out, strict=True):
                self._cache[text] = emb
        for t in texts:
            self._cache.move_to_end(t)
        result = torch.stack([self._cache[t] for t in texts])
        if self.cache_size is not None:
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return result

    def _apply(self, fn, recurse=True):  # keep cached tensors on the tower's device
        super()._apply(fn, recurse)
        self._cache = OrderedDict((k, fn(v)) for k, v in self._cache.items())
        return self


class TextProjection(nn.Linear):
    """The learned Linear ``in_dim -> 2 * dense_dim`` on the frozen tower's pooled output."""

    def __init__(self, in_dim: int = 768, dense_dim: int = 512) -> None:
        super().__init__(in_dim, 2 * dense_dim)
        self.dense_dim = dense_dim


def dense_text_half(embedding: Tensor) -> Tensor:
    """The normalised second half of projected text embeddings ``[K, 2d]`` -> ``[K, d]``."""
    return F.normalize(embedding[:, embedding.shape[1] // 2 :], dim=-1)
