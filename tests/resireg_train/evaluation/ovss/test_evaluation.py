"""The OVSS engine shared by ReSiRegEval and resireg-eval."""

import numpy as np
import pytest
import torch
from sklearn.metrics import confusion_matrix, jaccard_score

from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.method.variants import build_variant, build_variants
from resireg.models import ResiregVLM
from resireg.ovss import predict, text_prototypes
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.data.specs import dataset_conf
from resireg_train.data.synthetic import SYNTHETIC_CLASSES
from resireg_train.evaluation.ovss.engine import OVSSEngine, StageTimer

SPEC = dataset_conf("synthetic", size=10, image_size=[40, 56], seed=5, short_side=48)
FULL = {"n_prototypes": 6, "n_components": 6}


@pytest.fixture(scope="module")
def vlm():
    torch.manual_seed(0)
    return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()


def _engine(batch_size=4):
    return OVSSEngine(build_segmentation_set(SPEC, patch_size=16), batch_size=batch_size)


def test_prototypes_embed_prompts_once_and_apply_the_current_projection(vlm):
    engine = _engine()
    calls = []
    handle = vlm.text.tower.register_forward_hook(lambda m, i, o: calls.append(o.shape[0]))
    try:
        first = engine.prototypes(vlm)
        again = engine.prototypes(vlm)
        # The reference path: every prompt through encode_text (tower + projection + half).
        reference = text_prototypes(vlm.encode_text, SYNTHETIC_CLASSES)
        n_reference_calls = len(calls) - 1
        with torch.no_grad():
            vlm.text_proj.weight.mul_(-1.0)  # a different projection, as after a training step
        flipped = engine.prototypes(vlm)
        with torch.no_grad():
            vlm.text_proj.weight.mul_(-1.0)
    finally:
        handle.remove()
    assert calls[0] == len(SYNTHETIC_CLASSES) * 80 and engine.tower_calls == 1
    assert len(calls) == 1 + n_reference_calls  # later prototype calls ran no tower
    torch.testing.assert_close(first, again, rtol=0, atol=0)
    torch.testing.assert_close(first, reference, rtol=1e-5, atol=1e-6)
    assert first.shape == (8, 48) and not torch.allclose(flipped, first)


def test_scores_match_an_independent_per_image_computation(vlm):
    """Confusion of the engine == sklearn's over encode_image + predict image by image."""
    engine = _engine(batch_size=3)
    variants = build_variants(["bb", "lite", "full"], {"lite": {"alpha": 10.0}, "full": FULL})
    result = engine.run(vlm, variants)
    assert result.images == 10 and result.skipped == 0
    assert result.batch_sizes == {1: 1, 3: 3}
    protos = engine.prototypes(vlm)
    ds = engine.dataset
    scores = result.scores()
    assert set(scores) == {f"val/ovss/synthetic/{m}_{v}" for m in ("miou", "fmiou")
                           for v in ("bb", "lite", "full")}  # fmt: skip
    for name, kwargs in (("bb", {}), ("lite", {"alpha": 10.0}), ("full", FULL)):
        expected = np.zeros((8, 8), dtype=np.int64)
        labels, preds = [], []
        for batch in ds.batches(3):
            images = torch.stack([ds[i]["image"] for i in batch])
            dense = vlm.encode_image(images, name, **kwargs)
            for j, i in enumerate(batch):
                label = ds[i]["label"]
                pred = predict(dense[j : j + 1], protos, tuple(label.shape))
                expected += confusion_matrix(label.flatten(), pred.flatten(), labels=range(8))
                labels.append(label.flatten().numpy())
                preds.append(pred.flatten().numpy())
        assert np.array_equal(result.metrics[name].confusion.numpy(), expected), name
        # mIoU over classes present in labels or predictions, f-mIoU weighted by label frequency.
        y, p = np.concatenate(labels), np.concatenate(preds)
        present = np.union1d(y, p)
        iou = jaccard_score(y, p, labels=present, average=None)
        assert scores[f"val/ovss/synthetic/miou_{name}"] == pytest.approx(iou.mean(), abs=1e-12)
        freq = np.array([(y == c).mean() for c in present])
        assert scores[f"val/ovss/synthetic/fmiou_{name}"] == pytest.approx(
            (freq * iou).sum(), abs=1e-12
        )


