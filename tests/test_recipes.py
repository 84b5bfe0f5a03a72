"""The "adding a ..." recipes of docs/architecture.md, done in a copy of the project: each edits
exactly the files its recipe names (counted by comparing the copy with the checkout), and the
new component then runs through ``resireg-eval`` with no other edit.

- a variant: its module, its table entry, its defaults block (3 files);
- a 3D metric: its scorer's module and its table entry (2 files).

The encoder recipe (module, entry point, conf file) is followed from outside the project in
``tests/test_specs.py``, the task and dataset recipes in ``tests/test_tasks.py``, the map
source recipe in ``tests/test_sources.py``."""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import sys
from pathlib import Path

import pytest

from _run import run

ROOT = Path(__file__).resolve().parents[1]
TEST_CONF = Path(__file__).parent / "conf"
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
