"""The SAM 2.1 segmentation prior (resireg.priors) and ReSiReg Full / Lite with a prior.

The provider runs transformers' real SAM 2 classes and mask-generation pipeline on a tiny
random-initialised SAM 2 saved to disk (tests/helpers/sam.py), offline. References are computed
independently: the pipeline called directly plus a numpy implementation of the overlap rule,
and a dense float64 softmax of Lite's stated formula.
"""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from helpers.run import run
from helpers.sam import save_tiny_sam

pytest.importorskip("transformers")

from resireg.method.full import ReSiRegFull  # noqa: E402
from resireg.method.lite import ReSiRegLite  # noqa: E402
from resireg.priors import SAM_DEFAULTS, SamPrior, masks_to_instances  # noqa: E402

# Settings that make the random tiny SAM return many overlapping masks quickly: 16 point
# prompts, no quality filters, NMS that keeps everything (box IoU is never above 1).
LOOSE = {
    "points_per_side": 4,
    "pred_iou_thresh": 0.0,
    "stability_score_thresh": 0.0,
    "box_nms_thresh": 1.0,
}


@pytest.fixture(scope="module")
def tiny_sam(tmp_path_factory):
    return save_tiny_sam(tmp_path_factory.mktemp("sam") / "tiny-sam2")


@pytest.fixture(scope="module")
def provider(tiny_sam):
    return SamPrior(model=str(tiny_sam), device="cpu", **LOOSE)


@pytest.fixture(scope="module")
def images():
    """Two uint8 RGB images ``[2, 3, 32, 48]`` with blocky structure plus noise."""
    g = torch.Generator().manual_seed(3)
    blocks = torch.randint(0, 256, (2, 3, 4, 6), generator=g, dtype=torch.int64)
    big = blocks.repeat_interleave(8, 2).repeat_interleave(8, 3)
    noise = torch.randint(-20, 21, big.shape, generator=g)
    return (big + noise).clamp(0, 255).to(torch.uint8)


