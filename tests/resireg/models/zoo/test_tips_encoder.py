"""TipsEncoder offline: tiny TIPS models written as release-format ``.npz`` checkpoints.

The checkpoints are written by this test from its own list of the release's parameter
names and shapes (google-deepmind/tips ``pytorch/image_encoder.py``: ``VisionTransformer``
built with ``block_chunks=0, init_values=1.0``, one register token; ``pytorch/text_encoder.py``:
``TextEncoder`` plus the ``temperature`` scalar the repo pops), saved with ``np.savez`` and
loaded through the adapter's real path (``weights`` -> ``<stem>_text.npz`` and
``tokenizer.model`` beside it). Tiny size: patch 14, width 32, 2 blocks, 2 heads, a 4 x 4
positional grid (56 px), one text layer, 64 ids. Expected values are recomputed here from
the model's own modules, following the repo's code (its attention, its zero-shot notebook's
``encode_image_value_attention``, its text tower with ``nn.MultiheadAttention`` and a float
mask), never through the adapter's forward functions.
"""

from __future__ import annotations

import math
import sys
import time

import pytest
import torch
import torch.nn.functional as F

import resireg.models.hub as hub_module
from helpers.fake_hubs.common import refuse_network, token_grid
from helpers.fake_hubs.tips import (
    TIPS_GRID,
    TIPS_P,
    TIPS_STEM,
    TIPS_TINY,
    TIPS_WIDTH,
    TipsWordTokenizer,
    train_sentencepiece,
    write_tips_release,
)
from resireg.models.hub import WeightsUnavailableError
from resireg.models.zoo.tips import TIPS_TOKENIZER_URL, TIPS_WEIGHTS_URL, TipsEncoder
from resireg.models.zoo.tips_towers import TIPS_VARIANTS, TipsTextEncoder, TipsVisionTransformer

# The tiny release of tests/helpers/fake_hubs/tips.py under this module's short names.
P, WIDTH, GRID, STEM, TINY = TIPS_P, TIPS_WIDTH, TIPS_GRID, TIPS_STEM, TIPS_TINY
WordTokenizer, _write_release = TipsWordTokenizer, write_tips_release


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tips")
    vision, text = _write_release(folder)
    return folder, vision, text


def _build(folder, **kwargs):
    kwargs = {"variant": TINY, "tokenizer": WordTokenizer(), "image_size": 70, **kwargs}
    return TipsEncoder(weights=str(folder / f"{STEM}_vision.npz"), **kwargs)


@pytest.fixture(scope="module")
def encoder(release):
    return _build(release[0])


