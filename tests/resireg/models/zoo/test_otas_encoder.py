"""OtasEncoder offline: a local torch.hub repo for DINOv2 and a random-init open_clip ViT-B/16.

The fake hub repo's ``hubconf.py`` (``tests/helpers/fake_hubs/dinov2.py``: ``DINOV2_HUBCONF``) exposes ``dinov2_vits14_reg`` like facebookresearch/dinov2:
it takes ``pretrained`` and keyword overrides and returns a ``DinoVisionTransformer`` with
the real attribute layout (``patch_size``, ``embed_dim``, ``num_register_tokens``,
``interpolate_antialias`` / ``interpolate_offset`` read at every call, ``pos_embed`` on a
37 x 37 grid as with ``img_size=518``, ``forward_features`` -> ``x_norm_patchtokens`` with
CLS and 4 registers removed) at a tiny width (32) and depth (1). Expected values are
recomputed here from the models' own modules and plain torch / numpy / scikit-learn, never
through the adapter's helpers: OTAS's steps as written in its ``src/model.py`` and
``maskclip_onnx`` (see :mod:`resireg.models.zoo.otas`).
"""

from __future__ import annotations

import inspect
import math
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml
from huggingface_hub import constants as hf_constants
from sklearn.cluster import KMeans
from sklearn.decomposition import PCA

import resireg.models.hub as hub_module
from helpers.fake_hubs.common import build_offline, offline_hub
from helpers.fake_hubs.dinov2 import dinov2_repo
from helpers.paths import ROOT
from resireg.models.hub import WeightsUnavailableError
from resireg.models.zoo.otas import OTAS_CHECKPOINTS, OTAS_ENTRY_POINT, OtasEncoder

WIDTH = 32  # fake DINOv2 width
EMBED = 512  # CLIP ViT-B/16 embedding
CLIP_SIDE = 64  # CLIP's native side here (4 x 4 positional grid) and OTAS's CLIP input side
CONF = ROOT / "conf" / "encoder" / "otas.yaml"
_CACHED = [OTAS_CHECKPOINTS[OTAS_ENTRY_POINT]]  # the DINOv2 weights in the hub cache


@pytest.fixture(scope="module")
def fake_repo(tmp_path_factory):
    return Path(dinov2_repo(tmp_path_factory.mktemp("dinov2")))


def _build(repo, **kwargs):
    kwargs = {"source": "local", "clip": {"weights": None, "image_size": CLIP_SIDE}, **kwargs}
    kwargs.setdefault("clip_input_size", CLIP_SIDE)
    return OtasEncoder(repo=str(repo), **kwargs)


@pytest.fixture(scope="module")
def encoder(fake_repo, tmp_path_factory):
    return build_offline(tmp_path_factory, _CACHED, _build, fake_repo)


@pytest.fixture
def offline(monkeypatch, tmp_path):
    """No network (any probe fails the test); a torch hub cache with the DINOv2 weights."""
    offline_hub(monkeypatch, tmp_path / "hub", _CACHED)
    return monkeypatch


def _canvas(h, w, b=1, seed=0):
    """A normalised canvas with some structure (blocks of colour plus noise)."""
    g = torch.Generator().manual_seed(seed)
    blocks = torch.rand(b, 3, h // 14, w // 14, generator=g)
    x = F.interpolate(blocks, size=(h, w), mode="nearest") + 0.1 * torch.rand(
        b, 3, h, w, generator=g
    )
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    return (x.clamp(0, 1) - mean) / std


# ------------------------------------------------------------------ the reference
def _resize(x, size):
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)


def _reference_labels(tokens, n_clusters=24, n_components=12, side=16):
    """OTAS's clustering of one image's tokens [N, D]: normalise, PCA, normalise, k-means
    (scikit-learn, random_state 0), label grid resized (nearest) to side x side."""
    feats = F.normalize(tokens, dim=-1).numpy().astype(np.float32)
    reduced = PCA(n_components=n_components, svd_solver="full").fit_transform(feats)
    reduced /= np.linalg.norm(reduced, axis=1, keepdims=True)
    labels = KMeans(n_clusters=n_clusters, random_state=0).fit_predict(reduced)
    g = math.isqrt(len(labels))
    grid = torch.from_numpy(labels).reshape(1, 1, g, g).float()
    return F.interpolate(grid, size=(side, side), mode="nearest")[0, 0].long()


