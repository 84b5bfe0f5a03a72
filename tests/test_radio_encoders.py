"""RADIO and RADSeg dense encoders through local torch.hub repositories (no network).

The fake repositories below expose the real entry points (``radio_model`` of NVlabs/RADIO,
``radseg_encoder`` of RADSeg-OVSS/RADSeg) with their signatures, and return tiny random
modules with the real attribute layout and output structure: ``RADIOModel`` with
``input_conditioner``, ``make_preprocessor_external``, ``min_resolution_step``,
``adaptors[name]`` (``GenericAdaptor``: ``head_idx``, ``head_mlp`` / ``feat_mlp`` as
``MLP2``; the ``siglip2`` and ``open_clip`` types with ``tokenizer`` / ``encode_text``), a
``forward(x, feature_fmt)`` returning ``RadioOutput(summary, features)`` or a dict
``{"backbone": ..., <adaptor>: ...}``; ``RADSegEncoder`` loading ``NVlabs/RADIO`` itself
through ``torch.hub`` (here: the hub cache, GitHub unreachable), detaching the adaptors,
replacing the last attention, ``encode_image_to_feat_map`` (sliding window or one pass,
then SCGA), ``align_spatial_features_with_language``, ``encode_prompts``.

Expected values are recomputed from a second, independently loaded copy of the fake
model (same seed), through its own modules, never from the adapter.
"""

import textwrap
import time
from urllib.error import URLError

import pytest
import torch
import torch.nn.functional as F

from resireg.models import WeightsUnavailableError
from resireg.models import hub as hub_module
from resireg.models.zoo.radio import RADIO_CHECKPOINTS, RadioEncoder, RadSegEncoder

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

NORM_MEAN, NORM_STD = (0.45, 0.40, 0.35), (0.27, 0.26, 0.28)  # the fake checkpoint's conditioner
TEXTS = ["a photo of a cat", "the sky", "Grass_field"]


def _no_network(host, timeout):
    raise AssertionError(f"a test probed the network ({host})")


def _offline_urlopen(*args, **kwargs):
    raise URLError("no network in tests")


@pytest.fixture(autouse=True)
def hub(tmp_path, monkeypatch):
    """A private torch hub cache holding the fake NVlabs/RADIO (what RADSeg loads from GitHub)
    and the RADIO checkpoints' names; GitHub unreachable; network probes fail the test."""
    hub_dir = tmp_path / "hub"
    (hub_dir / "NVlabs_RADIO_main").mkdir(parents=True)
    (hub_dir / "NVlabs_RADIO_main" / "hubconf.py").write_text(FAKE_RADIO)
    (hub_dir / "checkpoints").mkdir()
    for name in RADIO_CHECKPOINTS.values():
        (hub_dir / "checkpoints" / name).write_bytes(b"")  # cached (the fake never reads it)
    monkeypatch.setattr(torch.hub, "_hub_dir", str(hub_dir))
    monkeypatch.setattr(torch.hub, "urlopen", _offline_urlopen)
    monkeypatch.setattr(hub_module, "_resolves", _no_network)
    return hub_dir


@pytest.fixture
def radio_repo(tmp_path):
    repo = tmp_path / "RADIO"
    repo.mkdir()
    (repo / "hubconf.py").write_text(FAKE_RADIO)
    return str(repo)


@pytest.fixture
def radseg_repo(tmp_path):
    repo = tmp_path / "RADSeg"
    repo.mkdir()
    (repo / "hubconf.py").write_text(FAKE_RADSEG)
    return str(repo)


def _rgb(b=2, h=48, w=64):
    return torch.rand(b, 3, h, w, generator=torch.Generator().manual_seed(1))


def _check_frozen(enc, modules):
    enc.train()
    for module in modules:
        assert not any(p.requires_grad for p in module.parameters())
        assert not any(m.training for m in module.modules())


