"""The CLIP intermediate-layer sweep: ``<variant>@layer:<block>`` configurations.

One encoder pass per batch serves every block (``ClipEncoder.encode_layers``); each
configuration must score exactly what a run of the encoder built with that block as its
``intermediate_layer`` scores (confusion matrices equal, through the real engine). Also the
checks before encoding, the feature cache's key and contents, the sweep config and the
report's table and figure.
"""

import math

import pandas as pd
import pytest
import torch
from hydra import compose, initialize_config_dir
from PIL import Image

from helpers.sweeps import make_job as _job
from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.errors import ConfigError
from resireg.method.variants import build_variants
from resireg.models import ResiregVLM
from resireg.models.zoo.clip import ClipEncoder
from resireg.ovss import TEMPLATES
from resireg.specs.variants import parse_variant, variant_layer
from resireg_train.checks.eval import validate_eval
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.data.specs import dataset_conf
from resireg_train.evaluation.cache import FeatureCache
from resireg_train.evaluation.ovss.engine import OVSSEngine, requested_layers
from resireg_train.report import collect, layer_sweep_table, report

B16 = "ViT-B-16"
SIDE = 64  # CLIP's native side here: a 4 x 4 token grid keeps the test fast
SPEC = dataset_conf("synthetic", size=6, image_size=[48, 64], seed=5, short_side=48)
FULL = {"n_prototypes": 6, "n_components": 6}
PARAMS = {"full": FULL, "calib": {"n_neighbors": 5}}  # LOF: 12 tokens per image here


def _clip(**kwargs):
    return ClipEncoder(B16, weights=None, image_size=SIDE, **kwargs)  # seed 0: same weights


@pytest.fixture(scope="module")
def enc():
    return _clip()


def _task():
    # two templates: the text tower's cost, not the point of these tests
    dataset = build_segmentation_set(SPEC, patch_size=16)
    return OVSSEngine(dataset, batch_size=3, templates=TEMPLATES[:2])


class _Passes:
    """Counts the passes through the first block (one per encoded batch)."""

    def __init__(self, encoder):
        self.n = 0
        first = encoder.model.visual.transformer.resblocks[0]
        self._hook = first.register_forward_pre_hook(lambda m, a: setattr(self, "n", self.n + 1))

    def remove(self):
        self._hook.remove()


@pytest.mark.slow
def test_one_pass_with_many_layers_equals_a_run_per_layer(enc):
    names = ["bb", "lite@layer:2", "full@layer:2", "lite@layer:7", "full@layer:7",
             "calib@layer:7", "full@layer:-1"]  # fmt: skip
    passes = _Passes(enc)
    try:
        together = _task().run(enc, build_variants(names, PARAMS))
    finally:
        passes.remove()
    assert passes.n == 2  # 6 images in batches of 3: one pass per batch for all the blocks
    for layer, configs in ((2, ["lite", "full"]), (7, ["lite", "full", "calib"]), (11, ["full"])):
        alone = _task().run(
            _clip(intermediate_layer=layer), build_variants(["bb", *configs], PARAMS)
        )
        for variant in configs:
            name = f"{variant}@layer:{-1 if layer == 11 else layer}"
            expected = alone.metrics[variant].confusion
            assert torch.equal(together.metrics[name].confusion, expected), name
        assert torch.equal(together.metrics["bb"].confusion, alone.metrics["bb"].confusion)
    # the block matters: the sweep would not see a wrong block otherwise
    for variant in ("lite", "full"):
        a, b = (together.metrics[f"{variant}@layer:{i}"].confusion for i in (2, 7))
        assert not torch.equal(a, b), variant
    scores = together.scores()
    assert "val/ovss/synthetic/miou_lite@layer:7" in scores


def test_configuration_syntax_and_checks_before_encoding(enc, monkeypatch):
    assert parse_variant("lite@layer:3@alpha:2.0") == ("lite", {"alpha": 2.0})
    assert variant_layer("full+prior@n_prototypes:24@layer:-1") == -1
    assert variant_layer("full@n_prototypes:24") is None
    with pytest.raises(ValueError, match=r"'lite@layer:x': @layer: takes a block index"):
        variant_layer("lite@layer:x")
    assert requested_layers(enc, ["bb", "lite@layer:-1", "full@layer:11", "full@layer:3"]) == (
        3,
        11,
    )

    def never(*args, **kwargs):
        raise AssertionError("nothing may be encoded")

    monkeypatch.setattr(enc, "encode_layers", never)
    monkeypatch.setattr(enc, "encode", never)
    task = _task()
    with pytest.raises(ValueError, match=r"'bb@layer:3': bb scores the language tokens alone"):
        task.run(enc, build_variants(["bb@layer:3"]))
    with pytest.raises(ValueError, match=r"'lite@layer:12': layer=12 is out of range for ViT-B-16"):
        task.run(enc, build_variants(["lite", "lite@layer:12"]))
    torch.manual_seed(0)
    vlm = ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()
    with pytest.raises(ValueError, match=r"ResiregVLM returns no per-block intermediates"):
        task.run(vlm, build_variants(["lite@layer:1"]))


