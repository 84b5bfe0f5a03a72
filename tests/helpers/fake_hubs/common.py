"""Fake torch.hub repositories of the encoder zoo, shared by every test (no network).

Each fake exposes the real entry point(s) with their signatures and returns tiny random
modules with the real attribute layout and output structure, so an adapter runs its real
loading path (``torch.hub.load(..., source="local")``) and the tests recompute expected values
from a second, independently loaded copy through the fake's own modules:

- :data:`FAKE_RADIO`: NVlabs/RADIO ``hubconf.radio_model`` (``RADIOModel``, ``GenericAdaptor``
  with the ``siglip2`` / ``open_clip`` types, ``input_conditioner``,
  ``make_preprocessor_external``, ``min_resolution_step``; weights seeded by the version),
- :data:`FAKE_RADSEG`: RADSeg-OVSS/RADSeg ``hubconf.radseg_encoder`` (``RADSegEncoder``
  loading ``NVlabs/RADIO`` itself through ``torch.hub``: here the hub cache, GitHub
  unreachable; SCRA on the last block, SCGA, ``align_spatial_features_with_language``,
  ``encode_prompts``),
- :data:`RADSEG_STANDIN`: a minimal ``radseg_encoder`` that records its arguments and checks
  that inputs arrive on the device it was built for (the teacher's per-rank build),
- :data:`DINOTXT_FILES`: facebookresearch/dinov2's dino.txt hub code (``hubconf.py`` ->
  ``dinov2.hub.dinotxt``; ``DinoTxt``, its tokenizer package),
- :data:`DINOV2_HUBCONF`: facebookresearch/dinov2 ``dinov2_vits14_reg`` (OTAS's DINOv2),
  the same ViT (:data:`DINOV2_VIT`, one token path) as dino.txt's backbone,
- :func:`write_tips_release`: TIPSv2's release files (no hub: ``.npz`` state dicts) at a tiny
  size (:data:`TIPS_TINY`), and :func:`train_sentencepiece` a real tokenizer file.

:func:`offline_hub` points torch's hub cache at a private folder (with the checkpoints' names
and, optionally, the fake RADIO as ``NVlabs_RADIO_main``) and makes any network probe fail
the test (:func:`refuse_network`); :func:`build_offline` builds an encoder under it (a
module-scoped fixture's), and :func:`token_grid` lays patch tokens out as maps.
"""

from __future__ import annotations

import gzip
import sys
import textwrap
from collections.abc import Iterable
from pathlib import Path
from urllib.error import URLError

import numpy as np
import pytest
import torch

import resireg.models.hub as hub_module