# --------------------------------------------------------------------------- RADIO
@pytest.mark.parametrize(
    ("version", "adaptor", "expected_adaptor"),
    [
        ("c-radio_v3-b", "clip", "clip"),
        ("c-radio_v3-b", None, "siglip2"),
        ("c-radio_v4-so400m", None, "siglip2-g"),
    ],
)
def test_radio_encoder_matches_the_models_own_outputs(
    radio_repo, version, adaptor, expected_adaptor
):
    enc = RadioEncoder(repo=radio_repo, source="local", version=version, adaptor=adaptor)
    assert enc.adaptor_name == expected_adaptor
    rule = enc.input_rule
    assert rule.patch_size == 16
    assert rule.mean == pytest.approx(NORM_MEAN) and rule.std == pytest.approx(NORM_STD)

    rgb = _rgb()
    x = enc.preprocess(rgb)  # [0, 1] RGB -> the rule's normalisation
    out = enc.encode(x)

    # Reference: an independent load, RADIO's documented use (RGB in [0, 1], own conditioner).
    ref = torch.hub.load(radio_repo, "radio_model", source="local", version=version,
                         adaptor_names=[expected_adaptor]).eval()  # fmt: skip
    with torch.no_grad():
        ref_out = ref(rgb, feature_fmt="NCHW")
        feats = ref_out["backbone"].features  # [B, C, 3, 4]
        head = ref.adaptors[expected_adaptor].head_mlp
        lang = head(feats.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)  # summary head per location
        ada = ref.adaptors[expected_adaptor]
        text = F.normalize(ada.encode_text(ada.tokenizer(TEXTS)), dim=-1)

    d_text = ada.head_mlp.final[-1].out_features
    assert out.intermediates.shape == (2, 32, 3, 4) and out.intermediates.dtype == torch.float32
    assert out.language.shape == (2, d_text, 3, 4) and out.language.dtype == torch.float32
    assert out.embedding.shape == (2, d_text) and out.embedding.dtype == torch.float32
    torch.testing.assert_close(out.intermediates, feats, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.language, lang, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(
        out.embedding, ref_out[expected_adaptor].summary, rtol=1e-5, atol=1e-5
    )
    # The language tokens come from the summary head, not the patch head.
    feat_head = ref_out[expected_adaptor].features
    assert feat_head.shape[1] != d_text or not torch.allclose(out.language, feat_head)

    queries = enc.encode_text(TEXTS)
    assert queries.shape == (len(TEXTS), out.language.shape[1]) and queries.dtype == torch.float32
    torch.testing.assert_close(queries.norm(dim=-1), torch.ones(len(TEXTS)))
    torch.testing.assert_close(queries, text, rtol=1e-5, atol=1e-6)
    _check_frozen(enc, [enc])


def test_radio_unknown_adaptor_names_the_key(radio_repo):
    with pytest.raises(ValueError, match=r"model\.adaptor='dino_v3'.*Known names"):
        RadioEncoder(repo=radio_repo, source="local", version="c-radio_v3-b", adaptor="dino_v3")


def test_radio_rejects_sizes_off_the_resolution_step(radio_repo):
    enc = RadioEncoder(repo=radio_repo, source="local")
    with pytest.raises(ValueError, match="multiple of RADIO's resolution step 16"):
        enc.encode(torch.zeros(1, 3, 40, 64))


# --------------------------------------------------------------------------- RADSeg
def test_radseg_encoder_matches_radsegs_own_outputs(radseg_repo):
    enc = RadSegEncoder(repo=radseg_repo, source="local")
    # One pass, no prediction: what RADSeg was built with.
    assert enc.encoder.slide_crop == 0 and enc.encoder.predict is False
    assert enc.input_rule.patch_size == 16
    assert enc.input_rule.mean == pytest.approx(NORM_MEAN)
    assert enc.input_rule.std == pytest.approx(NORM_STD)

    rgb = _rgb()
    out = enc.encode(enc.preprocess(rgb))

    ref = torch.hub.load(radseg_repo, "radseg_encoder", source="local", slide_crop=0, device="cpu")
    with torch.no_grad():
        feats = ref.model(rgb).features.transpose(1, 2).reshape(2, -1, 3, 4)  # RADIO in RADSeg
        agg = ref._self_correlating_global_aggregation(feats)
        head = ref.lang_adaptor.head_mlp
        lang = head(agg.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
        lang_api = ref.align_spatial_features_with_language(ref.encode_image_to_feat_map(rgb))
        text = ref.encode_prompts(TEXTS)

    d_text = head.final[-1].out_features
    assert out.intermediates.shape == (2, 32, 3, 4) and out.intermediates.dtype == torch.float32
    assert out.language.shape == (2, d_text, 3, 4) and out.language.dtype == torch.float32
    assert out.embedding is None
    torch.testing.assert_close(out.intermediates, feats, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.language, lang, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.language, lang_api, rtol=1e-5, atol=1e-5)

    queries = enc.encode_text(TEXTS)
    assert queries.shape == (len(TEXTS), d_text) and queries.dtype == torch.float32
    torch.testing.assert_close(queries.norm(dim=-1), torch.ones(len(TEXTS)))
    torch.testing.assert_close(queries, text, rtol=1e-5, atol=1e-6)
    _check_frozen(enc, [enc.encoder.model, enc.encoder.lang_adaptor])

    agg_enc = RadSegEncoder(repo=radseg_repo, source="local", intermediates="aggregated")
    torch.testing.assert_close(
        agg_enc.encode(agg_enc.preprocess(rgb)).intermediates, agg, rtol=1e-5, atol=1e-5
    )


def test_radseg_encoder_refuses_sliding_windows_and_prediction(radseg_repo):
    for bad in ({"slide_crop": 336}, {"predict": True}, {"sam_refinement": True}):
        with pytest.raises(ValueError, match="one pass without prediction"):
            RadSegEncoder(repo=radseg_repo, source="local", **bad)


# --------------------------------------------------------------------------- offline
def _hub_load_forbidden(*args, **kwargs):
    raise AssertionError("torch.hub.load must not run when the network check fails")


def test_unreachable_github_fails_at_once_naming_the_keys(monkeypatch):
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    start = time.monotonic()
    for cls in (RadioEncoder, RadSegEncoder):
        with pytest.raises(WeightsUnavailableError, match=r"github\.com") as err:
            cls(source="github")
        assert "model.repo=" in str(err.value) and "model.source=local" in str(err.value)
    assert time.monotonic() - start < 2.0


def test_radseg_without_radio_in_the_hub_cache_fails_at_once(radseg_repo, hub, monkeypatch):
    (hub / "NVlabs_RADIO_main" / "hubconf.py").unlink()
    (hub / "NVlabs_RADIO_main").rmdir()
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    with pytest.raises(WeightsUnavailableError, match="NVlabs_RADIO_main"):
        RadSegEncoder(repo=radseg_repo, source="local")


def test_uncached_radio_weights_fail_at_once(radio_repo, hub, monkeypatch):
    (hub / "checkpoints" / RADIO_CHECKPOINTS["c-radio_v3-b"]).unlink()
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    with pytest.raises(WeightsUnavailableError, match=r"huggingface\.co.*model\.version="):
        RadioEncoder(repo=radio_repo, source="local", version="c-radio_v3-b")


# --------------------------------------------------------------------------- ReSiReg
@pytest.mark.parametrize("kind", ["radio", "radseg"])
def test_encode_image_with_resireg_full(kind, radio_repo, radseg_repo):
    if kind == "radio":
        enc = RadioEncoder(repo=radio_repo, source="local")
    else:
        enc = RadSegEncoder(repo=radseg_repo, source="local")
    images = (_rgb(2, 50, 70) * 255).to(torch.uint8)  # resized to 48 x 64 (3 x 4 patches)
    base = enc.encode_image(images)
    full = enc.encode_image(images, resireg="full", n_prototypes=4)
    d_text = enc.encode_text(["x"]).shape[1]
    assert base.shape == (2, d_text, 3, 4)
    assert full.shape == (2, d_text, 6, 8)  # ReSiReg Full upsamples x2
    assert torch.isfinite(full).all()
    torch.testing.assert_close(full.norm(dim=1), torch.ones(2, 6, 8), rtol=1e-4, atol=1e-4)
    sim = enc.similarity(images, TEXTS, resireg="full", n_prototypes=4)
    assert sim.shape == (2, len(TEXTS), 6, 8)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_encoders_run_on_the_device_they_are_built_for(radio_repo, radseg_repo):
    encoders = [
        RadioEncoder(repo=radio_repo, source="local", device="cuda"),
        RadSegEncoder(repo=radseg_repo, source="local", device="cuda"),
    ]
    for enc in encoders:
        assert enc.device.type == "cuda"
        out = enc.encode(enc.preprocess(_rgb()))
        assert out.intermediates.device.type == "cuda" and out.language.device.type == "cuda"
        assert enc.encode_text(TEXTS).device.type == "cuda"
        sim = enc.similarity(_rgb(), TEXTS, resireg="full", n_prototypes=4)
        assert sim.shape == (2, len(TEXTS), 6, 8)
