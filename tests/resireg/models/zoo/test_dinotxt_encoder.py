"""DinoTxtEncoder offline: a local torch.hub repo laid out like facebookresearch/dinov2.

The fake repo (``tests/helpers/fake_hubs/dinotxt.py``: ``DINOTXT_FILES``) has the same entry point name, package layout and class/attribute layout as
dino.txt's hub code (``hubconf.py`` -> ``dinov2.hub.dinotxt``; ``DinoTxt`` with
``visual_model`` = ``VisionTower(DINOv2Wrapper(ViT), VisionHead)``, ``text_model``,
``model_config``, ``encode_image`` / ``encode_text`` / ``get_visual_class_and_patch_tokens``;
``dinov2.hub.text.tokenizer.Tokenizer(vocab_path)`` and ``dinov2.hub.dinotxt.get_tokenizer``)
at tiny sizes: patch 14, width 32, 4 registers, a 4 x 4 positional grid (image 56),
``embed_dim`` 64 (= 2 x 32, so the head has no projection, as in the real model). Expected
values are recomputed from the fake model's own modules, never through the adapter.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

import resireg.models.hub as hub_module
from helpers.fake_hubs.common import build_offline, offline_hub, token_grid
from helpers.fake_hubs.dinotxt import DINOTXT_VOCAB, dinotxt_repo
from helpers.fake_hubs.dinov2 import drop_dinov2_modules, restore_dinov2_modules
from resireg.models.hub import WeightsUnavailableError
from resireg.models.zoo.dinotxt import DINOTXT_CHECKPOINTS, DINOTXT_ENTRY_POINT, DinoTxtEncoder

WIDTH, EMBED, SIDE = 32, 64, 56  # backbone width, text/image embedding width, fake native size
VOCAB = DINOTXT_VOCAB  # inside the fake repo


@pytest.fixture(scope="module")
def fake_repo(tmp_path_factory):
    """The fake dinov2 clone; its ``dinov2`` package is dropped from ``sys.modules`` after."""
    repo = dinotxt_repo(tmp_path_factory.mktemp("dinotxt") / "dinov2")
    saved = drop_dinov2_modules()
    yield repo
    restore_dinov2_modules(saved)


def _build(repo, **kwargs):
    kwargs = {"source": "local", "image_size": SIDE, "vocab": str(repo / VOCAB), **kwargs}
    return DinoTxtEncoder(repo=str(repo), **kwargs)


@pytest.fixture(scope="module")
def encoder(fake_repo, tmp_path_factory):
    return build_offline(tmp_path_factory, DINOTXT_CHECKPOINTS, _build, fake_repo)


@pytest.fixture
def offline(monkeypatch, tmp_path):
    """No network (any probe fails the test); a torch hub cache with the weights."""
    offline_hub(monkeypatch, tmp_path / "hub", DINOTXT_CHECKPOINTS)
    return monkeypatch


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
            token_grid(tokens, (4, 4)), size=(5, 7), mode="bilinear", align_corners=False
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
        out.intermediates, token_grid(backbone["x_norm_patchtokens"], (3, 5)), atol=1e-5, rtol=1e-5
    )
    torch.testing.assert_close(out.language, token_grid(head, (3, 5)), atol=1e-5, rtol=1e-5)


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


def test_input_rule_and_frozen(encoder):
    rule = encoder.input_rule
    assert rule.patch_size == 14
    assert rule.mean == pytest.approx((0.485, 0.456, 0.406))
    assert rule.std == pytest.approx((0.229, 0.224, 0.225))
    assert not any(p.requires_grad for p in encoder.parameters())
    encoder.train()
    assert not encoder.training and not encoder.model.training


def test_uncached_weights_offline_fail_at_once(fake_repo, monkeypatch, tmp_path):
    offline_hub(monkeypatch, tmp_path / "hub")  # nothing cached
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    with pytest.raises(WeightsUnavailableError) as err:
        _build(fake_repo)
    message = str(err.value)
    assert "dl.fbaipublicfiles.com" in message and DINOTXT_CHECKPOINTS[1] in message
    assert str(tmp_path / "hub" / "checkpoints") in message


def test_vocabulary_download_offline_fails_naming_model_vocab(fake_repo, offline):
    offline.setattr(hub_module, "_resolves", lambda host, timeout: False)
    with pytest.raises(WeightsUnavailableError, match=r"vocabulary.* vocab=/path/to/"):
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
    with pytest.raises(FileNotFoundError, match=r"^repo="):
        DinoTxtEncoder(repo=str(tmp_path / "absent"), source="local")
    with pytest.raises(ValueError, match=r"^image_size=50"):
        _build(fake_repo, image_size=50)
