"""The contract of every encoder kind of the registry (``resireg.models.factory.ENCODERS``).

One test per property, parametrised over every kind, each built through ``build_encoder``
from its config entry with same-architecture random weights (a tiny ResiregVLM export, a
seeded random open_clip ViT-B/16, TIPS release files written here) or the local fake hub
repos of ``tests/helpers/fake_hubs/`` (RADIO, RADSeg, dino.txt, OTAS's DINOv2):

- the dense output: dtypes (float32), shapes (``[B, D, H/p, W/p]`` for both maps on the
  patch grid of the input, ``[B, De]`` or no embedding), unit-norm text queries in the
  language tokens' width;
- ``spec()``: JSON-able, names the kind, and ``build_encoder(**spec)`` builds the same
  encoder (the same spec, and the same outputs on the same input);
- offline with nothing cached: a :class:`WeightsUnavailableError` at once (no
  ``torch.hub.load``, no network wait), naming the config key to set.

The per-encoder test files check each adapter's values against its upstream code; this file
holds what every encoder must do, so a kind added to the registry without an entry in
``CONFIGS`` fails :func:`test_every_registry_kind_is_covered`.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest
import torch
from huggingface_hub import constants as hf_constants

import resireg.models.hub as hub_module
from helpers.fake_hubs.common import offline_hub
from helpers.fake_hubs.dinotxt import DINOTXT_VOCAB, dinotxt_repo
from helpers.fake_hubs.dinov2 import dinov2_repo, drop_dinov2_modules, restore_dinov2_modules
from helpers.fake_hubs.radio import radio_repo
from helpers.fake_hubs.radseg import radseg_repo
from helpers.fake_hubs.tips import TIPS_STEM, TIPS_TINY, train_sentencepiece, write_tips_release
from resireg.models import WeightsUnavailableError
from resireg.models.factory import ENCODERS, build_encoder
from resireg.models.zoo.dinotxt import DINOTXT_CHECKPOINTS
from resireg.models.zoo.otas import OTAS_CHECKPOINTS
from resireg.models.zoo.radio import RADIO_CHECKPOINTS

KEY = "encoder"  # the config prefix every error names at resireg_train's boundary
TEXTS = ["a photo of a cat", "the sky", "road"]


def _configs(root: Path, export: Path) -> dict[str, dict]:
    """Every kind's config entry (``build_encoder`` keys) on local, tiny, random models."""
    tips = root / "tips"
    tips.mkdir()
    write_tips_release(tips)
    (tips / "tokenizer.model").write_bytes(train_sentencepiece(tips).read_bytes())
    return {
        "resireg_vlm": {"path": str(export)},
        "clip": {"model_name": "ViT-B-16", "weights": None, "image_size": 64, "seed": 3},
        "radio": {"repo": radio_repo(root / "RADIO"), "source": "local"},
        "radseg": {"repo": radseg_repo(root / "RADSeg"), "source": "local"},
        "dinotxt": {
            "repo": str(dinotxt_repo(root / "dinov2")),
            "source": "local",
            "image_size": 56,
            "vocab": str(root / "dinov2" / DINOTXT_VOCAB),
        },
        "tips": {
            "variant": TIPS_TINY,
            "weights": str(tips / f"{TIPS_STEM}_vision.npz"),
            "image_size": 56,
        },
        "otas": {
            "repo": dinov2_repo(root / "otas_dinov2"),
            "source": "local",
            "clip": {"weights": None, "image_size": 64},
            "clip_input_size": 64,
        },
    }


#: Offline with nothing cached: the kind's config (defaults: the hub / release sources) and
#: what the error must say (the keys to set, the host that could not be reached).
OFFLINE = {
    "resireg_vlm": ({"path": "someone/some-vlm"}, [f"{KEY}.path='someone/some-vlm'", "export"]),
    "clip": (
        {"weights": "openai"},
        [f"{KEY}.weights=/path/to/", "HF_HUB_OFFLINE", "ViT-B-16/openai"],
    ),
    "radio": ({}, ["github.com", f"{KEY}.repo=", f"{KEY}.source=local"]),
    "radseg": ({}, ["github.com", f"{KEY}.repo=", f"{KEY}.source=local"]),
    "dinotxt": (
        {},
        ["github.com", f"{KEY}.repo=/path/to/dinov2", f"{KEY}.source=local", f"{KEY}.vocab="],
    ),
    "tips": ({}, [f"{KEY}.weights is not set", "storage.googleapis.com"]),
    "otas": ({}, ["github.com", f"{KEY}.repo=/path/to/dinov2", f"{KEY}.source=local"]),
}

