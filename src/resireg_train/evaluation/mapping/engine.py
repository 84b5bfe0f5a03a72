"""The 3D semantic-mapping task (paper Table 2, Fig. 4b; docs/maps.md#scannet-evaluation).

Per scene, batches of consecutive kept frames (:meth:`ScanNetFrames.batches`; ReSiReg Full's
batch = scene is a video window). Per batch the encoder runs once (``encode``) and every
variant / configuration is applied to that one output, as in the OVSS engine (through
:func:`resireg.method.variants.apply_variant`, so Full's configurations share one PCA per batch).
Each variant's features are lifted to 3D on its own grid (:class:`MappingSettings` ``points``)
and fused into one :class:`~resireg.mapping.SemanticMap` per variant (:meth:`SemanticMap.fuse`:
running sums in a :class:`~resireg.mapping.VoxelMap`; the L2-normalised mean is read at scene
end). A robot's ``SemanticMap.add`` runs the same lift-and-fuse code on its own windows:

- ``patch`` (default): one point per patch, its centre unprojected with the patch's depth
  (:func:`resireg.mapping.patch_points`): OTAS's ``src/model.py`` ``batch_embed_rgbd``, the
  code the paper's sentence describes;
- ``pixel``: every pixel of a lifted patch at the patch's depth with the patch's feature, as
  (patch, voxel, count) pairs (:func:`resireg.mapping.pixel_pairs`).

The ground truth is built independently of any feature grid: every pixel of the label image at
``gt_resolution`` is unprojected with the depth at that resolution and votes for its class in
a :class:`~resireg.mapping.LabelVoxelMap` of the same lattice. ``gt_unlabelled`` (:data:`GT_RULES`):

- ``rayfronts`` (default): RayFronts' ``semseg_eval.py`` ``compute_semseg_gt``: the one-hot
  labels with the ignore class (pixels of ignored classes vote for it) are averaged per voxel
  and labelled by ``compute_semseg_preds(votes, one-hot prompts of the labelled classes, 0,
  0.1)``: softmax of 100 x the cosine to the labelled classes only, ignored below 0.1, so
  ignored pixels never outvote labelled ones but can dilute them;
- ``vote``: ignored pixels vote as one more class; a voxel they win (argmax) is not scored;
- ``drop``: ignored pixels cast no vote.

A dataset whose ground truth is labelled points rather than frames (``ground_truth =
"external"``: Replica's HOV-SG points, :mod:`resireg_train.data.replica`) gives them per scene
(``scene_ground_truth``); they vote in the same lattice and are labelled by RayFronts'
``load_externel_semseg_gt`` rule (:func:`external_labels`), and its frames carry no labels.

At scene end each variant's voxel features are classified against the class text prototypes
(the OVSS task's text path: 80 templates, ``text_features`` once, ``dense_text``, averaged;
cosine argmax, or RayFronts' rule with ``prediction_threshold`` / ``prompt_denoising``), the
predictions are transferred to the ground-truth voxels (``knn``: the mode of the ``k`` nearest
predicted voxels, RayFronts' ``align_labels_with_knn``; 0: the same voxel or no prediction) and
scored per scene (:mod:`resireg.mapping.metric`).

Precision: ``"32"`` or ``"bf16"`` applies to the encoder pass and the variants, as in the OVSS
engine; lifting, fusion, the ground truth and the classification always run with autocast off
(fp32 / fp64).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch
from torch import Tensor, nn

from resireg.mapping import (
    LabelVoxelMap,
    SemanticMap,
    classify,
    transfer_labels,
    transfer_labels_by_voxel,
    unproject,
)
from resireg.mapping import metric as metrics
from resireg.method.variants import apply_variant
from resireg.models import DenseEncoder
from resireg.specs.mapping import POINTS, compact_defaults
from resireg_train.data.scannet import ScanNetFrames, collate_frames
from resireg_train.data.segmentation import SkippedSample
from resireg_train.data.specs import GT_RULES, check_dataset_values, dataset_conf
from resireg_train.evaluation.engine import (
    EvalEngine,
    StageTimer,
    inference,
    no_timer,
    nonfinite_output,
)
from resireg_train.evaluation.mapping.result import MappingResult

__all__ = [
    "GT_RULES",
    "POINTS",
    "TASK_KEYS",
    "MappingSettings",
    "MappingEngine",
]

#: RayFronts' ground-truth rule: ``compute_semseg_preds(votes, prompts, 0, 0.1)``, and the
#: ``eps`` of its ``ImageSemSegEncoder.encode_labels`` one-hot prompts.
_GT_THRESHOLD, _GT_EPS = 0.1, 1e-10


@dataclass(frozen=True)
class MappingSettings:
    """The task's settings: the ``conf/dataset/scannet.yaml`` keys of the same names, which
    hold the protocol's values and document each. No field has a Python default: ``conf/`` is
    their one source (:meth:`from_spec` takes them from a dataset entry, :meth:`from_conf` from
    a ``conf/dataset/`` file).

    Attributes:
        voxel_size: voxel edge in metres (feature maps and ground truth).
        lattice: ``round`` or ``floor`` (:mod:`resireg.mapping.keys`).
        gt_unlabelled: :data:`GT_RULES`.
        points: :data:`POINTS`.
        storage: the feature maps' storage (:data:`resireg.specs.mapping.STORAGES`;
            ``compact`` takes ``conf/map.yaml``'s ``compact`` block).
        knn: neighbours of the label transfer (0: same voxel only).
        prediction_threshold: ``None`` or RayFronts' "no prediction" probability.
        prompt_denoising: ``None`` or RayFronts' prompt-denoising probability.
        metric: :data:`resireg.mapping.metric.METRICS` (the metric table's voxel scorers).
    """

    voxel_size: float
    lattice: str
    gt_unlabelled: str
    points: str
    storage: str
    knn: int
    prediction_threshold: float | None
    prompt_denoising: float | None
    metric: str

    def __post_init__(self) -> None:
        # every field by the dataset table's rule of its key (the config check's), one format
        check_dataset_values("scannet", {f.name: getattr(self, f.name) for f in fields(self)})

    @classmethod
    def from_spec(cls, spec: Mapping[str, Any], key: str = "dataset") -> MappingSettings:
        """The settings of a dataset entry (``conf/dataset/scannet.yaml``), which must hold
        every one of them: ``conf/`` is their one source of defaults (an entry without one is
        an error naming ``<key>.<name>``, not a silent Python default)."""
        missing = [f.name for f in fields(cls) if f.name not in spec]
        if missing:
            raise ValueError(
                f"{key}: no {', '.join(f'{key}.{m}' for m in missing)} (the task's settings; "
                "conf/dataset/scannet.yaml holds every one)"
            )
        return cls(**{f.name: spec[f.name] for f in fields(cls)})

    @classmethod
    def from_conf(cls, dataset: str = "scannet", **settings: Any) -> MappingSettings:
        """The settings of ``conf/dataset/<dataset>.yaml`` (read by
        :func:`resireg_train.data.specs.dataset_conf`, its ``defaults`` composed, so
        ``scannet_legacy`` holds ``scannet``'s), ``settings`` in place of its values: the
        Python API's defaults are the config's, read from it rather than typed again."""
        unknown = sorted(set(settings) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"unknown settings {unknown}; the task's are {list(TASK_KEYS)}")
        spec = {k: v for k, v in dataset_conf(dataset).items() if k in TASK_KEYS}
        return cls.from_spec({**spec, **settings}, key=f"conf/dataset/{dataset}.yaml")


#: The dataset-entry keys the task reads (:class:`MappingSettings`).
TASK_KEYS = tuple(f.name for f in fields(MappingSettings))


def _fp32(device: torch.device) -> torch.autocast:
    """Autocast off: geometry, votes and classification run in their own dtypes (fp32 / fp64)
    whatever the encoder pass's precision."""
    return torch.autocast(device.type, enabled=False)


def ground_truth_labels(gt: LabelVoxelMap, rule: str, num_classes: int, ignore: int) -> Tensor:
    """The label of every ground-truth voxel (in :attr:`LabelVoxelMap.indices` order) from its
    votes under ``rule`` (module docstring); ``ignore`` where it is not scored.

    ``rayfronts`` and ``vote`` maps hold ``K + 1`` vote columns, the last for ignored pixels;
    for ``rayfronts`` the votes are put in RayFronts' column order (the ignore class first) and
    averaged in float32 (its ``pointcloud_to_sparse_voxels(aggregation="mean")``), and each
    labelled class's prompt is its one-hot vector with ``1e-10`` elsewhere
    (``ImageSemSegEncoder.encode_labels``); a voxel with no labelled vote is not scored (with
    fewer than 11 classes RayFronts would give it the first class)."""
    k = num_classes
    votes = gt.votes
    if rule == "drop":
        return torch.argmax(votes, dim=1)
    if rule == "vote":
        label = torch.argmax(votes, dim=1)
        return torch.where(label >= k, ignore, label)
    mean = torch.cat([votes[:, k:], votes[:, :k]], dim=1).float()
    mean /= votes.sum(1, keepdim=True).float()
    prompts = torch.full((k, k + 1), _GT_EPS, dtype=torch.float32, device=votes.device)
    prompts[torch.arange(k), torch.arange(1, k + 1)] = 1.0
    # prompt_denoising_thresh 0 removes no class: the rule is the threshold alone
    label = classify(mean, prompts, threshold=_GT_THRESHOLD, none=ignore)
    # A voxel without a labelled vote has the same cosine to every class, so its probability
    # is 1/K: below 0.1 for K >= 11 (ScanNet's 37), but with fewer classes RayFronts' rule
    # labels it as the first class. That contradicts the rule's intent (an ignored pixel never
    # labels a voxel), so such a voxel is not scored (docs/protocol.md section 5).
    return torch.where(votes[:, :k].sum(1) == 0, ignore, label)


def external_labels(votes: Tensor, num_classes: int, ignore: int) -> Tensor:
    """The labels of ground-truth voxels read from labelled points (Replica's HOV-SG file,
    :meth:`resireg_train.data.posed3d.PosedFrames.scene_ground_truth`): RayFronts'
    ``load_externel_semseg_gt``: the one-hot votes summed per voxel, "no label" (the last of
    ``votes``' ``K + 1`` columns here, RayFronts' index 0) put first, argmax: ties go to "no
    label", then to the smaller class; ``ignore`` where "no label" wins."""
    k = num_classes
    label = torch.argmax(torch.cat([votes[:, k:], votes[:, :k]], dim=1), dim=1) - 1
    return torch.where(label < 0, ignore, label)


class MappingEngine(EvalEngine):
    """3D semantic mapping of a :class:`ScanNetFrames` set (module docstring).

    The class prototypes are the 2D task's (the shared text path,
    :class:`resireg_train.evaluation.base.ClassPrototypes`, of the dataset's class names).

    Args:
        dataset: the frames.
        batch_size: consecutive frames per encoder pass (Full's scene).
        protocol: the task's settings (:class:`MappingSettings`); keywords of it may be given
            directly instead (``voxel_size=0.1``), the others then come from
            ``conf/dataset/scannet.yaml`` (:meth:`MappingSettings.from_conf`).
        num_workers: DataLoader workers reading and resizing frames.
    """

    collate = staticmethod(collate_frames)
    unit = "frames"

    def __init__(
        self,
        dataset: ScanNetFrames,
        batch_size: int = 8,
        protocol: MappingSettings | None = None,
        num_workers: int = 2,
        **settings: Any,
    ) -> None:
        super().__init__(dataset, batch_size, num_workers)
        if protocol is None:
            self.protocol = MappingSettings.from_conf(**settings)
        else:
            self.protocol = MappingSettings(**{**asdict(protocol), **settings})
        self.voxel_size = float(self.protocol.voxel_size)

    def batch_shapes(self) -> list[tuple[int, int, int]]:
        """``(frames, height, width)`` of every batch (every frame has the same size)."""
        h, w = self.dataset.grid_size()
        return [(len(b), h, w) for b in self.dataset.batches(self.batch_size)]

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
            variants: ``resireg.method.variants.build_variants`` output.
            precision: ``"32"`` (fp32) or ``"bf16"`` (autocast), as the OVSS engine.
            timer: collects seconds per stage (``data``, ``encoder``,
                ``reconstruction/<variant>``, ``fusion``, ``ground_truth``, ``metric``).
        """
        timed = timer or no_timer
        result = MappingResult(
            self.dataset.name,
            tuple(self.dataset.classes),
            self.protocol.metric,
            confusions={v: {} for v in variants},
            feature_voxels={v: {} for v in variants},
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
                bad = self._map_batch(encoder, batch, variants, state, timed)
                if bad is not None:  # non-finite encoder output: not fused, skipped, counted
                    result.skipped_samples.extend(
                        SkippedSample(i, self.dataset.describe(i), bad) for i in batch["index"]
                    )
                    continue
                result.frames[state["name"]] = result.frames.get(state["name"], 0) + len(
                    batch["index"]
                )
        for scene in self.dataset.scenes:  # scenes with no usable frame are listed with 0
            result.frames.setdefault(scene, 0)
        return result

    def _start_scene(self, scene: int, variants, device: torch.device) -> dict[str, Any]:
        k = len(self.dataset.classes)
        external = getattr(self.dataset, "ground_truth", "frames") == "external"
        with_ignored = external or self.protocol.gt_unlabelled in ("rayfronts", "vote")
        p = self.protocol
        state = {
            "scene": scene,
            "name": self.dataset.scenes[scene],
            "maps": {  # one map per variant: the fusion a robot's SemanticMap.add runs
                name: SemanticMap(
                    None,
                    variant,
                    self.voxel_size,
                    points=p.points,
                    lattice=p.lattice,
                    colour=False,
                    device=device,
                    storage=p.storage,
                    compact=compact_defaults() if p.storage == "compact" else None,
                )
                for name, variant in variants.items()
            },  # fmt: skip
            "gt": LabelVoxelMap(
                self.voxel_size,
                k + 1 if with_ignored else k,
                ignore_index=-1 if with_ignored else self.dataset.ignore_index,
                device=device,
                lattice=self.protocol.lattice,
            ),  # fmt: skip
        }
        if external:  # the scene's labelled points, "no label" voting as class K
            points, labels = self.dataset.scene_ground_truth(scene)
            labels = torch.where(labels == self.dataset.ignore_index, k, labels)
            state["gt"].add(points.to(device), labels.to(device))
        return state

    def _map_batch(self, encoder, batch, variants, state, timed) -> str | None:
        """Fuse one batch into every variant's map and its labels into the ground truth;
        returns why it was not (a non-finite encoder output, :func:`nonfinite_output`: neither
        its features nor its labels enter the scene) or ``None``."""
        device = encoder.device
        x = encoder.input_rule.normalize(batch["image"].to(device))
        with timed("encoder"):
            out = encoder.encode(x)
        bad = nonfinite_output(out)
        if bad is not None:
            return bad
        depth = batch["depth"].to(device)
        k_img = batch["intrinsics"].to(device)
        pose = batch["pose"].to(device)
        shared: dict = {}  # work common to the configurations of this batch (apply_variant)
        lifted: dict[tuple[int, int], tuple] = {}  # lifted points per grid, shared by the maps
        for name, variant in variants.items():
            with timed(f"reconstruction/{name}"):
                dense = apply_variant(variant, out.intermediates, out.language, shared=shared)
            with timed("fusion"), _fp32(device):
                state["maps"][name].fuse(dense, depth, k_img, pose, lifted=lifted)
        if batch["gt_label"] is None:  # the ground truth is the dataset's own (external)
            return None
        with timed("ground_truth"), _fp32(device):
            label = batch["gt_label"].to(device)
            points, valid = unproject(
                batch["gt_depth"].to(device), batch["gt_intrinsics"].to(device), pose
            )
            if self.protocol.gt_unlabelled != "drop":  # ignored pixels vote as class K
                label = torch.where(label == self.dataset.ignore_index, len(self.dataset.classes),
                                    label)  # fmt: skip
            state["gt"].add(points[valid], label[valid])
        return None

    def _finish_scene(self, state, protos, result: MappingResult, timed) -> None:
        k = len(self.dataset.classes)
        ignore = self.dataset.ignore_index
        p = self.protocol
        with timed("metric"), _fp32(torch.device(state["gt"].device)):
            if getattr(self.dataset, "ground_truth", "frames") == "external":
                gt = external_labels(state["gt"].votes, k, ignore)
            else:
                gt = ground_truth_labels(state["gt"], p.gt_unlabelled, k, ignore)
            result.voxels[state["name"]] = int((gt != ignore).sum())
            for name, vmap in state["maps"].items():
                vmap.fit_pending()  # a compact map of a short scene: its basis on what it saw
                scored = int((gt != ignore).sum())
                if not len(vmap):
                    if scored:  # no valid feature point at all: nothing predicted
                        raise RuntimeError(
                            f"scene {state['name']}: variant {name} placed no point in the map "
                            "(no valid depth at its patch centres)"
                        )
                    at_gt = torch.full_like(gt, k)
                else:
                    centres = vmap.centres()
                    # the map's own features: a compact map's in its basis's space
                    pred = vmap.classify_features(vmap.project(protos.to(centres.device)),
                                                  p.prediction_threshold, p.prompt_denoising,
                                                  none=k)  # fmt: skip
                    if p.knn == 0:
                        at_gt = transfer_labels_by_voxel(vmap.indices, pred, state["gt"].indices, k)
                    else:  # the mode's ties go to the smaller label: in RayFronts' numbering
                        # "no prediction" is 0, the smallest, so it is voted in that numbering
                        shifted = transfer_labels(
                            centres,
                            (pred + 1) % (k + 1),
                            state["gt"].centres(),
                            min(p.knn, len(vmap)),
                        )
                        at_gt = (shifted - 1) % (k + 1)  # fmt: skip
                result.confusions[name][state["name"]] = metrics.confusion(at_gt, gt, k, ignore)
                result.feature_voxels[name][state["name"]] = len(vmap)
