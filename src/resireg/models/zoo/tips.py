"""TIPSv2 (Google DeepMind, "Text-Image Pretraining with Spatial awareness", v2) as a
:class:`DenseEncoder`: a backbone-only reference.

What the release is (read from github.com/google-deepmind/tips: ``README.md``,
``pytorch/image_encoder.py``, ``pytorch/text_encoder.py``,
``pytorch/run_image_encoder_inference.py``, ``pytorch/run_text_encoder_inference.py``,
``pytorch/checkpoints/download_checkpoints.sh``, ``pytorch/TIPS_Demo.ipynb`` and
``pytorch/TIPS_zeroshot_segmentation.ipynb``); this module reimplements the same
architecture with the same parameter names, so it loads the release files as they are:

- Files: one NumPy ``.npz`` per tower, a flat PyTorch state dict (name -> array), read with
  ``np.load(path, allow_pickle=False)`` and loaded with ``load_state_dict`` (strict):
  ``tips_v2_oss_{b14,l14,so14,g14}_{vision,text}.npz`` at
  ``https://storage.googleapis.com/tips_data/v2_0/checkpoints/pytorch/``; the text file also
  holds ``temperature`` (dropped, as the repo does). The tokenizer is a SentencePiece model
  shared with TIPS v1, ``https://storage.googleapis.com/tips_data/v1_0/checkpoints/tokenizer.model``
  (32000 ids, padding id 0). (JAX/Scenic ``.npz`` files with other names and layouts are
  published too, and converted weights as Hugging Face ``google/tipsv2-{b14,l14,so400m14,g14}``
  for transformers' ``Tipsv2Model``; neither is what this module reads.)
- Image encoder: a DINOv2-style ViT with patch 14, one register token (which TIPS uses as
  a second CLS token), LayerScale (``init_values=1.0``), LayerNorm eps 1e-6, qkv bias, no
  block chunking (``block_chunks=0``). B/14: width 768, 12 blocks, 12 heads; L/14: 1024, 24,
  16; So400m/14: 1152, 27, 16, MLP 4304; g/14 (``vit_giant2``): 1536, 40, 24, SwiGLU MLP
  (``w12`` / ``w3``, hidden ``(int(4 * 1536 * 2 / 3) + 7) // 8 * 8 = 4096``); the others a
  GELU MLP (``fc1`` / ``fc2``). TIPSv2 checkpoints hold a 32 x 32 positional grid (448 px);
  other sizes interpolate it bilinearly with antialiasing and no offset
  (``interpolate_antialias=True, interpolate_offset=0.0``).
- Input: RGB in [0, 1], no normalisation (``IMAGE_MEAN = (0, 0, 0)``, ``IMAGE_STD = (1, 1, 1)``).
- Text encoder: token embedding (scaled by ``sqrt(width)``) plus fixed sinusoidal positions,
  pre-norm transformer blocks (``nn.MultiheadAttention`` masked on padding, ReLU MLP whose
  output is zeroed on padding), ``ln_final``, mean over the non-padding tokens; no
  projection. Width equals the vision width; 12 layers (27 for So400m). Tokenisation: lower
  case (``tf.strings.lower``, ASCII), SentencePiece ids without BOS / EOS, cut or padded with
  0 to 64.
- Zero-shot segmentation (``TIPS_zeroshot_segmentation.ipynb``): the MaskCLIP "values trick"
  on the last block. With ``x`` the last block's input, the value slice of
  ``attn.qkv(norm1(x))`` goes through ``attn.proj`` and ``ls1`` and is added to ``x`` (no
  attention), then the block's MLP residual (``x + ls2(mlp(norm2(x)))``) and the final
  ``norm`` follow; the patch tokens of that (CLS and register dropped) are compared, L2
  normalised, with the normalised text embeddings. No projection on either side.
- Image-text (``TIPS_Demo.ipynb``, Hugging Face ``Tipsv2Model``): the first CLS token after
  the final norm.

This adapter, in one pass of the vision tower:

- ``intermediates`` ``[B, D, h, w]``: the final-norm patch tokens of the ordinary forward
  (``x_norm_patchtokens``),
- ``language`` ``[B, D, h, w]``: the value-path patch tokens above (what TIPS segments with;
  a different tensor from the intermediates, sharing all blocks but the last), raw (the
  ``bb`` variant normalises). ``language_tokens="final"`` takes the final-norm patch tokens
  instead (then ``language`` and ``intermediates`` are the same tokens; the snippet once on
  the Hugging Face model cards did this, the repo's zero-shot notebook does not),
- ``embedding`` ``[B, D]``: the first CLS token (not normalised),
- ``encode_text``: the text tower's pooled embedding, L2-normalised (``[K, D]``, the width of
  the language tokens).

Resolution: with ``image_size=574`` (default) every canvas batch ``[B, 3, H, W]`` is resized
(bilinear, ``align_corners=False``) to ``574 x 574`` (41 x 41 patches; the 32 x 32
positional grid is interpolated as the repo does), and both dense maps are resized
bilinearly (``align_corners=False``) to the canvas's patch grid ``(H / 14, W / 14)``.
``image_size=None`` runs each canvas at its own size. TIPS's own zero-shot evaluation instead
slides 448 px windows (stride 336) over a short-side-448 image; here it is one pass.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.errors import ConfigError
from resireg.models.frozen import FrozenModule
from resireg.models.hub import WeightsUnavailableError
from resireg.models.images import resize_square, tokens_to_grid
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule

__all__ = [
    "TIPS_TOKENIZER_URL",
    "TIPS_VARIANTS",
    "TIPS_WEIGHTS_URL",
    "SentencePieceTokenizer",
    "TipsArch",
    "TipsEncoder",
    "TipsTextEncoder",
    "TipsVisionTransformer",
    "load_npz_state_dict",
]

#: Folder of the TIPSv2 PyTorch checkpoints (``<stem>_vision.npz``, ``<stem>_text.npz``).
TIPS_WEIGHTS_URL = "https://storage.googleapis.com/tips_data/v2_0/checkpoints/pytorch/"
#: The SentencePiece tokenizer (shared by TIPS v1 and v2).
TIPS_TOKENIZER_URL = "https://storage.googleapis.com/tips_data/v1_0/checkpoints/tokenizer.model"
TOKENIZER_FILE = "tokenizer.model"


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


# ---------------------------------------------------------------------- files and tokens
class _Tokenizer(Protocol):
    def encode(self, text: str) -> list[int]: ...


class SentencePieceTokenizer:
    """TIPS's tokenizer file through the ``sentencepiece`` package (no BOS / EOS)."""

    def __init__(self, path: str | os.PathLike) -> None:
        try:
            import sentencepiece
        except ImportError as err:
            raise ImportError(
                "TIPS's tokenizer is a SentencePiece model: pip install sentencepiece"
            ) from err
        self.path = os.fspath(path)
        self.model = sentencepiece.SentencePieceProcessor(model_file=self.path)

    def encode(self, text: str) -> list[int]:
        return list(self.model.encode(text))