FAKE_RADIO = textwrap.dedent(
    '''
    """Fake NVlabs/RADIO hubconf: tiny random modules with the real layout."""
    dependencies = ["torch"]

    import types
    import zlib
    from typing import NamedTuple

    import torch
    import torch.nn.functional as F
    from torch import nn


    class RadioOutput(NamedTuple):  # radio/adaptor_base.py
        summary: torch.Tensor
        features: torch.Tensor

        def to(self, *args, **kwargs):
            return RadioOutput(self.summary.to(*args, **kwargs), self.features.to(*args, **kwargs))


    class AdaptorInput(NamedTuple):
        images: torch.Tensor
        summary: torch.Tensor
        features: torch.Tensor
        feature_fmt: str
        patch_size: int


    class InputConditioner(nn.Module):  # radio/input_conditioner.py
        def __init__(self, input_scale, norm_mean, norm_std, dtype=None):
            super().__init__()
            self.dtype = dtype
            self.register_buffer("norm_mean", torch.tensor(norm_mean).view(-1, 1, 1) / input_scale)
            self.register_buffer("norm_std", torch.tensor(norm_std).view(-1, 1, 1) / input_scale)

        def forward(self, x):
            y = (x - self.norm_mean) / self.norm_std
            return y.to(self.dtype) if self.dtype is not None else y


    class MLP2(nn.Module):  # radio/adaptor_mlp.py
        def __init__(self, input_size, hidden_size, output_size, num_inner=0, upsample_factor=1):
            super().__init__()
            self.pre_norm = nn.Identity()
            self.upsample_factor = upsample_factor
            self.fc1 = nn.Linear(input_size, hidden_size)
            self.blocks = nn.ModuleList(
                nn.Sequential(nn.LayerNorm(hidden_size), nn.GELU(), nn.Linear(hidden_size, hidden_size))
                for _ in range(num_inner)
            )
            self.final = nn.Sequential(
                nn.LayerNorm(hidden_size), nn.GELU(), nn.Linear(hidden_size, output_size)
            )

        def forward(self, x, images=None, patch_size=None):
            x = self.fc1(self.pre_norm(x))
            for block in self.blocks:
                x = x + block(x)
            return self.final(x)


    class GenericAdaptor(nn.Module):  # radio/adaptor_generic.py
        def __init__(self, embed_dim, summary_dim, feature_dim):
            super().__init__()
            self.head_idx = 0
            self.head_mlp = MLP2(embed_dim, 40, summary_dim, 1)
            self.feat_mlp = MLP2(embed_dim, 40, feature_dim, 1)

        def forward(self, input):
            dtype = next(self.parameters()).dtype
            summary = self.head_mlp(input.summary.to(dtype)).to(input.summary.dtype)
            feat = self.feat_mlp(input.features.to(dtype), images=input.images,
                                 patch_size=input.patch_size).to(input.features.dtype)
            if input.feature_fmt == "NCHW":
                h, w = (d // input.patch_size for d in input.images.shape[-2:])
                feat = feat.reshape(feat.shape[0], h, w, feat.shape[2]).permute(0, 3, 1, 2)
            return RadioOutput(summary, feat)


    def _ids(text, length=12, vocab=97):
        ids = [1 + zlib.crc32(word.encode()) % (vocab - 1) for word in text.split()][:length]
        return ids + [0] * (length - len(ids))


    class _BatchFeature(dict):  # transformers.BatchFeature: a dict with .to(device)
        def to(self, device):
            return _BatchFeature({k: v.to(device) for k, v in self.items()})


    class SigLIP2WrappedTokenizer:  # radio/siglip2_adaptor.py
        def __call__(self, text):
            text = [" ".join(t.replace("_", " ").lower().split()) for t in text]
            ids = torch.tensor([_ids(t) for t in text])
            return _BatchFeature(input_ids=ids, attention_mask=(ids > 0).long())


    class _SiglipTextModel(nn.Module):  # stands in for transformers' SigLIP 2 text model
        def __init__(self, out_dim, vocab=97):
            super().__init__()
            self.embeddings = nn.Embedding(vocab, 16)
            self.head = nn.Linear(16, out_dim)

        def forward(self, input_ids, attention_mask=None, return_dict=True):
            mask = attention_mask.unsqueeze(-1).float()
            pooled = (self.embeddings(input_ids) * mask).sum(1) / mask.sum(1).clamp(min=1)
            return types.SimpleNamespace(pooler_output=self.head(pooled))


    class SigLIP2Adaptor(GenericAdaptor):
        def __init__(self, embed_dim, summary_dim, feature_dim):
            super().__init__(embed_dim, summary_dim, feature_dim)
            self.tokenizer = SigLIP2WrappedTokenizer()
            self.text_model = _SiglipTextModel(summary_dim)

        def encode_text(self, text, normalize=False):
            token = self.text_model(**text, return_dict=True).pooler_output
            return F.normalize(token, dim=-1) if normalize else token


    class _OpenClipModel(nn.Module):
        def __init__(self, out_dim, vocab=97):
            super().__init__()
            self.token_embedding = nn.Embedding(vocab, 16)
            self.text_projection = nn.Linear(16, out_dim, bias=False)

        def encode_text(self, text, normalize=False):
            x = self.text_projection(self.token_embedding(text).mean(1))
            return F.normalize(x, dim=-1) if normalize else x


    class OpenCLIP_RADIO(GenericAdaptor):  # radio/open_clip_adaptor.py
        def __init__(self, embed_dim, summary_dim, feature_dim):
            super().__init__(embed_dim, summary_dim, feature_dim)
            self.oc_model = _OpenClipModel(summary_dim)
            self.tokenizer = lambda texts: torch.tensor([_ids(t) for t in texts])

        def encode_text(self, text, normalize=False):
            return self.oc_model.encode_text(text, normalize=normalize)


    class Attention(nn.Module):  # timm's Attention layout (what RADSeg wraps)
        def __init__(self, dim, num_heads):
            super().__init__()
            self.num_heads = num_heads
            self.qkv = nn.Linear(dim, dim * 3)
            self.q_norm = self.k_norm = nn.Identity()
            self.attn_drop = nn.Dropout(0.0)
            self.proj = nn.Linear(dim, dim)
            self.proj_drop = nn.Dropout(0.0)

        def forward(self, x):
            b, n, c = x.shape
            q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, -1).permute(2, 0, 3, 1, 4)
            x = F.scaled_dot_product_attention(q, k, v)
            return self.proj_drop(self.proj(x.transpose(1, 2).reshape(b, n, c)))


    class Block(nn.Module):
        def __init__(self, dim, num_heads):
            super().__init__()
            self.norm1 = nn.LayerNorm(dim)
            self.attn = Attention(dim, num_heads)
            self.norm2 = nn.LayerNorm(dim)
            self.mlp = nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))

        def forward(self, x):
            x = x + self.attn(self.norm1(x))
            return x + self.mlp(self.norm2(x))


    class ViTPatchGenerator(nn.Module):  # radio/vit_patch_generator.py (CPE)
        def __init__(self, patch_size, dim, num_cls_tokens, num_registers):
            super().__init__()
            self.patch_size = patch_size
            self.num_cls_tokens = num_cls_tokens
            self.num_registers = num_registers
            self.num_skip = num_cls_tokens + num_registers
            self.embedder = nn.Conv2d(3, dim, patch_size, stride=patch_size)
            self.cls_token = nn.Parameter(torch.randn(self.num_skip, dim))

        def forward(self, x):
            tokens = self.embedder(x).flatten(2).transpose(1, 2)
            return torch.cat([self.cls_token.expand(x.shape[0], -1, -1), tokens], dim=1)


    class VisionTransformer(nn.Module):
        def __init__(self, dim, depth, num_heads, patch_size, num_cls_tokens):
            super().__init__()
            self.embed_dim = dim
            self.patch_generator = ViTPatchGenerator(patch_size, dim, num_cls_tokens, 1)
            self.blocks = nn.Sequential(*(Block(dim, num_heads) for _ in range(depth)))
            self.norm = nn.Identity()

        def forward_features(self, x):
            return self.norm(self.blocks(self.patch_generator(x)))


    class RADIOModel(nn.Module):  # radio/radio_model.py
        def __init__(self, model, input_conditioner, patch_size, max_resolution,
                     preferred_resolution, summary_idxs=None, window_size=None, adaptors=None):
            super().__init__()
            self.model = model
            self.input_conditioner = input_conditioner
            self.register_buffer("summary_idxs", summary_idxs)
            self._patch_size = patch_size
            self._max_resolution = max_resolution
            self._preferred_resolution = preferred_resolution
            self._window_size = window_size
            self.adaptors = nn.ModuleDict(adaptors or {})
            self.feature_normalizer = nn.Identity()

        @property
        def num_summary_tokens(self):
            return self.model.patch_generator.num_skip

        @property
        def num_cls_tokens(self):
            return self.model.patch_generator.num_cls_tokens

        @property
        def patch_size(self):
            return self._patch_size

        @property
        def window_size(self):
            return self._window_size

        @property
        def min_resolution_step(self):
            return self.patch_size * (self.window_size or 1)

        @property
        def embed_dim(self):
            return self.model.embed_dim

        def make_preprocessor_external(self):
            ret = self.input_conditioner
            self.input_conditioner = nn.Identity()
            return ret

        def get_nearest_supported_resolution(self, height, width):
            step = self.min_resolution_step
            return (max(step, round(height / step) * step), max(step, round(width / step) * step))

        def forward(self, x, feature_fmt="NLC"):
            step = self.min_resolution_step
            if x.shape[-2] % step or x.shape[-1] % step:
                raise ValueError(f"The input resolution must be a multiple of {step}")
            x = self.input_conditioner(x)
            y = self.model.forward_features(x)
            return self._extract_final(x, y, feature_fmt)

        def _extract_final(self, x, y, feature_fmt="NLC"):
            all_summary = y[:, : self.num_cls_tokens]
            bb_summary = all_summary[:, self.summary_idxs]
            all_feat = self.feature_normalizer(y[:, self.num_summary_tokens :])
            if feature_fmt == "NCHW":
                h, w = x.shape[-2] // self.patch_size, x.shape[-1] // self.patch_size
                fmt_feat = all_feat.reshape(all_feat.shape[0], h, w, -1).permute(0, 3, 1, 2)
            else:
                fmt_feat = all_feat
            ret = RadioOutput(bb_summary.flatten(1), fmt_feat)
            if self.adaptors:
                ret = dict(backbone=ret)
                for name, adaptor in self.adaptors.items():
                    summary = all_summary[:, adaptor.head_idx]
                    ada_input = AdaptorInput(images=x, summary=summary.float(), features=all_feat,
                                             feature_fmt=feature_fmt, patch_size=self.patch_size)
                    ret[name] = adaptor(ada_input).to(torch.float32)
            return ret


    # Checkpoint teachers per version: (name, adaptor type, summary width, feature width).
    _TEACHERS = {
        "c-radio_v3-b": [("clip", "open_clip", 24, 28), ("siglip2", "siglip2", 20, 30),
                         ("dino_v2", "generic", 36, 36), ("sam", "generic", 12, 12)],
        "c-radio_v4-so400m": [("siglip2-g", "siglip2", 26, 22), ("dino_v3", "generic", 36, 36),
                              ("sam3", "generic", 12, 12)],
    }
    _TYPES = {"siglip2": SigLIP2Adaptor, "open_clip": OpenCLIP_RADIO, "generic": GenericAdaptor}
    # The checkpoint's input conditioner (RADIO loads it from the state dict).
    _NORM = ((0.45, 0.40, 0.35), (0.27, 0.26, 0.28))


    def radio_model(version="", progress=True, adaptor_names=None, neck_name=None,
                    vitdet_window_size=None, return_checkpoint=False, **kwargs):
        teachers = _TEACHERS[version]
        if isinstance(adaptor_names, str):
            adaptor_names = [adaptor_names]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(zlib.crc32(version.encode()))
            vit = VisionTransformer(32, 2, 2, 16, num_cls_tokens=len(teachers))
            adaptors = {}
            for tidx, (name, kind, sdim, fdim) in enumerate(teachers):
                ada = _TYPES[kind](32, sdim, fdim)  # every teacher's weights drawn in order
                ada.head_idx = tidx
                adaptors[name] = ada
        for name in adaptor_names or []:
            if name not in adaptors:
                known = [t[0] for t in teachers]
                raise ValueError(f"Unable to find the specified adaptor name. Known names: {known}")
        dtype = torch.float32 if version.startswith("c-radio_v4") else None
        conditioner = InputConditioner(1.0, *_NORM, dtype=dtype)
        return RADIOModel(vit, conditioner, patch_size=16, max_resolution=2048,
                          preferred_resolution=(512, 512),
                          summary_idxs=torch.arange(len(teachers)),
                          window_size=vitdet_window_size,
                          adaptors={n: adaptors[n] for n in adaptor_names or []})
    '''
)