@pytest.mark.slow
def test_sharded_passes_reduced_equal_the_single_process_pass(vlm):
    variants = build_variants(["bb", "full"], {"full": FULL})
    single = _engine().run(vlm, variants)
    shards = [_engine().run(vlm, variants, rank=r, world_size=3) for r in range(3)]
    assert sum(s.images for s in shards) == single.images == 10

    # What trainer.strategy.reduce(t, "sum") returns on every rank: the sum of the packs.
    cpu = torch.device("cpu")
    packs, skips = [], [s.skipped_samples for s in shards]
    for shard in shards:
        shard.reduce(lambda t: packs.append(t.clone()) or t, lambda o: skips, cpu)  # capture
    total = torch.stack(packs).sum(0)
    shards[0].reduce(lambda t: total, lambda o: skips, cpu)
    for name in variants:
        assert torch.equal(shards[0].metrics[name].confusion, single.metrics[name].confusion)
    assert shards[0].images == 10 and shards[0].scores() == single.scores()
    assert shards[0].batch_sizes == single.batch_sizes == {2: 1, 4: 2}


def test_bf16_pass_agrees_with_fp32_and_timer_splits_the_cost(vlm):
    """bf16 autocast changes some predictions (it really ran in bf16) but stays within a
    stated tolerance of the fp32 protocol: at most 10% of pixels move between confusion
    cells and mIoU moves by at most 0.05."""
    variants = build_variants(["bb", "full"], {"full": FULL})
    fp32 = _engine().run(vlm, variants)
    timer = StageTimer()
    bf16 = _engine().run(vlm, variants, precision="bf16", timer=timer)
    for name in variants:
        a, b = fp32.metrics[name].confusion, bf16.metrics[name].confusion
        moved = (a - b).abs().sum().item() / 2 / a.sum().item()
        assert 0 < moved <= 0.10, (name, moved)
        miou_a, miou_b = (r.scores()[f"val/ovss/synthetic/miou_{name}"] for r in (fp32, bf16))
        assert abs(miou_a - miou_b) <= 0.05, (name, miou_a, miou_b)
    assert {
        "data",
        "encoder",
        "reconstruction/bb",
        "reconstruction/full",
        "metric",
    } <= set(timer.seconds)
    with pytest.raises(ValueError, match="precision='fp8'"):
        _engine().run(vlm, build_variants(["bb"]), precision="fp8")


def test_callback_reduces_on_the_modules_device_and_logs_the_single_process_scores(
    vlm, monkeypatch
):
    """NCCL reduces only tensors on the rank's GPU: the strategy must receive the pack on the
    module's device ('meta' stands in for cuda:N), and the reduced sums give the scores."""
    from types import SimpleNamespace

    from resireg_train.evaluation.ovss import callback as callback_module
    from resireg_train.evaluation.ovss.callback import ReSiRegEval

    callback = ReSiRegEval({"synthetic": SPEC}, variants=["bb", "full"], batch_size=4,
                           full=FULL)  # fmt: skip
    module = SimpleNamespace(vlm=vlm, device=torch.device("meta"))
    callback.setup(None, module, "fit")
    (engine,) = callback.engines.values()
    single = engine.run(vlm, callback.variants)
    packed = []
    single.reduce(lambda t: packed.append(t) or t, lambda o: [o], torch.device("cpu"))

    class Strategy:
        calls = []

        def reduce(self, tensor, reduce_op):
            assert tensor.device == module.device and reduce_op == "sum"
            self.calls.append(tensor.shape)
            return packed[0]  # the sum over ranks of what they packed

    trainer = SimpleNamespace(global_rank=1, world_size=2, strategy=Strategy(),
                              is_global_zero=False)  # fmt: skip
    gathered = []
    monkeypatch.setattr(callback_module, "_all_gather_object",
                        lambda o: gathered.append(o) or [o, []])  # fmt: skip
    scores = callback.evaluate(trainer, module)
    assert Strategy.calls == [packed[0].shape] and gathered == [[]]
    assert scores == {**single.scores(), "val/ovss/synthetic/skipped": 0.0}


def test_variant_names_and_modes_are_checked(vlm):
    with pytest.raises(ValueError, match=r"^names=\['bb', 'mid'\]: unknown \['mid'\]"):
        build_variants(["bb", "mid"])
    with pytest.raises(ValueError, match="n_prototypes"):
        build_variants(["full"], {"full": {"n_prototypes": 0}})
    vlm.head.train()
    _engine().run(vlm, build_variants(["bb"]))
    assert vlm.head.training and not vlm.backbone.training  # modes restored after the pass
    vlm.eval()


