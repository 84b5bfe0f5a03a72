"""ScanNet v2 frames for the 3D semantic-mapping task (docs/design.md section 10).

Layout read (the ScanNet ``SensReader`` export plus the ``2d-label-filt`` archive)::

    <path>/scannetv2-labels.combined.tsv           (or dataset.label_map)
    <path>/<scene>/color/<i>.jpg                    RGB
    <path>/<scene>/depth/<i>.png                    uint16 millimetres (0 = no depth)
    <path>/<scene>/pose/<i>.txt                     4 x 4 camera-to-world
    <path>/<scene>/intrinsic/intrinsic_depth.txt    4 x 4, top-left 3 x 3 = K of the depth image
    <path>/<scene>/label-filt/<i>.png               uint16 raw ScanNet label ids
        (or <path>/<scene>/<scene>_2d-label-filt/label-filt/<i>.png, the unzipped archive
        as RayFronts reads it)

**Labels.** A raw id maps through the tsv's ``id -> nyu40id`` columns to NYU40, then to the 37
evaluated classes (:data:`resireg.ovss.SCANNET_CLASSES`, NYU40 without otherstructure,
otherfurniture, otherprop); 0 (unlabelled), ids absent from the tsv and the three "other"
classes become 255 (ignored).

**Frames.** ``frame_skip = s`` keeps frame ``i`` when ``i % (s + 1) == 0``: one frame is
consumed, then ``s`` are dropped (frames 0, 11, 22, ... for ``s = 10``). This is RayFronts'
``ScanNetDataset`` rule, whose evaluation RADSeg and the paper's Table 2 use, so "frame skip
10" selects the same frames as theirs. Of the kept frames, one whose pose has a non-finite
entry (ScanNet writes ``-inf`` where tracking was lost) is dropped up front and listed; a
frame whose colour, depth, label or pose file is missing or cannot be decoded is skipped
when it is loaded and listed; neither stops the run.

**Resolution.** Colour is resized (bilinear, antialiased) and depth (nearest-exact) to
``image_size`` (640 x 864 in the protocol); the depth intrinsics are scaled from the depth
image to it (:func:`resireg.mapping.scale_intrinsics`). The encoder's input rule then applies
(``short_side``; sides rounded to its patch size); features are placed in 3D by
:func:`resireg.mapping.patch_points` from the ``image_size`` depth, so the patch grid follows
the features' grid exactly. Colour and depth are taken to share the field of view (ScanNet's
colour and depth intrinsics give the same ~58 degrees horizontally), as RayFronts does.

**Ground truth** uses the label image at ``gt_resolution`` (``null``: the label file's own
resolution) with the depth nearest-resized to it and the depth intrinsics scaled alike; the
prototype/batch ablation uses ``[228, 308]``.
"""

from __future__ import annotations

import csv
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from resireg.mapping import nearest_downsample, scale_intrinsics
from resireg.models.images import patch_grid_size, pil_to_tensor, resize_to_patch_grid
from resireg.ovss import NYU40_CLASSES, SCANNET_CLASSES
from resireg_train.files import DECODE_ERRORS
from resireg_train.ovss.datasets import IGNORE_INDEX, SkippedSample

__all__ = [
    "DEFAULT_SCENES",
    "LABEL_MAP_FILE",
    "ScanNetFrames",
    "build_scannet",
    "collate_frames",
    "label_lookup",
    "read_label_map",
]

log = logging.getLogger(__name__)

LABEL_MAP_FILE = "scannetv2-labels.combined.tsv"
#: The 12 validation scenes of RayFronts / RADSeg (``conf/dataset/scannet.yaml``).
DEFAULT_SCENES: tuple[str, ...] = (
    "scene0050_00", "scene0050_01", "scene0050_02", "scene0231_00", "scene0231_01",
    "scene0231_02", "scene0378_00", "scene0378_01", "scene0378_02", "scene0518_00",
    "scene0011_00", "scene0011_01",
)  # fmt: skip
_LABEL_DIRS = ("label-filt", "{scene}_2d-label-filt/label-filt")


def check_scannet_source(root: str | Path, scenes: Sequence[str], key: str = "dataset") -> None:
    """A FileNotFoundError naming ``<key>.path`` or ``<key>.scenes`` unless ``root`` is a folder
    holding every scene folder. :class:`ScanNetFrames` starts with it; ``resireg-eval`` calls
    it before loading the encoder, so a wrong path costs no model load."""
    folder = Path(root).expanduser()
    if not folder.is_dir():
        raise FileNotFoundError(
            f"{key}.path={str(root)!r}: no such folder (the ScanNet root holding "
            f"<scene>/{{color,depth,pose,intrinsic,label-filt}}); set {key}.path"
        )
    if not scenes:
        raise ValueError(f"{key}.scenes=[]: name at least one scene")
    missing = [s for s in scenes if not (folder / s).is_dir()]
    if missing:
        raise FileNotFoundError(f"{key}.scenes: {missing} not found under {key}.path={str(root)!r}")


