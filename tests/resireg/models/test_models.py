"""Models: EUPE loading (timm and Meta formats), frozen parts, head, text cache, export."""

import time

import pytest
import timm
import torch
from PIL import Image
from safetensors.torch import save_file

from helpers.fake_hubs.common import offline_hub
from helpers.fake_hubs.radio import radio_repo
from helpers.fake_hubs.radseg import radseg_repo
from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.models import (
    EUPEBackbone,
    FrozenTextTower,
    LanguageHead,
    ResiregVLM,
    WeightsUnavailableError,
)
from resireg.models import hub as hub_module
from resireg_train.training.teacher import ConvTeacher, RadSegTeacher

TINY = {"embed_dim": 64, "depth": 2, "num_heads": 2}
NAME = "vit_small_patch16_dinov3_qkvb.eupe_lvd1689m"


def _count(module):
    return sum(p.numel() for p in module.parameters())


def test_parameter_counts():
    backbone = EUPEBackbone(weights=None)
    head = LanguageHead(in_dim=backbone.embed_dim)
    assert round(_count(backbone) / 1e6, 1) == 21.6
    assert 3.6e6 < _count(head) < 3.8e6
    assert 25.0e6 <= _count(backbone) + _count(head) <= 25.6e6


def _meta_state_dict(timm_sd, num_heads):
    """Meta's original EUPE layout, built from a timm state dict (inverse of timm's conversion)."""
    meta = {}
    for k, v in timm_sd.items():
        if k.endswith("attn.q_bias"):
            v_bias = timm_sd[k.replace("q_bias", "v_bias")]
            meta[k.replace("q_bias", "qkv.bias")] = torch.cat([v, torch.zeros_like(v), v_bias])
            # Meta saves this buffer uninitialised; NaNs must never reach the model.
            meta[k.replace("q_bias", "qkv.bias_mask")] = torch.full((3 * v.numel(),), float("nan"))
            continue
        if k.endswith("attn.v_bias"):
            continue
        k = (
            k.replace("reg_token", "storage_tokens")
            .replace("gamma_1", "ls1.gamma")
            .replace("gamma_2", "ls2.gamma")
        )
        meta[k] = v
    dim = timm_sd["cls_token"].shape[-1]
    meta["mask_token"] = torch.randn(1, dim)
    meta["rope_embed.periods"] = torch.randn(dim // num_heads // 4)
    meta["projectors.0.weight"] = torch.randn(32, dim)  # training-only distillation heads
    meta["projectors.0.bias"] = torch.randn(32)
    return meta


def test_meta_checkpoint_loads_like_timm_format(tmp_path):
    ref = timm.create_model(NAME, pretrained=False, num_classes=0, dynamic_img_size=True, **TINY)
    with torch.no_grad():  # non-trivial values everywhere, including the biases and layer scales
        for p in ref.parameters():
            p.copy_(torch.randn_like(p) * 0.05)
    sd = ref.state_dict()
    assert "storage_tokens" not in sd
    save_file({k: v.contiguous() for k, v in sd.items()}, tmp_path / "timm.safetensors")
    meta = _meta_state_dict(sd, TINY["num_heads"])
    assert {
        "storage_tokens",
        "blocks.0.attn.qkv.bias_mask",
        "rope_embed.periods",
        "projectors.0.weight",
    } <= meta.keys()
    torch.save(meta, tmp_path / "EUPE-ViT-S.pt")

    from_timm = EUPEBackbone(NAME, weights=str(tmp_path / "timm.safetensors"), **TINY)
    from_meta = EUPEBackbone(NAME, weights=str(tmp_path / "EUPE-ViT-S.pt"), **TINY)
    x = torch.randn(2, 3, 48, 80)
    a, b = from_timm(x), from_meta(x)
    with torch.no_grad():
        expected = ref.forward_features(x)
    assert torch.isfinite(b.patches).all()
    assert torch.equal(a.patches, b.patches) and torch.equal(a.cls, b.cls)
    assert torch.allclose(a.cls, expected[:, 0])
    assert a.patches.shape == (2, 64, 3, 5) and a.registers.shape == (2, 4, 64)


def test_missing_weights_file_is_clear():
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        EUPEBackbone(weights="/nope.pt", **TINY)


def test_backbone_is_frozen_and_unchanged_by_head_training():
    backbone = EUPEBackbone(**TINY_BACKBONE)
    head = LanguageHead(in_dim=64, **TINY_HEAD)
    assert not any(p.requires_grad for p in backbone.parameters())
    x = torch.randn(2, 3, 32, 48)
    before = backbone(x).patches.clone()
    backbone.train()
    assert not backbone.training  # stays in eval mode
    opt = torch.optim.AdamW(head.parameters(), lr=1e-2)
    out = head(backbone(x))
    out.embedding.pow(2).sum().backward()
    opt.step()
    assert all(p.grad is None for p in backbone.parameters())
    assert torch.equal(backbone(x).patches, before)
    assert out.embedding.shape == (2, 96) and out.patches.shape == (2, 48, 2, 3)


def test_head_uses_registers_when_asked():
    backbone = EUPEBackbone(**TINY_BACKBONE)
    feats = backbone(torch.randn(1, 3, 32, 32))
    torch.manual_seed(0)
    with_regs = LanguageHead(in_dim=64, use_registers=True, **TINY_HEAD).eval()
    torch.manual_seed(0)
    without = LanguageHead(in_dim=64, **TINY_HEAD).eval()
    assert not torch.allclose(with_regs(feats).patches, without(feats).patches)


def test_text_cache_encodes_each_caption_once():
    tower = FrozenTextTower.tiny()
    rows = []
    tower.tower.register_forward_hook(lambda m, args, out: rows.append(args[0].shape[0]))
    captions = ["a red car", "a dog", "a red car", "grass"]
    first = tower(captions)
    second = tower(captions)
    assert sum(rows) == 3  # three unique captions, tower run once
    assert torch.equal(first, second)
    assert tower.misses == 3 and tower.hits == 5
    assert not any(p.requires_grad for p in tower.parameters())


def test_text_cache_is_bounded():
    tower = FrozenTextTower.tiny(cache_size=2)
    tower(["a", "b", "c"])
    assert len(tower._cache) == 2


def test_text_cache_size_is_a_config_key_and_survives_export(tmp_path):
    model = ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, {**TINY_TEXT, "cache_size": 3})
    model.text(["a", "b", "c", "d", "e"])
    assert model.text.cache_size == 3 and list(model.text._cache) == ["c", "d", "e"]
    model.save_pretrained(tmp_path / "export")
    assert ResiregVLM.from_pretrained(tmp_path / "export").text.cache_size == 3
    with pytest.raises(ValueError, match=r"model\.text\.cache_size=-1"):
        ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, {**TINY_TEXT, "cache_size": -1})


