"""ClipEncoder: OpenAI CLIP ViTs (open_clip, random init here) as a DenseEncoder.

Every expected value is recomputed independently of the adapter: from open_clip's own
forward pass (hooks on its blocks, ``model.encode_image`` / ``encode_text``) and, for the
two dense paths (``value``: SC-CLIP's / OTAS's; ``maskclip``: the official MaskCLIP's, with
the last block's residual and MLP), from the last block's own modules (``ln_1``, its
``nn.MultiheadAttention`` with every token attending only to itself, ``ln_2``, ``mlp``) and
the model's ``ln_post`` / ``proj``, or with plain torch ops on the parameters.
"""

import time

import open_clip
import pytest
import torch
import torch.nn.functional as F
import yaml
from huggingface_hub import constants as hf_constants
from PIL import Image
from safetensors.torch import save_file

from helpers.paths import ROOT
from resireg.method.lite import ReSiRegLite
from resireg.models import WeightsUnavailableError
from resireg.models import hub as hub_module
from resireg.models.zoo.clip import ClipEncoder

B16 = "ViT-B-16"


@pytest.fixture(scope="module")
def enc():
    return ClipEncoder(B16, weights=None)


def _images(h, w, b=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, 3, h, w, generator=g)


def _native(images, size=224):
    return F.interpolate(images, size=(size, size), mode="bilinear", align_corners=False,
                         antialias=True)  # fmt: skip


def _grid(tokens, size):
    """Patch tokens [B, g*g, D] (class token already dropped) -> [B, D, *size], bilinear."""
    g = int(round(tokens.shape[1] ** 0.5))
    maps = tokens.reshape(tokens.shape[0], g, g, -1).permute(0, 3, 1, 2)
    return F.interpolate(maps, size=size, mode="bilinear", align_corners=False)


def _reference(model, images, layer):
    """open_clip's own forward on the native-size batch, recording with hooks the input of
    the last block and the output of block ``layer``; returns those and encode_image."""
    blocks = model.visual.transformer.resblocks
    seen = {}
    h1 = blocks[-1].register_forward_pre_hook(lambda m, args: seen.__setitem__("last_in", args[0]))
    h2 = blocks[layer].register_forward_hook(lambda m, a, out: seen.__setitem__("inter", out))
    try:
        with torch.no_grad():
            emb = model.encode_image(_native(images))
    finally:
        h1.remove()
        h2.remove()
    assert model.visual.transformer.batch_first  # hooks saw [B, L, D]
    return seen["last_in"], seen["inter"], emb


def _value_path_by_hand(model, x):
    """Value-path language tokens from the last block's input x [B, L, D], plain torch ops."""
    blk, visual = model.visual.transformer.resblocks[-1], model.visual
    d = x.shape[-1]
    ln = F.layer_norm(x, (d,), blk.ln_1.weight, blk.ln_1.bias, blk.ln_1.eps)
    v = F.linear(ln, blk.attn.in_proj_weight[2 * d :], blk.attn.in_proj_bias[2 * d :])
    out = F.linear(v, blk.attn.out_proj.weight, blk.attn.out_proj.bias)
    post = F.layer_norm(out, (d,), visual.ln_post.weight, visual.ln_post.bias, visual.ln_post.eps)
    return post @ visual.proj


# ---------------------------------------------------------------------------- building
def test_input_rule_frozen_and_architecture(enc):
    rule = enc.input_rule
    assert rule.patch_size == 16
    assert rule.mean == tuple(open_clip.OPENAI_DATASET_MEAN)
    assert rule.std == tuple(open_clip.OPENAI_DATASET_STD)
    assert (enc.image_size, enc.depth, enc.width, enc.embed_dim) == (224, 12, 768, 512)
    assert enc.intermediate_layer == 8  # SC-CLIP's pre_adjust_idx for ViT-B/16
    assert not any(p.requires_grad for p in enc.parameters())
    enc.train()
    assert not enc.training and not enc.model.training
    # The OpenAI weights were trained with QuickGELU; open_clip's plain config uses GELU.
    assert isinstance(enc.model.visual.transformer.resblocks[0].mlp.gelu, open_clip.model.QuickGELU)


def test_layer_and_name_checks():
    assert ClipEncoder(B16, weights=None, intermediate_layer=-1).intermediate_layer == 11
    with pytest.raises(ValueError, match="intermediate_layer=12 is out of range"):
        ClipEncoder(B16, weights=None, intermediate_layer=12)
    with pytest.raises(ValueError, match="model_name='ViT-B-32'"):
        ClipEncoder("ViT-B-32", weights=None)
    with pytest.raises(ValueError, match="not a multiple of the patch size"):
        ClipEncoder(B16, weights=None, image_size=100)