def _reference_map(masks: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """numpy reference of the overlap rule: per pixel, the covering mask of smallest area,
    then highest score, then lowest index; surviving masks renumbered 1..m in input order."""
    m, h, w = masks.shape
    out = np.zeros((h, w), dtype=np.int64)
    if m == 0:
        return out
    area = masks.reshape(m, -1).sum(1)
    for y in range(h):
        for x in range(w):
            cover = [i for i in range(m) if masks[i, y, x]]
            if cover:
                out[y, x] = 1 + min(cover, key=lambda i: (area[i], -scores[i], i))
    survivors = sorted(set(out[out > 0].tolist()))
    relabel = {old: new for new, old in enumerate(survivors, start=1)}
    return np.vectorize(lambda v: relabel.get(v, 0))(out)


@pytest.fixture(scope="module")
def reference_maps(tiny_sam, images):
    """transformers' mask-generation pipeline called directly on each image, its masks
    resolved by the numpy reference: ``[2, 32, 48]`` int64."""
    from transformers import pipeline

    gen = pipeline("mask-generation", model=str(tiny_sam), device="cpu")
    maps = []
    for image in images:
        out = gen(
            Image.fromarray(image.permute(1, 2, 0).numpy()),
            points_per_crop=LOOSE["points_per_side"],
            points_per_batch=64,
            pred_iou_thresh=0.0,
            stability_score_thresh=0.0,
            crops_nms_thresh=1.0,
        )
        masks = np.stack([np.asarray(m, dtype=bool) for m in out["masks"]])
        maps.append(_reference_map(masks, np.asarray(out["scores"], dtype=np.float64)))
    return torch.from_numpy(np.stack(maps))


@pytest.fixture(scope="module")
def prior_maps(provider, images):
    """The provider's maps of ``images`` (computed once)."""
    return provider(images)


# ----------------------------------------------------------------------------- overlap rule
def test_overlapping_masks_resolve_smaller_wins_then_score_then_order():
    h, w = 8, 10
    a = np.zeros((h, w), bool)
    a[0:6, 0:8] = True  # 48 px, the largest
    b = np.zeros((h, w), bool)
    b[1:4, 1:4] = True  # 9 px, score 0.5
    c = np.zeros((h, w), bool)
    c[2:5, 2:5] = True  # 9 px, score 0.95: wins the overlap with b (equal area)
    d = b | c  # 14 px, entirely covered by the smaller b and c: gets no id
    e = np.zeros((h, w), bool)
    e[6:8, 8:10] = True  # 4 px, disjoint
    masks = torch.from_numpy(np.stack([a, b, c, d, e]))
    scores = torch.tensor([0.9, 0.5, 0.95, 0.99, 0.1])
    # By hand: a -> 1, b -> 2, c -> 3, d vanishes, e -> 4 (input order, contiguous).
    expected = np.zeros((h, w), np.int64)
    expected[a] = 1
    expected[b] = 2
    expected[c] = 3  # c beats b where they overlap (rows 2-3, cols 2-3)
    expected[e] = 4
    assert expected[2, 2] == 3 and expected[1, 1] == 2 and expected[5, 7] == 1
    got = masks_to_instances(masks, scores)
    assert got.dtype == torch.int64
    np.testing.assert_array_equal(got.numpy(), expected)
    np.testing.assert_array_equal(got.numpy(), _reference_map(masks.numpy(), scores.numpy()))
    # Without scores equal areas go by input order: b (earlier) now beats c.
    no_scores = masks_to_instances(masks)
    assert no_scores[2, 2] == 2 and no_scores[4, 4] == 3
    assert masks_to_instances(torch.zeros(0, 3, 4, dtype=torch.bool)).eq(0).all()


# ----------------------------------------------------------------------------- the provider
@pytest.mark.slow
def test_sam_provider_runs_the_real_pipeline_and_returns_an_instance_map(
    provider, images, prior_maps, reference_maps
):
    prior = prior_maps
    assert prior.shape == (2, 32, 48) and prior.dtype == torch.int64
    for b in range(2):
        ids = set(prior[b].unique().tolist()) - {0}
        assert len(ids) >= 2  # several overlapping masks survive the loose settings
        assert ids == set(range(1, len(ids) + 1))  # contiguous 1..m
    torch.testing.assert_close(prior, reference_maps, rtol=0, atol=0)
    # PIL input and float [0, 1] input give the same maps as uint8 tensors.
    assert torch.equal(provider(Image.fromarray(images[0].permute(1, 2, 0).numpy())), prior[:1])
    assert torch.equal(provider(images[1].float() / 255), prior[1:])
    with pytest.raises(ValueError, match="share a size"):
        provider([images[0], images[1, :, :16]])


def test_sam_defaults_are_sams_and_bad_values_name_the_key(tiny_sam):
    sam = SamPrior(model=str(tiny_sam))
    assert sam.settings["pred_iou_thresh"] == 0.8
    assert sam.settings["stability_score_thresh"] == 0.95
    assert sam.settings["points_per_side"] == 32 and sam.settings["box_nms_thresh"] == 0.7
    with pytest.raises(ValueError, match=r"^pred_iou_thresh=1\.5"):
        SamPrior(model=str(tiny_sam), pred_iou_thresh=1.5)
    with pytest.raises(ValueError, match=r"^points_per_side=0"):
        SamPrior(model=str(tiny_sam), points_per_side=0)
    with pytest.raises(FileNotFoundError, match=r"^model="):
        SamPrior(model=str(tiny_sam / "missing"))


def test_offline_without_cached_weights_names_prior_model(monkeypatch):
    from resireg.models import WeightsUnavailableError

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(WeightsUnavailableError, match=r"^model='facebook/sam2\.1-hiera-tiny'"):
        SamPrior(model="facebook/sam2.1-hiera-tiny")


# ----------------------------------------------------------------------------- with ReSiReg
def _encoder():
    from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
    from resireg.models import ResiregVLM

    torch.manual_seed(0)
    return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()


def test_full_and_lite_with_the_provider_equal_the_same_map_by_hand(
    provider, images, reference_maps
):
    encoder = _encoder()
    patch = encoder.input_rule.patch_size
    assert images.shape[-1] % patch == 0 and images.shape[-2] % patch == 0  # no resize
    calls = []

    def counted(raw):
        calls.append(raw.shape)
        return provider(raw)

    for name, kwargs in (("full", {"n_prototypes": 4}), ("lite", {})):
        with_provider = encoder.encode_image(images[:1], name, prior=counted, **kwargs)
        with_map = encoder.encode_image(images[:1], name, prior=reference_maps[:1], **kwargs)
        without = encoder.encode_image(images[:1], name, **kwargs)
        torch.testing.assert_close(with_provider, with_map, rtol=0, atol=0)
        assert not torch.allclose(with_map, without, atol=1e-4)  # the prior does act
    assert calls == [(1, 3, 32, 48)] * 2  # once per call, on the resized [0, 1] batch
    with pytest.raises(ValueError, match="normalized=False"):
        encoder.encode_image(encoder.preprocess(images), "lite", normalized=True, prior=provider)


def _dense_lite(inter, lang, prior, alpha, tau, s):
    """Lite's stated formula, dense in float64, per image: keys = every patch q (logit
    alpha <u_p, u_q>, value l_q) and every instance j of the image (logit alpha 1[S_p = j],
    value norm(sum_{S_q = j} l_q)); softmax over all keys, gate tau, normalise."""
    up = F.interpolate(inter.double(), scale_factor=s, mode="bilinear", align_corners=False)
    u = F.normalize(up, dim=1)
    b, _, h, w = u.shape
    lang_g = F.interpolate(lang.double(), size=(h, w), mode="nearest")
    seg = F.interpolate(prior[:, None].double(), size=(h, w), mode="nearest")[:, 0].long()
    outs = []
    for i in range(b):
        uq = u[i].reshape(u.shape[1], -1).T.numpy()  # [N, Dv]
        lq = lang_g[i].reshape(lang_g.shape[1], -1).T.numpy()  # [N, Dl]
        sp = seg[i].reshape(-1).numpy()
        ids = sorted(set(sp.tolist()) - {0})
        logits = [alpha * uq @ uq.T]
        values = [lq]
        for j in ids:
            member = sp == j
            logits.append(alpha * member[:, None].astype(np.float64))
            v = lq[member].sum(0)
            values.append((v / max(np.linalg.norm(v), 1e-12))[None])
        z = np.concatenate(logits, axis=1)
        a = np.exp(z - z.max(1, keepdims=True))
        a /= a.sum(1, keepdims=True)
        if tau > 0:
            a = a * (a >= tau)
        f = a @ np.concatenate(values, axis=0)
        f /= np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)
        outs.append(torch.from_numpy(f.T.reshape(-1, h, w)))
    return torch.stack(outs)