_ASCII_LOWER = str.maketrans("ABCDEFGHIJKLMNOPQRSTUVWXYZ", "abcdefghijklmnopqrstuvwxyz")


def load_npz_state_dict(path: str | os.PathLike) -> dict[str, Tensor]:
    """A release ``.npz`` -> ``{name: float32 tensor}`` (``np.load(allow_pickle=False)``)."""
    with np.load(os.fspath(path), allow_pickle=False) as arrays:
        return {k: torch.from_numpy(np.asarray(arrays[k])).to(torch.float32) for k in arrays.files}


def _resolve_arch(variant: str | Mapping[str, Any] | TipsArch) -> TipsArch:
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
            return replace(_resolve_arch(str(base)), **spec)
        return TipsArch(**spec)
    name = _ALIASES.get(str(variant).lower())
    if name is None:
        raise ConfigError(f"variant={variant!r}: expected one of {list(TIPS_VARIANTS)}")
    return TIPS_VARIANTS[name]


def _hint(stem: str) -> str:
    return (
        f"TIPSv2 weights are not downloaded automatically: fetch {stem}_vision.npz and "
        f"{stem}_text.npz from {TIPS_WEIGHTS_URL} and {TOKENIZER_FILE} from "
        f"{TIPS_TOKENIZER_URL} into one folder, then pass weights=/path/to/"
        f"{stem}_vision.npz (or the folder); the text weights and the tokenizer are found "
        f"beside it, or pass text_weights= / tokenizer=."
    )