def test_tiny_text_tower_is_open_clips_text_transformer():
    """The public TextTransformer we build equals open_clip's own CLIP text-tower builder."""
    from open_clip.model import CLIPTextCfg, _build_text_tower

    ours = FrozenTextTower.tiny(seed=3)
    cfg = CLIPTextCfg(context_length=32, width=64, heads=2, layers=2, no_causal_mask=True,
                      proj_bias=True, pool_type="argmax")  # fmt: skip
    torch.manual_seed(3)
    reference = _build_text_tower(96, cfg).eval()
    tokens = ours.tokenizer(["a photo of a cat", "grass"])
    with torch.no_grad():
        torch.testing.assert_close(ours.tower(tokens), reference(tokens), rtol=0, atol=0)


def test_intermediate_layer_is_that_blocks_output():
    """intermediates == block i's output recomputed from the timm model's own modules;
    the default (None) keeps the final-norm patch tokens, the head's input."""
    torch.manual_seed(0)
    x = torch.randn(2, 3, 32, 48)
    default = ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()
    first = ResiregVLM(default.backbone, default.head, default.text, default.text_proj, 0)
    vit = default.backbone.model
    with torch.no_grad():
        tokens, rope = vit._pos_embed(vit.patch_embed(x))
        block0 = vit.blocks[0](vit.norm_pre(tokens), rope=rope)[:, vit.num_prefix_tokens :]
        final = vit.forward_features(x)[:, vit.num_prefix_tokens :]
        out0, out = first.encode(x), default.encode(x)
    grid = lambda t: t.transpose(1, 2).reshape(2, -1, 2, 3)  # noqa: E731
    torch.testing.assert_close(out0.intermediates, grid(block0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.intermediates, grid(final), rtol=1e-5, atol=1e-5)
    assert torch.equal(out0.language, out.language)  # the head still reads final-norm tokens
    assert not torch.allclose(out0.intermediates, out.intermediates)
    with pytest.raises(ValueError, match=r"intermediate_layer=5 is out of range for .*\(2 blocks"):
        ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT, intermediate_layer=5)


