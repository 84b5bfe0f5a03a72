"""The 3D task's metric: a voxel confusion matrix and its two definitions (docs/maps.md#scannet-evaluation).

The confusion matrix is ``[K, K + 1]``: rows are the ground-truth class of the scored voxels
(labelled ones only), columns the predicted class, the last column "no prediction" (RayFronts'
prediction threshold, or a ground-truth voxel without a predicted voxel under ``knn: 0``): such a
voxel is a false negative of its class and a false positive of none.

Definitions (:data:`METRICS`, the voxel scorers of :data:`resireg.specs.metrics.METRIC_SPECS`), per class ``c`` with ``tp``, ``fp`` (over scored voxels),
``fn`` and ``freq = tp + fn`` (its ground-truth voxels):

- ``rayfronts`` (RayFronts' ``scripts/semseg_eval.py``, ``compute_semseg_metrics``): ``iou =
  tp / (tp + fp + fn)``, NaN for a class with no ground-truth voxel in the scene (``iou[freq ==
  0] = nan``: a predicted-but-absent class is left out); ``miou = nanmean(iou)``; ``fmiou =
  nansum(freq / sum(freq) * iou)``; ``acc`` = correct / scored voxels.
- ``union`` (this project's earlier definition, the OVSS task's
  :class:`resireg.ovss.SegmentationMetric`): the mean over classes with a non-empty union
  (ground truth or prediction), so a predicted-but-absent class counts as 0; f-mIoU and
  accuracy as above.

Scores are computed per scene; a table's figure is the mean of the scenes' values (RayFronts
scores one scene per job and the paper reports their mean), beside the pooled value of the
confusion matrix summed over scenes (every voxel of every scene once).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from resireg.specs.metrics import VOXEL_METRICS

__all__ = ["METRICS", "confusion", "mean_over_scenes", "scores"]

#: The definitions :func:`scores` computes (the metric table's voxel scorers).
METRICS = VOXEL_METRICS


def confusion(pred: Tensor, gt: Tensor, num_classes: int, ignore_index: int) -> Tensor:
    """``[K, K + 1]`` int64 confusion of voxel predictions ``pred`` (``0..K``, ``K`` = none)
    against ground truth ``gt`` (``0..K-1`` or ``ignore_index``, not scored)."""
    k = num_classes
    pred, gt = pred.reshape(-1).long().cpu(), gt.reshape(-1).long().cpu()
    if pred.shape != gt.shape:
        raise ValueError(f"pred of {tuple(pred.shape)} vs gt of {tuple(gt.shape)} voxels")
    scored = gt != ignore_index
    pred, gt = pred[scored], gt[scored]
    if bool(((gt < 0) | (gt >= k)).any()) or bool(((pred < 0) | (pred > k)).any()):
        raise ValueError(f"labels outside 0..{k - 1} (ground truth) or 0..{k} (prediction)")
    return torch.bincount(gt * (k + 1) + pred, minlength=k * (k + 1)).reshape(k, k + 1)


def scores(matrix: Tensor, metric: str = "rayfronts") -> dict[str, float | list[float]]:
    """``miou``, ``fmiou``, ``acc`` and per class ``iou`` (NaN where undefined) of a
    ``[K, K + 1]`` confusion matrix under ``metric`` (module docstring); NaN where nothing is
    scored."""
    if metric not in METRICS:
        raise ValueError(f"metric={metric!r}: expected one of {METRICS}")
    cm = matrix.double()
    k = cm.shape[0]
    tp = cm.diagonal()
    freq = cm.sum(1)
    fp = cm[:, :k].sum(0) - tp
    union = freq + fp
    nan = torch.full_like(tp, math.nan)
    total = freq.sum()
    if metric == "rayfronts":
        iou = torch.where(freq > 0, tp / union.clamp_min(1), nan)
    else:
        iou = torch.where(union > 0, tp / union.clamp_min(1), nan)
    defined = ~torch.isnan(iou)
    if not bool(defined.any()) or total == 0:
        return {"miou": math.nan, "fmiou": math.nan, "acc": math.nan, "iou": iou.tolist()}
    return {
        "miou": float(iou[defined].mean()),
        "fmiou": float((freq[defined] / total * iou[defined]).sum()),
        "acc": float(tp.sum() / total),
        "iou": iou.tolist(),
    }


def mean_over_scenes(values: list[float]) -> float:
    """The mean of the scenes' values that are defined (a scene with no scored voxel has
    NaN); NaN when none is."""
    kept = [v for v in values if not math.isnan(v)]
    return sum(kept) / len(kept) if kept else math.nan
