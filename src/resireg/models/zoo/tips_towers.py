"""TIPSv2's two towers, reimplemented with the release's parameter names so the release files
load as they are (:mod:`resireg.models.zoo.tips` reads the files and is the encoder).

Read from github.com/google-deepmind/tips (``pytorch/image_encoder.py``,
``pytorch/text_encoder.py``, ``pytorch/run_text_encoder_inference.py``):

- Image encoder: a DINOv2-style ViT with patch 14, one register token (which TIPS uses as
  a second CLS token), LayerScale (``init_values=1.0``), LayerNorm eps 1e-6, qkv bias, no
  block chunking (``block_chunks=0``). B/14: width 768, 12 blocks, 12 heads; L/14: 1024, 24,
  16; So400m/14: 1152, 27, 16, MLP 4304; g/14 (``vit_giant2``): 1536, 40, 24, SwiGLU MLP
  (``w12`` / ``w3``, hidden ``(int(4 * 1536 * 2 / 3) + 7) // 8 * 8 = 4096``); the others a
  GELU MLP (``fc1`` / ``fc2``). TIPSv2 checkpoints hold a 32 x 32 positional grid (448 px);
  other sizes interpolate it bilinearly with antialiasing and no offset
  (``interpolate_antialias=True, interpolate_offset=0.0``).
- Text encoder: token embedding (scaled by ``sqrt(width)``) plus fixed sinusoidal positions,
  pre-norm transformer blocks (``nn.MultiheadAttention`` masked on padding, ReLU MLP whose
  output is zeroed on padding), ``ln_final``, mean over the non-padding tokens; no
  projection. Width equals the vision width; 12 layers (27 for So400m). Tokenisation: lower
  case (``tf.strings.lower``, ASCII), SentencePiece ids without BOS / EOS, cut or padded with
  0 to 64.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import ConfigError

__all__ = ["TIPS_VARIANTS", "TipsArch", "TipsTextEncoder", "TipsVisionTransformer", "resolve_arch"]


@dataclass(frozen=True)
class TipsArch:
    """Sizes of one TIPS model (both towers).

    ``mlp_hidden`` is ``mlp_ratio * width`` as the repo passes it; a SwiGLU MLP (``ffn =
    "swiglu"``) narrows it to ``(int(mlp_hidden * 2 / 3) + 7) // 8 * 8``. ``pos_grid`` is the
    side of the checkpoint's positional grid; ``stem`` names the release files.
    """

    width: int
    depth: int
    heads: int
    mlp_hidden: int
    ffn: str
    text_layers: int
    text_heads: int
    text_mlp: int
    patch_size: int = 14
    pos_grid: int = 32
    num_registers: int = 1
    vocab_size: int = 32000
    max_len: int = 64
    stem: str | None = None


#: The TIPSv2 PyTorch release: ``pytorch/image_encoder.py`` (``vit_base``, ``vit_large``,
#: ``vit_so400m``, ``vit_giant2``; ``ffn_layer="swiglu"`` for g only) and
#: ``run_text_encoder_inference.get_config``.
TIPS_VARIANTS: dict[str, TipsArch] = {
    "B": TipsArch(768, 12, 12, 3072, "mlp", 12, 12, 3072, stem="tips_v2_oss_b14"),
    "L": TipsArch(1024, 24, 16, 4096, "mlp", 12, 16, 4096, stem="tips_v2_oss_l14"),
    "So400m": TipsArch(1152, 27, 16, 4304, "mlp", 27, 16, 4304, stem="tips_v2_oss_so14"),
    "g": TipsArch(1536, 40, 24, 6144, "swiglu", 12, 24, 6144, stem="tips_v2_oss_g14"),
}
_ALIASES = {"b": "B", "l": "L", "so": "So400m", "so400m": "So400m", "g": "g"}


# --------------------------------------------------------------------------- vision tower
class _PatchEmbed(nn.Module):
    def __init__(self, patch_size: int, width: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, width, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: Tensor) -> Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)  # [B, N, D], row-major grid


class _LayerScale(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class _Attention(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.num_heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads).unbind(2)
        out = F.scaled_dot_product_attention(
            q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2)
        )
        return self.proj(out.transpose(1, 2).reshape(b, n, d))

    def value_path(self, x: Tensor) -> Tensor:
        """MaskCLIP's path: every token keeps its own value (no attention)."""
        d = x.shape[-1]
        return self.proj(self.qkv(x)[..., 2 * d :])


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class _SwiGLU(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        hidden = (int(hidden * 2 / 3) + 7) // 8 * 8
        self.w12 = nn.Linear(dim, 2 * hidden)
        self.w3 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        x1, x2 = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(x1) * x2)