FAKE_RADSEG = textwrap.dedent(
    '''
    """Fake RADSeg-OVSS/RADSeg hubconf: RADSegEncoder's structure over the fake RADIO."""
    dependencies = ["torch"]

    import torch
    import torch.nn.functional as F
    from torch import nn


    class SelfCorrelatingRecursiveAttn(nn.Module):  # radseg/radseg.py (simplified)
        def __init__(self, orig_attn, device, dim, qk_norm=False, scra_scaling=10):
            super().__init__()
            self.num_heads = orig_attn.num_heads
            self.qkv, self.proj, self.proj_drop = orig_attn.qkv, orig_attn.proj, orig_attn.proj_drop
            self.scra_scaling = scra_scaling

        def forward(self, x, *args, **kwargs):
            b, n, c = x.shape
            q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, -1).permute(2, 0, 3, 1, 4)
            out = F.scaled_dot_product_attention(q, k, v)
            sim = F.normalize(out, dim=-1) @ F.normalize(out, dim=-1).transpose(-1, -2)
            out = torch.softmax(sim * self.scra_scaling, dim=-1) @ v
            return self.proj_drop(self.proj(out.transpose(1, 2).reshape(b, n, c)))


    class RADSegEncoder:
        def __init__(self, device=None, model_version="radio_v3-b", lang_model="siglip2",
                     return_radio_features=True, compile=False, amp=False, predict=False,
                     classes=None, text_query_mode="labels", prediction_thresh=0.0,
                     prompt_denoising_thresh=0.5, scra_scaling=10.0, scga_scaling=10.0,
                     slide_crop=336, slide_stride=224, sam_refinement=False, **sam_args):
            self.device = device or ("cuda" if torch.cuda.is_available() else "cpu")
            self.amp = amp
            self.return_radio_features = return_radio_features
            self.model = torch.hub.load("NVlabs/RADIO", "radio_model", version=model_version,
                                        progress=True, skip_validation=True,
                                        adaptor_names=[lang_model, "sam"])
            self.model.eval()
            self.model = self.model.to(self.device)
            self.lang_adaptor = self.model.adaptors[lang_model]
            self.sam_adaptor = self.model.adaptors["sam"]
            self.model.adaptors = None
            last_block = self.model.model.blocks[-1]
            last_block.attn = SelfCorrelatingRecursiveAttn(
                last_block.attn, dim=self.model.model.embed_dim, device=self.device,
                scra_scaling=scra_scaling)
            if predict or sam_refinement:
                raise AssertionError("the adapter must not ask RADSeg for prediction")
            self.predict = predict
            self.slide_stride = slide_stride
            self.slide_crop = slide_crop
            self.scga_scaling = scga_scaling

        def encode_prompts(self, prompts, onehot=True):
            text = self.lang_adaptor.tokenizer(prompts).to(self.device)
            text_features = self.lang_adaptor.encode_text(text)
            text_features /= text_features.norm(dim=-1, keepdim=True)
            return text_features

        def encode_image_to_feat_map(self, rgb_image, orig_img_size=None, return_preds=False,
                                     ignore_label=True):
            if self.slide_crop > 0:
                feat_map = self._sliding_inference(rgb_image)
            else:
                feat_map = self._single_inference(rgb_image)
            return self._self_correlating_global_aggregation(feat_map)

        def align_spatial_features_with_language(self, features, onehot=True):
            b, c, h, w = features.shape
            features = features.permute(0, 2, 3, 1).reshape(b, -1, c)
            out = self.lang_adaptor.head_mlp(features)
            return out.permute(0, 2, 1).reshape(b, -1, h, w)

        def get_nearest_size(self, h, w):
            return self.model.get_nearest_supported_resolution(h, w)

        def _single_inference(self, rgb_image):
            b, _, h, w = rgb_image.shape
            out = self.model(rgb_image).features
            p = self.model.patch_size
            return out.permute(0, 2, 1).reshape(b, -1, h // p, w // p)

        def _sliding_inference(self, img):
            # Two overlapping windows along the width, averaged (the real one tiles a grid).
            p = self.model.patch_size
            gw = img.shape[-1] // p
            half = max(1, gw // 2 + 1)
            left = self._single_inference(img[..., : half * p])
            right = self._single_inference(img[..., (gw - half) * p :])
            out = torch.zeros(*left.shape[:2], left.shape[2], gw)
            count = torch.zeros(1, 1, 1, gw)
            out[..., :half] += left
            out[..., gw - half :] += right
            count[..., :half] += 1
            count[..., gw - half :] += 1
            return out / count

        def _self_correlating_global_aggregation(self, feat_map):
            b, c, h, w = feat_map.shape
            tokens = feat_map.flatten(2).transpose(1, 2)
            sim = F.normalize(tokens, dim=-1) @ F.normalize(tokens, dim=-1).transpose(1, 2)
            sim = (sim - sim.mean()) * self.scga_scaling
            sim[sim < 0] = -torch.inf
            out = torch.softmax(sim, dim=-1) @ tokens
            return out.transpose(1, 2).reshape(b, c, h, w)


    def radseg_encoder(model_version="c-radio_v3-b", lang_model="siglip2", scra_scaling=10.0,
                       scga_scaling=10.0, **kwargs):
        return RADSegEncoder(model_version=model_version, lang_model=lang_model,
                             scra_scaling=scra_scaling, scga_scaling=scga_scaling, **kwargs)
    '''
)

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

