"""RADIO and RADSeg dense encoders through local torch.hub repositories (no network).

The fake repositories (``tests/helpers/fake_hubs/radio.py`` and ``radseg.py``: ``FAKE_RADIO``, ``FAKE_RADSEG``) expose the real entry points (``radio_model`` of NVlabs/RADIO,
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

import pytest
import torch
import torch.nn.functional as F

from helpers.fake_hubs.common import offline_hub
from helpers.fake_hubs.radio import radio_repo as _radio_repo
from helpers.fake_hubs.radseg import radseg_repo as _radseg_repo
from resireg.models import WeightsUnavailableError
from resireg.models import hub as hub_module
from resireg.models.zoo.radio import RADIO_CHECKPOINTS, RADIO_REF, RadioEncoder
from resireg.models.zoo.radseg import RadSegEncoder

NORM_MEAN, NORM_STD = (0.45, 0.40, 0.35), (0.27, 0.26, 0.28)  # the fake checkpoint's conditioner
TEXTS = ["a photo of a cat", "the sky", "Grass_field"]


@pytest.fixture(autouse=True)
def hub(tmp_path, monkeypatch):
    """A private torch hub cache holding the fake NVlabs/RADIO (what RADSeg loads from GitHub)
    and the RADIO checkpoints' names; GitHub unreachable; network probes fail the test."""
    return offline_hub(monkeypatch, tmp_path / "hub", RADIO_CHECKPOINTS.values(), radio_code=True)


@pytest.fixture
def radio_repo(tmp_path):
    return _radio_repo(tmp_path / "RADIO")


@pytest.fixture
def radseg_repo(tmp_path):
    return _radseg_repo(tmp_path / "RADSeg")


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
    with pytest.raises(ValueError, match=r"^adaptor='dino_v3'.*Known names"):
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


def test_radseg_without_radio_in_the_hub_cache_fails_at_once(radseg_repo, hub, monkeypatch):
    pinned = f"NVlabs_RADIO_{RADIO_REF}"  # RADSeg's own RADIO load is pinned to RADIO_REF
    for folder in (pinned, "NVlabs_RADIO_main"):
        (hub / folder / "hubconf.py").unlink()
        (hub / folder).rmdir()
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    with pytest.raises(WeightsUnavailableError, match=pinned):
        RadSegEncoder(repo=radseg_repo, source="local")
    with pytest.raises(WeightsUnavailableError, match="NVlabs_RADIO_main"):  # unpinned
        RadSegEncoder(repo=radseg_repo, source="local", radio_ref=None)


def test_uncached_radio_weights_fail_at_once(radio_repo, hub, monkeypatch):
    (hub / "checkpoints" / RADIO_CHECKPOINTS["c-radio_v3-b"]).unlink()
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    with pytest.raises(WeightsUnavailableError, match=r"huggingface\.co.* version=/path/to/"):
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
