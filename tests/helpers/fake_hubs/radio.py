"""The fake NVlabs/RADIO hub repository: ``hubconf.radio_model`` (``RADIOModel``,
``GenericAdaptor`` with the ``siglip2`` / ``open_clip`` types, ``input_conditioner``,
``make_preprocessor_external``, ``min_resolution_step``; weights seeded by the version) as
:data:`FAKE_RADIO`, and :func:`radio_repo`, a local clone of it.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

from helpers.fake_hubs.common import write_repo

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


def radio_repo(folder: Path) -> str:
    """A local NVlabs/RADIO clone (:data:`FAKE_RADIO`)."""
    return str(write_repo(folder, {"hubconf.py": FAKE_RADIO}))
