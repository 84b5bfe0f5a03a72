"""DinoTxtEncoder offline: a local torch.hub repo laid out like facebookresearch/dinov2.

The fake repo has the same entry point name, package layout and class/attribute layout as
dino.txt's hub code (``hubconf.py`` -> ``dinov2.hub.dinotxt``; ``DinoTxt`` with
``visual_model`` = ``VisionTower(DINOv2Wrapper(ViT), VisionHead)``, ``text_model``,
``model_config``, ``encode_image`` / ``encode_text`` / ``get_visual_class_and_patch_tokens``;
``dinov2.hub.text.tokenizer.Tokenizer(vocab_path)`` and ``dinov2.hub.dinotxt.get_tokenizer``)
at tiny sizes: patch 14, width 32, 4 registers, a 4 x 4 positional grid (image 56),
``embed_dim`` 64 (= 2 x 32, so the head has no projection, as in the real model). Expected
values are recomputed from the fake model's own modules, never through the adapter.
"""

from __future__ import annotations

import gzip
import sys
import textwrap
import time

import pytest
import torch
import torch.nn.functional as F

import resireg.models.hub as hub_module
from resireg.models.hub import WeightsUnavailableError
from resireg.models.zoo.dinotxt import DINOTXT_CHECKPOINTS, DINOTXT_ENTRY_POINT, DinoTxtEncoder

WIDTH, EMBED, SIDE = 32, 64, 56  # backbone width, text/image embedding width, fake native size
VOCAB = "dinov2/hub/bpe_simple_vocab_16e6.txt.gz"  # inside the fake repo
WORDS = "a photo of the cat dog car sky road tree person bicycle"

