"""The 3D semantic-mapping task (paper Table 2, Fig. 4b; docs/design.md section 10).

Per scene, batches of consecutive kept frames (:meth:`ScanNetFrames.batches`; ReSiReg Full's
batch = scene is a video window). Per batch the encoder runs once (``encode``) and every
variant / configuration is applied to that one output, as in the OVSS engine (through
:func:`resireg.variants.apply_variant`, so Full's configurations share one PCA per batch).
Each variant's features are placed at the world points of its own grid's patch centres
(:func:`resireg.mapping.patch_points` from the ``image_size`` depth, intrinsics and pose)
and fused into one :class:`~resireg.mapping.VoxelMap` per variant (running sums; the
L2-normalised mean is read at scene end).

The ground truth is built independently of any feature grid: every pixel of the label image at
``gt_resolution`` is unprojected with the depth at that resolution and votes for its class in
a :class:`~resireg.mapping.LabelVoxelMap` of the same voxel size. With ``gt_unlabelled:
vote`` (default, RayFronts' ground-truth lifting) ignored pixels (255: unlabelled, the
"other" classes) vote as one extra class, and a voxel they win is not scored; with ``drop``
they cast no vote.

At scene end each variant's voxel features are classified against the class text prototypes
(the OVSS task's text path: 80 templates, ``text_features`` once, ``dense_text``, averaged;
cosine argmax), the predictions are transferred to the ground-truth voxel centres by nearest
neighbour (no smoothing), and one confusion matrix per variant is accumulated per scene and
over all scenes (:class:`resireg.ovss.SegmentationMetric`: mIoU over classes present in the
ground truth or the prediction, f-mIoU weighted by ground-truth voxels).

Precision: ``"32"`` or ``"bf16"`` applies to the encoder pass and the variants, as in the OVSS
engine; unprojection, fusion, the ground truth and the classification always run with
autocast off (fp32 / fp64).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader

from resireg.mapping import (
    LabelVoxelMap,
    VoxelMap,
    classify,
    patch_points,
    transfer_labels,
    unproject,
)
from resireg.models import DenseEncoder
from resireg.ovss import SegmentationMetric
from resireg.variants import apply_variant
from resireg_train.mapping.scannet import ScanNetFrames, collate_frames
from resireg_train.ovss.datasets import SkippedSample
from resireg_train.ovss.engine import (
    OVSSTask,
    StageTimer,
    _no_timer,
    check_variants_on,
    inference,
)

__all__ = ["GT_UNLABELLED", "MappingResult", "MappingTask", "run_scannet3d"]

#: How ignored ground-truth pixels enter the voxel votes (module docstring).
GT_UNLABELLED = ("vote", "drop")


@dataclass
class MappingResult:
    """Confusion matrices (overall and per scene) per variant, and frame counts."""

    dataset: str
    metrics: dict[str, SegmentationMetric]
    scene_metrics: dict[str, dict[str, SegmentationMetric]] = field(default_factory=dict)
    frames: dict[str, int] = field(default_factory=dict)
    voxels: dict[str, int] = field(default_factory=dict)
    skipped_samples: list[SkippedSample] = field(default_factory=list)
    dropped_samples: list[SkippedSample] = field(default_factory=list)

    @property
    def images(self) -> int:
        """Frames mapped, over all scenes."""
        return sum(self.frames.values())

    def scores(self, prefix: str = "val/scannet3d") -> dict[str, float]:
        """``{"<prefix>/<dataset>/miou_<variant>": ..., ".../fmiou_<variant>": ...}`` of the
        confusion matrix summed over all scenes (every ground-truth voxel counts once)."""
        out = {}
        for variant, metric in self.metrics.items():
            computed = metric.compute()
            out[f"{prefix}/{self.dataset}/miou_{variant}"] = float(computed["miou"])
            out[f"{prefix}/{self.dataset}/fmiou_{variant}"] = float(computed["fmiou"])
        return out

    def per_scene(self) -> dict[str, dict[str, Any]]:
        """Per scene: frames, ground-truth voxels and each variant's mIoU / f-mIoU."""
        out = {}
        for scene, metrics in self.scene_metrics.items():
            scores = {}
            for variant, metric in metrics.items():
                c = metric.compute()
                scores[variant] = {"miou": float(c["miou"]), "fmiou": float(c["fmiou"])}
            out[scene] = {
                "frames": self.frames.get(scene, 0),
                "gt_voxels": self.voxels.get(scene, 0),
                "scores": scores,
            }
        return out

    def per_class_iou(self) -> dict[str, list[float]]:
        return {v: m.compute()["per_class_iou"] for v, m in self.metrics.items()}


def _fp32(device: torch.device) -> torch.autocast:
    """Autocast off: geometry, votes and classification run in their own dtypes (fp32 / fp64)
    whatever the encoder pass's precision."""
    return torch.autocast(device.type, enabled=False)