def test_non_default_head_and_layer_round_trip(tmp_path):
    head = {"out_dim": 32, "depth": 1, "num_heads": 4, "mlp_ratio": 2.0, "drop_path": 0.1,
            "use_registers": True}  # fmt: skip
    model = ResiregVLM.build(TINY_BACKBONE, head, TINY_TEXT, intermediate_layer=-2)
    model.save_pretrained(tmp_path / "export")
    loaded = ResiregVLM.from_pretrained(tmp_path / "export")
    assert loaded.head.spec() == head and loaded.intermediate_layer == -2
    assert len(loaded.head.blocks) == 1 and loaded.head.use_registers
    x = torch.randn(1, 3, 32, 32)
    model.eval()
    for a, b in zip(model.encode(x)[:2], loaded.encode(x)[:2], strict=True):
        assert torch.equal(a, b)


def test_export_source_is_a_folder_or_a_repo_id(tmp_path, monkeypatch):
    """Only a cache miss leads to the hub; a missing folder is never looked up there, and any
    other hub error is not disguised as 'offline'."""
    import huggingface_hub

    with pytest.raises(FileNotFoundError, match="not an export folder"):
        ResiregVLM.from_pretrained(tmp_path / "no" / "such" / "export")
    with pytest.raises(FileNotFoundError, match="not an export folder"):
        ResiregVLM.from_pretrained("./missing-export")

    def broken(*args, **kwargs):
        raise PermissionError("cache not readable")

    monkeypatch.setattr(huggingface_hub, "snapshot_download", broken)
    with pytest.raises(PermissionError, match="cache not readable"):
        ResiregVLM.from_pretrained("someone/some-vlm")


def _tiny_vlm():
    return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT)


def test_vlm_round_trip_is_exact(tmp_path):
    model = _tiny_vlm()
    with torch.no_grad():
        for p in model.head.parameters():
            p.add_(torch.randn_like(p) * 0.1)  # "trained" weights differ from a fresh init
    model.save_pretrained(tmp_path / "export")
    loaded = ResiregVLM.from_pretrained(tmp_path / "export")
    images = torch.rand(2, 3, 48, 64)
    for variant, kw in ((None, {}), ("lite", {}), ("full", {"n_prototypes": 6, "n_components": 6})):
        assert torch.equal(
            model.encode_image(images, variant, **kw), loaded.encode_image(images, variant, **kw)
        )
    texts = ["a cat", "the sky"]
    assert torch.equal(model.encode_text(texts), loaded.encode_text(texts))
    assert (tmp_path / "export" / "model.safetensors").exists()