def _resolve_files(
    arch: TipsArch,
    weights: str | os.PathLike | None,
    text_weights: str | os.PathLike | None,
    tokenizer: Any,
) -> tuple[str, str, Any]:
    """(vision npz, text npz, tokenizer path or object); a missing file raises at once."""
    stem = arch.stem or "tips_v2_oss_<size>14"
    hint = _hint(stem)
    if weights is None:
        raise WeightsUnavailableError(f"weights is not set. {hint}")
    vision = os.fspath(weights)
    if os.path.isdir(vision):
        if arch.stem is None:
            raise ConfigError(f"weights={vision!r}: a folder needs a release variant")
        vision = os.path.join(vision, f"{arch.stem}_vision.npz")
    if not os.path.isfile(vision):
        raise WeightsUnavailableError(f"weights={vision!r}: no such file. {hint}")
    folder = os.path.dirname(vision)
    if text_weights is None:
        base = os.path.basename(vision)
        if not base.endswith("_vision.npz"):
            raise WeightsUnavailableError(
                f"text_weights is not set and weights={vision!r} does not end in "
                f"'_vision.npz' (no release name to derive it from). {hint}"
            )
        text = os.path.join(folder, base[: -len("_vision.npz")] + "_text.npz")
    else:
        text = os.fspath(text_weights)
    if not os.path.isfile(text):
        raise WeightsUnavailableError(f"text_weights={text!r}: no such file. {hint}")
    if tokenizer is None or isinstance(tokenizer, (str, os.PathLike)):
        path = os.path.join(folder, TOKENIZER_FILE) if tokenizer is None else os.fspath(tokenizer)
        if not os.path.isfile(path):
            raise WeightsUnavailableError(f"tokenizer={path!r}: no such file. {hint}")
        tokenizer = path
    elif not callable(getattr(tokenizer, "encode", None)):
        raise TypeError("tokenizer: expected a path or an object with encode(text)")
    return vision, text, tokenizer


def _load(module: nn.Module, state: dict[str, Tensor], path: str) -> None:
    try:
        module.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as err:
        raise ValueError(
            f"{path}: not a checkpoint of the configured TIPS size (variant): {err}"
        ) from err