@pytest.mark.parametrize("tau", [0.0, 0.02])
def test_lite_with_a_prior_equals_the_dense_formula(prior_maps, tau):
    g = torch.Generator().manual_seed(5)
    inter = torch.randn(2, 12, 4, 6, generator=g)
    lang = torch.randn(2, 10, 2, 3, generator=g)
    prior = prior_maps.clone()  # [2, 32, 48]: nearest-resized to the 8 x 12 grid
    prior[1][prior[1] > 5] = 0  # unequal instance counts: Lite pads the slots of image 1
    lite = ReSiRegLite(alpha=10.0, tau=tau, upscale=2)
    out = lite(inter, lang, prior)
    ref = _dense_lite(inter, lang, prior, 10.0, tau, 2)
    torch.testing.assert_close(out.double(), ref, atol=2e-5, rtol=0)


def test_lite_at_widths_off_the_kernel_alignment_equals_the_dense_formula():
    """Key width 13 and value width 10 are zero-padded to 16 (a multiple of 8) for SDPA."""
    g = torch.Generator().manual_seed(7)
    inter = torch.randn(2, 13, 3, 5, generator=g)
    lang = torch.randn(2, 10, 3, 5, generator=g)
    none = torch.zeros(2, 3, 5, dtype=torch.long)
    out = ReSiRegLite(alpha=10.0, upscale=2)(inter, lang)
    torch.testing.assert_close(
        out.double(), _dense_lite(inter, lang, none, 10.0, 0.0, 2), atol=2e-5, rtol=0
    )


def test_an_all_zero_prior_changes_nothing():
    g = torch.Generator().manual_seed(6)
    inter = torch.randn(2, 12, 5, 6, generator=g)
    lang = torch.randn(2, 10, 5, 6, generator=g)
    zero = torch.zeros(2, 10, 12, dtype=torch.long)
    lite = ReSiRegLite(alpha=10.0)
    torch.testing.assert_close(lite(inter, lang, zero), lite(inter, lang), rtol=0, atol=1e-6)
    full = ReSiRegFull(n_prototypes=4, n_components=6)
    torch.testing.assert_close(full(inter, lang, zero), full(inter, lang), rtol=0, atol=1e-6)


# ----------------------------------------------------------------------------- names, config
def test_prior_configuration_names():
    from resireg.method.variants import build_variants
    from resireg.specs.variants import parse_variant, takes_prior

    assert parse_variant("full+prior@n_prototypes:24") == ("full", {"n_prototypes": 24})
    assert takes_prior("full+prior@n_prototypes:24") and takes_prior("lite+prior")
    assert not takes_prior("full@n_prototypes:24") and not takes_prior("full")
    built = build_variants(["full", "full+prior@n_prototypes:24", "lite+prior"])
    assert list(built) == ["full", "full+prior@n_prototypes:24", "lite+prior"]
    assert isinstance(built["full+prior@n_prototypes:24"], ReSiRegFull)
    assert built["full+prior@n_prototypes:24"].n_prototypes == 24
    with pytest.raises(ValueError, match="cannot take a prior"):
        build_variants(["bb+prior"])


