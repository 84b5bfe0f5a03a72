"""The "adding a ..." recipes of docs/architecture.md, done in a copy of the project: each edits
exactly the files its recipe names (counted by comparing the copy with the checkout), and the
new component then runs through ``resireg-eval`` with no other edit.

- a variant: its module, its table entry, its defaults block (3 files);
- a 3D metric: its scorer's module and its table entry (2 files);
- a distillation teacher: its module, its table entry, its conf file (3 files; it trains);
- a text tower: its builder's module, its table entry, its conf file (3 files).

The encoder recipe (module, entry point, conf file) is followed from outside the project in
``tests/resireg/specs/test_specs.py``, the task and dataset recipes in ``tests/resireg_train/evaluation/test_tasks.py``, the map
source recipe in ``tests/resireg/sources/test_sources.py``, the report section recipe in
``tests/resireg_train/report/test_report.py``."""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import sys
from pathlib import Path

import pytest
import yaml

from helpers.paths import ROOT, TESTS
from helpers.run import run

TEST_CONF = TESTS / "conf"
pytestmark = pytest.mark.slow


def _copy(tmp_path: Path) -> Path:
    copy = tmp_path / "project"
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "outputs", "mlruns")
    for part in ("src", "conf"):
        shutil.copytree(ROOT / part, copy / part, ignore=ignore)
    return copy


def _changed(copy: Path) -> list[str]:
    """The files of ``copy`` that differ from the checkout's (new files included)."""
    changed = []
    for part in ("src", "conf"):
        for path in sorted((copy / part).rglob("*")):
            if path.is_dir() or "__pycache__" in path.parts or ".egg-info" in str(path):
                continue
            original = ROOT / path.relative_to(copy)
            if not original.is_file() or not filecmp.cmp(path, original, shallow=False):
                changed.append(str(path.relative_to(copy)))
    return sorted(changed)


def _append(path: Path, text: str) -> None:
    path.write_text(path.read_text() + text)


def _env(copy: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(copy / "src"), *sys.path]),
            "RESIREG_CONFIG_DIR": str(copy / "conf")}  # fmt: skip


def test_adding_a_variant_is_three_files(tmp_path, tiny_export):
    """A variant that scales the language tokens' contrast (``sharp``, one parameter ``gain``):
    the module, the entry (with its rule), the defaults block. ``resireg-eval`` scores it beside
    ``bb``; its parameter's rule refuses a bad value naming the key."""
    copy = _copy(tmp_path)
    (copy / "src" / "resireg" / "sharp.py").write_text("""
import torch.nn.functional as F
from torch import nn

from resireg.specs.variants import check_variant_kwargs


class Sharp(nn.Module):
    def __init__(self, gain: float = 2.0):
        super().__init__()
        check_variant_kwargs("sharp", {"gain": gain})
        self.gain = gain

    def forward(self, intermediates, language, prior=None):
        return F.normalize(language.float().sign() * language.float().abs() ** self.gain, dim=1)
""")
    table = copy / "src" / "resireg" / "specs" / "variants.py"
    text = table.read_text()
    anchor = '    ),\n    where="resireg.specs.variants",\n)'
    assert anchor in text
    table.write_text(
        text.replace(
            anchor,
            """        VariantSpec("sharp", "resireg.sharp:Sharp", "Sharp", "Sharp",
                    {"gain": number(0, strict=True, finite=True)}),
"""
            + anchor,
        )
    )
    _append(copy / "conf" / "resireg" / "default.yaml", "\nsharp:\n  gain: 2.0\n")
    assert _changed(copy) == ["conf/resireg/default.yaml", "src/resireg/sharp.py",
                              "src/resireg/specs/variants.py"]  # fmt: skip
    args = ["resireg-eval", "encoder=tiny_vlm", f"model_path={tiny_export}", "dataset=synthetic",
            "dataset.size=4", "num_workers=0", "batch_size=2", "variants=[bb,sharp]",
            f"hydra.searchpath=[file://{TEST_CONF}]"]  # fmt: skip
    scores = {}
    for gain in (2.0, 1.0):
        out = tmp_path / f"gain{gain}"
        run(*args, f"sharp.gain={gain}", f"hydra.run.dir={out}", env=_env(copy))
        final = json.loads((out / "results.json").read_text())["final"]
        scores[gain] = {k.rsplit("_", 1)[0]: (final[k], final.get(k[: -len("bb")] + "sharp"))
                        for k in final if k.endswith("_bb")}  # fmt: skip
    # gain 1 keeps the language tokens as they are (sign(x) |x| = x): Sharp's scores are then
    # bb's, each one, computed through its own entry; gain 2 changes the ranking of classes.
    assert "val/ovss/synthetic/miou" in scores[1.0], scores
    for key, (bb, sharp) in scores[1.0].items():
        assert sharp == pytest.approx(bb, rel=1e-6, nan_ok=True), key
    bb, sharp = scores[2.0]["val/ovss/synthetic/miou"]
    assert sharp != pytest.approx(bb, rel=1e-6), scores[2.0]
    bad = run(*args, "sharp.gain=-1", f"hydra.run.dir={tmp_path / 'bad'}", env=_env(copy),
              check=False)  # fmt: skip
    assert bad.returncode != 0
    assert "sharp.gain=-1" in bad.stderr + bad.stdout