class MappingTask:
    """3D semantic mapping of a :class:`ScanNetFrames` set (module docstring).

    Args:
        dataset: the frames.
        batch_size: consecutive frames per encoder pass (Full's scene).
        voxel_size: voxel edge in metres, for the feature maps and the ground truth.
        num_workers: DataLoader workers reading and resizing frames.
        gt_unlabelled: ``vote`` or ``drop`` (module docstring).
    """

    def __init__(
        self,
        dataset: ScanNetFrames,
        batch_size: int = 8,
        voxel_size: float = 0.05,
        num_workers: int = 0,
        gt_unlabelled: str = "vote",
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if gt_unlabelled not in GT_UNLABELLED:
            raise ValueError(f"gt_unlabelled={gt_unlabelled!r}: expected one of {GT_UNLABELLED}")
        self.dataset = dataset
        self.batch_size = batch_size
        self.voxel_size = float(voxel_size)
        self.num_workers = num_workers
        self.gt_unlabelled = gt_unlabelled
        # The OVSS task's text path (class prompts, text_features once, dense_text, averaging);
        # it reads only the dataset's class names.
        self.text = OVSSTask(dataset, batch_size)  # type: ignore[arg-type]

    def prototypes(self, encoder: DenseEncoder) -> Tensor:
        """Class prototypes ``[K, Dl]``, exactly as the 2D task computes them."""
        return self.text.prototypes(encoder)

    def check_variants(self, variants: Mapping[str, nn.Module], key: str = "") -> None:
        """Fail before any encoding if a variant cannot run on some batch (e.g. more prototypes
        than a batch has points); the error names ``key.<variant>``."""
        h, w = self.dataset.grid_size()
        shapes = [(len(b), h, w) for b in self.dataset.batches(self.batch_size)]
        check_variants_on(variants, shapes, self.dataset.patch_size, self.dataset.name,
                          self.batch_size, "frames", key)  # fmt: skip

    def loader(self) -> DataLoader:
        return DataLoader(
            self.dataset,
            batch_sampler=self.dataset.batches(self.batch_size),
            collate_fn=collate_frames,
            num_workers=self.num_workers,
        )

    @torch.no_grad()
    def run(
        self,
        encoder: DenseEncoder,
        variants: Mapping[str, nn.Module],
        precision: str = "32",
        timer: StageTimer | None = None,
    ) -> MappingResult:
        """Map every scene with every variant and score it.

        Args:
            encoder: the model (its modules are put in eval mode for the pass and restored).
            variants: ``resireg.variants.build_variants`` output.
            precision: ``"32"`` (fp32) or ``"bf16"`` (autocast), as the OVSS engine.
            timer: collects seconds per stage (``data``, ``encoder``,
                ``reconstruction/<variant>``, ``fusion``, ``ground_truth``, ``metric``).
        """
        timed = timer or _no_timer
        k = len(self.dataset.classes)
        ignore = self.dataset.ignore_index
        result = MappingResult(
            self.dataset.name,
            {v: SegmentationMetric(k, ignore) for v in variants},
            dropped_samples=list(self.dataset.dropped),
        )
        device = encoder.device
        with inference(encoder, precision):
            with torch.autocast(device.type, enabled=False):
                protos = self.prototypes(encoder)  # the text path in fp32, whatever precision
            state: dict[str, Any] = {"scene": None}
            batches = iter(self.loader())
            while True:
                with timed("data"):
                    batch = next(batches, None)
                if batch is not None:
                    result.skipped_samples.extend(batch["skipped"])
                    if batch["image"] is None:
                        continue
                scene = None if batch is None else batch["scene"][0]
                if state["scene"] is not None and scene != state["scene"]:
                    self._finish_scene(state, protos, result, timed)
                if batch is None:
                    break
                if state["scene"] != scene:
                    state = self._start_scene(scene, variants, device)
                self._map_batch(encoder, batch, variants, state, timed)
                result.frames[state["name"]] = result.frames.get(state["name"], 0) + len(
                    batch["index"]
                )
        for scene in self.dataset.scenes:  # scenes with no usable frame are listed with 0
            result.frames.setdefault(scene, 0)
        return result

    def _start_scene(self, scene: int, variants, device: torch.device) -> dict[str, Any]:
        k = len(self.dataset.classes)
        return {
            "scene": scene,
            "name": self.dataset.scenes[scene],
            "maps": dict.fromkeys(variants),  # VoxelMap per variant, made at its first batch
            "gt": LabelVoxelMap(
                self.voxel_size,
                k + 1 if self.gt_unlabelled == "vote" else k,
                ignore_index=-1 if self.gt_unlabelled == "vote" else self.dataset.ignore_index,
                device=device,
            ),  # fmt: skip
        }

    def _map_batch(self, encoder, batch, variants, state, timed) -> None:
        device = encoder.device
        x = encoder.input_rule.normalize(batch["image"].to(device))
        depth = batch["depth"].to(device)
        k_img = batch["intrinsics"].to(device)
        pose = batch["pose"].to(device)
        with timed("encoder"):
            out = encoder.encode(x)
        shared: dict = {}  # work common to the configurations of this batch (apply_variant)
        grids: dict[tuple[int, int], tuple[Tensor, Tensor]] = {}  # patch points per grid
        for name, variant in variants.items():
            with timed(f"reconstruction/{name}"):
                dense = apply_variant(variant, out.intermediates, out.language, shared=shared)
            with timed("fusion"), _fp32(device):
                grid = tuple(dense.shape[-2:])
                if grid not in grids:  # configurations on one grid share their points
                    grids[grid] = patch_points(depth, k_img, pose, grid)
                points, valid = grids[grid]
                feats = dense.permute(0, 2, 3, 1)[valid]
                if state["maps"][name] is None:
                    state["maps"][name] = VoxelMap(self.voxel_size, feats.shape[-1], device)
                state["maps"][name].add(points[valid], feats.float())
        with timed("ground_truth"), _fp32(device):
            label = batch["gt_label"].to(device)
            points, valid = unproject(
                batch["gt_depth"].to(device), batch["gt_intrinsics"].to(device), pose
            )
            if self.gt_unlabelled == "vote":  # ignored pixels vote as class K
                label = torch.where(label == self.dataset.ignore_index, len(self.dataset.classes),
                                    label)  # fmt: skip
            state["gt"].add(points[valid], label[valid])

    def _finish_scene(self, state, protos, result: MappingResult, timed) -> None:
        k = len(self.dataset.classes)
        ignore = self.dataset.ignore_index
        with timed("metric"), _fp32(torch.device(state["gt"].device)):
            centres, gt = state["gt"].labels()
            gt = torch.where(gt >= k, ignore, gt)  # won by ignored pixels: not scored
            result.voxels[state["name"]] = int((gt != ignore).sum())
            scene_metrics = {}
            for name, vmap in state["maps"].items():
                metric = SegmentationMetric(k, ignore)
                if vmap is not None and len(vmap) and len(centres):
                    vox, feats = vmap.features()
                    pred = classify(feats, protos.to(feats.device))
                    at_gt = transfer_labels(vox, pred, centres)
                    metric.update(at_gt.cpu(), gt.cpu())
                elif len(centres):  # no valid feature point at all: nothing predicted
                    raise RuntimeError(
                        f"scene {state['name']}: variant {name} placed no point in the map "
                        "(no valid depth at its patch centres)"
                    )
                result.metrics[name].confusion += metric.confusion
                scene_metrics[name] = metric
            result.scene_metrics[state["name"]] = scene_metrics


def run_scannet3d(
    cfg: Any,
    out: Path,
    encoder: DenseEncoder,
    variants: Mapping[str, nn.Module],
    params: Mapping[str, Any],
) -> dict[str, Any]:
    """``resireg-eval task=scannet3d``: map the configured scenes with every variant and
    write ``results.json`` (same fields as the OVSS task, plus ``per_scene`` and
    ``frames``); returns its content."""
    import logging

    from resireg_train.mapping.scannet import build_scannet
    from resireg_train.results import update_results

    log = logging.getLogger("resireg_train.cli.eval")
    spec = params["dataset"]
    dataset = build_scannet(spec, encoder.input_rule.patch_size, key="dataset")
    task = MappingTask(
        dataset,
        int(cfg.batch_size),
        voxel_size=float(spec.get("voxel_size", 0.05)),
        num_workers=int(cfg.num_workers),
        gt_unlabelled=str(spec.get("gt_unlabelled", "vote")),
    )
    task.check_variants(variants)
    timer = StageTimer()
    result = task.run(encoder, variants, precision=str(cfg.precision), timer=timer)
    scores = result.scores()
    for name, value in scores.items():
        log.info("%s = %.4f", name, value)
    dropped = result.dropped_samples + result.skipped_samples
    if dropped:
        log.warning(
            "%s: %d frames dropped (non-finite pose) and %d skipped (unreadable): %s",
            dataset.name, len(result.dropped_samples), len(result.skipped_samples),
            "; ".join(f"{s.file}: {s.reason}" for s in dropped),
        )  # fmt: skip
    return update_results(
        out,
        status="completed",
        final=scores,
        per_class_iou={
            v: dict(zip(dataset.classes, ious, strict=True))
            for v, ious in result.per_class_iou().items()
        },  # fmt: skip
        per_scene=result.per_scene(),
        images=result.images,
        frames=dict(result.frames),
        frames_dropped=len(result.dropped_samples),
        skipped=len(result.skipped_samples),
        skipped_samples=[s.as_dict() for s in dropped],
        seconds={k: round(v, 4) for k, v in sorted(timer.seconds.items())},
    )
