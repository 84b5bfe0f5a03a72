"""resireg-eval's tasks (resireg_train.evaluation.specs, resireg_train.evaluation.base): a task
registered through the table runs through the eval entry point; the 2D and 3D tasks share one
class-prototype text path; the fields every task writes (elbo_prototypes) are written by the
3D task too."""

import json
from collections import Counter
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from resireg.errors import ConfigError
from resireg.method.variants import build_variants
from resireg.ovss import average_prompts, class_prompts
from resireg_train.checks.eval import validate_eval
from resireg_train.cli.eval import evaluate
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.data.segmentation import build_segmentation_set
from resireg_train.data.specs import DATASET_SPECS, dataset_conf
from resireg_train.evaluation.base import EvalTask, require_task
from resireg_train.evaluation.engine import ClassPrototypes, eval_loader
from resireg_train.evaluation.specs import TASK_SPECS, TaskSpec

SYNTHETIC = dataset_conf("synthetic", size=5, image_size=[32, 48], seed=3, short_side=32)


def _compose(*overrides):
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        return compose("eval", overrides=list(overrides))


# -------------------------------------------------------------- a throwaway task
class _LabelFrequencies:
    """The throwaway task's result: each class's share of the labelled pixels."""

    def __init__(self, counts: np.ndarray, images: int, classes) -> None:
        self.counts, self.images, self.classes = counts, images, classes

    def scores(self):
        share = self.counts / self.counts.sum()
        return {f"val/frequency/{c}": float(s) for c, s in zip(self.classes, share, strict=True)}

    def per_class_iou(self):
        return {"share": (self.counts / self.counts.sum()).tolist()}


class _FrequencyTask(EvalTask):
    """A task outside the project's two: the labels' class frequencies of a segmentation set,
    read through the shared loader (no encoder pass)."""

    def build(self, encoder, variants):
        self.dataset = build_segmentation_set(self.params["dataset"], 16, key="dataset")
        self.classes = self.dataset.classes
        return {"protocol": {"name": "frequency", "settings": {}}}

    def run(self, encoder, variants, timer):
        from resireg_train.data.segmentation import collate_segmentation

        counts, images = np.zeros(len(self.classes), dtype=np.int64), 0
        loader = eval_loader(self.dataset, self.dataset.batches(2), collate_segmentation, 0)
        with timer("count"):
            for batch in loader:
                for label in batch["label"]:
                    valid = label[label != self.dataset.ignore_index]
                    counts += np.bincount(valid.numpy().ravel(), minlength=len(self.classes))
                    images += 1
        return _LabelFrequencies(counts, images, self.classes)

    def results(self, result):
        return {"skipped": 0, "skipped_samples": [], "labelled_pixels": int(result.counts.sum())}


def test_a_task_registered_through_the_table_runs_through_resireg_eval(
    monkeypatch, tmp_path, tiny_export
):
    """One entry in resireg_train.evaluation.specs.TASK_SPECS (a task class outside the project), and
    its name among the tasks of the dataset table's entry it scores (resireg_train.data.specs),
    are all resireg-eval needs: the config check accepts the task, the entry point runs its
    check/build/run/results, and results.json holds its scores (compared with the class
    frequencies counted here from the dataset's own items, numpy), its own field and the shared
    ones. Without the entry the task is a ConfigError naming task=<value> and the known tasks;
    without the dataset's naming it, one naming the task that scores that kind."""
    overrides = [f"model_path={tiny_export}", "dataset=synthetic", "dataset.size=5",
                 "dataset.image_size=[32,48]", "dataset.seed=3", "dataset.short_side=32",
                 "num_workers=0", "variants=[bb]", f"paths.output_dir={tmp_path / 'run'}"]  # fmt: skip
    cfg = _compose("task=frequency", *overrides)
    with pytest.raises(
        ConfigError, match=r"task='frequency': expected one of \['ovss', 'scannet3d'\]"
    ):
        validate_eval(cfg)
    with pytest.raises(
        ConfigError, match=r"task='frequency': expected one of \['ovss', 'scannet3d'\]"
    ):
        require_task("frequency")
    target = f"{__name__}:{_FrequencyTask.__name__}"
    monkeypatch.setitem(TASK_SPECS, "frequency", TaskSpec(
        "frequency", target, "image", prior=False, layers=False, summary="class frequencies",
    ))  # fmt: skip
    with pytest.raises(ConfigError, match=r"task='frequency': dataset\.kind='synthetic' is "
                       r"scored by task=ovss"):  # fmt: skip
        validate_eval(cfg)
    # the datasets it scores name it (the dataset table)
    synthetic = DATASET_SPECS["synthetic"]
    monkeypatch.setitem(DATASET_SPECS, "synthetic",
                        replace(synthetic, tasks=(*synthetic.tasks, "frequency")))  # fmt: skip
    record = evaluate(cfg)
    on_disk = json.loads((tmp_path / "run" / "results.json").read_text())
    assert on_disk["status"] == "completed" and record["status"] == "completed"
    assert on_disk["params"]["task"] == "frequency"
    dataset = build_segmentation_set(SYNTHETIC, 16)
    counts = np.zeros(len(dataset.classes), dtype=np.int64)
    for i in range(len(dataset)):
        label = dataset[i]["label"].numpy().ravel()
        counts += np.bincount(label[label != dataset.ignore_index], minlength=len(counts))
    expected = counts / counts.sum()
    final = on_disk["final"]
    assert final == pytest.approx(
        {f"val/frequency/{c}": s for c, s in zip(dataset.classes, expected, strict=True)}
    )
    assert on_disk["per_class_iou"]["share"] == pytest.approx(
        dict(zip(dataset.classes, expected, strict=True))
    )
    assert on_disk["images"] == len(dataset) == 5 and on_disk["labelled_pixels"] == counts.sum()
    assert on_disk["protocol"] == {"name": "frequency", "settings": {}}
    assert "count" in on_disk["seconds"] and "elbo_prototypes" not in on_disk