@pytest.mark.slow
def test_unreadable_and_undecodable_images_are_counted_once_across_ranks(vlm, tmp_path):
    from helpers.ade20k import ade_folder

    ade_folder(tmp_path / "ade")  # 3 images + 1 file that is not an image
    spec = dataset_conf("ade20k", path=str(tmp_path / "ade"), short_side=32)
    engine = OVSSEngine(build_segmentation_set(spec, patch_size=16), batch_size=2)
    single = engine.run(vlm, build_variants(["bb"]))
    assert (single.images, single.skipped) == (3, 1)
    shards = [engine.run(vlm, build_variants(["bb"]), rank=r, world_size=2) for r in range(2)]
    assert sum(s.skipped for s in shards) == 1 and sum(s.images for s in shards) == 3


def test_resireg_eval_bad_values_are_listed_by_key_and_recorded(tmp_path):
    import json

    from hydra import compose, initialize_config_dir

    from resireg.errors import ConfigError
    from resireg_train.cli.eval import evaluate
    from resireg_train.config.paths import CONFIG_DIR

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("eval", overrides=["model_path=x", "precision=fp8", "variants=[bb,mid]",
                                         "batch_size=0", f"paths.output_dir={tmp_path}"])  # fmt: skip
    with pytest.raises(ConfigError) as err:
        evaluate(cfg)
    for expected in ("variants=['bb', 'mid']", "batch_size=0", "precision='fp8'"):
        assert expected in str(err.value)
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["status"] == "failed" and "batch_size=0" in results["error"]


@pytest.mark.slow
def test_many_configurations_in_one_pass_equal_separate_runs(vlm):
    """`full@n_prototypes:<n>` configurations scored on one encoded batch give exactly the
    confusion matrices of one run per configuration, and the encoder runs once per batch."""
    names = ["bb", "full@n_prototypes:4", "full@n_prototypes:6@alpha:2.0", "lite@upscale:1"]
    params = {"full": FULL, "lite": {"alpha": 10.0}}
    calls = []
    handle = vlm.head.register_forward_hook(lambda m, i, o: calls.append(1))
    try:
        together = _engine(batch_size=3).run(vlm, build_variants(names, params))
    finally:
        handle.remove()
    assert len(calls) == 4  # 10 images in batches of 3: one head pass per batch
    separate = {
        "bb": ("bb", {}),
        "full@n_prototypes:4": ("full", {**FULL, "n_prototypes": 4}),
        "full@n_prototypes:6@alpha:2.0": ("full", {**FULL, "n_prototypes": 6, "alpha": 2.0}),
        "lite@upscale:1": ("lite", {"alpha": 10.0, "upscale": 1}),
    }
    for name, (variant, kwargs) in separate.items():
        alone = _engine(batch_size=3).run(vlm, {variant: build_variant(variant, **kwargs)})
        assert torch.equal(together.metrics[name].confusion, alone.metrics[variant].confusion), name
    assert "val/ovss/synthetic/miou_full@n_prototypes:4" in together.scores()
    with pytest.raises(ValueError, match=r"expected <variant>@<key>:<value>"):
        build_variants(["full@n_prototypes=4"])


@pytest.mark.parametrize(
    ("overrides", "error", "message"),
    [
        (["task=scannet3d", "dataset=scannet", "dataset.path=/nonexistent/scannet"],
         FileNotFoundError, r"dataset\.path='/nonexistent/scannet': no such folder"),
        (["task=scannet3d", "dataset=replica", "dataset.path=/nonexistent/replica"],
         FileNotFoundError, r"dataset\.path: no folder '/nonexistent/replica' \(download: "
         r"NICE-SLAM's Replica, .*\); set dataset\.path$"),
        (["task=scannet3d", "dataset=tartanair", "dataset.path=/nonexistent/tartanair"],
         FileNotFoundError, r"dataset\.path: no folder '/nonexistent/tartanair' \(download: "
         r"TartanGround"),
        (["dataset=orad3d", "dataset.path=/nonexistent/orad"],
         FileNotFoundError, r"dataset\.path='/nonexistent/orad': no /nonexistent/orad/"),
        (["dataset=ade20k", "dataset.path=./no/such/ade"],
         FileNotFoundError, r"dataset\.path='\./no/such/ade' does not exist"),
        (["dataset=synthetic", "variants=[full+prior]", "prior=sam2",
          "prior.model=/nonexistent/sam"],
         FileNotFoundError, r"prior\.model='/nonexistent/sam': no such directory"),
    ],
)  # fmt: skip
def test_a_missing_dataset_or_prior_model_fails_before_the_encoder_loads(
    monkeypatch, tmp_path, overrides, error, message
):
    """resireg-eval checks the dataset folder and the prior's model before building the
    encoder (minutes for a large backbone): the error names the key, no encoder is built."""
    from hydra import compose, initialize_config_dir

    import resireg.models
    from resireg_train.cli.eval import evaluate
    from resireg_train.config.paths import CONFIG_DIR

    def no_encoder(*args, **kwargs):
        raise AssertionError("the encoder was built before the sources were checked")

    monkeypatch.setattr(resireg.models, "build_encoder", no_encoder)
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        # model_path: a repo id's form passes the export check (the encoder is never built)
        cfg = compose("eval", ["model_path=owner/x", f"paths.output_dir={tmp_path}", *overrides])
    with pytest.raises(error, match=message):
        evaluate(cfg)