def test_vlm_outputs_and_preprocessing():
    model = _tiny_vlm()
    image = Image.new("RGB", (100, 70), (120, 30, 200))
    x = model.preprocess(image, short_side=48)
    assert x.shape == (1, 3, 48, 64)  # 70 -> 48, 100 -> 68.6 -> rounded to 64
    expected = (
        torch.tensor([120, 30, 200]) / 255.0 - torch.tensor(model.backbone.mean)
    ) / torch.tensor(model.backbone.std)
    assert torch.allclose(x[0, :, 10, 10], expected, atol=1e-3)
    dense = model.encode_image([image, image], short_side=48)
    assert dense.shape == (2, 48, 3, 4)
    assert torch.allclose(dense.norm(dim=1), torch.ones(2, 3, 4), atol=1e-5)
    text = model.encode_text(["a", "b", "c"])
    assert text.shape == (3, 48) and torch.allclose(text.norm(dim=1), torch.ones(3), atol=1e-5)
    sim = model.similarity(image, ["a", "b"], short_side=48)
    # Cosine similarity recomputed from the model's own parts: backbone -> head -> normalise.
    with torch.no_grad():
        lang = model.head(model.backbone(x)).patches
        queries = model.text_proj(model.text.tower(model.text.tokenizer(["a", "b"])))
    expected = torch.einsum(
        "dhw,kd->khw",
        torch.nn.functional.normalize(lang[0], dim=0),
        torch.nn.functional.normalize(queries[:, 48:], dim=1),
    )
    torch.testing.assert_close(sim[0], expected, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="unknown ReSiReg variant 'fancy'"):
        model.encode_image(image, "fancy")


def test_offline_hub_requests_fail_fast(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))  # an empty cache
    start = time.monotonic()
    with pytest.raises(
        WeightsUnavailableError, match=r"model\.backbone\.weights=/path/to/EUPE-ViT-S\.pt"
    ):
        EUPEBackbone(weights="hub")
    with pytest.raises(WeightsUnavailableError, match=r"model\.text\.weights="):
        FrozenTextTower.pretrained()
    with pytest.raises(WeightsUnavailableError, match="export directory"):
        ResiregVLM.from_pretrained("someone/some-vlm")
    assert time.monotonic() - start < 5.0


def test_unreachable_github_names_local_alternative(monkeypatch):
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    with pytest.raises(WeightsUnavailableError, match="source=local") as err:
        RadSegTeacher()
    message = str(err.value)
    assert "model.teacher.repo=/path/to/RADSeg" in message
    assert "model.teacher.source=local" in message and "model.loss.distill.scale=0" in message


def _hub_load_forbidden(*args, **kwargs):
    raise AssertionError("torch.hub.load must not run when the offline checks fail")


def test_radseg_teacher_gets_radsegs_offline_checks(tmp_path, monkeypatch):
    """The teacher loads through the one RADSeg loader (resireg.models.zoo.radseg.load_radseg):
    with a local RADSeg clone but RADIO's code (which RADSeg torch.hub.loads itself) or its
    checkpoint neither cached nor reachable, it fails at once, before torch.hub.load."""
    repo = radseg_repo(tmp_path / "RADSeg")
    hub = offline_hub(monkeypatch, tmp_path / "hub")  # no RADIO code, no checkpoint
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    monkeypatch.setattr(torch.hub, "load", _hub_load_forbidden)
    start = time.monotonic()
    pinned = f"NVlabs_RADIO_{hub_module.PINNED_REFS['NVlabs/RADIO']}"  # RADSeg's RADIO: pinned
    with pytest.raises(WeightsUnavailableError, match=pinned):
        RadSegTeacher(repo=repo, source="local")
    radio_repo(hub / pinned)  # RADIO's code cached, its checkpoint not
    with pytest.raises(WeightsUnavailableError, match=r"huggingface\.co.*model\.teacher\.repo="):
        RadSegTeacher(repo=repo, source="local")
    assert time.monotonic() - start < 2.0