DINOTXT_VOCAB = "dinov2/hub/bpe_simple_vocab_16e6.txt.gz"  # inside the fake repo
DINOTXT_WORDS = "a photo of the cat dog car sky road tree person bicycle"

DINOTXT_FILES = {
    "hubconf.py": """
        dependencies = ["torch"]
        from dinov2.hub.dinotxt import dinov2_vitl14_reg4_dinotxt_tet1280d20h24l
    """,
    "dinov2/__init__.py": "",
    "dinov2/hub/__init__.py": "",
    "dinov2/layers/__init__.py": """
        from torch import nn

        class NestedTensorBlock(nn.Module):  # pre-norm attention block
            def __init__(self, dim, num_heads):
                super().__init__()
                self.norm1 = nn.LayerNorm(dim)
                self.attn = nn.MultiheadAttention(dim, num_heads, batch_first=True)
                self.norm2 = nn.LayerNorm(dim)
                self.mlp = nn.Sequential(nn.Linear(dim, 2 * dim), nn.GELU(), nn.Linear(2 * dim, dim))

            def forward(self, x):
                y = self.norm1(x)
                x = x + self.attn(y, y, y, need_weights=False)[0]
                return x + self.mlp(self.norm2(x))
    """,
    "dinov2/models/__init__.py": "",
    "dinov2/models/vision_transformer.py": textwrap.dedent(
        """
        import math
        import torch
        from torch import nn
        from dinov2.layers import NestedTensorBlock as Block
        """
    )
    + DINOV2_VIT,
    "dinov2/hub/text/dinov2_wrapper.py": """
        import torch

        class DINOv2Wrapper(torch.nn.Module):
            def __init__(self, model):
                super().__init__()
                self.model = model
                self.embed_dim = model.embed_dim
                self.num_heads = model.num_heads
                self.num_register_tokens = model.num_register_tokens

            def get_intermediate_layers(self, x, n=1, reshape=False, return_class_token=False,
                                        return_register_tokens=False, norm=True):
                outputs = self.model._get_intermediate_layers_not_chunked(x, n)
                if norm:
                    outputs = [self.model.norm(out) for out in outputs]
                r = self.model.num_register_tokens
                class_tokens = [out[:, 0] for out in outputs]
                register_tokens = [out[:, 1 : 1 + r] for out in outputs]
                outputs = [out[:, 1 + r :] for out in outputs]
                assert not reshape
                if return_class_token and return_register_tokens:
                    return tuple(zip(outputs, class_tokens, register_tokens))
                if return_class_token:
                    return tuple(zip(outputs, class_tokens))
                if return_register_tokens:
                    return tuple(zip(outputs, register_tokens))
                return tuple(outputs)
    """,
    "dinov2/hub/text/vision_tower.py": """
        import torch
        from torch import nn
        from dinov2.layers import NestedTensorBlock as AttentionBlock

        class VisionHead(nn.Module):
            def __init__(self, input_dim, embed_dim, num_heads, num_blocks, use_class_token,
                         use_patch_tokens):
                super().__init__()
                self.block_list = nn.ModuleList(
                    AttentionBlock(input_dim, num_heads) for _ in range(num_blocks))
                self.ln_final = nn.LayerNorm(input_dim)
                self.num_blocks = num_blocks
                multiplier = 2 if use_class_token and use_patch_tokens else 1
                self.linear_projection = nn.Identity()
                if multiplier * input_dim != embed_dim:
                    self.linear_projection = nn.Linear(input_dim, embed_dim // multiplier, bias=False)

            def forward(self, image_tokens):
                for block in self.block_list:
                    image_tokens = block(image_tokens)
                return self.linear_projection(self.ln_final(image_tokens))

        class VisionTower(nn.Module):
            def __init__(self, backbone, embed_dim, num_head_blocks, use_class_token,
                         use_patch_tokens, patch_token_layer, patch_tokens_pooler_type):
                super().__init__()
                self.backbone = backbone
                self.use_class_token = use_class_token
                self.use_patch_tokens = use_patch_tokens
                self.patch_token_layer = patch_token_layer
                self.patch_tokens_pooler_type = patch_tokens_pooler_type
                self.num_register_tokens = backbone.num_register_tokens
                self.head = VisionHead(backbone.embed_dim, embed_dim, backbone.num_heads,
                                       num_head_blocks, use_class_token, use_patch_tokens)

            def get_backbone_features(self, images):
                tokens = self.backbone.get_intermediate_layers(
                    images, n=self.patch_token_layer, return_class_token=True,
                    return_register_tokens=True)
                return tokens[-1][1], tokens[0][0], tokens[0][2]

            def get_class_and_patch_tokens(self, images):
                class_token, patch_tokens, register_tokens = self.get_backbone_features(images)
                image_tokens = self.head(
                    torch.cat([class_token.unsqueeze(1), register_tokens, patch_tokens], dim=1))
                return image_tokens[:, 0], image_tokens[:, self.num_register_tokens + 1 :]

            def forward(self, images):
                class_token, patch_tokens = self.get_class_and_patch_tokens(images)
                return torch.cat([class_token, patch_tokens.mean(dim=1)], dim=-1)
    """,
    "dinov2/hub/text/text_tower.py": """
        import torch
        from torch import nn
        from dinov2.layers import NestedTensorBlock

        class TextTransformer(nn.Module):
            def __init__(self, context_length, vocab_size, dim, num_heads, num_layers):
                super().__init__()
                self.embed_dim, self.num_heads = dim, num_heads
                self.token_embedding = nn.Embedding(vocab_size, dim)
                self.positional_embedding = nn.Parameter(torch.randn(context_length, dim))
                self.blocks = nn.ModuleList(NestedTensorBlock(dim, num_heads) for _ in range(num_layers))
                self.ln_final = nn.LayerNorm(dim)

            def forward(self, token_indices):
                x = self.token_embedding(token_indices) + self.positional_embedding[: token_indices.shape[1]]
                for block in self.blocks:
                    x = block(x)
                return self.ln_final(x)

        class TextTower(nn.Module):
            def __init__(self, backbone, embed_dim):
                super().__init__()
                self.backbone = backbone
                self.head = nn.Linear(backbone.embed_dim, embed_dim, bias=False)
                self.tokens_pooler_type = "argmax"

            def forward(self, token_indices):
                text_tokens = self.head(self.backbone(token_indices))
                return text_tokens[torch.arange(text_tokens.shape[0]), token_indices.argmax(dim=-1)]
    """,
    "dinov2/hub/text/dinotxt_model.py": """
        from dataclasses import dataclass
        import torch.nn.functional as F
        from torch import nn
        from .vision_tower import VisionTower
        from .text_tower import TextTower

        @dataclass
        class DinoTxtConfig:
            embed_dim: int
            vision_model_use_class_token: bool = True
            vision_model_use_patch_tokens: bool = True
            vision_model_num_head_blocks: int = 2
            vision_model_patch_tokens_pooler_type: str = "mean"
            vision_model_patch_token_layer: int = 1

        class DinoTxt(nn.Module):
            def __init__(self, model_config, vision_backbone, text_backbone):
                super().__init__()
                c = self.model_config = model_config
                self.visual_model = VisionTower(
                    vision_backbone, c.embed_dim, c.vision_model_num_head_blocks,
                    c.vision_model_use_class_token, c.vision_model_use_patch_tokens,
                    c.vision_model_patch_token_layer, c.vision_model_patch_tokens_pooler_type)
                self.text_model = TextTower(text_backbone, c.embed_dim)

            def get_visual_class_and_patch_tokens(self, image):
                return self.visual_model.get_class_and_patch_tokens(image)

            def encode_image(self, image, normalize=False):
                features = self.visual_model(image)
                return F.normalize(features, dim=-1) if normalize else features

            def encode_text(self, text, normalize=False):
                features = self.text_model(text)
                return F.normalize(features, dim=-1) if normalize else features
    """,
    "dinov2/hub/text/tokenizer.py": """
        import gzip
        import torch

        class Tokenizer:  # whitespace words of the vocabulary file; SOT / EOT are the top ids
            def __init__(self, vocab_path):
                self.vocab_path = vocab_path
                with gzip.open(vocab_path) as f:
                    words = f.read().decode("utf-8").split()
                self.encoder = {w: i + 2 for i, w in enumerate(words)}  # 0 pad, 1 unknown
                self.encoder["<|startoftext|>"] = len(words) + 2
                self.encoder["<|endoftext|>"] = len(words) + 3

            def encode(self, text):
                return [self.encoder.get(w, 1) for w in text.lower().split()]

            def tokenize(self, texts, context_length=77):
                if isinstance(texts, str):
                    texts = [texts]
                sot, eot = self.encoder["<|startoftext|>"], self.encoder["<|endoftext|>"]
                result = torch.zeros(len(texts), context_length, dtype=torch.long)
                for i, text in enumerate(texts):
                    tokens = [sot] + self.encode(text) + [eot]
                    result[i, : len(tokens)] = torch.tensor(tokens[:context_length])
                return result
    """,
    "dinov2/hub/dinotxt.py": """
        import os
        from dinov2.models.vision_transformer import DinoVisionTransformer

        def dinov2_vitl14_reg4_dinotxt_tet1280d20h24l():
            from .text.dinotxt_model import DinoTxtConfig, DinoTxt
            from .text.dinov2_wrapper import DINOv2Wrapper
            from .text.text_tower import TextTransformer

            vision_backbone = DINOv2Wrapper(DinoVisionTransformer(
                img_size=56, depth=2, num_register_tokens=4, interpolate_antialias=True,
                interpolate_offset=0.0))
            text_backbone = TextTransformer(context_length=77, vocab_size=64, dim=32,
                                            num_heads=2, num_layers=1)
            model = DinoTxt(DinoTxtConfig(embed_dim=64), vision_backbone, text_backbone)
            model.eval()
            return model

        def get_tokenizer():  # the real one downloads the vocabulary; this one is bundled
            from .text.tokenizer import Tokenizer
            return Tokenizer(vocab_path=os.path.join(os.path.dirname(__file__),
                                                     "bpe_simple_vocab_16e6.txt.gz"))
    """,
}


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


