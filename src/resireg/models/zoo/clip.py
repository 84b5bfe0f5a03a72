"""``ClipEncoder``: OpenAI CLIP ViT-B/16 and ViT-L/14@336 (open_clip) as a :class:`DenseEncoder`.

One frozen open_clip ``CLIP`` model gives everything:

- ``intermediates`` ``[B, width, H/p, W/p]``: the tokens of one earlier block
  (``intermediate_layer``): that block's output (the residual stream, no final norm),
  class token dropped, patch tokens reshaped to the grid. Default: SC-CLIP's mid-level
  block (see :class:`ClipEncoder`). :meth:`ClipEncoder.encode_layers` returns, from the
  same single pass, the tokens of every block it is asked for (``DenseOutput.layers``: the
  CLIP layer sweep, docs/method.md#2d-evaluation-ovss).
- ``language`` ``[B, embed_dim, H/p, W/p]``: the dense tokens of the last block with its
  attention replaced by the identity (every token attends only to itself), then
  ``ln_post`` and ``proj``. With ``x`` the last block's input and
  ``a = ls_1(out_proj(V(ln_1(x))))`` (``V`` the value slice of its attention's
  ``in_proj``), ``dense_path`` chooses what follows:

  - ``"value"`` (default): ``ln_post(a) @ proj``. The block's residual and MLP are dropped
    too. This is the value path of SC-CLIP's last block (SuleBai/SC-CLIP
    ``clip/model.py``, ``VisionTransformer.forward``: ``custom_attn`` with no residual or
    MLP, then ``ln_post @ proj``), of ClearCLIP and NACLIP (``arch="reduced"``), and of the
    MaskCLIP port OTAS ships (SimonSchwaiger/otas
    ``src/foundation_models/maskclip_onnx/model.py``, ``ResidualAttentionBlock.forward_v``,
    whose comment says adding the residual or the MLP "degrades the performance").
  - ``"maskclip"``: ``ln_post(y + ls_2(mlp(ln_2(y)))) @ proj`` with ``y = x + a``: the
    official MaskCLIP release (chongzhou96/MaskCLIP ``mmseg/models/backbones/vit.py``,
    ``TransformerEncoderLayer.forward`` with ``return_qkv``: ``v += x`` then
    ``v = self.ffn(self.norm2(v), identity=v)``; ``final_norm`` and the ``MaskClipHead``
    ``proj`` follow), which keeps the residual and the MLP.

  Why ``value`` is the default: docs/protocol.md section 2.
- ``embedding`` ``[B, embed_dim]``: the ordinary CLIP image embedding (class token,
  ``ln_post``, ``proj``; not normalised), i.e. ``model.encode_image``.

``encode_text`` gives open_clip's text embedding of the same model, normalised
(``[K, embed_dim]``, the language tokens' space).

**Resolution.** CLIP's ViTs are run at their native input resolution in a single pass:
the canvas ``[B, 3, H, W]`` is resized (bilinear, antialiased) to ``image_size`` x
``image_size`` (224 for ViT-B-16, 336 for ViT-L-14-336), so the positional embedding
is used exactly as trained, and both dense maps are upsampled bilinearly from the native
grid (14 x 14, 24 x 24) to the canvas grid ``(H/p, W/p)``. This undoes the aspect
distortion of the square resize; the maps are as coarse as the native grid. A sliding
window over the canvas (SCLIP / SC-CLIP's evaluation, 224 crops, stride 112) would keep
more detail but needs several passes per image and window stitching: the protocol here
is one pass at native resolution, so ReSiReg is compared on the backbone's own grid.
Resizing the already normalised batch equals normalising the resized image (bilinear
weights sum to one and the normalisation is per-channel affine).

**Weights.** ``weights="openai"`` is open_clip's tag (from the Hugging Face cache, or
downloaded when online; offline with nothing cached it fails at once with a
:class:`~resireg.models.hub.WeightsUnavailableError` naming ``weights``), a local
open_clip checkpoint file (a state dict: ``.bin`` / ``.pt`` / ``.safetensors``, loaded by
``open_clip.create_model(..., pretrained=path)``), or ``None`` for a seeded random init
(tests). The architecture is always built with QuickGELU, the activation the OpenAI
weights were trained with (open_clip's plain ``ViT-B-16`` config uses nn.GELU and only
warns about the mismatch).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import open_clip
import torch
import torch.nn.functional as F
from open_clip.transformer import ResidualAttentionBlock
from torch import Tensor

from resireg.errors import ConfigError
from resireg.models.frozen import FrozenModule
from resireg.models.hub import require_open_clip_tag
from resireg.models.images import tokens_to_grid
from resireg.models.interface import DenseEncoder, DenseOutput, InputRule, block_index

__all__ = ["CLIP_MODELS", "DENSE_PATHS", "ClipEncoder", "check_dense_path", "require_clip_weights"]

#: Supported open_clip model names -> default ``intermediate_layer`` (0-based block index).
#: ViT-B-16: SC-CLIP's ``pre_adjust_idx = 8`` (the 9th of 12 blocks); ViT-L-14-336: the
#: same relative depth (18th of 24 blocks), see :class:`ClipEncoder`.
CLIP_MODELS = {"ViT-B-16": 8, "ViT-L-14-336": 17}

#: ``dense_path`` values: what the last block does to the language tokens (module docstring).
DENSE_PATHS = ("value", "maskclip")


def check_dense_path(dense_path: str, name: str = "dense_path") -> str:
    """``dense_path`` if it is one of :data:`DENSE_PATHS`, else a
    :class:`~resireg.errors.ConfigError` naming the argument ``name``."""
    if dense_path not in DENSE_PATHS:
        raise ConfigError(
            f"{name}={dense_path!r}: expected one of {list(DENSE_PATHS)} "
            "(value: SC-CLIP's / OTAS's value path; maskclip: the official MaskCLIP, with the "
            "last block's residual and MLP)"
        )
    return dense_path


def require_clip_weights(model_name: str, weights: str, name: str = "weights") -> None:
    """Raise :class:`~resireg.models.hub.WeightsUnavailableError` at once when the open_clip
    tag ``weights`` of ``model_name`` is neither cached nor downloadable (the hint names the
    argument ``name``); an unknown tag is a ValueError naming it
    (:func:`~resireg.models.hub.require_open_clip_tag`)."""
    hint = (
        f"Pass a local file instead: {name}=/path/to/open_clip_pytorch_model.bin (an "
        f"open_clip checkpoint of {model_name} with OpenAI weights, .bin / .pt / .safetensors), "
        f"or {name}=null for a random init."
    )
    require_open_clip_tag(model_name, weights, name, hint)


class ClipEncoder(DenseEncoder, FrozenModule):
    """Frozen OpenAI CLIP ViT as a dense encoder (the last block's value path as language
    tokens, with or without its residual and MLP: ``dense_path``).

    Args:
        model_name: ``"ViT-B-16"`` (patch 16, width 768, 12 blocks, embed 512) or
            ``"ViT-L-14-336"`` (patch 14, width 1024, 24 blocks, embed 768).
        weights: ``"openai"`` (open_clip tag), a local open_clip checkpoint file, or ``None``
            (random init seeded by ``seed``).
        intermediate_layer: the block whose output tokens are the intermediates (0-based;
            negative counts from the end, ``-1`` = the last block). ``None`` (default): SC-CLIP's
            choice, block 8 of ViT-B/16 (its ``pre_adjust_idx``: the 9th of 12 blocks, three
            before the last), whose token affinities SC-CLIP found semantically coherent and
            uses to recalibrate the last block's attention and to aggregate its output. The
            deepest blocks are dominated by global, image-level information and by a few
            high-norm anomaly tokens, the shallow ones by low-level appearance; a mid-to-late
            block groups patches by object/stuff while staying spatially local, which is what
            ReSiReg clusters and attends with. SC-CLIP's release configures only ViT-B/16; for
            ViT-L-14-336 the default keeps the same relative depth, block 17 (18th of 24).
            SCLIP and MaskCLIP themselves use no intermediate block (only the last block).
        dense_path: ``"value"`` (default; SC-CLIP's / OTAS's language tokens: no residual or
            MLP in the last block) or ``"maskclip"`` (the official MaskCLIP code's: the last
            block's residual and MLP kept); see the module docstring.
        image_size: native input side of the ViT; ``None`` = the model's own (224 / 336). Other
            sizes build the positional embedding at that grid (open_clip interpolates a
            checkpoint's embedding when it loads it).
        device: where the model lives.
        seed: seed of the random init (``weights=None``), so a random encoder is rebuilt
            identically.
    """

    def __init__(
        self,
        model_name: str = "ViT-B-16",
        weights: str | os.PathLike | None = "openai",
        intermediate_layer: int | None = None,
        image_size: int | None = None,
        device: str | torch.device | None = None,
        seed: int = 0,
        dense_path: str = "value",
    ) -> None:
        super().__init__()
        if model_name not in CLIP_MODELS:
            raise ConfigError(f"model_name={model_name!r}: choose from {list(CLIP_MODELS)}")
        cfg = open_clip.get_model_config(model_name)
        vision = cfg["vision_cfg"]
        self.model_name = model_name
        self.weights = None if weights is None else os.fspath(weights)
        self.image_size = int(image_size or vision["image_size"])
        self.patch_size = int(vision["patch_size"])
        self.depth = int(vision["layers"])
        self.width = int(vision["width"])
        self.embed_dim = int(cfg["embed_dim"])
        self.seed = seed
        self.dense_path = check_dense_path(dense_path)
        if self.image_size % self.patch_size:
            raise ConfigError(
                f"image_size={self.image_size} is not a multiple of the patch size {self.patch_size}"
            )
        default = CLIP_MODELS[model_name]
        self.intermediate_layer = self._check_layer(
            default if intermediate_layer is None else intermediate_layer
        )
        if self.weights is not None and not os.path.isfile(self.weights):
            require_clip_weights(model_name, self.weights)

        kwargs: dict[str, Any] = {"force_quick_gelu": True}
        if self.image_size != vision["image_size"]:
            kwargs["force_image_size"] = self.image_size
        if self.weights is None:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                model = open_clip.create_model(model_name, pretrained=None, **kwargs)
        else:
            model = open_clip.create_model(model_name, pretrained=self.weights, **kwargs)
        self._check_architecture(model)
        self.model = model
        self.tokenizer = open_clip.get_tokenizer(model_name)  # bundled CLIP BPE: offline
        self._input_rule = InputRule(
            self.patch_size,
            tuple(open_clip.OPENAI_DATASET_MEAN),
            tuple(open_clip.OPENAI_DATASET_STD),
        )
        if device is not None:
            self.to(device)
        self.freeze()

    def _check_layer(self, layer: int, name: str = "intermediate_layer") -> int:
        """One block as a 0-based index (:func:`~resireg.models.interface.block_index`)."""
        return block_index(self.depth, layer, name, self.model_name)

    def check_layers(self, layers: Sequence[int], name: str = "layer") -> tuple[int, ...]:
        """The blocks of :meth:`encode_layers` as 0-based indices (the rule of
        :func:`~resireg.models.interface.block_indices`: negative ones counted from the end),
        sorted and each once; an index out of range is a ValueError naming ``name``."""
        return tuple(sorted({block_index(self.depth, i, name, self.model_name) for i in layers}))

    @staticmethod
    def _check_architecture(model: Any) -> None:
        visual = model.visual
        blocks = visual.transformer.resblocks
        if (
            visual.attn_pool is not None
            or visual.pool_type != "tok"
            or visual.final_ln_after_pool
            or visual.proj is None
            or not all(type(b) is ResidualAttentionBlock for b in blocks)
            or not all(
                b.attn._qkv_same_embed_dim and b.attn.in_proj_bias is not None for b in blocks
            )
        ):
            raise ValueError("ClipEncoder needs an OpenAI-style CLIP ViT (class token, packed qkv)")

    def spec(self) -> dict[str, Any]:
        """``kind`` and the constructor arguments that rebuild this encoder (``device`` aside)."""
        return {
            "kind": "clip",
            "model_name": self.model_name,
            "weights": self.weights,
            "intermediate_layer": self.intermediate_layer,
            "image_size": self.image_size,
            "seed": self.seed,
            "dense_path": self.dense_path,
        }

    # ------------------------------------------------------- DenseEncoder interface
    @property
    def input_rule(self) -> InputRule:
        return self._input_rule

    @staticmethod
    def value_path(block: ResidualAttentionBlock, x: Tensor) -> Tensor:
        """The value path of ``block`` on its (batch-first) input ``x`` ``[B, L, D]``.

        ``ls_1(out_proj(V(ln_1(x))))``: the attention branch with every token attending only
        to itself (softmax(QK^T) replaced by the identity), no residual, no MLP. Written by
        hand: neither open_clip nor torch exposes the value projection of a packed
        ``nn.MultiheadAttention``, so it is sliced out of ``in_proj_weight`` / ``in_proj_bias``.
        """
        attn = block.attn
        d = attn.embed_dim
        v = F.linear(block.ln_1(x), attn.in_proj_weight[2 * d :], attn.in_proj_bias[2 * d :])
        return block.ls_1(attn.out_proj(v))

    @classmethod
    def dense_tokens(cls, block: ResidualAttentionBlock, x: Tensor, dense_path: str) -> Tensor:
        """The last block's dense tokens ``[B, L, D]`` (before ``ln_post`` and ``proj``) on its
        batch-first input ``x``: :meth:`value_path` alone (``"value"``), or with the block's
        residual and MLP (``"maskclip"``: ``y = x + value_path``, ``y + ls_2(mlp(ln_2(y)))``,
        the official MaskCLIP's ``TransformerEncoderLayer.forward``)."""
        values = cls.value_path(block, x)
        if check_dense_path(dense_path) == "value":
            return values
        y = x + values
        return y + block.ls_2(block.mlp(block.ln_2(y)))

    @torch.no_grad()
    def encode(self, images: Tensor) -> DenseOutput:
        """Normalised images ``[B, 3, H, W]`` -> (intermediates ``[B, width, H/p, W/p]``,
        language tokens ``[B, embed_dim, H/p, W/p]``, embedding ``[B, embed_dim]``), float32."""
        return self._encode(images, ())

    @torch.no_grad()
    def encode_layers(self, images: Tensor, layers: Sequence[int]) -> DenseOutput:
        """:meth:`encode`, plus ``layers``: ``{block: [B, width, H/p, W/p]}``, the output of
        every block in ``layers`` (0-based, negative from the end; keyed by the 0-based
        index) taken as ``intermediates`` is, all from the same single pass."""
        return self._encode(images, self.check_layers(layers))

    def _encode(self, images: Tensor, layers: tuple[int, ...]) -> DenseOutput:
        self._input_rule.check_size(images)
        h, w = images.shape[-2:]
        p, s = self.patch_size, self.image_size
        visual = self.model.visual
        x = images.to(self.device, visual.conv1.weight.dtype)
        if (h, w) != (s, s):
            x = F.interpolate(x, size=(s, s), mode="bilinear", align_corners=False, antialias=True)

        tokens = visual._embeds(x)  # conv1, class token, positional embedding, ln_pre
        transformer = visual.transformer
        batch_first = transformer.batch_first
        if not batch_first:
            tokens = tokens.transpose(0, 1)
        blocks = transformer.resblocks
        wanted = {self.intermediate_layer, *layers}
        seen: dict[int, Tensor] = {}  # block index -> its output, batch-first
        lang = None
        for i, block in enumerate(blocks):
            if i == len(blocks) - 1:  # the last block's input feeds the language tokens
                last_in = tokens if batch_first else tokens.transpose(0, 1)
                lang = self.dense_tokens(block, last_in, self.dense_path)
            tokens = block(tokens)
            if i in wanted:
                seen[i] = tokens if batch_first else tokens.transpose(0, 1)
        if not batch_first:
            tokens = tokens.transpose(0, 1)

        pooled, _ = visual._pool(tokens)  # open_clip's own pooling (class token, ln_post)
        embedding = pooled @ visual.proj
        lang = visual.ln_post(lang) @ visual.proj

        g = s // p
        grid = (h // p, w // p)
        maps = {i: tokens_to_grid(t[:, 1:], (g, g), grid) for i, t in seen.items()}
        return DenseOutput(
            maps[self.intermediate_layer],
            tokens_to_grid(lang[:, 1:], (g, g), grid),
            embedding.float(),
            {i: maps[i] for i in layers} if layers else None,
        )

    def text_features(self, texts: Sequence[str]) -> Tensor:
        """open_clip's text embeddings ``[K, embed_dim]`` (float32, not normalised)."""
        tokens = self.tokenizer(list(texts)).to(self.device)
        with torch.no_grad():
            return self.model.encode_text(tokens).float()

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        """Unit-norm text queries ``[K, embed_dim]``, the language tokens' space."""
        return self.dense_text(self.text_features(texts))