def test_radseg_teacher_is_radsegs_language_map(tmp_path, monkeypatch):
    """Against RADSeg's structure (tests/helpers/fake_hubs/radseg.py FAKE_RADSEG): the teacher's features are
    RADSeg's own language-aligned map of the un-normalised images (a second load, RADSeg's
    documented API), resized to the student's grid; and the same as the dense encoder's
    language tokens (both over the one loader)."""
    import torch.nn.functional as F
    from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD

    from resireg.models.zoo.radio import RADIO_CHECKPOINTS
    from resireg.models.zoo.radseg import RadSegEncoder

    offline_hub(monkeypatch, tmp_path / "hub", RADIO_CHECKPOINTS.values(), radio_code=True)
    repo = radseg_repo(tmp_path / "RADSeg")
    teacher = RadSegTeacher(repo=repo, source="local")
    rgb = torch.rand(2, 3, 48, 64, generator=torch.Generator().manual_seed(3))
    mean = torch.tensor(IMAGENET_DEFAULT_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_DEFAULT_STD).view(1, 3, 1, 1)
    out = teacher((rgb - mean) / std, (5, 6))

    ref = torch.hub.load(repo, "radseg_encoder", source="local", slide_crop=0, device="cpu")
    with torch.no_grad():
        lang = ref.align_spatial_features_with_language(ref.encode_image_to_feat_map(rgb))
    assert teacher.out_dim == lang.shape[1] == ref.lang_adaptor.head_mlp.final[-1].out_features
    expected = F.interpolate(lang, size=(5, 6), mode="bilinear", align_corners=False)
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)

    encoder = RadSegEncoder(repo=repo, source="local")
    dense = encoder.encode(encoder.preprocess(rgb)).language
    torch.testing.assert_close(teacher.dense((rgb - mean) / std), dense, rtol=1e-4, atol=1e-5)
    assert not any(p.requires_grad for p in teacher.parameters())


def test_radseg_teacher_through_local_torch_hub(tmp_path, monkeypatch):
    """The real torch.hub path (source='local') against a repo with RADSeg's entry-point API."""
    offline_hub(monkeypatch, tmp_path / "hub", ["c-radio_v3-b_half.pth.tar"], radio_code=True)
    radseg_repo(tmp_path / "RADSeg", standin=True)
    teacher = RadSegTeacher(repo=str(tmp_path / "RADSeg"), source="local")
    assert teacher.encoder.calls == {
        "model_version": "c-radio_v3-b",
        "lang_model": "siglip2",
        "slide_crop": 0,
        "device": "cpu",
    }
    _check_radseg_teacher(teacher)


def test_radseg_teacher_is_built_per_rank_on_the_modules_device(tmp_path, monkeypatch):
    """The training module builds the teacher in setup, on the device Lightning gives the rank
    (here 'meta', standing in for cuda:N), and RADSeg receives its inputs there."""
    from resireg_train.training.module import ResiregModule

    offline_hub(monkeypatch, tmp_path / "hub", ["c-radio_v3-b_half.pth.tar"], radio_code=True)
    radseg_repo(tmp_path / "RADSeg", standin=True)
    teacher = {"kind": "radseg", "repo": str(tmp_path / "RADSeg"), "source": "local"}
    module = ResiregModule(
        TINY_BACKBONE, TINY_HEAD, TINY_TEXT, teacher=teacher,
        optimizer=torch.optim.AdamW, scheduler={"min_lr": 1e-6}, steps_per_epoch=8,
        loss={"contrastive": {"scale": 1.0, "warmup_epochs": 0},
              "distill": {"scale": 0.1, "warmup_epochs": 0}},
        logit_scale={"init": 1 / 0.07, "max": 100.0},
    )  # fmt: skip
    assert module.teacher is None  # nothing device-bound is built in __init__
    module._device = torch.device("meta")  # what Lightning sets before calling setup
    module.setup("fit")
    assert module.teacher.encoder.calls["device"] == "meta"
    assert module.teacher.out_dim == 24 and module.distill_head.in_features == 24
    assert module.distill_head.weight.device.type == "meta"


def _check_radseg_teacher(teacher):
    assert teacher.out_dim == 24
    out = teacher(torch.randn(2, 3, 70, 90), (5, 6))
    assert out.shape == (2, 24, 5, 6)
    assert not any(p.requires_grad for p in teacher.parameters())


def test_conv_teacher_matches_student_grid():
    teacher = ConvTeacher(out_dim=20)
    assert teacher(torch.randn(2, 3, 64, 96), (4, 6)).shape == (2, 20, 4, 6)
