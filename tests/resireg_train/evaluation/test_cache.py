"""The on-disk feature cache: exact outputs, invalidation, partial fills, and resireg-eval."""

import json
import os

import pytest
import torch

from helpers.run import evaluate, run
from helpers.tiny import TINY_BACKBONE, TINY_HEAD, TINY_TEXT
from resireg.method.variants import build_variants
from resireg.models import ResiregVLM
from resireg.models.factory import weights_fingerprint
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.data.specs import dataset_conf
from resireg_train.evaluation.cache import FeatureCache
from resireg_train.evaluation.ovss.engine import OVSSEngine, StageTimer

SPEC = dataset_conf("synthetic", size=6, image_size=[40, 56], seed=3, noise=12.0, short_side=32)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()


def _cache(root, model, spec=SPEC, precision="32", **kw):
    dataset = build_segmentation_set(spec, model.input_rule.patch_size)
    key = FeatureCache.key_for(model, {"kind": "tiny"}, spec, model.input_rule.patch_size,
                               precision)  # fmt: skip
    return dataset, FeatureCache(root, key, dataset.describe, **kw)


class _Counting:
    """Counts the encoder's passes (the cache must make them unnecessary)."""

    def __init__(self, model):
        self.calls, self._encode = 0, model.encode

    def __call__(self, x):
        self.calls += 1
        return self._encode(x)


def test_cache_returns_exactly_the_encoders_outputs(tmp_path, model):
    dataset, cache = _cache(tmp_path, model, shard_images=4)
    engine = OVSSEngine(dataset, batch_size=2)
    engine.run(model, build_variants(["bb"]), cache=cache)
    assert len(cache) == len(dataset) and cache.bytes_written == cache.disk_bytes() > 0
    reread = FeatureCache(tmp_path, cache.key, dataset.describe)  # a later job: from disk
    for batch in engine.loader():
        expected = model.encode(model.input_rule.normalize(batch["image"]))
        got = reread.get(batch["index"])
        assert torch.equal(got.intermediates, expected.intermediates)
        assert torch.equal(got.language, expected.language)
        assert got.intermediates.dtype == expected.intermediates.dtype


def test_cached_pass_scores_identically_without_encoding(tmp_path, model, monkeypatch):
    dataset, cache = _cache(tmp_path, model)
    names = ["bb", "lite", "full@n_prototypes:6"]
    engine = OVSSEngine(dataset, batch_size=3)
    plain = engine.run(model, build_variants(names))
    engine.run(model, build_variants(names), cache=cache)  # fills
    counter = _Counting(model)
    monkeypatch.setattr(model, "encode", counter)
    timer = StageTimer()
    again = engine.run(model, build_variants(names), timer=timer, cache=FeatureCache(
        tmp_path, cache.key, dataset.describe))  # fmt: skip
    assert counter.calls == 0 and "encoder" not in timer.seconds and "cache" in timer.seconds
    for name in names:
        assert torch.equal(again.metrics[name].confusion, plain.metrics[name].confusion)


def test_any_change_of_weights_resolution_or_precision_is_a_new_key(tmp_path, model):
    _, cache = _cache(tmp_path, model)
    changed = ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()
    changed.load_state_dict(model.state_dict())
    assert weights_fingerprint(changed) == weights_fingerprint(model)
    with torch.no_grad():
        next(changed.parameters()).view(-1)[0] += 1e-3
    assert weights_fingerprint(changed) != weights_fingerprint(model)
    folders = {
        cache.folder,
        _cache(tmp_path, changed)[1].folder,
        _cache(tmp_path, model, spec={**SPEC, "short_side": 48})[1].folder,
        _cache(tmp_path, model, precision="bf16")[1].folder,
    }
    assert len(folders) == 4


@pytest.mark.slow
def test_new_weights_read_their_own_outputs_not_stale_ones(tmp_path, model):
    dataset, cache = _cache(tmp_path, model)
    engine = OVSSEngine(dataset, batch_size=2)
    engine.run(model, build_variants(["bb"]), cache=cache)
    changed = ResiregVLM.build(TINY_BACKBONE, TINY_HEAD, TINY_TEXT).eval()  # other weights
    _, fresh = _cache(tmp_path, changed)
    assert len(fresh) == 0 and fresh.get([0]) is None
    engine.run(changed, build_variants(["bb"]), cache=fresh)
    batch = next(iter(engine.loader()))
    expected = changed.encode(changed.input_rule.normalize(batch["image"]))
    assert torch.equal(fresh.get(batch["index"]).language, expected.language)


def test_partial_cache_encodes_only_what_is_missing(tmp_path, model, monkeypatch):
    dataset, cache = _cache(tmp_path, model, shard_images=2)
    engine = OVSSEngine(dataset, batch_size=2)
    first = next(iter(engine.loader()))  # an interrupted job: one batch stored
    cache.put(first["index"], model.encode(model.input_rule.normalize(first["image"])))
    assert len(FeatureCache(tmp_path, cache.key, dataset.describe)) == 2
    (cache.folder / "shard-broken.json").write_text("{not json")  # a torn listing is ignored
    counter = _Counting(model)
    monkeypatch.setattr(model, "encode", counter)
    resumed = FeatureCache(tmp_path, cache.key, dataset.describe)
    engine.run(model, build_variants(["bb"]), cache=resumed)
    assert counter.calls == len(dataset) // 2 - 1 and resumed.hits == 1