# -------------------------------------------------------------------------------- encoder
class TipsEncoder(DenseEncoder, FrozenModule):
    """Frozen TIPSv2 dense encoder (see the module docstring).

    Args:
        variant: ``"B"``, ``"L"``, ``"So400m"`` (``"So"``) or ``"g"`` (the release's sizes,
            :data:`TIPS_VARIANTS`), or a mapping of :class:`TipsArch` fields (a custom size;
            ``base`` names a variant to start from).
        weights: the vision checkpoint ``<stem>_vision.npz`` (or the folder holding the
            release files). Required: nothing is downloaded.
        text_weights: the text checkpoint; ``None`` = ``<stem>_text.npz`` beside ``weights``.
        tokenizer: the SentencePiece ``tokenizer.model`` (``None`` = beside ``weights``), or
            an object with ``encode(text) -> list[int]``.
        image_size: side of the square model input every canvas is resized to (a multiple of
            14), or ``None`` to run canvases at their own size.
        language_tokens: ``"values"`` (the last block's value path, TIPS's zero-shot
            segmentation) or ``"final"`` (the final-norm patch tokens, = the intermediates).
        device: where the model is placed (default CPU).
        text_batch_size: texts per text-tower call.
    """

    def __init__(
        self,
        variant: str | Mapping[str, Any] | TipsArch = "g",
        weights: str | os.PathLike | None = None,
        text_weights: str | os.PathLike | None = None,
        tokenizer: str | os.PathLike | _Tokenizer | None = None,
        image_size: int | None = 574,
        language_tokens: str = "values",
        device: str | torch.device | None = None,
        text_batch_size: int = 256,
    ) -> None:
        super().__init__()
        if language_tokens not in ("values", "final"):
            raise ConfigError(f"language_tokens={language_tokens!r}: 'values' or 'final'")
        self.language_tokens = language_tokens
        arch = _resolve_arch(variant)
        self.arch = arch
        self.patch_size = arch.patch_size
        if image_size is not None and (image_size <= 0 or image_size % self.patch_size):
            raise ConfigError(
                f"image_size={image_size}: not a positive multiple of the patch size "
                f"{self.patch_size}"
            )
        self.image_size = image_size
        self.text_batch_size = int(text_batch_size)
        vision_path, text_path, tok = _resolve_files(arch, weights, text_weights, tokenizer)
        self.weights, self.text_weights = vision_path, text_path
        self.tokenizer_path = tok if isinstance(tok, str) else None
        self.tokenizer = SentencePieceTokenizer(tok) if isinstance(tok, str) else tok

        with torch.device("meta"):  # no random init of ~1.5B parameters: the files fill them
            self.visual = TipsVisionTransformer(arch)
            self.text = TipsTextEncoder(arch)
        _load(self.visual, load_npz_state_dict(vision_path), vision_path)
        text_state = load_npz_state_dict(text_path)
        for name in [n for n in text_state if n.startswith("temperature")]:
            del text_state[name]  # the contrastive temperature (popped by the repo too)
        _load(self.text, text_state, text_path)
        self.to(torch.device(device if device is not None else "cpu"))
        self.freeze()

    def spec(self) -> dict[str, Any]:
        """``kind`` and the constructor arguments that rebuild this encoder (``device`` aside):
        the release size by name (else every :class:`TipsArch` field) and the resolved file
        paths. An encoder built with a tokenizer *object* has no such config (ValueError)."""
        if self.tokenizer_path is None:
            raise ValueError(
                f"this TipsEncoder was built with a tokenizer object "
                f"({type(self.tokenizer).__name__}); only a tokenizer file has a config"
            )
        named = [n for n, arch in TIPS_VARIANTS.items() if arch == self.arch]
        return {
            "kind": "tips",
            "variant": named[0] if named else asdict(self.arch),
            "weights": self.weights,
            "text_weights": self.text_weights,
            "tokenizer": self.tokenizer_path,
            "image_size": self.image_size,
            "language_tokens": self.language_tokens,
            "text_batch_size": self.text_batch_size,
        }

    # ------------------------------------------------------------------ interface
    @property
    def input_rule(self) -> InputRule:
        return InputRule(self.patch_size, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))

    def encode(self, images: Tensor) -> DenseOutput:
        self.input_rule.check_size(images)
        _, _, h, w = images.shape
        p = self.patch_size
        x = resize_square(images.to(self.device, torch.float32), self.image_size)
        native = (x.shape[-2] // p, x.shape[-1] // p)
        with torch.no_grad():
            cls, patches, values = self.visual.dense_features(x)
        grid = (h // p, w // p)
        intermediates = tokens_to_grid(patches, native, grid)
        if self.language_tokens == "final":
            language = intermediates
        else:
            language = tokens_to_grid(values, native, grid)
        return DenseOutput(intermediates, language, cls.float())

    def tokenize(self, texts: Sequence[str]) -> tuple[Tensor, Tensor]:
        """Texts -> (ids ``[K, 64]`` long, paddings ``[K, 64]`` float, 1 = padding), as the
        repo's ``Tokenizer.tokenize``: ASCII lower case, no BOS / EOS, cut / padded with 0."""
        n = self.arch.max_len
        ids = torch.zeros(len(texts), n, dtype=torch.long)
        for i, text in enumerate(texts):
            tokens = list(self.tokenizer.encode(text.translate(_ASCII_LOWER)))[:n]
            if not tokens:
                raise ValueError(f"text {text!r} has no tokens")
            ids[i, : len(tokens)] = torch.tensor(tokens, dtype=torch.long)
        return ids, (ids == 0).to(torch.float32)

    def text_features(self, texts: Sequence[str]) -> Tensor:
        """TIPS text embeddings ``[K, D]`` (not normalised)."""
        texts = [texts] if isinstance(texts, str) else list(texts)
        out = []
        with torch.no_grad():
            for i in range(0, len(texts), self.text_batch_size):
                ids, paddings = self.tokenize(texts[i : i + self.text_batch_size])
                out.append(self.text(ids.to(self.device), paddings.to(self.device)).float())
        return torch.cat(out) if out else torch.zeros(0, self.arch.width, device=self.device)

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        return self.dense_text(self.text_features(texts))