RADSEG_STANDIN = textwrap.dedent(
    """
    dependencies = ["torch"]
    import torch

    class _Encoder:
        # Like RADSegEncoder: a plain object (no .to()) whose modules stay on the
        # device it was built for; inputs must arrive there.
        def __init__(self, model_version, lang_model, slide_crop, device=None, **kw):
            self.device = torch.device(device or "cuda")
            self.calls = {"model_version": model_version, "lang_model": lang_model,
                          "slide_crop": slide_crop, "device": str(self.device)}
            self.proj = torch.nn.Conv2d(3, 40, 16, stride=16).to(self.device)
            self.lang = torch.nn.Conv2d(40, 24, 1).to(self.device)
        def get_nearest_size(self, h, w):
            return (h // 16) * 16, (w // 16) * 16
        def encode_image_to_feat_map(self, rgb):
            assert rgb.device == self.device, (rgb.device, self.device)
            if rgb.device.type != "meta":
                assert rgb.min() >= 0 and rgb.max() <= 1  # RADIO takes [0, 1] RGB
            return self.proj(rgb)
        def align_spatial_features_with_language(self, feat):
            assert feat.device == self.device
            return self.lang(feat)

    def radseg_encoder(model_version="c-radio_v3-b", lang_model="siglip2", **kwargs):
        return _Encoder(model_version, lang_model, **kwargs)
    """
)