_CHECKPOINTS = [*RADIO_CHECKPOINTS.values(), *DINOTXT_CHECKPOINTS, *OTAS_CHECKPOINTS.values()]


@pytest.fixture(scope="module")
def configs(tmp_path_factory, tiny_export):
    saved = drop_dinov2_modules()  # the fake dino.txt clone's `dinov2` package
    yield _configs(tmp_path_factory.mktemp("encoders"), tiny_export)
    restore_dinov2_modules(saved)


@pytest.fixture(scope="module")
def hub(tmp_path_factory):
    """torch's hub cache with the fake RADIO code and every checkpoint's name; no network."""
    with pytest.MonkeyPatch.context() as mp:
        offline_hub(mp, tmp_path_factory.mktemp("hub"), _CHECKPOINTS, radio_code=True)
        yield


def _build(kind, config):
    torch.manual_seed(0)  # the fakes draw their random weights from torch's global generator
    return build_encoder(kind, **config)


@pytest.fixture(scope="module")
def built(configs, hub):
    """kind -> (encoder, normalised input, its output), each built once."""
    out = {}
    for kind, config in configs.items():
        enc = _build(kind, config)
        rgb = torch.rand(2, 3, 60, 90, generator=torch.Generator().manual_seed(1))
        x = enc.preprocess((rgb * 255).to(torch.uint8))
        out[kind] = (enc, x, enc.encode(x))
    return out


def test_every_registry_kind_is_covered():
    assert set(ENCODERS) == set(OFFLINE)


