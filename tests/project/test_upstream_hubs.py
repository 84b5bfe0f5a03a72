"""The hub adapters on the real upstream code, opt-in: clones given by environment variables.

``RESIREG_RADIO_REPO`` (a clone of NVlabs/RADIO) and ``RESIREG_RADSEG_REPO`` (RADSeg-OVSS/RADSeg,
which imports ``segment_anything``) run :class:`RadioEncoder`, :class:`RadSegEncoder` and the
distillation teacher through upstream's own ``hubconf.py`` with a random-weight RADIO checkpoint
written here in RADIO's format (``{"args", "state_dict"}``, which ``hubconf.radio_model`` reads
from a file path: ``version=<file>``): a 2-block ``vit_base_patch16_224`` with CPE and two
``generic`` teachers named ``siglip2`` and ``sam`` (the real ``siglip2`` adaptor type would
download its text model, so text is not run). ``RESIREG_DINOV2_REPO`` (facebookresearch/dinov2)
runs OTAS on the real ``dinov2_vits14_reg`` (``pretrained=False``). References are upstream's
own calls on a second load. Without the variables the tests are skipped (no network here).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys

import pytest
import torch
import torch.nn.functional as F
from timm.data import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD

from helpers.fake_hubs.common import offline_hub
from resireg.models import WeightsUnavailableError, build_encoder
from resireg.models import hub as hub_module
from resireg.models.zoo.radio import RadioEncoder
from resireg.models.zoo.radseg import RadSegEncoder

RADIO = os.environ.get("RESIREG_RADIO_REPO")
RADSEG = os.environ.get("RESIREG_RADSEG_REPO")
DINOV2 = os.environ.get("RESIREG_DINOV2_REPO")
TEACHERS = [{"name": "siglip2", "type": "generic"}, {"name": "sam", "type": "generic"}]


def _random_radio_checkpoint(radio_dir, path):
    """A RADIO checkpoint file with random weights, built with RADIO's own modules."""
    sys.path.insert(0, radio_dir)
    try:
        from radio.adaptor_module_factory import create_mlp_from_config
        from radio.radio_model import create_model_from_args

        args = argparse.Namespace(
            model="vit_base_patch16_224", in_chans=None, input_size=None,
            model_kwargs={"depth": 2, "embed_dim": 64, "num_heads": 2}, pretrained=False,
            num_classes=0, drop=0.0, drop_path=None, drop_block=None, gp=None,
            bn_momentum=None, bn_eps=None, torchscript=False, initial_checkpoint="",
            model_norm=False, cpe_max_size=2048, teachers=TEACHERS, cls_token_per_teacher=True,
            spectral_reparam=False, damp=None, mlp_version="v2", dtype=torch.float32,
        )  # fmt: skip
        torch.manual_seed(0)
        build_args = argparse.Namespace(**{**vars(args), "model_kwargs": dict(args.model_kwargs)})
        state = {
            f"base_model.{k}": v for k, v in create_model_from_args(build_args).state_dict().items()
        }
        state["input_conditioner.norm_mean"] = torch.tensor([0.48, 0.46, 0.41]).view(3, 1, 1)
        state["input_conditioner.norm_std"] = torch.tensor([0.27, 0.26, 0.28]).view(3, 1, 1)
        for i, teacher in enumerate(TEACHERS):
            dim = 24 if teacher["name"] == "siglip2" else 12
            for prefix, summary in (("_heads", True), ("_feature_projections", False)):
                mlp = create_mlp_from_config("v2", 64, 32, dim, 1, is_summary=summary)
                state.update({f"{prefix}.{i}.{k}": v for k, v in mlp.state_dict().items()})
        torch.save({"args": args, "state_dict": state}, path)
    finally:
        sys.path.remove(radio_dir)
        for name in [k for k in sys.modules if k == "radio" or k.startswith("radio.")]:
            del sys.modules[name]
    return str(path)


