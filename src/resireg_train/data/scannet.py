"""ScanNet v2 frames for the 3D semantic-mapping task (docs/maps.md#scannet-evaluation).

Layout read (the ScanNet ``SensReader`` export plus the ``2d-label-filt`` archive)::

    <path>/scannetv2-labels.combined.tsv           (or dataset.label_map)
    <path>/<scene>/color/<i>.jpg                    RGB
    <path>/<scene>/depth/<i>.png                    uint16 millimetres (0 = no depth)
    <path>/<scene>/pose/<i>.txt                     4 x 4 camera-to-world
    <path>/<scene>/intrinsic/intrinsic_depth.txt    4 x 4, top-left 3 x 3 = K of the depth image
    <path>/<scene>/label-filt/<i>.png               uint16 raw ScanNet label ids
        (or <path>/<scene>/<scene>_2d-label-filt/label-filt/<i>.png, the unzipped archive
        as RayFronts reads it)

**Classes** (RayFronts' ``ScanNetDataset`` + ``SemSegDataset._init_semseg_mappings``): a raw id
maps through the tsv's ``id -> nyu40id`` columns to an NYU40 id; the classes are the NYU40 ids
the label map holds, in id order, named by its ``nyu40class`` column (``class_names:
label_map``) or by :data:`resireg.ovss.NYU40_CLASSES` (``nyu40``), without
``classes_to_ignore`` (default otherstructure, otherfurniture, otherprop: RADSeg's
``evaluation/3d/configs/scannet_radseg.yaml``, 37 classes on ScanNet). Raw id 0 (unlabelled),
ids absent from the tsv and the ignored classes become 255 (ignored).

**Frames.** ``frame_skip = s`` keeps frame ``i`` when ``i % (s + 1) == 0``: one frame is
consumed, then ``s`` are dropped (frames 0, 11, 22, ... for ``s = 10``). This is RayFronts'
``ScanNetDataset`` rule, whose evaluation RADSeg and the paper's Table 2 use, so "frame skip
10" selects the same frames as theirs. Of the kept frames, one whose pose has a non-finite
entry (ScanNet writes ``-inf`` where tracking was lost) is dropped up front and listed; a
frame whose colour, depth, label or pose file is missing or cannot be decoded is skipped
when it is loaded and listed with that file; neither stops the run.

**Resolution.** Colour is resized (bilinear, antialiased) and depth by the ``resize`` rule
(:data:`RESIZES`: ``torch``, ``torch.nn.functional.interpolate(mode="nearest-exact")`` as
RayFronts; ``exact``: :func:`resireg.mapping.nearest_downsample`) to ``image_size`` (640 x 864 in
the protocol); the depth intrinsics are scaled from the depth image to it by the
``intrinsics`` rule (:data:`INTRINSICS`: ``multiply``, ``c' = c s`` as RayFronts; ``half_pixel``,
:func:`resireg.mapping.scale_intrinsics`). The encoder's input rule then applies
(``short_side``; sides rounded to its patch size). Colour and depth are taken to share the field
of view (ScanNet's colour and depth intrinsics give the same ~58 degrees horizontally), as
RayFronts does.

**Ground truth** uses the label image at ``gt_resolution``: ``image`` (default) = ``image_size``,
the RGB-D resolution, labels resized like depth (RayFronts: labels at ``rgb_resolution`` =
``depth_resolution``); ``label`` = the label file's own size; or ``[H, W]`` (the
prototype/batch ablation: ``[228, 308]``). The depth is resized to it by the same ``resize``
rule and its intrinsics scaled by the ``intrinsics`` rule.

One idea: the ScanNet reader. Its layout, classes, frame selection, resolution and ground truth
are the one protocol of RayFronts' ``ScanNetDataset`` (above), read by one dataset class and
its checks, with :class:`SceneFrames`, what every 3D set of posed frames shares; Replica and
TartanAir, which yield the same items, build on :mod:`resireg_train.data.posed3d`.
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
from resireg.ovss import NYU40_CLASSES
from resireg.sources.frames import DECODE_ERRORS
from resireg.sources.scannet import (
    FrameFileError,
    read_image,
    read_matrix,
    resize_rgb,
    scannet_rgbd,
)
from resireg.specs.rules import check_batch_size
from resireg_train.data.segmentation import IGNORE_INDEX, SkippedSample
from resireg_train.data.specs import (
    CLASS_NAMES,
    GT_RESOLUTIONS,
    INTRINSICS,
    RESIZES,
    check_dataset_keys,
    check_dataset_values,
    require_keys,
)

__all__ = [
    "CLASS_NAMES",
    "DEFAULT_IGNORED",
    "GT_RESOLUTIONS",
    "INTRINSICS",
    "LABEL_MAP_FILE",
    "RESIZES",
    "ScanNetFrames",
    "SceneFrames",
    "build_scannet",
    "check_scannet_spec",
    "collate_frames",
    "evaluated_classes",
    "label_lookup",
    "read_label_map",
    "resize_nearest",
    "scale_camera",
    "scannet_rgbd",
]

log = logging.getLogger(__name__)

LABEL_MAP_FILE = "scannetv2-labels.combined.tsv"
_LABEL_DIRS = ("label-filt", "{scene}_2d-label-filt/label-filt")
#: The classes RADSeg's ScanNet config leaves out (``classes_to_ignore``).
DEFAULT_IGNORED = ("otherstructure", "otherfurniture", "otherprop")


def resize_nearest(image: torch.Tensor, size: tuple[int, int], rule: str) -> torch.Tensor:
    """Nearest resize of the last two axes of a depth or label map ``[..., H, W]`` by ``rule``:
    ``torch`` (``F.interpolate(mode="nearest-exact")`` in float32, RayFronts' depth and label
    resize; integer labels come back as int64) or ``exact`` (the integer rule of
    :func:`resireg.mapping.nearest_downsample`)."""
    if tuple(image.shape[-2:]) == tuple(size):
        return image
    if rule == "exact":
        return nearest_downsample(image, size)
    if rule != "torch":
        raise ValueError(f"resize={rule!r}: expected one of {RESIZES}")
    lead = image.shape[:-2]
    x = image.reshape(1, -1, *image.shape[-2:]).float()
    out = torch.nn.functional.interpolate(x, size=tuple(size), mode="nearest-exact")
    out = out.reshape(*lead, *size)
    return out if image.is_floating_point() else out.long()


def scale_camera(
    intrinsics: torch.Tensor, from_hw: tuple[int, int], to_hw: tuple[int, int], rule: str
) -> torch.Tensor:
    """Intrinsics ``[3, 3]`` of an image resized from ``from_hw`` to ``to_hw`` by ``rule``:
    ``multiply`` (``K[0] *= W'/W``, ``K[1] *= H'/H``: RayFronts' ``ScanNetDataset``) or
    ``half_pixel`` (:func:`resireg.mapping.scale_intrinsics`: ``c' = (c + 0.5) s - 0.5``)."""
    if rule == "half_pixel":
        return scale_intrinsics(intrinsics, from_hw, to_hw)
    if rule != "multiply":
        raise ValueError(f"intrinsics={rule!r}: expected one of {INTRINSICS}")
    out = intrinsics.to(torch.float64).clone()
    out[0] *= to_hw[1] / from_hw[1]
    out[1] *= to_hw[0] / from_hw[0]
    return out.to(intrinsics.dtype)


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


def read_label_map(
    path: str | Path, key: str = "dataset.label_map"
) -> tuple[dict[int, int], dict[int, str]]:
    """``({raw ScanNet id: NYU40 id}, {NYU40 id: nyu40class name})`` from
    ``scannetv2-labels.combined.tsv`` (tab-separated, columns ``id`` and ``nyu40id``, and
    ``nyu40class`` if present; rows with an empty NYU40 id are left out)."""
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
        raw_to_nyu, names = {}, {}
        for row in reader:
            if str(row["id"]).strip() and str(row["nyu40id"]).strip():
                nyu = int(row["nyu40id"])
                raw_to_nyu[int(row["id"])] = nyu
                name = str(row.get("nyu40class") or "").strip()
                if nyu not in names and name:
                    names[nyu] = name
    return raw_to_nyu, names


def evaluated_classes(
    raw_to_nyu40: Mapping[int, int],
    nyu40_names: Mapping[int, str],
    class_names: str = "label_map",
    ignore: Sequence[str] = DEFAULT_IGNORED,
    key: str = "dataset",
) -> tuple[tuple[int, ...], tuple[str, ...]]:
    """The evaluated classes: ``(NYU40 ids, names)`` in id order (module docstring).

    The NYU40 ids (1..40) the label map uses, named by its ``nyu40class`` column
    (``label_map``; an id without a name there takes NYU40's) or by NYU40's names (``nyu40``),
    without the names in ``ignore``. A name in ``ignore`` that is neither an NYU40 class nor a
    class of the label map is an error naming ``<key>.classes_to_ignore``."""
    check_dataset_values("scannet", {"class_names": class_names}, key)
    ids = sorted({n for n in raw_to_nyu40.values() if 1 <= n <= len(NYU40_CLASSES)})
    name = {
        n: (nyu40_names.get(n) if class_names == "label_map" else None) or NYU40_CLASSES[n - 1]
        for n in ids
    }
    unknown = sorted(set(ignore) - set(name.values()) - set(NYU40_CLASSES))
    if unknown:
        raise ValueError(
            f"{key}.classes_to_ignore={list(ignore)!r}: {unknown} name no NYU40 class nor a "
            f"class of the label map (its classes: {[name[n] for n in ids]})"
        )
    kept = [n for n in ids if name[n] not in set(ignore)]
    if not kept:
        raise ValueError(f"{key}.classes_to_ignore={list(ignore)!r}: no class is left to evaluate")
    return tuple(kept), tuple(name[n] for n in kept)


def label_lookup(raw_to_nyu40: Mapping[int, int], class_ids: Sequence[int]) -> np.ndarray:
    """A ``[65536]`` uint8 table: raw uint16 label id -> index of its NYU40 id in
    ``class_ids`` (:func:`evaluated_classes`), or 255 for unlabelled (0), unknown ids and NYU40
    ids that are not evaluated."""
    index = {nyu: i for i, nyu in enumerate(class_ids)}
    table = np.full(1 << 16, IGNORE_INDEX, dtype=np.uint8)
    for raw, nyu in raw_to_nyu40.items():
        if 0 < raw < (1 << 16):
            table[raw] = index.get(nyu, IGNORE_INDEX)
    return table


@dataclass(frozen=True)
class _Frame:
    scene: int
    index: int
    color: Path
    depth: Path
    label: Path
    pose: np.ndarray


class SceneFrames(torch.utils.data.Dataset):
    """What every 3D evaluation set of posed frames shares (:class:`ScanNetFrames`,
    :class:`resireg_train.data.posed3d.PosedFrames`): its length, a frame's name, the encoder's
    grid and the batches of consecutive frames of one scene. A subclass sets ``frames`` (each
    with its ``color`` path), ``frames_per_scene`` (item indices, scene by scene),
    ``image_size``, ``short_side`` and ``patch_size``."""

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
        check_batch_size(batch_size)
        return [
            items[i : i + batch_size]
            for items in self.frames_per_scene
            for i in range(0, len(items), batch_size)
        ]


class ScanNetFrames(SceneFrames):
    """The kept frames of the chosen scenes, scene by scene in frame order.

    Item ``i`` (:meth:`__getitem__`) is a dict of tensors, or a :class:`SkippedSample`
    naming the frame's file that could not be read (colour, depth or label) and why:

    - ``image`` float ``[3, h, w]`` in [0, 1]: colour at ``image_size``, then the encoder's
      input rule (``short_side``, patch size),
    - ``depth`` float ``[H, W]`` metres at ``image_size`` and ``intrinsics`` ``[3, 3]`` for it,
    - ``gt_label`` int64 ``[Hg, Wg]`` (class ids, 255 = ignore), ``gt_depth`` ``[Hg, Wg]``
      and ``gt_intrinsics`` ``[3, 3]`` at ``gt_resolution``,
    - ``pose`` float64 ``[4, 4]`` camera-to-world, ``scene`` (position in :attr:`scenes`),
      ``frame`` (frame number) and ``index`` (item index).

    Args (module docstring): ``resize`` in :data:`RESIZES`, ``intrinsics`` in
    :data:`INTRINSICS`, ``gt_resolution`` ``"image"``, ``"label"`` or ``(H, W)``,
    ``class_names`` in :data:`CLASS_NAMES`, ``classes_to_ignore`` class names.

    Attributes:
        scenes: scene names; :attr:`frames_per_scene` item indices per scene.
        classes: the evaluated class names; :attr:`class_ids` their NYU40 ids.
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
        gt_resolution: str | tuple[int, int] = "image",
        short_side: int | None = None,
        patch_size: int = 16,
        limit: int | None = None,
        name: str = "scannet",
        key: str = "dataset",
        resize: str = "torch",
        intrinsics: str = "multiply",
        class_names: str = "label_map",
        classes_to_ignore: Sequence[str] = DEFAULT_IGNORED,
    ) -> None:
        self.name = name
        self.ignore_index = IGNORE_INDEX
        self.root = Path(root).expanduser()
        self.frame_skip = int(frame_skip)
        self.image_size = (int(image_size[0]), int(image_size[1]))
        # the table's rules (gt_resolution's only for a name: Python may pass (H, W) tuples)
        named = {"gt_resolution": gt_resolution} if isinstance(gt_resolution, str) else {}
        check_dataset_values("scannet", {**named, "resize": resize, "intrinsics": intrinsics}, key)
        if isinstance(gt_resolution, str):
            self.gt_resolution: str | tuple[int, int] = gt_resolution
        else:
            self.gt_resolution = (int(gt_resolution[0]), int(gt_resolution[1]))
        self.resize, self.intrinsics_rule = resize, intrinsics
        self.short_side = short_side
        self.patch_size = patch_size
        check_scannet_source(root, scenes, key)
        label_path = Path(label_map).expanduser() if label_map else self.root / LABEL_MAP_FILE
        raw_to_nyu, nyu_names = read_label_map(label_path, f"{key}.label_map")
        self.class_ids, self.classes = evaluated_classes(
            raw_to_nyu, nyu_names, class_names, tuple(classes_to_ignore), key
        )
        self.lookup = label_lookup(raw_to_nyu, self.class_ids)
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
        self.intrinsics.append(read_matrix(k_path, (4, 4))[:3, :3])
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
                pose = read_matrix(pose_file, (4, 4))
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

    def _load(self, frame: _Frame) -> dict[str, Any]:
        k = torch.from_numpy(self.intrinsics[frame.scene])
        colour = read_image(frame.color, "colour", pil_to_tensor)
        depth_mm = read_image(frame.depth, "depth").astype(np.float32)
        raw = read_image(frame.label, "label")
        if depth_mm.ndim != 2:
            raise FrameFileError(
                frame.depth, f"depth has shape {depth_mm.shape}: expected one channel"
            )
        if raw.ndim != 2:
            raise FrameFileError(frame.label, f"label has shape {raw.shape}: expected one channel")
        depth = torch.from_numpy(depth_mm / 1000.0)
        size = tuple(depth.shape)
        image = resize_to_patch_grid(resize_rgb(colour, self.image_size), self.short_side,
                                     self.patch_size)  # fmt: skip
        label = torch.from_numpy(self.lookup[raw.astype(np.int64)].astype(np.int64))
        gt_size = {"image": self.image_size, "label": tuple(label.shape)}.get(
            self.gt_resolution,
            self.gt_resolution,  # type: ignore[arg-type]
        )
        rule, camera = self.resize, self.intrinsics_rule
        return {
            "image": image,
            "depth": resize_nearest(depth, self.image_size, rule),
            "intrinsics": scale_camera(k, size, self.image_size, camera).float(),
            "gt_label": resize_nearest(label, gt_size, rule),
            "gt_depth": resize_nearest(depth, gt_size, rule),
            "gt_intrinsics": scale_camera(k, size, gt_size, camera).float(),
            "pose": torch.from_numpy(frame.pose),
            "scene": frame.scene,
            "frame": frame.index,
        }

    def __getitem__(self, index: int) -> dict[str, Any] | SkippedSample:
        frame = self.frames[index]
        try:
            item = self._load(frame)
        except FrameFileError as err:
            return SkippedSample(index, str(err.path), err.reason)
        item["index"] = index
        return item


def collate_frames(items: list[dict[str, Any] | SkippedSample]) -> dict[str, Any]:
    """Stack the frames of a batch (all of one scene and size); ``skipped`` lists the
    batch's :class:`SkippedSample` records; tensors are ``None`` when all were skipped (and
    ``gt_label`` when the frames carry none)."""
    kept = [item for item in items if not isinstance(item, SkippedSample)]
    out: dict[str, Any] = {"skipped": [i for i in items if isinstance(i, SkippedSample)]}
    for name in ("image", "depth", "intrinsics", "gt_label", "gt_depth", "gt_intrinsics", "pose"):
        # gt_label is absent where the ground truth is not lifted from frames (Replica's)
        out[name] = torch.stack([item[name] for item in kept]) if kept and name in kept[0] else None
    for name in ("scene", "frame", "index"):
        out[name] = [item[name] for item in kept]
    return out


#: Keys of a ``conf/dataset/scannet.yaml`` entry read by :class:`ScanNetFrames`; the entry's
#: every key (these, the task's and its own: name, kind, path, scenes, protocol) is listed by
#: the dataset table (:data:`resireg_train.data.specs.DATASET_SPECS`).
READER_KEYS = ("label_map", "frame_skip", "image_size", "gt_resolution", "short_side", "limit",
               "resize", "intrinsics", "class_names", "classes_to_ignore")  # fmt: skip


def scannet_source(spec: Mapping[str, Any], key: str = "dataset") -> tuple[str, list[str]]:
    """The root folder and the scenes of a ``conf/dataset/scannet.yaml`` entry (which holds
    both: a missing one is an error naming it); check them with :func:`check_scannet_source`."""
    if not spec.get("path"):
        raise ValueError(f"{key}.path={spec.get('path')!r}: set the ScanNet root folder")
    _require(spec, ("scenes",), key)
    return str(spec["path"]), list(spec["scenes"])


def _require(spec: Mapping[str, Any], names: Sequence[str], key: str) -> None:
    """A ValueError naming ``<key>.<name>`` for each of ``names`` the entry lacks (``conf/`` is
    the one source of the defaults)."""
    require_keys(spec, names, key, "conf/dataset/scannet.yaml")


def check_scannet_spec(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """What can be checked of a ScanNet entry before the encoder loads (a large backbone takes
    minutes): the root and scene folders (:func:`check_scannet_source`), the label map and
    ``classes_to_ignore`` against its classes (:func:`evaluated_classes`); each error names
    its key."""
    root, scenes = scannet_source(spec, key)
    check_scannet_source(root, scenes, key)
    _require(spec, ("label_map", "class_names", "classes_to_ignore"), key)
    label_map = spec["label_map"]
    path = Path(label_map).expanduser() if label_map else Path(root).expanduser() / LABEL_MAP_FILE
    raw_to_nyu, names = read_label_map(path, f"{key}.label_map")
    evaluated_classes(raw_to_nyu, names, str(spec["class_names"]),
                      tuple(spec["classes_to_ignore"]), key)  # fmt: skip


def build_scannet(spec: Mapping[str, Any], patch_size: int, key: str = "dataset") -> ScanNetFrames:
    """:class:`ScanNetFrames` from a ``conf/dataset/scannet.yaml`` entry, which holds every key
    of the kind ``scannet`` of the dataset table (:data:`resireg_train.data.specs.
    DATASET_SPECS`: the entry's own, the reader's :data:`READER_KEYS` and the 3D task's); any
    other key, or a missing one, is an error naming it."""
    if spec.get("kind") != "scannet":
        raise ValueError(f"{key}.kind={spec.get('kind')!r}: the scannet3d task needs 'scannet'")
    check_dataset_keys(spec, key)
    root, scenes = scannet_source(spec, key)
    options = {k: spec[k] for k in READER_KEYS}
    for size in ("image_size", "gt_resolution"):
        if isinstance(options.get(size), (list, tuple)):
            options[size] = tuple(int(v) for v in options[size])
    return ScanNetFrames(root, scenes, patch_size=patch_size,
                         name=str(spec.get("name") or "scannet"), key=key, **options)  # fmt: skip