@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(ENCODERS))
def test_dense_output_shapes_and_dtypes(kind, built):
    enc, x, out = built[kind]
    p = enc.input_rule.patch_size
    b, _, h, w = x.shape
    assert h % p == 0 and w % p == 0
    grid = (h // p, w // p)
    assert out.intermediates.dtype == torch.float32 and out.language.dtype == torch.float32
    assert out.intermediates.ndim == 4 and out.intermediates.shape[0] == b
    assert tuple(out.intermediates.shape[-2:]) == grid
    assert out.language.ndim == 4 and out.language.shape[0] == b
    assert tuple(out.language.shape[-2:]) == grid
    assert torch.isfinite(out.intermediates).all() and torch.isfinite(out.language).all()
    if out.embedding is not None:
        assert out.embedding.dtype == torch.float32 and out.embedding.shape[0] == b
        assert out.embedding.ndim == 2
    assert out.layers is None  # only encode_layers returns per-block maps
    queries = enc.encode_text(TEXTS)
    assert queries.dtype == torch.float32
    assert queries.shape == (len(TEXTS), out.language.shape[1])
    torch.testing.assert_close(queries.norm(dim=-1), torch.ones(len(TEXTS)), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("kind", sorted(ENCODERS))
def test_a_query_does_not_depend_on_its_batch(kind, built, monkeypatch):
    """A text's query is the same encoded alone, with others, or split into text batches
    (``text_batch_size`` where the kind has one)."""
    enc, _, _ = built[kind]
    texts = ["cat", "dog", "car", "sky", "road"]
    whole = enc.encode_text(texts)
    torch.testing.assert_close(enc.encode_text(texts[3:4]), whole[3:4], atol=1e-6, rtol=1e-6)
    if hasattr(enc, "text_batch_size"):
        monkeypatch.setattr(enc, "text_batch_size", 2)
        torch.testing.assert_close(enc.encode_text(texts), whole, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("kind", sorted(ENCODERS))
def test_lite_similarity_is_the_cosine_of_its_map_and_each_query(kind, built):
    """similarity(images, texts, resireg="lite") is, per pixel, torch's cosine similarity of
    encode_image's lite map and each text query (so that map is unit-norm per pixel)."""
    import torch.nn.functional as F

    enc, _, _ = built[kind]
    rgb = torch.rand(2, 3, 70, 98, generator=torch.Generator().manual_seed(2))
    images = (rgb * 255).to(torch.uint8)
    dense = enc.encode_image(images, resireg="lite")
    sim = enc.similarity(images, TEXTS, resireg="lite")
    queries = enc.encode_text(TEXTS)
    expected = F.cosine_similarity(dense[:, None].float(), queries[None, :, :, None, None], dim=2)
    assert sim.shape == (2, len(TEXTS), *dense.shape[-2:])
    torch.testing.assert_close(sim, expected, atol=1e-5, rtol=1e-5)


@pytest.mark.slow  # rebuilds every encoder (CLIP ViT-B/16 twice, with OTAS's)
@pytest.mark.parametrize("kind", sorted(ENCODERS))
def test_spec_round_trip(kind, built):
    enc, x, out = built[kind]
    spec = enc.spec()
    assert spec["kind"] == kind
    text = json.dumps(spec)  # JSON-able
    rebuilt = _build(spec["kind"], {k: v for k, v in json.loads(text).items() if k != "kind"})
    assert type(rebuilt) is type(enc) and rebuilt.spec() == spec
    again = rebuilt.encode(x)
    torch.testing.assert_close(again.intermediates, out.intermediates)
    torch.testing.assert_close(again.language, out.language)
    if out.embedding is None:
        assert again.embedding is None
    else:
        torch.testing.assert_close(again.embedding, out.embedding)
    torch.testing.assert_close(rebuilt.encode_text(TEXTS), enc.encode_text(TEXTS))


def _hub_load_forbidden(*args, **kwargs):
    raise AssertionError("torch.hub.load must not run when the offline checks fail")


@pytest.mark.parametrize("kind", sorted(ENCODERS))
def test_offline_and_not_cached_fails_at_once_naming_the_key(kind, tmp_path, monkeypatch):
    """The library's message names its own arguments (``repo=``); through resireg_train's
    boundary (:func:`resireg_train.config.errors.config_path`) the same error names the config
    keys (``encoder.repo=``)."""
    from resireg_train.config.errors import config_path, encoder_arguments

    config, expected = OFFLINE[kind]
    offline_hub(monkeypatch, tmp_path / "hub")  # an empty torch hub cache
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(tmp_path / "hf"))  # an empty cache
    start = time.monotonic()
    with pytest.raises(WeightsUnavailableError) as err:
        build_encoder(kind, **config)
    assert time.monotonic() - start < 2.0
    message = str(err.value)
    for fragment in expected:
        assert fragment.replace(f"{KEY}.", "") in message, (fragment, message)
    assert not re.search(rf"(?<![\w.]){KEY}\.", message), message  # no config key
    entry = {"kind": kind, **config}
    with pytest.raises(WeightsUnavailableError) as err:
        with config_path(KEY, encoder_arguments(entry)):
            build_encoder(**entry)
    message = str(err.value)
    for fragment in expected:
        assert fragment in message, (fragment, message)


def test_block_index_rule():
    """The one block-index rule (resireg.models.interface.block_indices, over timm's
    feature_take_indices) against Python's own indexing of the block list: negative indices
    count from the end, an int n is the last n blocks; anything else names the key and value."""
    from resireg.models.interface import block_index, block_indices

    blocks = list(range(12))
    for i in range(-12, 12):
        assert block_index(12, i, "intermediate_layer") == blocks[i]
    assert block_indices(12, [3, -1, 0]) == (blocks[3], blocks[-1], blocks[0])  # order kept
    for n in (1, 5, 12):
        assert block_indices(12, n) == tuple(blocks[-n:])
    with pytest.raises(ValueError, match=r"intermediate_layer=12 is out of range for ViT-B-16"):
        block_index(12, 12, "intermediate_layer", "ViT-B-16")
    with pytest.raises(ValueError, match=r"layer=-13 is out of range"):
        block_indices(12, [0, -13])
    with pytest.raises(ValueError, match=r"layer=13: the last 13 blocks, but the model has 12"):
        block_indices(12, 13)
    for bad in (True, "3", 2.0, [1.5], None):
        with pytest.raises(TypeError, match=r"layer="):
            block_indices(12, bad)


def test_an_encoder_outside_the_registry_has_no_spec_and_says_so():
    """A DenseEncoder of one's own (no registry kind) answers spec() with a ValueError naming
    its class, as a ResiregVLM built in Python does, not with a config that rebuilds nothing."""
    from resireg.models import DenseEncoder, DenseOutput, InputRule

    class Own(DenseEncoder):
        input_rule = InputRule(patch_size=16, mean=(0.5,) * 3, std=(0.5,) * 3)

        def encode(self, images):
            return DenseOutput(images, images, None)

        def encode_text(self, texts):
            return torch.eye(len(texts), 3)

    with pytest.raises(ValueError, match=r"^Own has no construction config \(spec\)"):
        Own().spec()