def test_config_checks_name_the_variants_key():
    base = {"encoder": {"kind": "clip", "name": "clip_vit_b16", "third_party": True}}
    validate_eval({**base, "variants": ["bb", "lite@layer:4"]})
    with pytest.raises(ConfigError, match=r"variants=\['lite@layer:x'\]: expected .*lite@layer:5"):
        validate_eval({**base, "variants": ["lite@layer:x"]})
    scannet = {**base, "task": "scannet3d", "dataset": {"kind": "scannet"}}
    with pytest.raises(ConfigError, match=r"@layer: configurations are scored by task=ovss only"):
        validate_eval({**scannet, "variants": ["full@layer:4"]})


@pytest.mark.slow
def test_feature_cache_keys_and_stores_the_blocks(tmp_path, enc, monkeypatch):
    dataset = build_segmentation_set(SPEC, patch_size=16)
    names = ["lite@layer:2", "lite@layer:7", "lite"]
    layers = requested_layers(enc, names)
    plain_key = FeatureCache.key_for(enc, {"kind": "clip"}, SPEC, 16, "32")
    key = FeatureCache.key_for(enc, {"kind": "clip"}, SPEC, 16, "32", layers)
    assert key["layers"] == [2, 7] and "layers" not in plain_key
    assert (
        FeatureCache(tmp_path, key, dataset.describe).folder
        != FeatureCache(tmp_path, plain_key, dataset.describe).folder
    )
    variants = build_variants(names)
    plain = _task().run(enc, variants)
    _task().run(enc, variants, cache=FeatureCache(tmp_path, key, dataset.describe))  # fills
    reread = FeatureCache(tmp_path, key, dataset.describe)
    assert reread.layers == (2, 7) and len(reread) == len(dataset)
    calls = []
    monkeypatch.setattr(enc, "encode_layers", lambda *a: calls.append(1))
    again = _task().run(enc, variants, cache=reread)
    assert not calls  # read from disk
    for name in names:
        assert torch.equal(again.metrics[name].confusion, plain.metrics[name].confusion), name
    with pytest.raises(ValueError, match=r"holds the intermediates of blocks \[\], the "
                                         r"configurations run on \[2, 7\]"):  # fmt: skip
        _task().run(enc, variants, cache=FeatureCache(tmp_path, plain_key, dataset.describe))


def test_clip_layers_sweep_config():
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=["sweep=clip_layers"], return_hydra_config=True)
    assert cfg.hydra.mode.name == "MULTIRUN" and cfg.name == "clip_layers"
    assert cfg.hydra.sweeper.params.encoder == "clip_vit_b16"
    assert cfg.hydra.sweeper.params.dataset == "ade20k"
    expected = ["bb"] + [f"{v}@layer:{i}" for v in ("lite", "full") for i in range(12)]
    assert list(cfg.variants) == expected
    validate_eval({"encoder": {"kind": "clip", "name": "clip_vit_b16", "third_party": True},
                   "variants": list(cfg.variants)})  # fmt: skip


def test_report_draws_miou_against_the_block(tmp_path):
    """Two encoders' jobs (one failed): the table holds each (variant, block)'s mIoU x100 as
    recorded, BB once per job with no block, the failed job's cells empty; the markdown names
    the best block; the PNG is written."""
    sweep = tmp_path / "sweep"
    names = ["bb"] + [f"{v}@layer:{i}" for v in ("lite", "full") for i in range(3)]
    final = {"val/ovss/ade20k/miou_bb": 0.10, "val/ovss/ade20k/fmiou_bb": 0.2}
    for i in range(3):
        final[f"val/ovss/ade20k/miou_lite@layer:{i}"] = 0.11 + 0.01 * i
        final[f"val/ovss/ade20k/miou_full@layer:{i}"] = [0.15, 0.12, 0.13][i]
        final[f"val/ovss/ade20k/fmiou_full@layer:{i}"] = 0.3
    params = {"variants": names, "dataset": {"name": "ade20k"}}
    _job(sweep, 0, {"encoder": "clip_vit_b16"}, {
        "status": "completed", "params": {**params, "encoder": {"name": "clip_vit_b16"}},
        "encoder": {"name": "clip_vit_b16"}, "final": final})  # fmt: skip
    _job(sweep, 1, {"encoder": "clip_vit_l14_336"}, {
        "status": "failed", "error": "ValueError: x",
        "params": {**params, "encoder": {"name": "clip_vit_l14_336"}}})  # fmt: skip
    files = report(sweep)
    table = pd.read_csv(files["layer_sweep_csv"])
    b16 = table[table.encoder == "clip_vit_b16"].set_index(["variant", "block"])
    assert b16.loc[("lite", 2), "miou"] == pytest.approx(13.0)
    assert b16.loc[("full", 0), "miou"] == pytest.approx(15.0)
    assert b16.loc[("full", 1), "fmiou"] == pytest.approx(30.0)
    bb = table[(table.encoder == "clip_vit_b16") & (table.variant == "bb")]
    assert len(bb) == 1 and math.isnan(bb.block.iloc[0]) and bb.miou.iloc[0] == pytest.approx(10)
    l14 = table[table.encoder == "clip_vit_l14_336"]
    assert len(l14) == 7 and l14.miou.isna().all() and set(l14.status) == {"failed"}
    md = files["layer_sweep_md"].read_text()
    assert "## clip_vit_b16 / ade20k" in md and "BB (no intermediates): 10.0." in md
    assert "Lite: block 2 (13.0); Full: block 0 (15.0)" in md
    with Image.open(files["layer_sweep_png"]) as png:
        assert png.size[0] > png.size[1] > 0  # two panels side by side
    assert "layer_sweep.md" in files["md"].read_text()
    assert len(layer_sweep_table(collect(sweep))) == len(table)