def test_adding_a_3d_metric_is_two_files(tmp_path, tiny_export):
    """A voxel metric (``recall``: the mean over classes of tp / ground-truth voxels): its
    scorer's module and its entry. ``resireg-eval task=scannet3d dataset.metric=recall``
    scores with it: its pooled mIoU is the mean of its per-class values, and a run of the same
    job under ``rayfronts`` gives each class an IoU no larger (tp / (tp + fn + fp) <= tp /
    (tp + fn)), the two differing where the map predicts a class falsely."""
    from resireg_train.data.scannet_room import SyntheticRoom, write_scene

    copy = _copy(tmp_path)
    (copy / "src" / "resireg" / "recall.py").write_text("""
import math


def recall(matrix, metric):
    cm = matrix.double()
    k = cm.shape[0]
    tp, freq = cm.diagonal(), cm.sum(1)
    iou = [float(t / f) if f > 0 else math.nan for t, f in zip(tp, freq)]
    kept = [v for v in iou if not math.isnan(v)]
    total = float(freq.sum())
    return {"miou": sum(kept) / len(kept) if kept else math.nan,
            "fmiou": sum(float(f) / total * v for f, v in zip(freq, iou) if not math.isnan(v)),
            "acc": float(tp.sum()) / total if total else math.nan, "iou": iou}
""")
    table = copy / "src" / "resireg" / "specs" / "metrics.py"
    text = table.read_text()
    anchor = '    ),\n    where="resireg.specs.metrics",\n)  # fmt: skip'
    assert anchor in text
    table.write_text(
        text.replace(
            anchor,
            """        MetricSpec("recall", "resireg.recall:recall", "voxel", ("miou", "fmiou", "acc", "iou"),
                   ("miou", "fmiou", "acc"), "per-class recall of the voxels"),
"""
            + anchor,
        )
    )
    assert _changed(copy) == ["src/resireg/recall.py", "src/resireg/specs/metrics.py"]
    root = tmp_path / "scannet"
    write_scene(root, "synthetic0000_00", SyntheticRoom())
    out = tmp_path / "out"
    run("resireg-eval", "task=scannet3d", "dataset=scannet_synthetic", f"dataset.path={root}",
        "dataset.metric=recall", "encoder=tiny_vlm", f"model_path={tiny_export}",
        "num_workers=0", "variants=[bb]", f"hydra.searchpath=[file://{TEST_CONF}]",
        f"hydra.run.dir={out}", env=_env(copy))  # fmt: skip
    record = json.loads((out / "results.json").read_text())
    assert record["protocol"]["settings"]["metric"] == "recall"
    recall = record["per_class_iou"]["bb"]
    kept = [v for v in recall.values() if v is not None]
    miou = record["final"]["val/scannet3d/scannet_synthetic/pooled_miou_bb"]
    assert miou == pytest.approx(sum(kept) / len(kept))
    run("resireg-eval", "task=scannet3d", "dataset=scannet_synthetic", f"dataset.path={root}",
        "encoder=tiny_vlm", f"model_path={tiny_export}", "num_workers=0", "variants=[bb]",
        f"hydra.searchpath=[file://{TEST_CONF}]", f"hydra.run.dir={tmp_path / 'iou'}",
        env=_env(copy))  # fmt: skip
    iou = json.loads((tmp_path / "iou" / "results.json").read_text())["per_class_iou"]["bb"]
    assert recall.keys() == iou.keys()
    pairs = [(recall[c], iou[c]) for c in iou if iou[c] is not None and recall[c] is not None]
    assert pairs and all(r >= i - 1e-12 for r, i in pairs)
    assert any(r > i for r, i in pairs)