# ---------------------------------------------------------- a throwaway dataset kind
def _stripes_source(name, spec, key, common):
    """The throwaway kind's builder: ``count`` images of ``height`` x 2 ``height`` px, the left
    half one class, the right half the other (each image's colours its own)."""
    from PIL import Image

    from resireg_train.data.segmentation import SegmentationSet

    h = int(spec["height"])

    def load(i):
        image = np.zeros((h, 2 * h, 3), np.uint8)
        image[:, :h] = (200, 20 * i, 0)
        image[:, h:] = (0, 20 * i, 200)
        label = np.zeros((h, 2 * h), np.uint8)
        label[:, h:] = 1
        return Image.fromarray(image), label

    return SegmentationSet(name, ("red", "blue"), load, lambda i: (h, 2 * h),
                           int(spec["count"]), **common)  # fmt: skip


def test_a_dataset_kind_registered_through_the_table_runs_through_resireg_eval(
    monkeypatch, tmp_path, tiny_export
):
    """One builder (here, outside the project), one entry in the dataset table
    (resireg_train.data.specs.DATASET_SPECS) and one conf/dataset/ file (here on Hydra's search
    path) are all resireg-eval needs for a new dataset: the config check accepts the kind and
    its keys, task=ovss builds and scores it, and results.json holds its scores under its name
    with its classes and image count (the builder's, written here). Without the entry the kind
    is a ConfigError naming dataset.kind and the known kinds; with it, a key the kind does not
    read is one naming the key and the allowed keys, and a missing one names dataset.<key>."""
    from resireg_train.data.specs import DatasetSpec

    conf = tmp_path / "conf" / "dataset"
    conf.mkdir(parents=True)
    (conf / "stripes.yaml").write_text(
        # the 2D protocol's keys from conf/protocol/paper.yaml (docs/architecture.md)
        "defaults:\n  - /protocol/paper@_here_\n  - _self_\n"
        "name: stripes\nkind: stripes\ncount: 3\nheight: 32\nshort_side: 32\nlimit: null\n"
    )
    overrides = [f"model_path={tiny_export}", "dataset=stripes", "num_workers=0",
                 "batch_size=2", "variants=[bb,lite]", f"paths.output_dir={tmp_path / 'run'}",
                 f"hydra.searchpath=[file://{tmp_path / 'conf'}]"]  # fmt: skip
    cfg = _compose(*overrides)
    with pytest.raises(ConfigError, match=r"dataset\.kind='stripes': expected one of "
                       r"\['synthetic', 'ade20k', 'orad3d', 'voc', .*'scannet'\]"):  # fmt: skip
        validate_eval(cfg)
    from resireg_train.data.specs import SEGMENTATION_KEYS

    keys = (*SEGMENTATION_KEYS, "count", "height")
    monkeypatch.setitem(DATASET_SPECS, "stripes", DatasetSpec(
        "stripes", f"{__name__}:{_stripes_source.__name__}", keys, ("ovss",),
        "two-class stripes",
    ))  # fmt: skip
    validate_eval(cfg)
    with pytest.raises(ConfigError, match=r"dataset: unknown keys \['width'\] for kind "
                       r"'stripes' \(\['antialias', .*'count', 'height', 'kind', 'limit', "
                       r"'long_side', 'name', .*'upsample'\]\)"):  # fmt: skip
        validate_eval(_compose(*overrides, "+dataset.width=4"))
    with pytest.raises(ConfigError, match=r"dataset: no dataset\.height"):
        validate_eval(_compose(*overrides, "~dataset.height"))
    with pytest.raises(ConfigError, match=r"task='scannet3d': dataset\.kind='stripes' is "
                       r"scored by task=ovss"):  # fmt: skip
        validate_eval(_compose(*overrides, "task=scannet3d"))
    record = evaluate(cfg)
    on_disk = json.loads((tmp_path / "run" / "results.json").read_text())
    assert on_disk["status"] == "completed" and record["status"] == "completed"
    assert on_disk["images"] == 3 and on_disk["params"]["dataset"]["kind"] == "stripes"
    for variant in ("bb", "lite"):
        assert 0.0 <= on_disk["final"][f"val/ovss/stripes/miou_{variant}"] <= 1.0
        assert set(on_disk["per_class_iou"][variant]) == {"red", "blue"}
    assert on_disk["protocol"]["name"] == "ovss/stripes"