def test_a_prior_configuration_without_a_prior_is_a_config_error():
    from resireg.errors import ConfigError
    from resireg_train.checks.eval import validate_eval

    cfg = {"model_path": "x", "encoder": {"kind": "resireg_vlm", "name": "ours",
           "third_party": False}, "variants": ["full", "full+prior"]}  # fmt: skip
    with pytest.raises(ConfigError, match=r"prior=None: variants \['full\+prior'\]"):
        validate_eval(cfg)
    validate_eval({**cfg, "prior": {"kind": "sam2", "model": "facebook/sam2.1-hiera-tiny"}})
    with pytest.raises(ConfigError, match=r"prior\.box_nms_thresh=2"):
        validate_eval({**cfg, "prior": {"kind": "sam2", "model": "m", "box_nms_thresh": 2}})


@pytest.mark.parametrize(
    ("name", "bad"),
    [("points_per_side", 0), ("points_per_batch", 1.5), ("pred_iou_thresh", -0.1),
     ("stability_score_thresh", True), ("stability_score_offset", float("nan")),
     ("mask_threshold", "0"), ("box_nms_thresh", 2), ("crop_n_layers", -1),
     ("crop_overlap_ratio", 1.01), ("crop_n_points_downscale_factor", 0)],
)  # fmt: skip
def test_the_config_check_and_the_provider_reject_a_setting_alike(tiny_sam, name, bad):
    """One rule per SAM setting: resireg-eval's config check fails fast with the message the
    provider itself would give (so neither accepts what the other rejects)."""
    from resireg.errors import ConfigError
    from resireg_train.checks.eval import validate_eval

    cfg = {"model_path": "x", "encoder": {"kind": "resireg_vlm", "name": "ours",
           "third_party": False}, "variants": ["full+prior"]}  # fmt: skip
    with pytest.raises(ValueError) as provider:
        SamPrior(model=str(tiny_sam), **{name: bad})
    assert str(provider.value).startswith(f"{name}=")
    with pytest.raises(ConfigError) as config:
        validate_eval({**cfg, "prior": {"kind": "sam2", "model": "m", name: bad}})
    assert str(provider.value) in str(config.value)
    SamPrior(model=str(tiny_sam), **{name: SAM_DEFAULTS[name]})  # the default passes both
    validate_eval({**cfg, "prior": {"kind": "sam2", "model": "m", name: SAM_DEFAULTS[name]}})


# ----------------------------------------------------------------------------- entry point
def test_resireg_eval_scores_with_and_without_the_prior_in_one_run(tiny_export, tiny_sam, tmp_path):
    out = tmp_path / "eval"
    run("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=4",
        "num_workers=0", "batch_size=2", "full.n_prototypes=12", "variants=[full,full+prior]",
        "prior=sam2", f"prior.model={tiny_sam}", "prior.points_per_side=4",
        "prior.pred_iou_thresh=0", "prior.stability_score_thresh=0", "prior.box_nms_thresh=1",
        f"hydra.run.dir={out}", "device=cpu")  # fmt: skip
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "completed"
    final = results["final"]
    for config in ("full", "full+prior"):
        assert 0 <= final[f"val/ovss/synthetic/miou_{config}"] <= 1
    assert final["val/ovss/synthetic/miou_full"] != final["val/ovss/synthetic/miou_full+prior"]
    assert results["seconds"]["prior"] > 0
    assert results["params"]["prior"]["model"] == str(tiny_sam)


def test_resireg_report_lists_every_prior_configuration_of_the_ablation(tmp_path):
    """A prior_ablation multirun as Hydra and resireg-eval leave it: one job per dataset."""
    import pandas as pd

    from resireg_train.report import report

    configs = ["lite", "lite+prior", "full", "full+prior"]
    scores = {"ade20k": [0.21, 0.23, 0.25, 0.26], "orad3d": [0.41, 0.44, 0.45, 0.47]}
    for number, (dataset, values) in enumerate(scores.items()):
        folder = tmp_path / f"{number}_dataset={dataset}"
        (folder / ".hydra").mkdir(parents=True)
        (folder / ".hydra" / "overrides.yaml").write_text(f"- dataset={dataset}\n")
        final = {f"val/ovss/{dataset}/miou_{c}": v for c, v in zip(configs, values, strict=True)}
        results = {"status": "completed", "final": final,
                   "params": {"variants": configs, "dataset": {"name": dataset}}}  # fmt: skip
        (folder / "results.json").write_text(json.dumps(results))
    files = report(tmp_path)
    table = pd.read_csv(files["csv"])
    for dataset, values in scores.items():
        row = table[table["dataset"] == dataset].iloc[0]
        for config, value in zip(configs, values, strict=True):
            assert row[f"val/ovss/{dataset}/miou_{config}"] == value
    assert "val/ovss/orad3d/miou_full+prior" in files["md"].read_text()