def _in_copy(copy: Path, code: str) -> dict:
    """Run ``code`` (which prints one JSON line last) in a process that imports the copy."""
    out = run(sys.executable, "-c", code, env=_env(copy), timeout=600)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_adding_a_teacher_is_three_files(tmp_path):
    """A distillation teacher (``pool``: the image's mean colour over cells of ``cell`` pixels):
    its module, its entry in resireg_train.training.specs, its conf/model/teacher/ file.
    ``model/teacher=pool`` selects it: the config check accepts it (and names the closest kind
    for a typo), the teacher built from the composed config gives the cell means (numpy), and
    ``resireg-train`` trains an epoch distilling from it."""
    copy = _copy(tmp_path)
    (copy / "src" / "resireg_train" / "training" / "pool_teacher.py").write_text("""
import torch.nn.functional as F

from resireg_train.training.teacher import FrozenTeacher


class PoolTeacher(FrozenTeacher):
    def __init__(self, cell: int = 8, device=None):
        super().__init__()
        self.cell, self.out_dim = cell, 3
        self.freeze()
        self.to(device or "cpu")

    def dense(self, images):
        return F.avg_pool2d(images, self.cell)
""")
    table = copy / "src" / "resireg_train" / "training" / "specs.py"
    text = table.read_text()
    anchor = '    ),\n    name="kind",\n    where="resireg_train.training.specs",'
    assert anchor in text
    table.write_text(text.replace(anchor, """        TeacherSpec("pool", "resireg_train.training.pool_teacher:PoolTeacher",
                    "the mean colour of image cells"),
""" + anchor))  # fmt: skip
    (copy / "conf" / "model" / "teacher" / "pool.yaml").write_text("kind: pool\ncell: 8\n")
    assert _changed(copy) == ["conf/model/teacher/pool.yaml",
                              "src/resireg_train/training/pool_teacher.py",
                              "src/resireg_train/training/specs.py"]  # fmt: skip
    found = _in_copy(
        copy,
        """
import json, numpy as np, torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from resireg.errors import ConfigError
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.checks.train import validate
from resireg_train.training.teacher import build_teacher
with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
    cfg = compose("train", overrides=["experiment=smoke", "model/teacher=pool"])
    typo = compose("train", overrides=["experiment=smoke", "model.teacher.kind=pol"])
validate(cfg)
try:
    validate(typo)
    error = ""
except ConfigError as err:
    error = str(err)
teacher = build_teacher(**OmegaConf.to_container(cfg.model.teacher))
images = torch.rand(2, 3, 32, 48, generator=torch.Generator().manual_seed(0))
out = teacher(images, (4, 6)).numpy()
reference = images.numpy().reshape(2, 3, 4, 8, 6, 8).mean(axis=(3, 5))
print(json.dumps({"kind": type(teacher).__name__, "error": error,
                  "difference": float(np.abs(out - reference).max())}))
""",
    )
    assert found["kind"] == "PoolTeacher" and found["difference"] < 1e-6
    assert "model.teacher.kind='pol': expected one of [" in found["error"]
    assert "'pool'" in found["error"]
    out = tmp_path / "train"
    run("resireg-train", "experiment=smoke", "model/teacher=pool", "trainer.max_epochs=1",
        "~callbacks.progress_bar", f"hydra.run.dir={out}", env=_env(copy))  # fmt: skip
    record = json.loads((out / "results.json").read_text())
    assert record["status"] == "completed"
    assert "train/loss_distill" in record["final"]  # the pool teacher's distillation loss
    saved = yaml.safe_load((out / ".hydra" / "config.yaml").read_text())
    assert saved["model"]["teacher"] == {"kind": "pool", "cell": 8}