def _reference_maskclip(model, x, side, dense_path="value"):
    """maskclip_onnx's patch encodings ([B, 512, h, w]) and global embedding of canvas x:
    shorter side to 224, conv stem, positional embedding interpolated (bicubic, +0.1
    offset), all blocks but the last, the last block's value path, ln_post, proj. With
    ``dense_path="maskclip"`` the value path is followed by the last block's residual and
    its MLP on ln_2 (the official MaskCLIP's ``v += x; v = ffn(norm2(v), identity=v)``)."""
    h, w = x.shape[-2:]
    size = (side, int(side * w / h)) if w > h else (int(side * h / w), side)
    x = _resize(x, size)
    visual = model.visual
    d = visual.conv1.out_channels
    t = F.conv2d(x, visual.conv1.weight, stride=visual.conv1.stride)
    gh, gw = t.shape[-2:]
    t = torch.cat([visual.class_embedding.expand(x.shape[0], 1, d), t.flatten(2).mT], dim=1)
    pos = visual.positional_embedding
    if not (gh * gw == pos.shape[0] - 1 and x.shape[-2] == x.shape[-1]):
        m = math.isqrt(pos.shape[0] - 1)
        grid = pos[1:].reshape(1, m, m, d).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, scale_factor=((gh + 0.1) / m, (gw + 0.1) / m),
                             mode="bicubic", align_corners=False)  # fmt: skip
        pos = torch.cat([pos[:1], grid.flatten(2)[0].T])
    t = visual.ln_pre(t + pos)
    blocks = visual.transformer.resblocks
    for blk in blocks[:-1]:
        t = blk(t)
    last = blocks[-1]
    ln = F.layer_norm(t, (d,), last.ln_1.weight, last.ln_1.bias, last.ln_1.eps)
    v = F.linear(ln, last.attn.in_proj_weight[2 * d :], last.attn.in_proj_bias[2 * d :])
    v = F.linear(v, last.attn.out_proj.weight, last.attn.out_proj.bias)
    if dense_path == "maskclip":
        y = t + v
        v = y + last.mlp(last.ln_2(y))
    dense = visual.ln_post(v[:, 1:]) @ visual.proj
    embedding = visual.ln_post(last(t)[:, 0]) @ visual.proj
    return dense.mT.reshape(x.shape[0], -1, gh, gw), embedding


def _reference_pool(labels, clip_map, side=16):
    """clip_shared_feat_map (nearest lookup) then masked_average_pooling_cpu, as loops."""
    c, hs, ws = clip_map.shape
    rows = [min(math.floor(i * hs / side), hs - 1) for i in range(side)]
    cols = [min(math.floor(j * ws / side), ws - 1) for j in range(side)]
    shared = clip_map[:, rows][:, :, cols]
    out = shared.clone()
    for label in labels.unique():
        mask = labels == label
        mean = shared[:, mask].mean(dim=1)
        out[:, mask] = (mean / mean.norm())[:, None]
    return out


def _reference(encoder, x):
    with torch.no_grad():
        tokens = encoder.dino.forward_features(_resize(x, (224, 224)))["x_norm_patchtokens"]
        clip_maps, embedding = _reference_maskclip(encoder.clip.model, x, encoder.clip_input_size)
    pooled = torch.stack(
        [_reference_pool(_reference_labels(t), c) for t, c in zip(tokens, clip_maps, strict=True)]
    )
    return tokens, pooled, embedding


# ------------------------------------------------------------------ dense output
@pytest.fixture(scope="module")
def canvas():
    return _canvas(70, 98, b=2, seed=1)


@pytest.fixture(scope="module")
def encoded(encoder, canvas):
    return encoder.encode(canvas)


def test_output_shapes_and_dtype(encoded):
    assert encoded.intermediates.shape == (2, WIDTH, 5, 7)
    assert encoded.language.shape == (2, EMBED, 5, 7)
    assert encoded.embedding.shape == (2, EMBED)
    dtypes = {encoded.intermediates.dtype, encoded.language.dtype, encoded.embedding.dtype}
    assert dtypes == {torch.float32}


