"""What the 3D semantic-mapping task scored (:class:`MappingResult`): per variant and scene the
voxel confusion matrix and the frame and voxel counts that
:class:`~resireg_train.evaluation.mapping.engine.MappingEngine` fills; the scores of the
task table's prefix (the mean over scenes, and the confusion pooled over them, by the metric
table's scorer), per scene, per class, and RayFronts' CSV files.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from resireg.mapping import metric as metrics
from resireg.specs.metrics import METRIC_SPECS
from resireg_train.data.segmentation import SkippedSample
from resireg_train.evaluation.specs import TASK_SPECS

__all__ = ["METRIC_PREFIX", "MappingResult"]

#: What the scores' names start with, ``val/scannet3d/``: the task table's
#: (:attr:`resireg_train.evaluation.specs.TaskSpec.metric_prefix`).
METRIC_PREFIX = TASK_SPECS["scannet3d"].metric_prefix


@dataclass
class MappingResult:
    """Per variant and scene the voxel confusion matrix, and frame / voxel counts."""

    dataset: str
    classes: tuple[str, ...]
    metric: str = "rayfronts"
    confusions: dict[str, dict[str, Tensor]] = field(default_factory=dict)  # variant -> scene
    frames: dict[str, int] = field(default_factory=dict)
    voxels: dict[str, int] = field(default_factory=dict)
    feature_voxels: dict[str, dict[str, int]] = field(default_factory=dict)  # variant -> scene
    skipped_samples: list[SkippedSample] = field(default_factory=list)
    dropped_samples: list[SkippedSample] = field(default_factory=list)

    @property
    def images(self) -> int:
        """Frames mapped, over all scenes."""
        return sum(self.frames.values())

    def pooled(self, variant: str) -> Tensor:
        """The variant's confusion matrix summed over the scenes."""
        k = len(self.classes)
        total = torch.zeros(k, k + 1, dtype=torch.int64)
        for matrix in self.confusions[variant].values():
            total += matrix
        return total

    def scene_scores(self, variant: str) -> dict[str, dict[str, Any]]:
        return {s: self._score(m, self.metric) for s, m in self.confusions[variant].items()}

    def _score(self, matrix: Any, metric: str) -> dict[str, Any]:
        """The scores of a voxel confusion matrix by the scorer of ``metric`` in the metric
        table (:data:`resireg.specs.metrics.METRIC_SPECS`: a new definition is a scorer and
        an entry there)."""
        return METRIC_SPECS[metric].load()(matrix, metric)

    def scores(self, prefix: str = METRIC_PREFIX) -> dict[str, float]:
        """Per variant: ``miou_<v>``, ``fmiou_<v>``, ``acc_<v>``, each the mean over the scenes
        (the table's figure), and ``pooled_miou_<v>``, ... of the confusion summed over the
        scenes, under ``<prefix><dataset>/`` (``prefix`` ends with ``/``; :data:`METRIC_PREFIX`,
        the task table's, by default)."""
        out = {}
        for variant in self.confusions:
            per_scene = self.scene_scores(variant).values()
            pooled = self._score(self.pooled(variant), self.metric)
            logged = METRIC_SPECS[self.metric].logged  # miou, fmiou, acc
            for name in logged:
                mean = metrics.mean_over_scenes([s[name] for s in per_scene])
                out[f"{prefix}{self.dataset}/{name}_{variant}"] = mean
            for name in logged:
                out[f"{prefix}{self.dataset}/pooled_{name}_{variant}"] = pooled[name]
        return out

    def per_scene(self) -> dict[str, dict[str, Any]]:
        """Per scene: frames, scored ground-truth voxels and each variant's mIoU / f-mIoU / acc
        and feature voxels."""
        out: dict[str, dict[str, Any]] = {}
        for scene in self.frames:
            scores = {}
            for variant in self.confusions:
                if scene in self.confusions[variant]:
                    c = self._score(self.confusions[variant][scene], self.metric)
                    scores[variant] = {"miou": c["miou"], "fmiou": c["fmiou"], "acc": c["acc"],
                                       "voxels": self.feature_voxels[variant].get(scene, 0)}  # fmt: skip
            out[scene] = {
                "frames": self.frames.get(scene, 0),
                "gt_voxels": self.voxels.get(scene, 0),
                "scores": scores,
            }
        return out

    def per_class_iou(self) -> dict[str, list[float]]:
        """Per variant the pooled per-class IoU (NaN where undefined)."""
        return {v: self._score(self.pooled(v), self.metric)["iou"] for v in self.confusions}

    def write_csv(self, out: Path) -> dict[str, str]:
        """Per variant, next to ``results.json``: ``scannet3d/<variant>/<scene>_class_results.csv``
        (per class: index, label, tp, fp, fn, iou, fiou) and ``scannet3d/<variant>/summary.csv``
        (per scene: miou, fmiou, acc, voxels; then the mean over scenes and the pooled row):
        RayFronts' ``semseg_final_class_results.csv`` / ``..._summary_results.csv``. Returns
        ``{variant: folder}`` relative to ``out``."""
        written = {}
        k = len(self.classes)
        for variant, scenes in self.confusions.items():
            folder = Path("scannet3d") / re.sub(r"[^\w.@=+-]", "_", variant)
            (out / folder).mkdir(parents=True, exist_ok=True)
            rows = []
            for scene, matrix in [*scenes.items(), ("pooled", self.pooled(variant))]:
                c = self._score(matrix, self.metric)
                cm = matrix.double()
                tp, freq = cm.diagonal(), cm.sum(1)
                fp = cm[:, :k].sum(0) - tp
                total = float(freq.sum())
                with (out / folder / f"{scene}_class_results.csv").open("w", newline="") as f:
                    writer = csv.writer(f)
                    writer.writerow(["index", "label", "tp", "fp", "fn", "iou", "fiou"])
                    for i, name in enumerate(self.classes):
                        fiou = float(freq[i]) / total * c["iou"][i] if total else float("nan")
                        writer.writerow([i, name, int(tp[i]), int(fp[i]), int(freq[i] - tp[i]),
                                         c["iou"][i], fiou])  # fmt: skip
                if scene != "pooled":
                    rows.append([scene, c["miou"], c["fmiou"], c["acc"],
                                 int(freq.sum())])  # fmt: skip
            pooled = self._score(self.pooled(variant), self.metric)
            mean = [metrics.mean_over_scenes([r[i] for r in rows]) for i in (1, 2, 3)]
            with (out / folder / "summary.csv").open("w", newline="") as f:
                writer = csv.writer(f)
                writer.writerow(["scene_name", "miou", "fmiou", "acc", "gt_voxels"])
                writer.writerows(rows)
                writer.writerow(["mean over scenes", *mean, sum(r[4] for r in rows)])
                writer.writerow(["pooled", pooled["miou"], pooled["fmiou"], pooled["acc"],
                                 sum(r[4] for r in rows)])  # fmt: skip
            written[variant] = str(folder)
        return written