# ----------------------------------------------------------- the repo's computation
def _ref_block(blk, x):
    """``image_encoder.Block`` at inference with ``Attention.forward``'s explicit softmax."""
    y = blk.norm1(x)
    b, n, c = y.shape
    h = blk.attn.num_heads
    qkv = blk.attn.qkv(y).reshape(b, n, 3, h, c // h).permute(2, 0, 3, 1, 4)
    q, k, v = qkv[0] * (c // h) ** -0.5, qkv[1], qkv[2]
    attn = (q @ k.transpose(-2, -1)).softmax(dim=-1)
    y = blk.attn.proj((attn @ v).transpose(1, 2).reshape(b, n, c))
    x = x + blk.ls1(y)
    return x + blk.ls2(blk.mlp(blk.norm2(x)))


def _ref_tokens(model, img):
    """``prepare_tokens_with_masks`` with ``interpolate_antialias=True, offset=0``."""
    _, _, hh, ww = img.shape
    x = model.patch_embed.proj(img).flatten(2).transpose(1, 2)
    x = torch.cat([model.cls_token.expand(x.shape[0], -1, -1), x], dim=1)
    n = model.pos_embed.shape[1] - 1
    m = int(math.sqrt(n))
    if (hh // P, ww // P) == (m, m):
        pos = model.pos_embed
    else:
        patch = model.pos_embed[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
        patch = F.interpolate(patch, size=(hh // P, ww // P), mode="bilinear", antialias=True)
        patch = patch.permute(0, 2, 3, 1).reshape(1, -1, x.shape[-1])
        pos = torch.cat([model.pos_embed[:, :1], patch], dim=1)
    x = x + pos
    return torch.cat([x[:, :1], model.register_tokens.expand(x.shape[0], -1, -1), x[:, 1:]], dim=1)


def _ref_vision(model, img):
    """-> (x_norm_1st_clstoken, x_norm_patchtokens, value-attention patch tokens), as grids."""
    x = _ref_tokens(model, img)
    blocks = list(model.blocks)
    for blk in blocks[:-1]:
        x = _ref_block(blk, x)
    final = model.norm(_ref_block(blocks[-1], x))
    # TIPS_zeroshot_segmentation.ipynb, encode_image_value_attention (last block)
    blk = blocks[-1]
    x_normed = blk.norm1(x)
    b, n, c = x_normed.shape
    qkv = blk.attn.qkv(x_normed).reshape(b, n, 3, blk.attn.num_heads, c // blk.attn.num_heads)
    v = qkv.permute(2, 0, 3, 1, 4)[2]
    x_val = blk.ls1(blk.attn.proj(v.transpose(1, 2).reshape(b, n, c))) + x
    x_val = x_val + blk.ls2(blk.mlp(blk.norm2(x_val)))
    values = model.norm(x_val)
    r = 1 + model.num_register_tokens
    return final[:, 0], final[:, r:], values[:, r:]


def _ref_text(model, ids, paddings):
    """``text_encoder.TextEncoder.__call__``: LND layout, float -inf mask, masked MLP."""
    _, length = ids.shape
    d = model.width
    mask = (paddings == 0).float()
    x = model.token_embedding(ids) * d**0.5
    half = d // 2
    inc = math.log(10_000.0) / max(half - 1, 1)
    inv = torch.exp(torch.arange(half, dtype=torch.float32) * -inc)
    t = torch.arange(length, dtype=torch.float32)[None, :, None] * inv[None, None, :]
    x = x + torch.cat([torch.sin(t), torch.cos(t)], dim=2)
    x = x.permute(1, 0, 2)
    for blk in model.transformer.resblocks:
        heads = blk.attn.num_heads
        am = mask[:, None, None, :].repeat(1, heads, length, 1).flatten(0, 1)
        am = torch.zeros_like(am).masked_fill(am == 0, float("-inf"))
        y = blk.ln_1(x)
        x = x + blk.attn(y, y, y, need_weights=False, attn_mask=am)[0]
        y = blk.ln_2(x)
        y = F.relu(blk.mlp.c_fc(y)) * mask.T[..., None]
        x = x + blk.mlp.c_proj(y) * mask.T[..., None]
    x = model.ln_final(x.permute(1, 0, 2))
    x = torch.where(paddings[..., None] > 0, torch.zeros_like(x), x)
    return x.sum(dim=1) / (mask.sum(dim=1, keepdim=True) + 1e-8)


# ---------------------------------------------------------------------------- tests
def test_release_checkpoints_load_strictly(encoder, release):
    _, vision, text = release
    state = encoder.visual.state_dict()
    assert set(state) == set(vision)
    for name, value in vision.items():
        torch.testing.assert_close(state[name], torch.from_numpy(value))
    text_state = encoder.text.state_dict()
    assert set(text_state) == set(text) - {"temperature"}
    for name in text_state:
        torch.testing.assert_close(text_state[name], torch.from_numpy(text[name]))
    assert all(p.device.type == "cpu" and p.dtype == torch.float32 for p in encoder.parameters())


def test_dense_maps_match_the_repos_computation(encoder):
    """Canvas 70 x 98 (grid 5 x 7) -> resized to 70 x 70 (grid 5 x 5, positional grid
    interpolated from 4 x 4), one pass, both maps upsampled bilinearly to 5 x 7."""
    x = torch.rand(2, 3, 70, 98)
    out = encoder.encode(x)
    assert out.intermediates.shape == out.language.shape == (2, WIDTH, 5, 7)
    assert out.intermediates.dtype == out.language.dtype == out.embedding.dtype == torch.float32
    small = F.interpolate(x, size=(70, 70), mode="bilinear", align_corners=False)
    with torch.no_grad():
        cls, final, values = _ref_vision(encoder.visual, small)

    def up(tokens):
        return F.interpolate(
            token_grid(tokens, (5, 5)), size=(5, 7), mode="bilinear", align_corners=False
        )

    torch.testing.assert_close(out.intermediates, up(final), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.language, up(values), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.embedding, cls, atol=1e-5, rtol=1e-5)
    assert out.embedding.shape == (2, WIDTH)
    assert not torch.allclose(out.intermediates, out.language, atol=1e-2)  # different tokens


def test_native_resolution_and_native_grid(release):
    """image_size=None runs the canvas as it is (3 x 5 grid, interpolated positions);
    image_size=56 is the checkpoint's own 4 x 4 grid (positions used as stored)."""
    enc = _build(release[0], image_size=None)
    x = torch.rand(1, 3, 42, 70)
    out = enc.encode(x)
    with torch.no_grad():
        _, final, values = _ref_vision(enc.visual, x)
    torch.testing.assert_close(out.intermediates, token_grid(final, (3, 5)), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.language, token_grid(values, (3, 5)), atol=1e-5, rtol=1e-5)

    enc = _build(release[0], image_size=GRID * P)
    x = torch.rand(1, 3, 56, 56)
    with torch.no_grad():
        _, final, _ = _ref_vision(enc.visual, x)
    torch.testing.assert_close(
        enc.encode(x).intermediates, token_grid(final, (4, 4)), atol=1e-5, rtol=1e-5
    )


def test_final_language_tokens_are_the_intermediates(release):
    enc = _build(release[0], language_tokens="final")
    out = enc.encode(torch.rand(1, 3, 42, 56))
    assert out.language is out.intermediates


def test_swiglu_checkpoint_as_vit_giant(tmp_path):
    """g/14's FFN: ``w12`` / ``w3`` with hidden (int(h * 2 / 3) + 7) // 8 * 8."""
    vision, _ = _write_release(tmp_path, ffn="swiglu", seed=3)
    assert vision["blocks.0.mlp.w3.weight"].shape == (WIDTH, 48)
    enc = _build(tmp_path, variant={**TINY, "ffn": "swiglu"}, image_size=None)
    x = torch.rand(1, 3, 56, 42)
    with torch.no_grad():
        _, final, values = _ref_vision(enc.visual, x)
    out = enc.encode(x)
    torch.testing.assert_close(out.intermediates, token_grid(final, (4, 3)), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.language, token_grid(values, (4, 3)), atol=1e-5, rtol=1e-5)


def test_text_queries_are_the_normalised_text_embeddings(encoder):
    texts = ["a photo of a cat", "A photo of the SKY", "road", "a tree and a person"]
    queries = encoder.encode_text(texts)
    assert queries.shape == (4, WIDTH)
    assert queries.shape[1] == encoder.encode(torch.rand(1, 3, 28, 28)).language.shape[1]
    torch.testing.assert_close(queries.norm(dim=-1), torch.ones(4))

    ids, paddings = encoder.tokenize(texts)
    assert ids.shape == paddings.shape == (4, 64) and ids.dtype == torch.long
    assert paddings[2].tolist() == [0.0] + [1.0] * 63
    with torch.no_grad():
        expected = _ref_text(encoder.text, ids, paddings)
    torch.testing.assert_close(encoder.text_features(texts), expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(queries, F.normalize(expected, dim=-1), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(encoder.dense_text(encoder.text_features(texts)), queries)


def test_tokenize_follows_the_repo(release):
    """ASCII lower case, no BOS / EOS, cut at 64, pad id 0; padding length does not matter."""
    tok = WordTokenizer()
    enc = _build(release[0], tokenizer=tok)
    ids, paddings = enc.tokenize(["Ärger A Cat", " ".join(["w"] * 80)])
    assert tok.seen == ["Ärger a cat", " ".join(["w"] * 80)]
    assert ids[0, :3].tolist() == tok.encode("Ärger a cat") and ids[0, 3:].eq(0).all()
    assert paddings[1].eq(0).all() and ids[1].ne(0).all()
    short = enc.text(ids[:1, :8], paddings[:1, :8])
    torch.testing.assert_close(short, enc.text(ids[:1], paddings[:1]), atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="no tokens"):
        enc.tokenize([""])


def test_input_rule_and_frozen(encoder):
    rule = encoder.input_rule
    assert rule.patch_size == 14
    assert rule.mean == (0.0, 0.0, 0.0) and rule.std == (1.0, 1.0, 1.0)
    assert not any(p.requires_grad for p in encoder.parameters())
    encoder.train()
    assert not encoder.training and not encoder.visual.training and not encoder.text.training


def test_release_sizes_match_the_published_parameter_counts():
    """Text towers: the README's counts (109.6M, 183.9M, 448.3M, 389.1M). Vision: the README
    counts match a 16 x 16 positional grid (its numbers are TIPS v1's, 224 px); v2 files hold
    32 x 32 (448 px), so the 32 x 32 count minus the difference is compared."""
    readme = {"B": (85.7, 109.6), "L": (303.2, 183.9), "So400m": (412.4, 448.3), "g": (1136, 389.1)}
    for name, arch in TIPS_VARIANTS.items():
        with torch.device("meta"):
            vision, text = TipsVisionTransformer(arch), TipsTextEncoder(arch)
        n_vision = sum(p.numel() for p in vision.parameters())
        n_vision_16 = n_vision - (32**2 - 16**2) * arch.width
        n_text = sum(p.numel() for p in text.parameters())
        assert round(n_text / 1e6, 1) == readme[name][1], name
        assert abs(n_vision_16 / 1e6 - readme[name][0]) < 0.2 or name == "g", name
        assert arch.patch_size == 14 and arch.pos_grid == 32 and arch.num_registers == 1
    assert round(n_vision / 1e9, 1) == 1.1  # g/14
    assert TIPS_VARIANTS["g"].ffn == "swiglu" and TIPS_VARIANTS["g"].stem == "tips_v2_oss_g14"


def test_missing_weights_fail_at_once_naming_the_key(monkeypatch, tmp_path):
    monkeypatch.setattr(hub_module, "_resolves", refuse_network)
    start = time.monotonic()
    with pytest.raises(WeightsUnavailableError) as err:
        TipsEncoder()
    assert time.monotonic() - start < 2
    message = str(err.value)
    assert message.startswith("weights is not set") and TIPS_WEIGHTS_URL in message
    assert "tips_v2_oss_g14_vision.npz" in message and TIPS_TOKENIZER_URL in message
    with pytest.raises(WeightsUnavailableError, match=r"^weights=.*no such file"):
        TipsEncoder(weights=str(tmp_path / "absent.npz"))
    with pytest.raises(WeightsUnavailableError, match=r"^weights=.*tips_v2_oss_l14_vision"):
        TipsEncoder(variant="L", weights=str(tmp_path))  # a folder without the files


def test_missing_text_weights_and_tokenizer_name_their_keys(tmp_path):
    _write_release(tmp_path)
    (tmp_path / f"{STEM}_text.npz").unlink()
    with pytest.raises(WeightsUnavailableError, match=r"^text_weights=.*_text\.npz"):
        _build(tmp_path)
    _write_release(tmp_path)
    (tmp_path / "tokenizer.model").unlink()
    with pytest.raises(WeightsUnavailableError, match=r"^tokenizer=.*tokenizer\.model"):
        _build(tmp_path, tokenizer=None)


def test_folder_weights_and_explicit_paths(release, tmp_path):
    folder = release[0]
    enc = TipsEncoder(variant=TINY, weights=str(folder), tokenizer=WordTokenizer())
    assert enc.weights == str(folder / f"{STEM}_vision.npz")
    assert enc.text_weights == str(folder / f"{STEM}_text.npz")
    assert enc.image_size == 574
    copy = tmp_path / "vision_weights.npz"
    copy.write_bytes((folder / f"{STEM}_vision.npz").read_bytes())
    with pytest.raises(WeightsUnavailableError, match=r"^text_weights is not set"):
        TipsEncoder(variant=TINY, weights=str(copy), tokenizer=WordTokenizer())
    enc = TipsEncoder(
        variant=TINY,
        weights=str(copy),
        text_weights=str(folder / f"{STEM}_text.npz"),
        tokenizer=WordTokenizer(),
    )
    assert enc.weights == str(copy)


def test_wrong_size_checkpoint_and_bad_arguments(release):
    folder = release[0]
    with pytest.raises(ValueError, match=r"\(variant\)"):
        _build(folder, variant={**TINY, "depth": 3})
    with pytest.raises(ValueError, match=r"^variant='XL'"):
        _build(folder, variant="XL")
    with pytest.raises(ValueError, match=r"^variant: unknown fields \['depht'\]"):
        _build(folder, variant={**TINY, "depht": 3})
    with pytest.raises(ValueError, match=r"^image_size=50"):
        _build(folder, image_size=50)
    with pytest.raises(ValueError, match=r"^language_tokens='cls'"):
        _build(folder, language_tokens="cls")


def test_tokenizer_file_needs_sentencepiece(release, monkeypatch):
    monkeypatch.setitem(sys.modules, "sentencepiece", None)
    with pytest.raises(ImportError, match="pip install sentencepiece"):
        _build(release[0], tokenizer=None)


def test_sentencepiece_tokenizer_file(tmp_path):
    """A real SentencePiece model file (trained here), loaded by path like tokenizer.model."""
    spm = pytest.importorskip("sentencepiece")
    prefix = str(train_sentencepiece(tmp_path))[: -len(".model")]
    folder = tmp_path / "release"
    folder.mkdir()
    _write_release(folder)
    (folder / "tokenizer.model").write_bytes((tmp_path / "sp.model").read_bytes())
    enc = _build(folder, tokenizer=None)
    processor = spm.SentencePieceProcessor(model_file=prefix + ".model")
    ids, _ = enc.tokenize(["A Photo of a CAT"])
    expected = processor.encode("a photo of a cat")
    assert ids[0, : len(expected)].tolist() == expected and ids[0, len(expected) :].eq(0).all()
    assert enc.encode_text(["a cat", "the sky"]).shape == (2, WIDTH)


def test_config_entry_keys_are_constructor_arguments(tmp_path):
    """conf/encoder/tipsv2.yaml, composed by resireg-eval: every key but name / kind /
    third_party is an argument; with no files at the default place (paths.data_dir/tipsv2)
    it stops at once naming encoder.weights and where to download."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from resireg_train.config.errors import config_path, encoder_arguments
    from resireg_train.config.paths import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        composed = compose("eval", overrides=["encoder=tipsv2", f"paths.data_dir={tmp_path}"])
    cfg = OmegaConf.to_container(composed.encoder, resolve=True)
    assert (cfg.pop("name"), cfg.pop("kind"), cfg.pop("third_party")) == ("tipsv2", "tips", True)
    assert cfg["variant"] == "g" and cfg["image_size"] == 574
    assert cfg["weights"] == f"{tmp_path}/tipsv2"
    with pytest.raises(WeightsUnavailableError, match=r"encoder\.weights=.*storage\.googleapis"):
        with config_path("encoder", encoder_arguments({"kind": "tips", **cfg})):
            TipsEncoder(**cfg, device="cpu")