def write_repo(folder: Path, files: dict[str, str]) -> Path:
    """``files`` (relative path -> source, dedented) written under ``folder``."""
    for rel, text in files.items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return folder


def radio_repo(folder: Path) -> str:
    """A local NVlabs/RADIO clone (:data:`FAKE_RADIO`)."""
    return str(write_repo(folder, {"hubconf.py": FAKE_RADIO}))


def radseg_repo(folder: Path, standin: bool = False) -> str:
    """A local RADSeg-OVSS/RADSeg clone (:data:`FAKE_RADSEG`, or :data:`RADSEG_STANDIN`)."""
    return str(write_repo(folder, {"hubconf.py": RADSEG_STANDIN if standin else FAKE_RADSEG}))


def dinov2_repo(folder: Path) -> str:
    """A local facebookresearch/dinov2 clone with OTAS's entry point (:data:`DINOV2_HUBCONF`)."""
    return str(write_repo(folder, {"hubconf.py": DINOV2_HUBCONF}))


def dinotxt_repo(folder: Path) -> Path:
    """A local facebookresearch/dinov2 clone with dino.txt (:data:`DINOTXT_FILES`) and its
    vocabulary at ``folder / DINOTXT_VOCAB``."""
    write_repo(folder, DINOTXT_FILES)
    with gzip.open(folder / DINOTXT_VOCAB, "wb") as f:
        f.write(DINOTXT_WORDS.replace(" ", "\n").encode())
    return folder


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


