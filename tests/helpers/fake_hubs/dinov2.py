"""The fake facebookresearch/dinov2 hub repository for OTAS: :data:`DINOV2_HUBCONF`
(``dinov2_vits14_reg``) over :data:`DINOV2_VIT`, the ViT that dino.txt's fake holds too;
:func:`dinov2_repo`, a local clone; and :func:`drop_dinov2_modules` /
:func:`restore_dinov2_modules`, so that two clones in one session do not share the imported
``dinov2`` package.
"""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

from helpers.fake_hubs.common import write_repo

# facebookresearch/dinov2's ViT (dinov2/models/vision_transformer.py) as both fake dinov2 clones
# hold it: one token path (patch embedding, CLS, positions interpolated by DINOv2's rule from
# the attributes read at every call, registers after CLS, blocks, final norm) for dino.txt's
# backbone and OTAS's ``dinov2_vits14_reg``. ``Block(dim, num_heads)`` is the clone's own block.
DINOV2_VIT = textwrap.dedent(
    """
    class DinoVisionTransformer(nn.Module):
        def __init__(self, img_size=518, patch_size=14, embed_dim=32, depth=1, num_heads=2,
                     num_register_tokens=0, interpolate_antialias=False, interpolate_offset=0.1):
            super().__init__()
            self.patch_size, self.embed_dim, self.num_heads = patch_size, embed_dim, num_heads
            self.num_register_tokens = num_register_tokens
            self.interpolate_antialias = interpolate_antialias
            self.interpolate_offset = interpolate_offset
            self.chunked_blocks = False
            m = img_size // patch_size
            self.patch_embed = nn.Conv2d(3, embed_dim, patch_size, stride=patch_size)
            self.cls_token = nn.Parameter(torch.randn(1, 1, embed_dim))
            self.pos_embed = nn.Parameter(torch.randn(1, 1 + m * m, embed_dim))
            self.register_tokens = nn.Parameter(torch.randn(1, num_register_tokens, embed_dim))
            self.mask_token = nn.Parameter(torch.zeros(1, embed_dim))
            self.blocks = nn.ModuleList(Block(embed_dim, num_heads) for _ in range(depth))
            self.norm = nn.LayerNorm(embed_dim, eps=1e-6)

        def interpolate_pos_encoding(self, x, w, h):  # DINOv2's rule (w, h = rows, cols)
            n = self.pos_embed.shape[1] - 1
            if x.shape[1] - 1 == n and w == h:
                return self.pos_embed
            w0, h0 = w // self.patch_size, h // self.patch_size
            m = int(math.sqrt(n))
            if self.interpolate_offset:
                size = {"scale_factor": ((w0 + self.interpolate_offset) / m,
                                         (h0 + self.interpolate_offset) / m)}
            else:
                size = {"size": (w0, h0)}
            patch = self.pos_embed[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
            patch = nn.functional.interpolate(patch, mode="bicubic",
                                              antialias=self.interpolate_antialias, **size)
            patch = patch.permute(0, 2, 3, 1).reshape(1, w0 * h0, -1)
            return torch.cat([self.pos_embed[:, :1], patch], dim=1)

        def prepare_tokens_with_masks(self, x, masks=None):
            _, _, w, h = x.shape
            x = self.patch_embed(x).flatten(2).transpose(1, 2)
            x = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), x], dim=1)
            x = x + self.interpolate_pos_encoding(x, w, h)
            regs = self.register_tokens.expand(x.shape[0], -1, -1)
            return torch.cat([x[:, :1], regs, x[:, 1:]], dim=1)

        def forward_features(self, x, masks=None):
            x = self.prepare_tokens_with_masks(x, masks)
            for blk in self.blocks:
                x = blk(x)
            x_norm = self.norm(x)
            r = self.num_register_tokens
            return {"x_norm_clstoken": x_norm[:, 0], "x_norm_regtokens": x_norm[:, 1 : r + 1],
                    "x_norm_patchtokens": x_norm[:, r + 1 :], "x_prenorm": x, "masks": masks}

        def _get_intermediate_layers_not_chunked(self, x, n=1):
            x = self.prepare_tokens_with_masks(x)
            take = range(len(self.blocks) - n, len(self.blocks)) if isinstance(n, int) else n
            output = []
            for i, blk in enumerate(self.blocks):
                x = blk(x)
                if i in take:
                    output.append(x)
            return output

        def forward(self, *args, is_training=False, **kwargs):
            ret = self.forward_features(*args, **kwargs)
            return ret if is_training else ret["x_norm_clstoken"]
    """
)


DINOV2_HUBCONF = (
    textwrap.dedent(
        """
        import math

        import torch
        from torch import nn

        dependencies = ["torch"]


        def Block(dim, num_heads):  # torch's pre-norm encoder layer
            return nn.TransformerEncoderLayer(dim, num_heads, 2 * dim, dropout=0.0,
                                              batch_first=True, norm_first=True)
        """
    )
    + DINOV2_VIT
    + textwrap.dedent(
        """

        def dinov2_vits14_reg(*, pretrained=True, **kwargs):
            return DinoVisionTransformer(num_register_tokens=4, interpolate_antialias=True,
                                         interpolate_offset=0.0, **kwargs)
        """
    )
)


def dinov2_repo(folder: Path) -> str:
    """A local facebookresearch/dinov2 clone with OTAS's entry point (:data:`DINOV2_HUBCONF`)."""
    return str(write_repo(folder, {"hubconf.py": DINOV2_HUBCONF}))


def _is_dinov2(name: str) -> bool:
    return name == "dinov2" or name.startswith("dinov2.")


def drop_dinov2_modules() -> dict:
    """Remove the ``dinov2`` package (one fake clone's) from ``sys.modules``; returns what was
    removed, for :func:`restore_dinov2_modules`. torch.hub imports a local repo's package by
    name, so two clones in one session must not share it."""
    return {k: sys.modules.pop(k) for k in list(sys.modules) if _is_dinov2(k)}


def restore_dinov2_modules(saved: dict) -> None:
    for k in [k for k in sys.modules if _is_dinov2(k)]:
        del sys.modules[k]
    sys.modules.update(saved)