@pytest.mark.slow
@pytest.mark.skipif(not (RADIO and RADSEG), reason="set RESIREG_RADIO_REPO, RESIREG_RADSEG_REPO")
def test_radio_radseg_and_teacher_on_upstream_code(tmp_path, monkeypatch):
    from resireg_train.training.teacher import RadSegTeacher

    hub = offline_hub(monkeypatch, tmp_path / "hub")
    # torch.hub's folder of NVlabs/RADIO at the pinned commit (RADSeg's own load is pinned)
    pinned = f"NVlabs_RADIO_{hub_module.PINNED_REFS['NVlabs/RADIO']}"
    radio_dir = str(hub / pinned)
    for folder in (radio_dir, str(hub / "NVlabs_RADIO_main")):  # upstream's own unpinned call
        shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(RADIO, folder, ignore=shutil.ignore_patterns(".git"))
    ckpt = _random_radio_checkpoint(radio_dir, tmp_path / "radio_random.pth.tar")
    rgb = torch.rand(2, 3, 64, 96, generator=torch.Generator().manual_seed(1))
    mean = torch.tensor(IMAGENET_DEFAULT_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_DEFAULT_STD).view(1, 3, 1, 1)

    teacher = RadSegTeacher(repo=RADSEG, source="local", model_version=ckpt)
    assert type(teacher.encoder).__module__ == "radseg.radseg"
    out = teacher((rgb - mean) / std, (5, 6))
    ref = torch.hub.load(RADSEG, "radseg_encoder", source="local", model_version=ckpt,
                         slide_crop=0, device="cpu")  # fmt: skip
    with torch.no_grad():
        lang = ref.align_spatial_features_with_language(ref.encode_image_to_feat_map(rgb))
    assert teacher.out_dim == lang.shape[1] == 24
    expected = F.interpolate(lang, size=(5, 6), mode="bilinear", align_corners=False)
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)

    encoder = RadSegEncoder(repo=RADSEG, source="local", model_version=ckpt)
    dense = encoder.encode(encoder.preprocess(rgb))
    assert dense.intermediates.shape == (2, 64, 4, 6) and dense.embedding is None
    torch.testing.assert_close(dense.language, lang, rtol=1e-4, atol=1e-5)
    assert encoder.spec()["model_version"] == ckpt and encoder.spec()["kind"] == "radseg"

    radio = RadioEncoder(repo=radio_dir, source="local", version=ckpt, adaptor="siglip2")
    got = radio.encode(radio.preprocess(rgb))
    fresh = torch.hub.load(radio_dir, "radio_model", source="local", version=ckpt,
                           adaptor_names=["siglip2"]).eval()  # fmt: skip
    with torch.no_grad():
        want = fresh(rgb, feature_fmt="NCHW")  # RGB in [0, 1], RADIO's own conditioner
        head = fresh.adaptors["siglip2"].head_mlp
        lang_ref = head(want["backbone"].features.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
    torch.testing.assert_close(got.intermediates, want["backbone"].features, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(got.language, lang_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(got.embedding, want["siglip2"].summary, rtol=1e-5, atol=1e-5)
    rebuilt = build_encoder(**json.loads(json.dumps(radio.spec())))
    torch.testing.assert_close(rebuilt.encode(radio.preprocess(rgb)).language, got.language)

    shutil.rmtree(radio_dir)  # RADIO's code neither cached nor reachable: the teacher stops
    monkeypatch.setattr(hub_module, "_resolves", lambda host, timeout: False)
    with pytest.raises(WeightsUnavailableError, match=pinned):
        RadSegTeacher(repo=RADSEG, source="local", model_version=ckpt)


@pytest.mark.slow
@pytest.mark.skipif(not DINOV2, reason="set RESIREG_DINOV2_REPO")
def test_otas_on_upstream_dinov2(monkeypatch, tmp_path):
    offline_hub(monkeypatch, tmp_path / "hub")
    torch.manual_seed(0)
    config = {"repo": DINOV2, "source": "local", "pretrained": False, "clip": {"weights": None}}
    encoder = build_encoder("otas", **config)
    assert type(encoder.dino).__module__ == "dinov2.models.vision_transformer"
    x = encoder.preprocess(torch.rand(1, 3, 224, 308, generator=torch.Generator().manual_seed(1)))
    out = encoder.encode(x)
    assert out.intermediates.shape == (1, 384, 16, 22) and out.language.shape == (1, 512, 16, 22)
    torch.manual_seed(0)
    again = build_encoder(**json.loads(json.dumps(encoder.spec())))
    assert again.spec() == encoder.spec() and encoder.spec()["pretrained"] is False
    torch.testing.assert_close(again.encode(x).language, out.language)
    ref = torch.hub.load(DINOV2, "dinov2_vits14_reg", source="local", pretrained=False)
    ref.load_state_dict(encoder.dino.state_dict())
    ref.interpolate_antialias, ref.interpolate_offset = False, 0.1  # OTAS's own ViT settings
    with torch.no_grad():
        square = F.interpolate(x, size=(224, 224), mode="bilinear", align_corners=False,
                               antialias=True)  # fmt: skip
        tokens = ref.forward_features(square)["x_norm_patchtokens"]
    torch.testing.assert_close(encoder.dino_tokens(x), tokens)