# ---------------------------------------------------- the shared text path
def test_the_3d_tasks_class_prototypes_are_the_2d_tasks(tmp_path, tiny_export):
    """MappingEngine and OVSSEngine take their class prototypes from one text path
    (ClassPrototypes); for the same class names and encoder both equal the prompts embedded
    by the encoder's text_features, projected by dense_text and averaged per class (computed
    here); the 3D task builds no OVSSEngine."""
    from resireg.models import ResiregVLM
    from resireg_train.data.scannet import ScanNetFrames
    from resireg_train.data.scannet_room import SyntheticRoom, write_scene
    from resireg_train.evaluation.mapping.engine import MappingEngine
    from resireg_train.evaluation.ovss import engine as ovss_engine

    vlm = ResiregVLM.from_pretrained(tiny_export).eval()
    room = SyntheticRoom()
    write_scene(tmp_path, "synthetic0000_00", room)
    frames = ScanNetFrames(tmp_path, ["synthetic0000_00"], frame_skip=0, image_size=room.image_size,
                           patch_size=vlm.input_rule.patch_size)  # fmt: skip

    def refuse(*args, **kwargs):
        raise AssertionError("the 3D task built an OVSSEngine")

    original = ovss_engine.OVSSEngine.__init__
    ovss_engine.OVSSEngine.__init__ = refuse
    try:
        three_d = MappingEngine(frames, batch_size=3, voxel_size=0.1)
    finally:
        ovss_engine.OVSSEngine.__init__ = original
    # the 2D task on the 3D set's class names and the 80 templates (its text path reads
    # nothing else of a dataset)
    names = SimpleNamespace(classes=tuple(frames.classes), templates="openai_imagenet")
    two_d = ovss_engine.OVSSEngine(names, batch_size=2)
    assert isinstance(three_d.text, ClassPrototypes) and isinstance(two_d.text, ClassPrototypes)
    with torch.no_grad():
        prompts = class_prompts(frames.classes)
        reference = average_prompts(vlm.dense_text(vlm.text_features(prompts)), len(frames.classes))
    got_3d, got_2d = three_d.prototypes(vlm), two_d.prototypes(vlm)
    assert got_3d.shape == (len(frames.classes), reference.shape[1])
    torch.testing.assert_close(got_3d, reference, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got_3d, got_2d, rtol=0, atol=0)
    assert three_d.tower_calls == two_d.tower_calls == 1


# ------------------------------------------- the shared results: elbo counts in 3D
@pytest.mark.slow
def test_scannet3d_results_hold_the_elbo_prototype_counts(tmp_path, tiny_export):
    """task=scannet3d with a full@n_prototypes:elbo configuration writes elbo_prototypes (the
    count each batch was given), as task=ovss does: equal to the counts of the engine run here
    on the same frames and settings, one per batch of the scene (ScanNetFrames.batches)."""
    from resireg.models import ResiregVLM
    from resireg_train.data.scannet import ScanNetFrames
    from resireg_train.data.scannet_room import SyntheticRoom, write_scene
    from resireg_train.evaluation.mapping.engine import MappingEngine

    room = SyntheticRoom()
    root = tmp_path / "scannet"
    write_scene(root, "synthetic0000_00", room)
    name, candidates = "full@n_prototypes:elbo", [2, 4, 8]
    out = tmp_path / "run"
    cfg = _compose(f"model_path={tiny_export}", "task=scannet3d", "dataset=scannet_synthetic",
                   f"dataset.path={root}", "num_workers=0", "batch_size=3",
                   f"variants=[bb,{name}]", f"full.elbo_candidates=[{','.join(map(str, candidates))}]",
                   f"paths.output_dir={out}")  # fmt: skip
    evaluate(cfg)
    r = json.loads((out / "results.json").read_text())
    assert r["status"] == "completed" and r["params"]["task"] == "scannet3d"
    vlm = ResiregVLM.from_pretrained(tiny_export)
    frames = ScanNetFrames(root, ["synthetic0000_00"], frame_skip=0, image_size=room.image_size,
                           patch_size=vlm.input_rule.patch_size, name="scannet_synthetic")  # fmt: skip
    params = {"full": {"n_prototypes": "elbo", "elbo_candidates": candidates, "n_components": None}}
    variants = build_variants([name], params)
    MappingEngine(frames, batch_size=3, voxel_size=0.1).run(vlm, variants)
    expected = dict(sorted(Counter(str(n) for n in variants[name].chosen).items(),
                           key=lambda c: int(c[0])))  # fmt: skip
    assert r["elbo_prototypes"] == {name: expected}
    assert sum(expected.values()) == len(frames.batches(3)) and set(expected) <= set(
        map(str, candidates)
    )