def test_language_is_otas_pooling_recomputed(encoder, canvas, encoded, monkeypatch):
    """Non-square canvas 70 x 98: DINOv2 at 224 x 224 (16 x 16 tokens, 24 clusters), CLIP at
    64 x 89 (4 x 5 tokens, 9 pixel columns dropped, positions interpolated from 4 x 4), pooled
    on the 16 x 16 grid; the canvas grid is bilinear of it."""
    tokens, pooled, embedding = _reference(encoder, canvas)

    up = F.interpolate(pooled, size=(5, 7), mode="bilinear", align_corners=False)
    torch.testing.assert_close(encoded.language, up, atol=1e-5, rtol=1e-5)
    intermediates = F.interpolate(tokens.mT.reshape(2, WIDTH, 16, 16), size=(5, 7),
                                  mode="bilinear", align_corners=False)  # fmt: skip
    torch.testing.assert_close(encoded.intermediates, intermediates, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(encoded.embedding, embedding, atol=1e-4, rtol=1e-4)

    monkeypatch.setattr(encoder, "output_grid", "shared")
    shared = encoder.encode(canvas).language
    assert shared.shape == (2, EMBED, 16, 16)
    torch.testing.assert_close(shared, pooled, atol=1e-5, rtol=1e-5)
    # hard masks: unit-norm features, one per cluster (at most 24 distinct per image)
    torch.testing.assert_close(shared.norm(dim=1), torch.ones(2, 16, 16))
    for image in shared:
        assert 1 < image.flatten(1).T.unique(dim=0).shape[0] <= 24


def test_dinov2_interpolates_positions_as_otas(encoder):
    """The hub entry point sets antialias / offset 0; OTAS's ViT copy uses False / 0.1."""
    assert encoder.dino.interpolate_antialias is False
    assert encoder.dino.interpolate_offset == 0.1
    x = _resize(_canvas(56, 56), (224, 224))
    with torch.no_grad():
        otas = encoder.dino.forward_features(x)["x_norm_patchtokens"]
        encoder.dino.interpolate_antialias, encoder.dino.interpolate_offset = True, 0.0
        try:
            hub = encoder.dino.forward_features(x)["x_norm_patchtokens"]
        finally:
            encoder.dino.interpolate_antialias, encoder.dino.interpolate_offset = False, 0.1
    assert not torch.allclose(otas, hub, atol=1e-3)


def test_square_clip_pass_is_open_clips_own(encoder):
    """At the native square size (no positional interpolation) the CLIP pass is open_clip's:
    the value path of the last block's input (captured with a hook), and encode_image."""
    x = _canvas(CLIP_SIDE, CLIP_SIDE, seed=2)
    model = encoder.clip.model
    seen = {}
    hook = model.visual.transformer.resblocks[-1].register_forward_pre_hook(
        lambda m, args: seen.__setitem__("last_in", args[0])
    )
    try:
        with torch.no_grad():
            embedding = model.encode_image(x)
    finally:
        hook.remove()
    with torch.no_grad():
        language = encoder.clip.value_path(model.visual.transformer.resblocks[-1], seen["last_in"])
        language = model.visual.ln_post(language[:, 1:]) @ model.visual.proj
    maps, emb = encoder.clip_dense(x)
    torch.testing.assert_close(maps, language.mT.reshape(1, EMBED, 4, 4), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(emb, embedding, atol=1e-5, rtol=1e-5)


def test_maskclip_dense_path_on_otas_clip_pass(fake_repo, offline, encoder):
    """dense_path="maskclip" keeps the last block's residual and MLP in OTAS's CLIP pass
    (positions interpolated on a non-square canvas); the default is OTAS's value path."""
    assert encoder.dense_path == "value" and encoder.spec()["dense_path"] == "value"
    torch.manual_seed(0)
    maskclip = _build(fake_repo, dense_path="maskclip")
    assert maskclip.clip.dense_path == "maskclip" and maskclip.spec()["dense_path"] == "maskclip"
    x = _canvas(70, 98, seed=3)
    with torch.no_grad():
        expected, embedding = _reference_maskclip(maskclip.clip.model, x, CLIP_SIDE, "maskclip")
        value, _ = _reference_maskclip(maskclip.clip.model, x, CLIP_SIDE)
    maps, emb = maskclip.clip_dense(x)
    torch.testing.assert_close(maps, expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(emb, embedding, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(encoder.clip_dense(x)[0], value, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(maps, value, atol=1e-2)


def test_pooling_on_a_small_example():
    labels = torch.tensor([[0, 0, 2], [1, 1, 2], [1, 1, 2]])
    feats = torch.randn(4, 3, 3)
    out = OtasEncoder.pool(labels, feats)
    for k in range(3):
        mask = labels == k
        mean = feats[:, mask].mean(dim=1)
        for i, j in mask.nonzero().tolist():
            torch.testing.assert_close(out[:, i, j], mean / mean.norm())


def test_images_of_a_batch_are_clustered_alone(encoder, canvas, encoded):
    single = encoder.encode(canvas[1:])
    torch.testing.assert_close(encoded.language[1:], single.language, atol=1e-5, rtol=1e-5)


def test_text_queries_are_clips_in_the_language_width(encoder, encoded):
    texts = ["a photo of a dog", "grass"]
    queries = encoder.encode_text(texts)
    assert queries.shape == (2, encoded.language.shape[1])
    torch.testing.assert_close(queries.norm(dim=-1), torch.ones(2))
    with torch.no_grad():
        expected = F.normalize(
            encoder.clip.model.encode_text(encoder.clip.tokenizer(texts)), dim=-1
        )
    torch.testing.assert_close(queries, expected, atol=1e-5, rtol=1e-5)


def test_input_rule_frozen_and_bb_similarity(encoder):
    rule = encoder.input_rule
    assert rule.patch_size == 14
    assert rule.mean == pytest.approx((0.485, 0.456, 0.406))
    assert rule.std == pytest.approx((0.229, 0.224, 0.225))
    assert not any(p.requires_grad for p in encoder.parameters())
    encoder.train()
    assert not encoder.training and not encoder.dino.training and not encoder.clip.training
    images = (torch.rand(1, 3, 70, 98) * 255).to(torch.uint8)
    sim = encoder.similarity(images, ["road"])  # bb
    assert sim.shape == (1, 1, 5, 7) and sim.abs().max() <= 1 + 1e-4


# ------------------------------------------------------------------ configuration
def test_config_keys_are_constructor_defaults(encoder):
    conf = yaml.safe_load(CONF.read_text())
    assert (conf["name"], conf["kind"], conf["third_party"]) == ("otas", "otas", True)
    keys = {k: v for k, v in conf.items() if k not in ("name", "kind", "third_party")}
    assert set(keys) == set(encoder.spec()) - {"kind"}  # every constructor argument, nothing else
    assert encoder.spec()["kind"] == "otas"
    defaults = inspect.signature(OtasEncoder).parameters
    for k, v in keys.items():
        if k != "clip":
            assert v == defaults[k].default, k
    assert keys["clip"] == {"model_name": "ViT-B-16", "weights": "openai"}  # OTAS's ViT-B/16.pt


def test_bad_arguments(fake_repo, offline, tmp_path):
    with pytest.raises(ValueError, match=r"^source="):
        _build(fake_repo, source="hf")
    with pytest.raises(FileNotFoundError, match=r"^repo="):
        _build(tmp_path / "absent")
    with pytest.raises(ValueError, match=r"^output_grid="):
        _build(fake_repo, output_grid="pixels")
    with pytest.raises(ValueError, match=r"^dino_input_size=100"):
        _build(fake_repo, dino_input_size=100)
    with pytest.raises(ValueError, match=r"^n_clusters=300"):
        _build(fake_repo, n_clusters=300)
    with pytest.raises(ValueError, match=r"^n_components=0"):
        _build(fake_repo, n_components=0)
    with pytest.raises(ValueError, match=r"^dense_path='values'"):
        _build(fake_repo, dense_path="values")
    with pytest.raises(ValueError, match=r"^clip\.dense_path: pass dense_path= instead"):
        _build(fake_repo, clip={"weights": None, "image_size": CLIP_SIDE, "dense_path": "value"})


# ------------------------------------------------------------------ offline
def test_uncached_dinov2_weights_offline_fail_at_once(fake_repo, monkeypatch, tmp_path):
    offline_hub(monkeypatch, tmp_path / "hub")  # nothing cached
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    start = time.monotonic()
    with pytest.raises(WeightsUnavailableError) as err:
        _build(fake_repo)
    assert time.monotonic() - start < 2
    message = str(err.value)
    assert "dl.fbaipublicfiles.com" in message and "dinov2_vits14_reg4_pretrain.pth" in message
    assert str(tmp_path / "hub" / "checkpoints") in message and " repo=/path/to/dinov2" in message


def test_clip_weights_offline_name_the_clip_key(fake_repo, offline, tmp_path):
    offline.setenv("HF_HUB_OFFLINE", "1")
    offline.setattr(hf_constants, "HF_HUB_CACHE", str(tmp_path / "hf"))  # an empty cache

    def no_hub(*args, **kwargs):
        raise AssertionError("DINOv2 must not be loaded before the CLIP weights are checked")

    offline.setattr(torch.hub, "load", no_hub)
    start = time.monotonic()
    with pytest.raises(WeightsUnavailableError, match=r"instead: clip\.weights=/path/to/"):
        _build(fake_repo, clip={"weights": "openai"})
    assert time.monotonic() - start < 2
