"""Frozen EUPE ViT backbone through timm.

EUPE ViT-S/16 is timm's ``vit_small_patch16_dinov3_qkvb.eupe_lvd1689m`` (21.6M parameters,
RoPE, one CLS and four register tokens, ImageNet mean/std, any input size divisible by the
patch size). Weights come from

- ``"hub"``: timm's Hugging Face id (cached, or downloaded when online),
- a local file: timm format (``.safetensors`` / ``.pth``) or Meta's original checkpoint
  (``EUPE-ViT-S.pt``: ``storage_tokens``, ``blocks.N.attn.qkv.bias_mask``,
  ``rope_embed.periods``, training-only ``projectors.*``). timm's own
  ``checkpoint_filter_fn`` recognises and converts the original layout; we pass the file
  through ``pretrained_cfg_overlay`` rather than writing a second converter,
- ``None``: random initialisation (tests, the smoke experiment).

The backbone is always frozen: ``eval()`` mode, no parameter requires grad, and its
forward runs under ``torch.no_grad()`` (not ``inference_mode``: inference tensors could
not be saved for the trained head's backward).
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import timm
import torch
from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from torch import Tensor

from resireg.models.frozen import FrozenModule
from resireg.models.hub import require_hf_files
from resireg.models.interface import block_index

__all__ = ["EUPE_MODELS", "BackboneOutput", "EUPEBackbone"]

#: EUPE ViTs by short name.
EUPE_MODELS = {
    "eupe_vit_t16": "vit_tiny_patch16_dinov3_qkvb.eupe_lvd1689m",
    "eupe_vit_s16": "vit_small_patch16_dinov3_qkvb.eupe_lvd1689m",
    "eupe_vit_b16": "vit_base_patch16_dinov3_qkvb.eupe_lvd1689m",
}


class BackboneOutput(NamedTuple):
    """Tokens of the backbone.

    Attributes:
        cls: ``[B, D]`` final-norm CLS token.
        registers: ``[B, R, D]`` final-norm register (storage) tokens.
        patches: ``[B, D, H/p, W/p]`` final-norm patch-token grid (the head's input).
        intermediates: ``[B, D, H/p, W/p]`` ReSiReg's intermediates: ``patches`` by
            default, or the output of the block chosen with ``intermediate_layer``.
    """

    cls: Tensor
    registers: Tensor
    patches: Tensor
    intermediates: Tensor


class EUPEBackbone(FrozenModule):
    """A frozen EUPE ViT.

    Args:
        model_name: timm model name (or a key of :data:`EUPE_MODELS`).
        weights: ``"hub"``, a local checkpoint path (timm or Meta format), or ``None``.
        seed: seed of the random init when ``weights`` is ``None``, so the frozen random
            backbone of a tiny/smoke model is rebuilt identically from its config.
        **overrides: timm constructor overrides (e.g. ``embed_dim=64, depth=2,
            num_heads=2`` for a tiny model of the same architecture).
    """

    def __init__(
        self,
        model_name: str = "eupe_vit_s16",
        weights: str | None = "hub",
        seed: int = 0,
        **overrides: Any,
    ) -> None:
        super().__init__()
        self.model_name = EUPE_MODELS.get(model_name, model_name)
        self.weights = weights
        self.seed = seed
        self.overrides = dict(overrides)
        kwargs: dict[str, Any] = {"num_classes": 0, "dynamic_img_size": True, **overrides}
        if weights is None:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                model = timm.create_model(self.model_name, pretrained=False, **kwargs)
        elif weights == "hub":
            cfg = timm.models.get_pretrained_cfg(self.model_name)
            repo = cfg.hf_hub_id if cfg is not None else None
            if repo:
                require_hf_files(
                    repo,
                    ["model.safetensors"],
                    f"EUPE weights {repo!r}",
                    "Pass a local checkpoint instead: model.backbone.weights=/path/to/EUPE-ViT-S.pt "
                    "(Meta's original file) or a timm .safetensors file, or weights=null for random init.",
                )
            model = timm.create_model(self.model_name, pretrained=True, **kwargs)
        else:
            path = os.fspath(weights)
            if not os.path.isfile(path):
                raise FileNotFoundError(f"backbone weights file {path!r} does not exist")
            model = timm.create_model(
                self.model_name, pretrained=True, pretrained_cfg_overlay={"file": path}, **kwargs
            )
        self.model = model
        self.patch_size = int(model.patch_embed.patch_size[0])
        self.embed_dim = int(model.embed_dim)
        self.num_registers = int(model.num_prefix_tokens) - 1
        cfg = model.pretrained_cfg
        self.mean = tuple(cfg.get("mean", IMAGENET_DEFAULT_MEAN))
        self.std = tuple(cfg.get("std", IMAGENET_DEFAULT_STD))
        self.depth = len(model.blocks)
        self.freeze()

    def check_layer(self, layer: int | None, name: str = "intermediate_layer") -> int | None:
        """``layer`` (``None``, or a block index: negative counts from the end) if it names a
        block, else a ValueError naming ``name`` (the rule of
        :func:`~resireg.models.interface.block_index`)."""
        if layer is not None:
            block_index(self.depth, layer, name, self.model_name)
        return layer

    def forward(self, images: Tensor, intermediate_layer: int | None = None) -> BackboneOutput:
        """Encode normalised images ``[B, 3, H, W]`` (H, W divisible by the patch size).

        Args:
            intermediate_layer: ``None``: the intermediates are the final-norm patch tokens;
                a block index: that block's output patch tokens (without the final norm),
                taken in the same pass by timm's ``forward_intermediates``.
        """
        b, _, h, w = images.shape
        if h % self.patch_size or w % self.patch_size:
            raise ValueError(
                f"image size {(h, w)} is not divisible by the patch size {self.patch_size}"
            )
        layer = self.check_layer(intermediate_layer)
        with torch.no_grad():
            if layer is None:
                tokens = self.model.forward_features(images)  # [B, 1 + R + N, D], final norm
            else:
                tokens, (inter,) = self.model.forward_intermediates(
                    images, indices=[layer % self.depth], norm=False, output_fmt="NCHW"
                )
        gh, gw = h // self.patch_size, w // self.patch_size
        prefix = 1 + self.num_registers
        patches = tokens[:, prefix:].transpose(1, 2).reshape(b, -1, gh, gw)
        return BackboneOutput(
            cls=tokens[:, 0],
            registers=tokens[:, 1:prefix],
            patches=patches,
            intermediates=patches if layer is None else inter,
        )

    def spec(self) -> dict[str, Any]:
        """JSON-serialisable description (name, weights source, overrides)."""
        return {"model_name": self.model_name, "weights": self.weights, "seed": self.seed,
                **self.overrides}  # fmt: skip
