"""The scores and the scorers that compute them: one vocabulary for 2D and 3D, without
importing torch.

**Scores** (:data:`SCORE_SPECS`): ``miou``, ``fmiou``, ``acc`` and ``iou`` (per class), each
with its label in reports and whether higher is better. The report (column labels), the
engines (which keys they log), the search (its direction) and the run index read the names
from here.

**Scorers** (:data:`METRIC_SPECS`): what turns predictions into those scores, by name:
``pixels`` (the OVSS task's confusion over pixels, :class:`resireg.ovss.SegmentationMetric`),
``rayfronts`` and ``union`` (the 3D task's two definitions over voxels,
:func:`resireg.mapping.metric.scores`; ``dataset.metric`` of ``conf/dataset/scannet.yaml``).
Every scorer returns a dict with its :attr:`MetricSpec.keys`.

Adding a metric: the scorer (returning its keys), one :class:`MetricSpec` below; a new score
key also gets one :class:`ScoreSpec` (label, direction). ``tests/resireg/specs/test_tables.py`` runs every
scorer once and checks it returns exactly its keys.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from resireg.specs.table import SpecTable

__all__ = [
    "METRIC_SPECS",
    "SCORE_SPECS",
    "SUMMARY_SCORES",
    "VOXEL_METRICS",
    "MetricSpec",
    "ScoreSpec",
    "direction",
]


@dataclass(frozen=True)
class ScoreSpec:
    """One score key.

    Attributes:
        name: the key (``miou``), in results, logged names (``val/ovss/ade20k/miou_full``) and
            report columns.
        label: its name in reports (``mIoU``).
        higher_is_better: the direction a search optimises it in.
        per_class: a list over classes rather than one number.
    """

    name: str
    label: str
    higher_is_better: bool = True
    per_class: bool = False


#: Every score key, in report order.
SCORE_SPECS: SpecTable[ScoreSpec] = SpecTable(
    "score",
    (
        ScoreSpec("miou", "mIoU"),
        ScoreSpec("fmiou", "f-mIoU"),
        ScoreSpec("acc", "Acc"),
        ScoreSpec("iou", "IoU", per_class=True),
    ),
    where="resireg.specs.metrics",
)
#: The one-number scores (what a run logs per configuration and a search may optimise).
SUMMARY_SCORES: tuple[str, ...] = tuple(n for n, s in SCORE_SPECS.items() if not s.per_class)


@dataclass(frozen=True)
class MetricSpec:
    """One scorer.

    Attributes:
        name: its name (``dataset.metric`` for the 3D ones).
        target: ``"module:attribute"``: the scorer (loaded when scoring).
        unit: what it scores (``pixel``, ``voxel``).
        keys: the score keys it returns (:data:`SCORE_SPECS`).
        logged: the keys an engine logs per configuration (the rest go to ``results.json``).
        summary: one line for errors and docs.
    """

    name: str
    target: str
    unit: str
    keys: tuple[str, ...]
    logged: tuple[str, ...]
    summary: str

    def load(self) -> Any:
        """The scorer (imports torch)."""
        from resireg.specs.table import load

        return load(self.target)


METRIC_SPECS: SpecTable[MetricSpec] = SpecTable(
    "metric",
    (
        MetricSpec(
            "pixels", "resireg.ovss:SegmentationMetric", "pixel", ("miou", "fmiou", "acc", "iou"),
            ("miou", "fmiou"),
            "mean IoU over classes with a non-empty union of pixels (the OVSS task; Table 1)",
        ),
        MetricSpec(
            "rayfronts", "resireg.mapping.metric:scores", "voxel", ("miou", "fmiou", "acc", "iou"),
            ("miou", "fmiou", "acc"),
            "RayFronts' voxel IoU: classes without ground truth left out (Table 2)",
        ),
        MetricSpec(
            "union", "resireg.mapping.metric:scores", "voxel", ("miou", "fmiou", "acc", "iou"),
            ("miou", "fmiou", "acc"),
            "voxel IoU over classes with a non-empty union, as the 2D task",
        ),
    ),
    where="resireg.specs.metrics",
)  # fmt: skip
#: The 3D task's definitions (``dataset.metric``).
VOXEL_METRICS: tuple[str, ...] = tuple(n for n, s in METRIC_SPECS.items() if s.unit == "voxel")


def direction(name: str) -> str | None:
    """``"max"`` / ``"min"`` for a logged name whose last part starts with a score key
    (``val/ovss/ade20k/miou_full`` -> ``max``), ``"min"`` for a loss, else ``None``."""
    last = str(name).rsplit("/", 1)[-1].lower()
    if "loss" in last:
        return "min"
    for score in sorted(SCORE_SPECS.values(), key=lambda s: -len(s.name)):
        if last == score.name or last.startswith(f"{score.name}_"):
            return "max" if score.higher_is_better else "min"
    return None