def test_an_entry_whose_file_changed_is_a_miss(tmp_path, model):
    dataset, cache = _cache(tmp_path, model)
    OVSSEngine(dataset, batch_size=2).run(model, build_variants(["bb"]), cache=cache)
    renamed = FeatureCache(tmp_path, cache.key, lambda i: f"other-{i}.jpg")
    assert renamed.get([0, 1]) is None and renamed.misses == 1


def test_resireg_eval_fills_then_reads_the_cache(tmp_path, tiny_export):
    """Three resireg-eval jobs, each its task run in this process (a fresh FeatureCache each,
    reading what the earlier job wrote to disk): the second reads the first's features, a
    third without the cache scores what the cached one scored."""
    args = [f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=6", "num_workers=0",
            "full.n_prototypes=6", f"feature_cache={tmp_path / 'cache'}"]  # fmt: skip
    results = []
    for job, variants in (("a", "[bb,full]"), ("b", "[full@n_prototypes:8]")):
        evaluate(*args, f"variants={variants}", f"paths.output_dir={tmp_path / job}")
        results.append(json.loads((tmp_path / job / "results.json").read_text()))
    first, second = results
    assert first["feature_cache"]["hits"] == 0 and first["feature_cache"]["images"] == 6
    assert second["feature_cache"]["misses"] == 0 and second["feature_cache"]["hits"] > 0
    assert "encoder" not in second["seconds"]
    # a job without the cache gives the cached job's score
    evaluate(*args[:-1], "variants=[full@n_prototypes:8]", f"paths.output_dir={tmp_path / 'c'}")
    plain = json.loads((tmp_path / "c" / "results.json").read_text())
    assert plain["final"] == second["final"]


def test_bad_feature_cache_value_names_the_key(tmp_path, tiny_export):
    proc = run("resireg-eval", f"model_path={tiny_export}", "dataset=synthetic",
               "feature_cache=3", f"hydra.run.dir={tmp_path}", check=False)  # fmt: skip
    assert proc.returncode != 0 and "feature_cache=3" in proc.stderr + proc.stdout


@pytest.mark.slow
def test_resireg_eval_names_sets_aside_and_re_encodes_a_damaged_shard(tmp_path, tiny_export):
    """A shard overwritten in place (same size: 0xFF over its second half) and, once
    re-encoded, the new shard truncated: each later job names it in a warning and in
    results.json, encodes its images again and scores what the clean cache gave."""
    cache = tmp_path / "cache"
    args = [f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=6", "num_workers=0",
            "variants=[bb,full]", "full.n_prototypes=6", f"feature_cache={cache}"]  # fmt: skip

    def job(name):
        proc = run("resireg-eval", *args, f"hydra.run.dir={tmp_path / name}")
        return proc.stdout + proc.stderr, json.loads((tmp_path / name / "results.json").read_text())

    def damage(how):
        (shard,) = cache.glob("*/shard-*.safetensors")
        size = shard.stat().st_size
        if how == "overwritten":  # same size, other bytes
            with open(shard, "r+b") as f:
                f.seek(size // 2)
                f.write(b"\xff" * (size - size // 2))
            assert shard.stat().st_size == size
            return shard, "content differs from its listing's digest"
        os.truncate(shard, size // 3)
        return shard, f"{size // 3} bytes, its listing says {size}"

    _, clean = job("clean")
    for how in ("overwritten", "truncated"):  # the second damages the re-encoded shard
        shard, reason = damage(how)
        said, results = job(how)
        assert f"damaged shard {shard} ({reason})" in said, said[-2000:]
        summary = results["feature_cache"]
        assert summary["damaged"] == [{"file": str(shard), "reason": reason}], how
        assert summary["damaged_shards"] == 1 and summary["hits"] == 0
        assert summary["bytes_written"] > 0  # its images were encoded and stored again
        assert results["status"] == "completed" and results["final"] == clean["final"], how
        assert shard.with_name(f"{shard.name}.damaged").is_file()  # set aside, never read again
        assert not shard.with_suffix(".json").exists()


def test_a_non_finite_batch_is_skipped_and_never_cached(tmp_path, model, monkeypatch):
    """The second batch's encoder output holds a NaN: its images are skipped samples, the
    cache stores the other batches only, and a later job reading the cache re-encodes just
    that batch (a clean encoder then scores it)."""
    dataset, cache = _cache(tmp_path, model)
    engine = OVSSEngine(dataset, batch_size=2)
    poisoned = dataset.batches(2)[1]
    real, calls = model.encode, []

    def encode(x):
        out = real(x)
        calls.append(1)
        if len(calls) == 2:
            out = out._replace(language=out.language.clone().fill_(float("nan")))
        return out

    monkeypatch.setattr(model, "encode", encode)
    result = engine.run(model, build_variants(["bb"]), cache=cache)
    monkeypatch.undo()
    assert [s.file for s in result.skipped_samples] == [dataset.describe(i) for i in poisoned]
    assert result.images == len(dataset) - len(poisoned)
    reread = FeatureCache(tmp_path, cache.key, dataset.describe)
    assert len(reread) == len(dataset) - len(poisoned) and reread.get(poisoned) is None
    counting = _Counting(model)
    monkeypatch.setattr(model, "encode", counting)
    again = engine.run(model, build_variants(["bb"]), cache=reread)
    assert counting.calls == 1 and again.skipped == 0 and again.images == len(dataset)