def refuse_network(host, timeout):
    """A stand-in for :func:`resireg.models.hub._resolves` that fails the test calling it."""
    raise AssertionError(f"a test probed the network ({host})")


def _offline_urlopen(*args, **kwargs):
    raise URLError("no network in tests")


def offline_hub(
    monkeypatch, hub_dir: Path, checkpoints: Iterable[str] = (), radio_code: bool = False
) -> Path:
    """torch's hub cache at ``hub_dir`` holding (empty files named like) ``checkpoints`` in
    ``checkpoints/`` and, with ``radio_code``, the fake NVlabs/RADIO as ``NVlabs_RADIO_main``
    and at the pinned commit (what RADSeg loads from GitHub); GitHub unreachable for torch.hub; any network probe of
    :mod:`resireg.models.hub` fails the test."""
    (hub_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    for name in checkpoints:
        (hub_dir / "checkpoints" / name).write_bytes(b"")  # cached (the fakes never read it)
    if radio_code:  # RADSeg's own load of RADIO, pinned (PINNED_REFS) or not (main)
        radio_repo(hub_dir / "NVlabs_RADIO_main")
        radio_repo(hub_dir / f"NVlabs_RADIO_{hub_module.PINNED_REFS['NVlabs/RADIO']}")
    monkeypatch.setattr(torch.hub, "_hub_dir", str(hub_dir))
    monkeypatch.setattr(torch.hub, "urlopen", _offline_urlopen)
    monkeypatch.setattr(hub_module, "_resolves", refuse_network)
    return hub_dir


def build_offline(tmp_path_factory, checkpoints: Iterable[str], build, *args, **kwargs):
    """``build(*args, **kwargs)`` under :func:`offline_hub` (a fresh hub cache holding
    ``checkpoints``), seeded with ``torch.manual_seed(0)`` (the fakes draw their weights from
    torch's global generator); the patches are undone after, so a module-scoped fixture can
    keep the encoder."""
    with pytest.MonkeyPatch.context() as mp:
        offline_hub(mp, tmp_path_factory.mktemp("hub"), checkpoints)
        torch.manual_seed(0)
        return build(*args, **kwargs)


def token_grid(tokens: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[B, N, D]`` patch tokens of a ``size`` grid -> ``[B, D, *size]`` (the tests' own
    reshape, not the adapters')."""
    return tokens.permute(0, 2, 1).unflatten(2, size)


# ------------------------------------------------------------------ TIPSv2 release files
TIPS_P, TIPS_WIDTH, TIPS_DEPTH, TIPS_HEADS, TIPS_GRID, TIPS_VOCAB, TIPS_TEXT_MLP = (
    14,
    32,
    2,
    2,
    4,
    64,
    48,
)
TIPS_STEM = "tips_v2_oss_tiny14"
TIPS_TINY = {
    "width": TIPS_WIDTH,
    "depth": TIPS_DEPTH,
    "heads": TIPS_HEADS,
    "mlp_hidden": 64,
    "ffn": "mlp",
    "text_layers": 1,
    "text_heads": TIPS_HEADS,
    "text_mlp": TIPS_TEXT_MLP,
    "pos_grid": TIPS_GRID,
    "vocab_size": TIPS_VOCAB,
    "stem": TIPS_STEM,
}


class TipsWordTokenizer:
    """A stand-in for the SentencePiece model: one id per word (1..TIPS_VOCAB-1), 0 never used."""

    def __init__(self):
        self.seen = []

    def encode(self, text):
        self.seen.append(text)
        return [1 + sum(map(ord, w)) % (TIPS_VOCAB - 1) for w in text.split()]


def _tips_vision_shapes(width, depth, pos_grid, ffn, mlp_hidden, patch=TIPS_P):
    d = width
    shapes = {
        "cls_token": (1, 1, d),
        "pos_embed": (1, 1 + pos_grid**2, d),
        "register_tokens": (1, 1, d),
        "mask_token": (1, d),
        "patch_embed.proj.weight": (d, 3, patch, patch),
        "patch_embed.proj.bias": (d,),
        "norm.weight": (d,),
        "norm.bias": (d,),
    }
    for i in range(depth):
        b = f"blocks.{i}."
        shapes.update({
            b + "norm1.weight": (d,), b + "norm1.bias": (d,),
            b + "attn.qkv.weight": (3 * d, d), b + "attn.qkv.bias": (3 * d,),
            b + "attn.proj.weight": (d, d), b + "attn.proj.bias": (d,),
            b + "ls1.gamma": (d,),
            b + "norm2.weight": (d,), b + "norm2.bias": (d,),
            b + "ls2.gamma": (d,),
        })  # fmt: skip
        if ffn == "swiglu":
            h = (int(mlp_hidden * 2 / 3) + 7) // 8 * 8
            shapes.update({
                b + "mlp.w12.weight": (2 * h, d), b + "mlp.w12.bias": (2 * h,),
                b + "mlp.w3.weight": (d, h), b + "mlp.w3.bias": (d,),
            })  # fmt: skip
        else:
            shapes.update({
                b + "mlp.fc1.weight": (mlp_hidden, d), b + "mlp.fc1.bias": (mlp_hidden,),
                b + "mlp.fc2.weight": (d, mlp_hidden), b + "mlp.fc2.bias": (d,),
            })  # fmt: skip
    return shapes


def _tips_text_shapes(width, layers, mlp, vocab):
    d = width
    shapes = {
        "token_embedding.weight": (vocab, d),
        "ln_final.weight": (d,),
        "ln_final.bias": (d,),
        "temperature": (),
    }
    for i in range(layers):
        b = f"transformer.resblocks.{i}."
        shapes.update({
            b + "attn.in_proj_weight": (3 * d, d), b + "attn.in_proj_bias": (3 * d,),
            b + "attn.out_proj.weight": (d, d), b + "attn.out_proj.bias": (d,),
            b + "ln_1.weight": (d,), b + "ln_1.bias": (d,),
            b + "mlp.c_fc.weight": (mlp, d), b + "mlp.c_fc.bias": (mlp,),
            b + "mlp.c_proj.weight": (d, mlp), b + "mlp.c_proj.bias": (d,),
            b + "ln_2.weight": (d,), b + "ln_2.bias": (d,),
        })  # fmt: skip
    return shapes


def _tips_random(shapes, seed):
    rng = np.random.default_rng(seed)
    out = {}
    for name, shape in shapes.items():
        x = rng.standard_normal(shape).astype(np.float32)
        scale = 0.1 if name.endswith(("norm1.weight", "norm2.weight", "gamma")) else 0.2
        offset = 1.0 if name.endswith(("norm.weight", "norm1.weight", "norm2.weight")) else 0.0
        out[name] = offset + scale * x if shape else np.float32(0.07)
    return out


def write_tips_release(folder, ffn="mlp", seed=0):
    """A tiny TIPS release (google-deepmind/tips ``pytorch/image_encoder.py`` /
    ``text_encoder.py`` parameter names and shapes): ``<TIPS_STEM>_vision.npz``, ``<TIPS_STEM>_text.npz`` and ``tokenizer.model`` in ``folder``."""
    vision = _tips_random(
        _tips_vision_shapes(TIPS_WIDTH, TIPS_DEPTH, TIPS_GRID, ffn, TIPS_TINY["mlp_hidden"]), seed
    )
    text = _tips_random(_tips_text_shapes(TIPS_WIDTH, 1, TIPS_TEXT_MLP, TIPS_VOCAB), seed + 1)
    np.savez(folder / f"{TIPS_STEM}_vision.npz", **vision)
    np.savez(folder / f"{TIPS_STEM}_text.npz", **text)
    (folder / "tokenizer.model").write_bytes(b"not read: a tokenizer object is passed")
    return vision, text


def train_sentencepiece(folder: Path) -> Path:
    """A real SentencePiece model (``folder / "sp.model"``, trained here on a few captions; pad
    id 0, no BOS / EOS, as TIPS's tokenizer), for loading by path like ``tokenizer.model``."""
    import sentencepiece as spm

    corpus = folder / "corpus.txt"
    corpus.write_text("\n".join(["a photo of a cat", "a photo of the sky", "road and tree"] * 20))
    spm.SentencePieceTrainer.train(
        input=str(corpus), model_prefix=str(folder / "sp"), vocab_size=TIPS_VOCAB // 2,
        model_type="unigram", pad_id=0, unk_id=1, bos_id=-1, eos_id=-1, hard_vocab_limit=False,
    )  # fmt: skip
    return folder / "sp.model"
