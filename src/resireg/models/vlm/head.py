"""The dino.txt-style language head of the 25M dense VLM (paper appendix).

Input: the backbone's [CLS, patch] tokens (registers optionally). Two pre-norm timm
``Block``s at the backbone width (384 for ViT-S, 8 heads, MLP ratio 4, drop-path 0.3
during training), a final LayerNorm and a Linear to 512 on every token. The image
embedding for the contrastive loss is ``concat(CLS_512, mean(patches_512))`` (1024-d);
the dense output is the 512-d patch grid.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from timm.layers import trunc_normal_
from timm.models.vision_transformer import Block
from torch import Tensor, nn

from resireg.models.vlm.eupe import BackboneOutput

__all__ = ["HeadOutput", "LanguageHead"]


class HeadOutput(NamedTuple):
    """Attributes:
    embedding: ``[B, 2*out_dim]`` image embedding ``concat(cls, mean(patches))``.
    patches: ``[B, out_dim, h, w]`` dense language tokens.
    """

    embedding: Tensor
    patches: Tensor


class LanguageHead(nn.Module):
    """Trainable head mapping backbone tokens to language-aligned tokens.

    Args:
        in_dim: backbone width.
        out_dim: language token width (512).
        depth: transformer blocks (2).
        num_heads: attention heads (8).
        mlp_ratio: MLP expansion (4).
        drop_path: stochastic depth rate during training (0.3).
        use_registers: feed the register tokens too (default off).
    """

    def __init__(
        self,
        in_dim: int = 384,
        out_dim: int = 512,
        depth: int = 2,
        num_heads: int = 8,
        mlp_ratio: float = 4.0,
        drop_path: float = 0.3,
        use_registers: bool = False,
    ) -> None:
        super().__init__()
        self._spec = {"out_dim": out_dim, "depth": depth, "num_heads": num_heads,
                      "mlp_ratio": mlp_ratio, "drop_path": drop_path,
                      "use_registers": use_registers}  # fmt: skip
        self.use_registers = use_registers
        self.out_dim = out_dim
        self.blocks = nn.Sequential(
            *[
                Block(in_dim, num_heads, mlp_ratio=mlp_ratio, qkv_bias=True, drop_path=drop_path)
                for _ in range(depth)
            ]
        )
        self.norm = nn.LayerNorm(in_dim)
        self.proj = nn.Linear(in_dim, out_dim)
        self.apply(self._init)

    def spec(self) -> dict:
        """Constructor arguments except ``in_dim`` (taken from the backbone on rebuild)."""
        return dict(self._spec)

    @staticmethod
    def _init(m: nn.Module) -> None:
        if isinstance(m, nn.Linear):
            trunc_normal_(m.weight, std=0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)

    def forward(self, feats: BackboneOutput) -> HeadOutput:
        b, d, h, w = feats.patches.shape
        patches = feats.patches.flatten(2).transpose(1, 2)  # [B, N, D]
        parts = [feats.cls.unsqueeze(1)]
        if self.use_registers:
            parts.append(feats.registers)
        parts.append(patches)
        x = self.proj(self.norm(self.blocks(torch.cat(parts, dim=1))))
        cls, out_patches = x[:, 0], x[:, -h * w :]
        embedding = torch.cat([cls, out_patches.mean(dim=1)], dim=1)
        return HeadOutput(
            embedding=embedding, patches=out_patches.transpose(1, 2).reshape(b, self.out_dim, h, w)
        )