_FILES = {
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
    "dinov2/models/vision_transformer.py": """
        import math
        import torch
        from torch import nn
        from dinov2.layers import NestedTensorBlock as Block

        class DinoVisionTransformer(nn.Module):
            def __init__(self, img_size=56, patch_size=14, embed_dim=32, depth=2, num_heads=2,
                         num_register_tokens=4):
                super().__init__()
                self.patch_size, self.embed_dim, self.num_heads = patch_size, embed_dim, num_heads
                self.num_register_tokens = num_register_tokens
                self.chunked_blocks = False
                m = img_size // patch_size
                self.patch_embed = nn.Conv2d(3, embed_dim, patch_size, stride=patch_size)
                self.cls_token = nn.Parameter(torch.randn(1, 1, embed_dim))
                self.pos_embed = nn.Parameter(torch.randn(1, 1 + m * m, embed_dim))
                self.register_tokens = nn.Parameter(torch.randn(1, num_register_tokens, embed_dim))
                self.blocks = nn.ModuleList(Block(embed_dim, num_heads) for _ in range(depth))
                self.norm = nn.LayerNorm(embed_dim)

            def interpolate_pos_encoding(self, x, h, w):  # as DINOv2 (size, antialias)
                n = self.pos_embed.shape[1] - 1
                h0, w0 = h // self.patch_size, w // self.patch_size
                if x.shape[1] - 1 == n and h == w:
                    return self.pos_embed
                m = int(math.sqrt(n))
                patch = self.pos_embed[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
                patch = nn.functional.interpolate(patch, size=(h0, w0), mode="bicubic", antialias=True)
                patch = patch.permute(0, 2, 3, 1).reshape(1, h0 * w0, -1)
                return torch.cat([self.pos_embed[:, :1], patch], dim=1)

            def prepare_tokens_with_masks(self, x, masks=None):
                _, _, h, w = x.shape
                x = self.patch_embed(x).flatten(2).transpose(1, 2)
                x = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), x], dim=1)
                x = x + self.interpolate_pos_encoding(x, h, w)
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
    """,
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

            vision_backbone = DINOv2Wrapper(DinoVisionTransformer())
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


def _is_dinov2(name: str) -> bool:
    return name == "dinov2" or name.startswith("dinov2.")


@pytest.fixture(scope="module")
def fake_repo(tmp_path_factory):
    """The fake dinov2 clone; its ``dinov2`` package is dropped from ``sys.modules`` after."""
    repo = tmp_path_factory.mktemp("dinotxt") / "dinov2"
    for rel, text in _FILES.items():
        path = repo / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    with gzip.open(repo / VOCAB, "wb") as f:
        f.write(WORDS.replace(" ", "\n").encode())
    saved = {k: sys.modules.pop(k) for k in list(sys.modules) if _is_dinov2(k)}
    yield repo
    for k in [k for k in sys.modules if _is_dinov2(k)]:
        del sys.modules[k]
    sys.modules.update(saved)


def _refuse(host, timeout):
    raise AssertionError(f"a test tried to reach {host}")


def _offline(mp, hub_dir, cached=True):
    """No network (any probe fails the test) and a torch hub cache, with the weights or not."""
    mp.setattr(hub_module, "_resolves", _refuse)
    (hub_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    for name in DINOTXT_CHECKPOINTS if cached else ():
        (hub_dir / "checkpoints" / name).touch()
    mp.setattr(torch.hub, "get_dir", lambda: str(hub_dir))


def _build(repo, **kwargs):
    kwargs = {"source": "local", "image_size": SIDE, "vocab": str(repo / VOCAB), **kwargs}
    return DinoTxtEncoder(repo=str(repo), **kwargs)


@pytest.fixture(scope="module")
def encoder(fake_repo, tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        _offline(mp, tmp_path_factory.mktemp("hub"))
        torch.manual_seed(0)
        return _build(fake_repo)


@pytest.fixture
def offline(monkeypatch, tmp_path):
    _offline(monkeypatch, tmp_path / "hub")
    return monkeypatch


def _grid(tokens, size):
    """``[B, N, D]`` tokens of a ``size`` grid -> ``[B, D, *size]`` (test's own reshape)."""
    return tokens.permute(0, 2, 1).unflatten(2, size)


def test_dense_maps_are_the_backbone_and_head_patch_tokens(encoder):
    """Non-square canvas 70 x 98 (grid 5 x 7): resized to 56 x 56 (grid 4 x 4), run once, both
    maps upsampled bilinearly to 5 x 7; embedding = the model's own encode_image."""
    x = torch.randn(2, 3, 70, 98)
    out = encoder.encode(x)
    assert out.intermediates.shape == (2, WIDTH, 5, 7)
    assert out.language.shape == (2, WIDTH, 5, 7)
    assert out.intermediates.dtype == out.language.dtype == torch.float32

    model = encoder.model
    small = F.interpolate(x, size=(SIDE, SIDE), mode="bilinear", align_corners=False)
    with torch.no_grad():
        backbone = model.visual_model.backbone.model.forward_features(small)["x_norm_patchtokens"]
        _, head = model.get_visual_class_and_patch_tokens(small)
        image_embedding = model.encode_image(small)

    def up(tokens):
        return F.interpolate(
            _grid(tokens, (4, 4)), size=(5, 7), mode="bilinear", align_corners=False
        )

    torch.testing.assert_close(out.intermediates, up(backbone), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.language, up(head), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.embedding, image_embedding, atol=1e-5, rtol=1e-5)
    assert out.embedding.shape == (2, EMBED)
    # the two maps are different things (head vs backbone)
    assert not torch.allclose(out.intermediates, out.language, atol=1e-2)


def test_native_resolution_runs_the_canvas_as_it_is(fake_repo, offline):
    """image_size=None: no resizing; the ViT interpolates its positional grid (3 x 5 here)."""
    encoder = _build(fake_repo, image_size=None)
    x = torch.randn(1, 3, 42, 70)
    out = encoder.encode(x)
    with torch.no_grad():
        backbone = encoder.model.visual_model.backbone.model.forward_features(x)
        _, head = encoder.model.get_visual_class_and_patch_tokens(x)
    torch.testing.assert_close(
        out.intermediates, _grid(backbone["x_norm_patchtokens"], (3, 5)), atol=1e-5, rtol=1e-5
    )
    torch.testing.assert_close(out.language, _grid(head, (3, 5)), atol=1e-5, rtol=1e-5)


def test_text_queries_are_the_normalised_patch_half(encoder):
    texts = ["a photo of a cat", "a photo of the sky", "road", "a tree and a person"]
    queries = encoder.encode_text(texts)
    assert queries.shape == (4, WIDTH)
    assert queries.shape[1] == encoder.encode(torch.randn(1, 3, 28, 28)).language.shape[1]
    torch.testing.assert_close(queries.norm(dim=-1), torch.ones(4))

    tokens = encoder.tokenizer.tokenize(texts)
    with torch.no_grad():
        full = encoder.model.encode_text(tokens)
    assert full.shape == (4, EMBED)
    torch.testing.assert_close(queries, F.normalize(full[:, EMBED // 2 :], dim=-1))
    assert not torch.allclose(queries, F.normalize(full[:, : EMBED // 2], dim=-1), atol=1e-2)
    # the two-step form (frozen features, then normalisation) gives the same queries
    torch.testing.assert_close(encoder.dense_text(encoder.text_features(texts)), queries)


def test_text_batches_do_not_change_queries(encoder, monkeypatch):
    texts = ["cat", "dog", "car", "sky", "road"]
    whole = encoder.encode_text(texts)
    monkeypatch.setattr(encoder, "text_batch_size", 2)
    torch.testing.assert_close(encoder.encode_text(texts), whole, atol=1e-6, rtol=1e-6)


def test_input_rule_and_frozen(encoder):
    rule = encoder.input_rule
    assert rule.patch_size == 14
    assert rule.mean == pytest.approx((0.485, 0.456, 0.406))
    assert rule.std == pytest.approx((0.229, 0.224, 0.225))
    assert not any(p.requires_grad for p in encoder.parameters())
    encoder.train()
    assert not encoder.training and not encoder.model.training


def test_encode_image_lite_and_similarity_run(encoder):
    images = (torch.rand(2, 3, 70, 98) * 255).to(torch.uint8)
    dense = encoder.encode_image(images, resireg="lite")
    assert dense.shape[:2] == (2, WIDTH) and dense.shape[-2] >= 5 and dense.shape[-1] >= 7
    assert torch.isfinite(dense).all()
    sim = encoder.similarity(images, ["cat", "sky"], resireg="lite")
    assert sim.shape == (2, 2, *dense.shape[-2:])
    assert sim.abs().max() <= 1 + 1e-4


def test_github_offline_fails_at_once_naming_the_key(monkeypatch, tmp_path):
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)

    def no_hub(*args, **kwargs):
        raise AssertionError("torch.hub.load must not be reached offline")

    monkeypatch.setattr(torch.hub, "load", no_hub)
    start = time.monotonic()
    with pytest.raises(WeightsUnavailableError) as err:
        DinoTxtEncoder()
    assert time.monotonic() - start < 2
    message = str(err.value)
    assert "github.com" in message
    assert "model.repo=/path/to/dinov2" in message and "model.source=local" in message
    assert "model.vocab=" in message


def test_uncached_weights_offline_fail_at_once(fake_repo, monkeypatch, tmp_path):
    _offline(monkeypatch, tmp_path / "hub", cached=False)
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    with pytest.raises(WeightsUnavailableError) as err:
        _build(fake_repo)
    message = str(err.value)
    assert "dl.fbaipublicfiles.com" in message and DINOTXT_CHECKPOINTS[1] in message
    assert str(tmp_path / "hub" / "checkpoints") in message


def test_vocabulary_download_offline_fails_naming_model_vocab(fake_repo, offline):
    offline.setattr(hub_module, "_resolves", lambda host, timeout: False)
    with pytest.raises(WeightsUnavailableError, match=r"vocabulary.*model\.vocab="):
        _build(fake_repo, vocab=None)


def test_default_tokenizer_is_the_repos_get_tokenizer(fake_repo, offline):
    hosts = []
    offline.setattr(hub_module, "_resolves", lambda host, timeout: hosts.append(host) or True)
    encoder = _build(fake_repo, vocab=None)
    assert hosts == ["dl.fbaipublicfiles.com"]  # the vocabulary check only (weights are cached)
    assert type(encoder.tokenizer).__module__ == "dinov2.hub.text.tokenizer"
    assert encoder.tokenizer.vocab_path == str(fake_repo / VOCAB)
    assert DINOTXT_ENTRY_POINT == "dinov2_vitl14_reg4_dinotxt_tet1280d20h24l"


def test_bad_local_repo_and_image_size(fake_repo, offline, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"model\.repo="):
        DinoTxtEncoder(repo=str(tmp_path / "absent"), source="local")
    with pytest.raises(ValueError, match=r"model\.image_size=50"):
        _build(fake_repo, image_size=50)