def test_too_many_prototypes_for_a_batch_name_the_variant_and_the_batch_of_images():
    engine = _engine(batch_size=4)  # 10 images of 48 x 64 px (3 x 4 patches): batches 4, 4, 2
    with pytest.raises(ValueError) as err:
        engine.check_variants(build_variants(["full@n_prototypes:97"]), "variants")
    assert str(err.value) == (
        "variants.full@n_prototypes:97: n_prototypes=97 exceeds the number of points N=96 "
        "(B*Hv*s*Wv*s for B=2 intermediates of 3 x 4, upscale=2); dataset 'synthetic' with "
        "batch_size=4 has a batch of 2 images of 48 x 64 px"
    )


def _poison_call(monkeypatch, encoder, call: int, field: str):
    """Make the ``call``-th ``encode`` (0-based) of ``encoder`` return one NaN in ``field``."""
    real = encoder.encode
    calls = []

    def encode(x):
        out = real(x)
        calls.append(len(calls))
        if calls[-1] == call:
            bad = getattr(out, field).clone()
            bad[0, 0, 0, 0] = float("nan")
            out = out._replace(**{field: bad})
        return out

    monkeypatch.setattr(encoder, "encode", encode)


@pytest.mark.parametrize("field", ["language", "intermediates"])
def test_a_non_finite_encoder_batch_is_skipped_counted_and_not_scored(
    vlm, monkeypatch, caplog, field
):
    """One NaN in the encoder's output of the second batch: that batch's 3 images are
    skipped (named, with the reason, in the record results.json gets and in the log) and
    the scores are those of the other batches alone (sklearn's confusion over
    encode_image + predict, image by image). Before the check, Full's whole batch scored
    NaN features as class 0 and a NaN in the intermediates failed the run."""
    from resireg_train.evaluation.ovss.task import OVSSTask

    engine = _engine(batch_size=3)
    batches = engine.dataset.batches(3)
    _poison_call(monkeypatch, vlm, 1, field)
    variants = build_variants(["bb", "full"], {"full": FULL})
    result = engine.run(vlm, variants)
    monkeypatch.undo()
    poisoned = batches[1]
    assert result.images == 10 - len(poisoned) and result.batch_sizes == {1: 1, 3: 2}
    ds = engine.dataset
    assert [s.file for s in result.skipped_samples] == [ds.describe(i) for i in poisoned]
    for s in result.skipped_samples:
        assert s.reason.startswith(f"encoder output {field} holds 1 non-finite value")
    protos = engine.prototypes(vlm)
    for name, kwargs in (("bb", {}), ("full", FULL)):
        expected = np.zeros((8, 8), dtype=np.int64)
        for batch in batches:
            if batch == poisoned:
                continue
            images = torch.stack([ds[i]["image"] for i in batch])
            dense = vlm.encode_image(images, name, **kwargs)
            for j, i in enumerate(batch):
                label = ds[i]["label"]
                pred = predict(dense[j : j + 1], protos, tuple(label.shape))
                expected += confusion_matrix(label.flatten(), pred.flatten(), labels=range(8))
        assert np.array_equal(result.metrics[name].confusion.numpy(), expected), name
    task = OVSSTask.__new__(OVSSTask)  # results() reads only its cache
    task.cache = None
    with caplog.at_level("WARNING"):
        record = task.results(result)
    assert record["skipped"] == 3 and record["batch_sizes"] == {"1": 1, "3": 2}
    assert [s["file"] for s in record["skipped_samples"]] == [ds.describe(i) for i in poisoned]
    assert f"skipped 3 of 10 images ({ds.describe(poisoned[0])}: encoder output" in caplog.text