class _Block(nn.Module):
    def __init__(self, arch: TipsArch) -> None:
        super().__init__()
        d = arch.width
        self.norm1 = nn.LayerNorm(d, eps=1e-6)
        self.attn = _Attention(d, arch.heads)
        self.ls1 = _LayerScale(d)
        self.norm2 = nn.LayerNorm(d, eps=1e-6)
        if arch.ffn == "swiglu":
            self.mlp: nn.Module = _SwiGLU(d, arch.mlp_hidden)
        elif arch.ffn == "mlp":
            self.mlp = _Mlp(d, arch.mlp_hidden)
        else:
            raise ConfigError(f"ffn={arch.ffn!r}: expected 'mlp' or 'swiglu'")
        self.ls2 = _LayerScale(d)

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))

    def value_forward(self, x: Tensor) -> Tensor:
        """The block with its attention replaced by the value path (zero-shot segmentation)."""
        x = x + self.ls1(self.attn.value_path(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class TipsVisionTransformer(nn.Module):
    """TIPS's image encoder (``pytorch/image_encoder.VisionTransformer``, inference path).

    Parameter names follow the release's state dict: ``cls_token``, ``pos_embed``,
    ``register_tokens``, ``mask_token`` (unused at inference, kept for strict loading),
    ``patch_embed.proj``, ``blocks.<i>.{norm1, attn.qkv, attn.proj, ls1.gamma, norm2,
    mlp.{fc1, fc2 | w12, w3}, ls2.gamma}``, ``norm``.
    """

    def __init__(self, arch: TipsArch) -> None:
        super().__init__()
        d = arch.width
        self.patch_size = arch.patch_size
        self.num_register_tokens = arch.num_registers
        self.patch_embed = _PatchEmbed(arch.patch_size, d)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + arch.pos_grid**2, d))
        self.register_tokens = nn.Parameter(torch.zeros(1, arch.num_registers, d))
        self.mask_token = nn.Parameter(torch.zeros(1, d))
        self.blocks = nn.ModuleList(_Block(arch) for _ in range(arch.depth))
        self.norm = nn.LayerNorm(d, eps=1e-6)

    def positional_embedding(self, grid: tuple[int, int]) -> Tensor:
        """``[1, 1 + gh * gw, D]``: the checkpoint's grid, bilinearly resized (antialiased)."""
        n = self.pos_embed.shape[1] - 1
        side = math.isqrt(n)
        if grid == (side, side):
            return self.pos_embed
        patch = self.pos_embed[:, 1:].float().reshape(1, side, side, -1).permute(0, 3, 1, 2)
        patch = F.interpolate(patch, size=grid, mode="bilinear", antialias=True)
        patch = patch.permute(0, 2, 3, 1).reshape(1, grid[0] * grid[1], -1)
        return torch.cat([self.pos_embed[:, :1], patch.to(self.pos_embed.dtype)], dim=1)

    def prepare_tokens(self, x: Tensor) -> Tensor:
        """Images ``[B, 3, H, W]`` -> ``[B, 1 + R + N, D]`` (CLS, registers, patches)."""
        grid = (x.shape[-2] // self.patch_size, x.shape[-1] // self.patch_size)
        tokens = self.patch_embed(x)
        tokens = torch.cat([self.cls_token.expand(tokens.shape[0], -1, -1), tokens], dim=1)
        tokens = tokens + self.positional_embedding(grid)
        registers = self.register_tokens.expand(tokens.shape[0], -1, -1)
        return torch.cat([tokens[:, :1], registers, tokens[:, 1:]], dim=1)

    def dense_features(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """One pass -> (first CLS ``[B, D]``, final-norm patch tokens ``[B, N, D]``,
        value-path patch tokens ``[B, N, D]``); the last block runs both ways."""
        tokens = self.prepare_tokens(x)
        *body, last = self.blocks
        for block in body:
            tokens = block(tokens)
        final = self.norm(last(tokens))
        values = self.norm(last.value_forward(tokens))
        start = 1 + self.num_register_tokens
        return final[:, 0], final[:, start:], values[:, start:]


# ----------------------------------------------------------------------------- text tower
def _sinusoids(length: int, dim: int, device: torch.device) -> Tensor:
    """``[1, length, dim]``: sin / cos halves, timescales 1 .. 10^4 (``PositionalEmbedding``)."""
    half = dim // 2
    step = math.log(10_000.0) / max(half - 1, 1)
    inv = torch.exp(torch.arange(half, dtype=torch.float32, device=device) * -step)
    angles = torch.arange(length, dtype=torch.float32, device=device)[:, None] * inv[None]
    signal = torch.cat([torch.sin(angles), torch.cos(angles)], dim=1)
    return F.pad(signal, (0, dim % 2))[None]


class _TextMlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.c_fc = nn.Linear(dim, hidden)
        self.c_proj = nn.Linear(hidden, dim)

    def forward(self, x: Tensor, valid: Tensor) -> Tensor:
        x = F.relu(self.c_fc(x)) * valid[..., None]
        return self.c_proj(x) * valid[..., None]


class _TextBlock(nn.Module):
    def __init__(self, dim: int, heads: int, hidden: int) -> None:
        super().__init__()
        self.num_heads = heads
        self.attn = nn.MultiheadAttention(dim, heads)  # its parameters only (names)
        self.ln_1 = nn.LayerNorm(dim)
        self.mlp = _TextMlp(dim, hidden)
        self.ln_2 = nn.LayerNorm(dim)

    def _attention(self, x: Tensor, valid: Tensor) -> Tensor:
        b, n, d = x.shape
        qkv = F.linear(x, self.attn.in_proj_weight, self.attn.in_proj_bias)
        q, k, v = qkv.reshape(b, n, 3, self.num_heads, d // self.num_heads).unbind(2)
        mask = valid.bool()[:, None, None, :]  # attend to non-padding keys only
        out = F.scaled_dot_product_attention(
            q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2), attn_mask=mask
        )
        return self.attn.out_proj(out.transpose(1, 2).reshape(b, n, d))

    def forward(self, x: Tensor, valid: Tensor) -> Tensor:
        x = x + self._attention(self.ln_1(x), valid)
        return x + self.mlp(self.ln_2(x), valid)


class _TextTransformer(nn.Module):
    def __init__(self, arch: TipsArch) -> None:
        super().__init__()
        self.resblocks = nn.ModuleList(
            _TextBlock(arch.width, arch.text_heads, arch.text_mlp) for _ in range(arch.text_layers)
        )

    def forward(self, x: Tensor, valid: Tensor) -> Tensor:
        for block in self.resblocks:
            x = block(x, valid)
        return x


class TipsTextEncoder(nn.Module):
    """TIPS's text encoder (``pytorch/text_encoder.TextEncoder``): ``token_embedding``,
    ``transformer.resblocks.<i>.{attn.in_proj_*, attn.out_proj, ln_1, mlp.c_fc, mlp.c_proj,
    ln_2}``, ``ln_final``; output = mean of the non-padding tokens after ``ln_final``."""

    def __init__(self, arch: TipsArch) -> None:
        super().__init__()
        self.width = arch.width
        self.token_embedding = nn.Embedding(arch.vocab_size, arch.width)
        self.transformer = _TextTransformer(arch)
        self.ln_final = nn.LayerNorm(arch.width)

    def forward(self, ids: Tensor, paddings: Tensor) -> Tensor:
        """``ids`` ``[K, L]`` and ``paddings`` ``[K, L]`` (1 = padding) -> ``[K, D]``."""
        valid = (paddings == 0).to(torch.float32)
        x = self.token_embedding(ids) * self.width**0.5
        x = x + _sinusoids(ids.shape[1], self.width, x.device).to(x.dtype)
        x = self.ln_final(self.transformer(x, valid))
        x = x * valid[..., None]
        return x.sum(dim=1) / (valid.sum(dim=1, keepdim=True) + 1e-8)


def resolve_arch(variant: str | Mapping[str, Any] | TipsArch) -> TipsArch:
    """The sizes of ``variant``: a release name of :data:`TIPS_VARIANTS` (or its alias), a
    :class:`TipsArch`, or a mapping of its fields (``base`` names a release to change)."""
    if isinstance(variant, TipsArch):
        return variant
    if isinstance(variant, Mapping):  # a custom size (tests); a base variant may be named
        spec = dict(variant)
        base = spec.pop("base", None)
        names = {f.name for f in fields(TipsArch)}
        unknown = sorted(set(spec) - names)
        if unknown:
            raise ConfigError(f"variant: unknown fields {unknown} (fields: {sorted(names)})")
        if base is not None:
            return replace(resolve_arch(str(base)), **spec)
        return TipsArch(**spec)
    name = _ALIASES.get(str(variant).lower())
    if name is None:
        raise ConfigError(f"variant={variant!r}: expected one of {list(TIPS_VARIANTS)}")
    return TIPS_VARIANTS[name]