def read_label_map(path: str | Path, key: str = "dataset.label_map") -> dict[int, int]:
    """``{raw ScanNet id: NYU40 id}`` from ``scannetv2-labels.combined.tsv`` (tab-separated,
    columns ``id`` and ``nyu40id``; rows with an empty NYU40 id are left out)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"{key}: no label map {str(path)!r} (ScanNet's {LABEL_MAP_FILE}, columns id and "
            f"nyu40id); put it at the dataset root or set {key} to its path"
        )
    with path.open(newline="") as f:
        reader = csv.DictReader(f, delimiter="\t")
        missing = {"id", "nyu40id"} - set(reader.fieldnames or ())
        if missing:
            raise ValueError(
                f"{key}={str(path)!r}: no column(s) {sorted(missing)} (found {reader.fieldnames})"
            )
        out = {}
        for row in reader:
            if str(row["id"]).strip() and str(row["nyu40id"]).strip():
                out[int(row["id"])] = int(row["nyu40id"])
    return out


def label_lookup(raw_to_nyu40: Mapping[int, int]) -> np.ndarray:
    """A ``[65536]`` uint8 table: raw uint16 label id -> index in :data:`SCANNET_CLASSES`, or
    255 for unlabelled (0), unknown ids and NYU40 ids outside the 37 evaluated classes."""
    index = {name: i for i, name in enumerate(SCANNET_CLASSES)}
    table = np.full(1 << 16, IGNORE_INDEX, dtype=np.uint8)
    for raw, nyu in raw_to_nyu40.items():
        if 0 < raw < (1 << 16) and 1 <= nyu <= len(NYU40_CLASSES):
            table[raw] = index.get(NYU40_CLASSES[nyu - 1], IGNORE_INDEX)
    return table


def _read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    m = np.loadtxt(path, dtype=np.float64, ndmin=2)
    if m.shape != shape:
        raise ValueError(f"{path}: expected a {shape[0]} x {shape[1]} matrix, got {m.shape}")
    return m


@dataclass(frozen=True)
class _Frame:
    scene: int
    index: int
    color: Path
    depth: Path
    label: Path
    pose: np.ndarray


class ScanNetFrames(torch.utils.data.Dataset):
    """The kept frames of the chosen scenes, scene by scene in frame order.

    Item ``i`` (:meth:`__getitem__`) is a dict of tensors, or a :class:`SkippedSample`
    naming the frame's file and why it was not used:

    - ``image`` float ``[3, h, w]`` in [0, 1]: colour at ``image_size``, then the encoder's
      input rule (``short_side``, patch size),
    - ``depth`` float ``[H, W]`` metres at ``image_size`` and ``intrinsics`` ``[3, 3]`` for it,
    - ``gt_label`` int64 ``[Hg, Wg]`` (class ids, 255 = ignore), ``gt_depth`` ``[Hg, Wg]``
      and ``gt_intrinsics`` ``[3, 3]`` at ``gt_resolution`` (the label file's size if null),
    - ``pose`` float64 ``[4, 4]`` camera-to-world, ``scene`` (position in :attr:`scenes`),
      ``frame`` (frame number) and ``index`` (item index).

    Attributes:
        scenes: scene names; :attr:`frames_per_scene` item indices per scene.
        dropped: the kept-by-skip frames dropped for a non-finite pose (or an unreadable
            pose file), as :class:`SkippedSample`.
    """

    def __init__(
        self,
        root: str | Path,
        scenes: Sequence[str],
        label_map: str | Path | None = None,
        frame_skip: int = 10,
        image_size: tuple[int, int] = (640, 864),
        gt_resolution: tuple[int, int] | None = None,
        short_side: int | None = None,
        patch_size: int = 16,
        limit: int | None = None,
        name: str = "scannet",
        key: str = "dataset",
    ) -> None:
        self.name = name
        self.classes = SCANNET_CLASSES
        self.ignore_index = IGNORE_INDEX
        self.root = Path(root).expanduser()
        self.frame_skip = int(frame_skip)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.gt_resolution = (
            None if gt_resolution is None else (int(gt_resolution[0]), int(gt_resolution[1]))
        )
        self.short_side = short_side
        self.patch_size = patch_size
        check_scannet_source(root, scenes, key)
        label_path = Path(label_map).expanduser() if label_map else self.root / LABEL_MAP_FILE
        self.lookup = label_lookup(read_label_map(label_path, f"{key}.label_map"))
        self.scenes = tuple(scenes)
        self.intrinsics: list[np.ndarray] = []
        self.depth_sizes: list[tuple[int, int]] = []
        self.frames: list[_Frame] = []
        self.frames_per_scene: list[list[int]] = []
        self.dropped: list[SkippedSample] = []
        for s, scene in enumerate(self.scenes):
            self.frames_per_scene.append(self._scan(s, scene, limit, key))

    def _scan(self, s: int, scene: str, limit: int | None, key: str) -> list[int]:
        folder = self.root / scene
        for sub in ("color", "depth", "pose"):
            if not (folder / sub).is_dir():
                raise FileNotFoundError(f"{key}.scenes: {folder} has no {sub}/ folder")
        k_path = folder / "intrinsic" / "intrinsic_depth.txt"
        if not k_path.is_file():
            raise FileNotFoundError(f"{key}.scenes: {folder} has no intrinsic/intrinsic_depth.txt")
        self.intrinsics.append(_read_matrix(k_path, (4, 4))[:3, :3])
        label_dir = next(
            (folder / d.format(scene=scene) for d in _LABEL_DIRS
             if (folder / d.format(scene=scene)).is_dir()),
            None,
        )  # fmt: skip
        if label_dir is None:
            raise FileNotFoundError(
                f"{key}.scenes: {folder} has no label-filt/ (nor {scene}_2d-label-filt/"
                "label-filt/) folder"
            )
        stems = {  # frame number -> file stem ("12" or a zero-padded "000012")
            int(p.stem): p.stem
            for p in (folder / "color").glob("*.jpg")
            if re.fullmatch(r"\d+", p.stem)
        }
        kept = [i for i in sorted(stems) if i % (self.frame_skip + 1) == 0]
        items, depth_size = [], None
        for i in kept:
            if limit is not None and len(items) >= limit:
                break
            stem = stems[i]
            pose_file = folder / "pose" / f"{stem}.txt"
            try:
                pose = _read_matrix(pose_file, (4, 4))
            except (OSError, ValueError) as err:
                self.dropped.append(SkippedSample(-1, str(pose_file), f"unreadable pose: {err}"))
                continue
            if not np.isfinite(pose).all():
                self.dropped.append(SkippedSample(-1, str(pose_file), "non-finite pose"))
                continue
            frame = _Frame(
                s, i, folder / "color" / f"{stem}.jpg", folder / "depth" / f"{stem}.png",
                label_dir / f"{stem}.png", pose,
            )  # fmt: skip
            if depth_size is None:
                try:
                    with Image.open(frame.depth) as im:
                        depth_size = (im.size[1], im.size[0])
                except DECODE_ERRORS:
                    pass
            items.append(len(self.frames))
            self.frames.append(frame)
        self.depth_sizes.append(depth_size or self.image_size)
        if not items:
            log.warning("%s: no usable frames in scene %s", self.name, scene)
        return items

    def __len__(self) -> int:
        return len(self.frames)

    def describe(self, index: int) -> str:
        return str(self.frames[index].color)

    def grid_size(self) -> tuple[int, int]:
        """``(H, W)`` of the encoder input (``image_size`` after the input rule)."""
        return patch_grid_size(self.image_size, self.short_side, self.patch_size)

    def batches(self, batch_size: int) -> list[list[int]]:
        """Consecutive frames of one scene per batch (a scene's last batch may be smaller):
        ReSiReg Full's batch = scene is a video window."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        return [
            items[i : i + batch_size]
            for items in self.frames_per_scene
            for i in range(0, len(items), batch_size)
        ]

    def _load(self, frame: _Frame) -> dict[str, Any]:
        k = torch.from_numpy(self.intrinsics[frame.scene])
        with Image.open(frame.color) as im:
            colour = pil_to_tensor(im)
        with Image.open(frame.depth) as im:
            depth_mm = np.asarray(im).astype(np.float32)
        with Image.open(frame.label) as im:
            raw = np.asarray(im)
        if depth_mm.ndim != 2:
            raise ValueError(f"depth has shape {depth_mm.shape}: expected one channel")
        if raw.ndim != 2:
            raise ValueError(f"label has shape {raw.shape}: expected one channel")
        depth = torch.from_numpy(depth_mm / 1000.0)
        size = tuple(depth.shape)
        image = resize_to_patch_grid(_resize_rgb(colour, self.image_size), self.short_side,
                                     self.patch_size)  # fmt: skip
        label = torch.from_numpy(self.lookup[raw.astype(np.int64)].astype(np.int64))
        gt_size = self.gt_resolution or tuple(label.shape)
        if tuple(label.shape) != gt_size:
            label = nearest_downsample(label, gt_size)
        return {
            "image": image,
            "depth": nearest_downsample(depth, self.image_size),
            "intrinsics": scale_intrinsics(k, size, self.image_size).float(),
            "gt_label": label,
            "gt_depth": nearest_downsample(depth, gt_size),
            "gt_intrinsics": scale_intrinsics(k, size, gt_size).float(),
            "pose": torch.from_numpy(frame.pose),
            "scene": frame.scene,
            "frame": frame.index,
        }

    def __getitem__(self, index: int) -> dict[str, Any] | SkippedSample:
        frame = self.frames[index]
        try:
            item = self._load(frame)
        except FileNotFoundError as err:
            return SkippedSample(index, self.describe(index), f"missing file: {err.filename}")
        except (*DECODE_ERRORS, RuntimeError) as err:
            return SkippedSample(index, self.describe(index), f"unreadable: {err}")
        item["index"] = index
        return item


def _resize_rgb(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """uint8 RGB ``[3, H, W]`` -> float ``[3, *size]`` in [0, 1] (bilinear, antialiased)."""
    x = image.float() / 255.0
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return torch.nn.functional.interpolate(
        x[None], size=size, mode="bilinear", align_corners=False, antialias=True
    )[0].clamp_(0, 1)


def collate_frames(items: list[dict[str, Any] | SkippedSample]) -> dict[str, Any]:
    """Stack the frames of a batch (all of one scene and size); ``skipped`` lists the
    batch's :class:`SkippedSample` records; tensors are ``None`` when all were skipped."""
    kept = [item for item in items if not isinstance(item, SkippedSample)]
    out: dict[str, Any] = {"skipped": [i for i in items if isinstance(i, SkippedSample)]}
    for name in ("image", "depth", "intrinsics", "gt_label", "gt_depth", "gt_intrinsics", "pose"):
        out[name] = torch.stack([item[name] for item in kept]) if kept else None
    for name in ("scene", "frame", "index"):
        out[name] = [item[name] for item in kept]
    return out


_KEYS = {"name", "kind", "path", "label_map", "scenes", "frame_skip", "image_size",
         "gt_resolution", "short_side", "limit", "voxel_size", "gt_unlabelled"}  # fmt: skip


def scannet_source(spec: Mapping[str, Any], key: str = "dataset") -> tuple[str, list[str]]:
    """The root folder and the scenes of a ``conf/dataset/scannet.yaml`` entry (the 12
    validation scenes when ``scenes`` is unset); check them with
    :func:`check_scannet_source`."""
    if not spec.get("path"):
        raise ValueError(f"{key}.path={spec.get('path')!r}: set the ScanNet root folder")
    return str(spec["path"]), list(spec.get("scenes") or DEFAULT_SCENES)


def build_scannet(spec: Mapping[str, Any], patch_size: int, key: str = "dataset") -> ScanNetFrames:
    """:class:`ScanNetFrames` from a ``conf/dataset/scannet.yaml`` entry (keys: ``path``,
    ``label_map``, ``scenes``, ``frame_skip``, ``image_size``, ``gt_resolution``,
    ``short_side``, ``limit`` (kept frames per scene); ``voxel_size`` and ``gt_unlabelled``
    are the task's, :class:`~resireg_train.mapping.engine.MappingTask`)."""
    if spec.get("kind") != "scannet":
        raise ValueError(f"{key}.kind={spec.get('kind')!r}: the scannet3d task needs 'scannet'")
    unknown = set(spec) - _KEYS
    if unknown:
        raise ValueError(
            f"{key}: unknown keys {sorted(unknown)} for kind 'scannet' ({sorted(_KEYS)})"
        )
    root, scenes = scannet_source(spec, key)
    gt = spec.get("gt_resolution")
    return ScanNetFrames(
        root,
        scenes,
        label_map=spec.get("label_map"),
        frame_skip=int(spec.get("frame_skip", 10)),
        image_size=tuple(spec.get("image_size") or (640, 864)),
        gt_resolution=tuple(gt) if gt else None,
        short_side=spec.get("short_side"),
        patch_size=patch_size,
        limit=spec.get("limit"),
        name=str(spec.get("name") or "scannet"),
        key=key,
    )