# ---------------------------------------------------------------------------- encode
def test_encode_shapes_on_a_non_square_canvas(enc):
    out = enc.encode(_images(48, 80))
    assert out.intermediates.shape == (2, 768, 3, 5)
    assert out.language.shape == (2, 512, 3, 5)
    assert out.embedding.shape == (2, 512)
    assert out.layers is None  # only encode_layers fills it
    for t in out[:3]:
        assert t.dtype == torch.float32 and torch.isfinite(t).all()
    with pytest.raises(ValueError, match="not a multiple of the patch size 16"):
        enc.encode(_images(40, 80))


@pytest.mark.parametrize("canvas", [(48, 80), (224, 224), (352, 192)])
def test_language_intermediates_and_embedding_match_open_clip(enc, canvas):
    images = _images(*canvas)
    grid = (canvas[0] // 16, canvas[1] // 16)
    out = enc.encode(images)
    last_in, inter, emb = _reference(enc.model, images, layer=8)
    with torch.no_grad():
        lang = _value_path_by_hand(enc.model, last_in)
    torch.testing.assert_close(out.language, _grid(lang[:, 1:], grid), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out.intermediates, _grid(inter[:, 1:], grid), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out.embedding, emb, rtol=1e-4, atol=1e-4)


def test_value_path_is_self_attention_without_residual_or_mlp(enc):
    """The hand-sliced value path equals the block's own nn.MultiheadAttention when every
    token may attend only to itself (so the q/k/v packing order is right), and differs from
    the block's normal output (attention, residual, MLP)."""
    model = enc.model
    blk = model.visual.transformer.resblocks[-1]
    last_in, _, _ = _reference(model, _images(224, 224, b=1), layer=0)
    n = last_in.shape[1]
    diagonal_only = torch.full((n, n), float("-inf")).fill_diagonal_(0.0)
    with torch.no_grad():
        attn = blk.attn(*[blk.ln_1(last_in)] * 3, attn_mask=diagonal_only, need_weights=False)[0]
        by_mha = model.visual.ln_post(attn) @ model.visual.proj
        full = model.visual.ln_post(blk(last_in)) @ model.visual.proj
        lang = _value_path_by_hand(model, last_in)
    torch.testing.assert_close(lang, by_mha, rtol=1e-4, atol=1e-4)
    assert not torch.allclose(lang, full, atol=1e-2)
    out = enc.encode(_images(224, 224, b=1))
    torch.testing.assert_close(out.language, _grid(by_mha[:, 1:], (14, 14)), rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_other_intermediate_layer_and_seeded_rebuild(enc):
    other = ClipEncoder(B16, weights=None, intermediate_layer=3)
    for (k, a), (_, b) in zip(
        enc.model.state_dict().items(), other.model.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), k  # same seed -> the same random model
    images = _images(64, 32)
    _, inter, _ = _reference(other.model, images, layer=3)
    out = other.encode(images)
    torch.testing.assert_close(out.intermediates, _grid(inter[:, 1:], (4, 2)), rtol=1e-4, atol=1e-4)
    assert not torch.allclose(out.intermediates, enc.encode(images).intermediates, atol=1e-3)


# ---------------------------------------------------------------------------- dense paths
def _dense_from_modules(model, x, dense_path):
    """The language tokens [B, L, embed] of either dense path, from the last block's own
    modules on its input x [B, L, D]: its nn.MultiheadAttention with a diagonal-only mask
    (every token attends to itself: softmax(QK^T) = I), then (maskclip) the residual and the
    block's MLP on ln_2, as chongzhou96/MaskCLIP's TransformerEncoderLayer.forward does
    (``v += x; v = ffn(norm2(v), identity=v)``); ln_post and proj last."""
    visual = model.visual
    blk = visual.transformer.resblocks[-1]
    n = x.shape[1]
    diagonal_only = torch.full((n, n), float("-inf")).fill_diagonal_(0.0)
    with torch.no_grad():
        a = blk.attn(*[blk.ln_1(x)] * 3, attn_mask=diagonal_only, need_weights=False)[0]
        if dense_path == "maskclip":
            y = x + a
            a = y + blk.mlp(blk.ln_2(y))
        return visual.ln_post(a) @ visual.proj


@pytest.fixture(scope="module")
def maskclip_enc():
    return ClipEncoder(B16, weights=None, dense_path="maskclip")  # the same seed: enc's weights


@pytest.mark.slow
@pytest.mark.parametrize("dense_path", ["value", "maskclip"])
def test_each_dense_path_matches_open_clips_modules(dense_path, enc, maskclip_enc):
    enc = {"value": enc, "maskclip": maskclip_enc}[dense_path]
    assert enc.dense_path == dense_path and enc.spec()["dense_path"] == dense_path
    canvas = (48, 80)
    images = _images(*canvas)
    last_in, inter, emb = _reference(enc.model, images, layer=8)
    expected = _dense_from_modules(enc.model, last_in, dense_path)
    out = enc.encode(images)
    grid = (canvas[0] // 16, canvas[1] // 16)
    torch.testing.assert_close(out.language, _grid(expected[:, 1:], grid), rtol=1e-4, atol=1e-4)
    # the path changes the language tokens only
    torch.testing.assert_close(out.intermediates, _grid(inter[:, 1:], grid), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out.embedding, emb, rtol=1e-4, atol=1e-4)


def test_the_two_dense_paths_differ_and_maskclip_is_the_blocks_output_without_attention(
    enc, maskclip_enc
):
    """maskclip = the last block run with the diagonal-only attention mask (what open_clip's
    own block computes then), value = its attention branch alone."""
    images = _images(224, 224, b=1)
    maskclip = maskclip_enc
    last_in, _, _ = _reference(enc.model, images, layer=0)
    n = last_in.shape[1]
    diagonal_only = torch.full((n, n), float("-inf")).fill_diagonal_(0.0)
    visual = enc.model.visual
    with torch.no_grad():
        by_block = visual.ln_post(
            visual.transformer.resblocks[-1](last_in, attn_mask=diagonal_only)
        )
        by_block = by_block @ visual.proj
    out = maskclip.encode(images).language
    torch.testing.assert_close(out, _grid(by_block[:, 1:], (14, 14)), rtol=1e-4, atol=1e-4)
    assert not torch.allclose(out, enc.encode(images).language, atol=1e-2)


def test_dense_path_is_checked_and_in_the_config():
    with pytest.raises(ValueError, match=r"^dense_path='clearclip'.*value.*maskclip"):
        ClipEncoder(B16, weights=None, dense_path="clearclip")
    conf = ROOT / "conf" / "encoder"
    for name in ("clip_vit_b16", "clip_vit_l14_336"):
        entry = yaml.safe_load((conf / f"{name}.yaml").read_text())
        assert entry["dense_path"] == "value", name  # the protocol's default (docs/protocol.md)


# ---------------------------------------------------------------------------- layers
def test_encode_layers_gives_every_requested_block_from_one_pass(enc):
    images = _images(48, 80)
    blocks = enc.model.visual.transformer.resblocks
    seen, hooks = {}, []
    for i in (0, 5, 11):
        hooks.append(blocks[i].register_forward_hook(
            lambda m, a, out, i=i: seen.__setitem__(i, out)))  # fmt: skip
    calls = []
    hooks.append(blocks[0].register_forward_pre_hook(lambda m, a: calls.append(1)))
    try:
        out = enc.encode_layers(images, [5, -1, 0, 5])
    finally:
        for h in hooks:
            h.remove()
    assert len(calls) == 1  # one pass for all the blocks
    assert sorted(out.layers) == [0, 5, 11]  # -1 is block 11; each block once
    for i, tokens in seen.items():
        expected = _grid(tokens[:, 1:], (3, 5))
        torch.testing.assert_close(out.layers[i], expected, rtol=1e-4, atol=1e-4)
    plain = enc.encode(images)
    for a, b in zip(out[:3], plain[:3], strict=True):
        assert torch.equal(a, b)  # the same pass: bitwise what encode gives
    with pytest.raises(ValueError, match="layer=12 is out of range for ViT-B-16"):
        enc.encode_layers(images, [3, 12])


# ---------------------------------------------------------------------------- text
@pytest.mark.slow
def test_text_queries_match_open_clip(enc):
    texts = ["a photo of a cat.", "a photo of a dog.", "sky"]
    queries = enc.encode_text(texts)
    assert queries.shape == (3, enc.encode(_images(32, 32, b=1)).language.shape[1])
    torch.testing.assert_close(queries.norm(dim=1), torch.ones(3))
    tokenizer = open_clip.get_tokenizer(B16)
    with torch.no_grad():
        expected = F.normalize(enc.model.encode_text(tokenizer(texts)), dim=-1)
    torch.testing.assert_close(queries, expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(enc.dense_text(enc.text_features(texts)), queries)
    assert not enc.text_features(texts).norm(dim=1).allclose(torch.ones(3))  # unnormalised


# ---------------------------------------------------------------------------- weights
@pytest.fixture
def no_network(monkeypatch):
    """Fail the test if anything tries the network or an open_clip download."""

    def refuse(*args, **kwargs):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(hub_module, "_resolves", refuse)
    monkeypatch.setattr(open_clip.factory, "download_pretrained", refuse)


@pytest.mark.parametrize("name", [B16, "ViT-L-14-336"])
def test_openai_weights_offline_fail_fast(name, tmp_path, monkeypatch, no_network):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(tmp_path / "hub"))  # an empty cache
    start = time.monotonic()
    with pytest.raises(WeightsUnavailableError, match=r"instead: weights=/path/to/") as err:
        ClipEncoder(name, weights="openai")
    assert time.monotonic() - start < 10.0
    assert "HF_HUB_OFFLINE" in str(err.value) and f"{name}/openai" in str(err.value)


def test_openai_weights_unreachable_host(tmp_path, monkeypatch):
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    hosts = []
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: hosts.append(host) or False)
    with pytest.raises(WeightsUnavailableError, match=r"cannot be reached.*instead: weights="):
        ClipEncoder(B16, weights="openai")
    assert hosts == ["huggingface.co"]
    with pytest.raises(ValueError, match="neither an existing file nor an open_clip pretrained"):
        ClipEncoder(B16, weights="no-such-tag")


@pytest.mark.slow
@pytest.mark.parametrize("suffix", ["pt", "safetensors"])
def test_local_checkpoint_file(enc, tmp_path, suffix, no_network):
    path = tmp_path / f"clip.{suffix}"
    state = {k: v.contiguous() for k, v in enc.model.state_dict().items()}
    if suffix == "pt":
        torch.save(state, path)
    else:
        save_file(state, path)
    torch.manual_seed(123)  # the architecture's random init differs from enc's
    loaded = ClipEncoder(B16, weights=str(path))
    assert loaded.weights == str(path)
    for k, v in state.items():
        assert torch.equal(loaded.model.state_dict()[k], v), k
    images = _images(48, 48)
    for a, b in zip(loaded.encode(images)[:3], enc.encode(images)[:3], strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.slow
def test_openai_tag_served_from_the_cache_offline(enc, tmp_path, monkeypatch):
    """A cached tag loads offline: the cache check and open_clip's hub download agree."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(hub_module, "_resolves", lambda *a: pytest.fail("network probed"))
    cache = tmp_path / "hub"
    repo = cache / "models--timm--vit_base_patch16_clip_224.openai"
    snapshot = repo / "snapshots" / ("0" * 40)
    snapshot.mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("0" * 40)
    torch.save(enc.model.state_dict(), snapshot / "open_clip_pytorch_model.bin")
    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(cache))
    loaded = ClipEncoder(B16, weights="openai")
    images = _images(32, 48, b=1)
    torch.testing.assert_close(loaded.encode(images).language, enc.encode(images).language)


# ---------------------------------------------------------------------------- integration
@pytest.mark.slow
def test_encode_image_lite_and_similarity(enc):
    images = _images(48, 80)
    dense = enc.encode_image(images, "lite", normalized=True)
    assert dense.shape == (2, 512, 6, 10)  # Lite: 2 x the intermediates' grid
    torch.testing.assert_close(dense.norm(dim=1), torch.ones(2, 6, 10), rtol=1e-4, atol=1e-4)
    out = enc.encode(images)
    torch.testing.assert_close(dense, ReSiRegLite()(out.intermediates, out.language))
    pil = Image.fromarray(torch.randint(0, 256, (60, 100, 3), dtype=torch.uint8).numpy())
    sim = enc.similarity(pil, ["cat", "dog"], "lite", short_side=48)
    assert sim.shape == (1, 2, 6, 10) and sim.abs().max() <= 1.0 + 1e-4


# ---------------------------------------------------------------------------- ViT-L/14@336
@pytest.mark.slow
def test_vit_l14_336_shapes():
    enc = ClipEncoder("ViT-L-14-336", weights=None)
    assert enc.input_rule.patch_size == 14 and enc.image_size == 336
    assert enc.intermediate_layer == 17
    out = enc.encode(_images(28, 42, b=1))
    assert out.intermediates.shape == (1, 1024, 2, 3)
    assert out.language.shape == (1, 768, 2, 3)
    assert out.embedding.shape == (1, 768)
    assert enc.encode_text(["a cat"]).shape == (1, 768)