def test_adding_a_text_tower_is_three_files(tmp_path):
    """A text tower (``small``: a one-layer random open_clip text transformer): its builder's
    module, its entry in resireg.specs.text, its conf/model/text/ file. ``model/text=small``
    selects it: the config check accepts it, and the VLM built from the composed config has the
    builder's tower (its outputs equal the same seeded tower built directly)."""
    copy = _copy(tmp_path)
    (copy / "src" / "resireg" / "models" / "vlm" / "small_text.py").write_text("""
from resireg.models.vlm.text import CAPTION_CACHE_SIZE, FrozenTextTower


def small_tower(width=32, heads=2, out_dim=48, seed=0, cache_size=CAPTION_CACHE_SIZE):
    tiny = FrozenTextTower.tiny(width=width, layers=1, heads=heads, out_dim=out_dim,
                                context_length=16, seed=seed)
    spec = {"kind": "small", "width": width, "heads": heads, "out_dim": out_dim, "seed": seed}
    return FrozenTextTower(tiny.tower, tiny.tokenizer, out_dim, spec, cache_size)
""")
    table = copy / "src" / "resireg" / "specs" / "text.py"
    text = table.read_text()
    anchor = '    ),\n    name="kind",\n    where="resireg.specs.text",'
    assert anchor in text
    table.write_text(text.replace(anchor, """        TextSpec("small", "resireg.models.vlm.small_text:small_tower", "one layer"),
""" + anchor))  # fmt: skip
    (copy / "conf" / "model" / "text" / "small.yaml").write_text(
        "kind: small\nwidth: 32\nheads: 2\nout_dim: 48\nseed: 3\ncache_size: 200000\n"
    )
    assert _changed(copy) == ["conf/model/text/small.yaml", "src/resireg/models/vlm/small_text.py",
                              "src/resireg/specs/text.py"]  # fmt: skip
    found = _in_copy(
        copy,
        """
import json, torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from resireg.models import ResiregVLM
from resireg.models.vlm.text import FrozenTextTower
from resireg_train.config.paths import CONFIG_DIR
from resireg_train.checks.train import validate
with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
    cfg = compose("train", overrides=["experiment=smoke", "model/text=small"])
validate(cfg)
model = OmegaConf.to_container(cfg.model, resolve=True)
vlm = ResiregVLM.build(model["backbone"], model["head"], model["text"])
direct = FrozenTextTower.tiny(width=32, layers=1, heads=2, out_dim=48, context_length=16, seed=3)
texts = ["a chair", "a wall"]
same = torch.equal(vlm.text(texts, cache=False), direct(texts, cache=False))
print(json.dumps({"spec": vlm.text.spec(), "same": same, "width": vlm.text_proj.in_features}))
""",
    )
    assert found["same"] and found["width"] == 48
    assert found["spec"]["kind"] == "small" and found["spec"]["seed"] == 3
