"""Segmentation datasets for OVSS evaluation: ADE20K-150, ORAD-3D and the synthetic scenes.

Every dataset is a map-style :class:`SegmentationSet` yielding the image resized so its
shorter side is ``short_side`` (576 in the paper's protocol; sides rounded to the patch
size) and the label map at full resolution (predictions are brought to the label size
with nearest upsampling, docs/method.md#2d-evaluation-ovss). The entry's 2D protocol
(:mod:`resireg_train.data.windows`: ``conf/protocol/paper.yaml`` or ``ovss8.yaml``) may
cap the longer side, drop the antialiasing and the patch rounding (sliding windows take any
size) and have the engine slide windows and resize logits bilinearly. The OVSS field's
benchmarks read from their downloaded folders are the kinds of :mod:`resireg_train.data.voc`,
:mod:`~resireg_train.data.context`, :mod:`~resireg_train.data.coco` and
:mod:`~resireg_train.data.cityscapes`.

Batches: ReSiReg Full treats a batch as one scene (prototypes shared across its images),
so every image of a batch must have the same resized size. :meth:`SegmentationSet.batches`
groups images by resized size, in dataset order: a batch is ``batch_size`` consecutive
images of one size, and a size's leftover images form one smaller batch at the end. With
images of one size (ORAD-3D, synthetic) that is plain consecutive batching; for ADE20K
the batch-size histogram is reported with the results.

Sources (``kind``; each an entry of the dataset table :data:`resireg_train.data.specs.
DATASET_SPECS`, which names its builder below and its keys; its ``conf/dataset/<kind>.yaml``
holds every key's value):

- ``ade20k``: ``path`` is a hub id (conf: ``zhoubolei/scene_parse_150``, config
  ``scene_parsing``, revision ``refs/convert/parquet``: the hub's script loader does not
  run with datasets >= 4), a local folder holding that parquet layout, or a local
  ``ADEChallengeData2016`` folder (``images/<split>/*.jpg``, ``annotations/<split>/*.png``).
  Labels 0..150 with 0 = "other", scored with ``reduce_zero_label``.
- ``orad3d``: a local ORAD-3D folder ``<path>/<split>/<sequence>/{image_data, gt_image,
  gt_image_multi_seg}``; see :func:`orad3d_label` for how labels are built.
- ``synthetic``: :class:`~resireg_train.data.synthetic.SyntheticScenes` with their masks.
"""

from __future__ import annotations

import io
import json
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image, ImageDraw

from resireg.models.hub import require_online
from resireg.models.images import pil_to_tensor, resize_to_patch_grid
from resireg.ovss import ADE20K_CLASSES, ORAD3D_CLASSES, label_problem
from resireg.sources.frames import DECODE_ERRORS
from resireg.specs.rules import check_batch_size
from resireg_train.config.errors import key_errors
from resireg_train.data.specs import check_dataset_keys, require_keys
from resireg_train.data.synthetic import SYNTHETIC_CLASSES, SyntheticScenes
from resireg_train.data.windows import WindowRules, window_rules

__all__ = [
    "SegmentationSet",
    "SkippedSample",
    "ade20k_source",
    "build_segmentation_set",
    "check_ade20k_source",
    "check_orad3d_source",
    "check_segmentation_source",
    "collate_segmentation",
    "orad3d_source",
    "synthetic_source",
    "orad3d_label",
]

log = logging.getLogger(__name__)

IGNORE_INDEX = 255
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


# ------------------------------------------------------------------------------ images
def _open(source: str | bytes | os.PathLike) -> Image.Image:
    return Image.open(io.BytesIO(source) if isinstance(source, bytes) else source)


def _header_size(source: str | bytes | os.PathLike) -> tuple[int, int]:
    """``(H, W)`` read from the file header (no decoding)."""
    with _open(source) as image:
        w, h = image.size
    return h, w


@dataclass(frozen=True)
class SkippedSample:
    """An image that was not scored: its dataset index, its file (or row) and why."""

    index: int
    file: str
    reason: str

    def as_dict(self) -> dict[str, str]:
        return {"file": self.file, "reason": self.reason}


class SegmentationSet(torch.utils.data.Dataset):
    """A segmentation dataset for OVSS: resized images and full-resolution labels.

    Args:
        name: dataset name (metric names ``val/ovss/<name>/...``).
        classes: class names, label ``i`` = ``classes[i]`` (after ``reduce_zero_label``).
        load: ``index -> (PIL image, label array [H, W])``.
        header_size: ``index -> (H, W)`` of the image without decoding it.
        length: number of images.
        short_side: shorter side after resizing (``None``: keep the size; the entry's
            ``short_side``, conf/dataset/: 576 in the paper's protocol).
        patch_size: sides are rounded to a multiple of it.
        reduce_zero_label: labels are 0 = unlabelled, ``c`` = class ``c - 1`` (ADE20K).
        describe: ``index -> str`` naming the sample's file (or row) in skip reports.
        windows: the entry's resize and window rules (:class:`~resireg_train.data.windows.
            WindowRules`: the longer side's cap, antialiasing, windows, upsampling,
            background); ``None``: ``conf/protocol/paper.yaml``'s.
        names: every name of each class (synonyms, ``conf/classes/``); ``None``: each class
            its own name.

    A sample whose image cannot be decoded, or whose label is not a single-channel map of
    the image's size holding valid class ids, is skipped: ``__getitem__`` returns a
    :class:`SkippedSample` naming the file and the reason, and the evaluation counts it.
    """

    def __init__(
        self,
        name: str,
        classes: Sequence[str],
        load: Callable[[int], tuple[Image.Image, np.ndarray]],
        header_size: Callable[[int], tuple[int, int]],
        length: int,
        short_side: int | None,
        patch_size: int,
        reduce_zero_label: bool = False,
        describe: Callable[[int], str] | None = None,
        windows: WindowRules | None = None,
        names: Sequence[Sequence[str]] | None = None,
    ) -> None:
        self.name = name
        self.classes = tuple(classes)
        self.names = tuple(tuple(n) for n in names) if names else tuple((c,) for c in classes)
        if len(self.names) != len(self.classes):
            raise ValueError(f"{len(self.names)} name lists for {len(self.classes)} classes")
        self.windows = windows if windows is not None else window_rules("paper")
        self._load = load
        self._header_size = header_size
        self.length = length
        self.short_side = short_side
        self.patch_size = patch_size
        self.reduce_zero_label = reduce_zero_label
        self.ignore_index = IGNORE_INDEX
        self._describe = describe or (lambda i: f"{name} #{i}")
        self._grid_sizes: dict[int, tuple[int, int]] | None = None
        self.unreadable: list[SkippedSample] = []

    def __len__(self) -> int:
        return self.length

    def describe(self, index: int) -> str:
        """The sample's file (or row), as skip reports name it."""
        return self._describe(index)

    def label_problem(self, label: np.ndarray, image_size: tuple[int, int]) -> str | None:
        """Why ``label`` cannot be scored against an image of ``image_size`` ``(H, W)``, or
        ``None``: it must be one class id per pixel, of the image's size (a label is never
        resized to fit), holding only valid ids (:func:`resireg.ovss.label_problem`)."""
        if label.ndim != 2:
            return (
                f"label has shape {tuple(label.shape)}: expected one class id per pixel "
                "(a single-channel map), not a colour image"
            )
        if tuple(label.shape) != tuple(image_size):
            (h, w), (ih, iw) = label.shape, image_size
            return f"label is {h} x {w} px but its image is {ih} x {iw} px"
        return label_problem(label, len(self.classes), self.ignore_index, self.reduce_zero_label)

    def __getitem__(self, index: int) -> dict[str, Any] | SkippedSample:
        """``{"image": float [3, h, w] in [0, 1], "label": int64 [H, W], "index"}``, or a
        :class:`SkippedSample` when the image or label cannot be decoded or scored."""
        try:
            image, label = self._load(index)
            pixels = pil_to_tensor(image)
            label = np.asarray(label)
        except DECODE_ERRORS as err:
            return SkippedSample(index, self.describe(index), f"unreadable: {err}")
        problem = self.label_problem(label, tuple(pixels.shape[-2:]))
        if problem is not None:
            return SkippedSample(index, self.describe(index), problem)
        return {
            "image": self.resize(pixels),
            "label": torch.from_numpy(label.astype(np.int64)),
            "index": index,
        }

    def resized_size(self, size: tuple[int, int]) -> tuple[int, int]:
        """``(H, W)`` an image of ``size`` is resized to (the protocol's rule:
        :meth:`~resireg_train.data.windows.WindowRules.resized_size`)."""
        return self.windows.resized_size(size, self.short_side, self.patch_size)

    def resize(self, pixels: torch.Tensor) -> torch.Tensor:
        """An RGB image ``[3, H, W]`` (uint8) -> float ``[3, h, w]`` in [0, 1] at
        :meth:`resized_size`, bilinear (``align_corners=False``), antialiased as the protocol
        says (the paper's path is :func:`resireg.models.images.resize_to_patch_grid`'s)."""
        size = self.resized_size(tuple(pixels.shape[-2:]))
        if (
            self.windows.antialias
            and not self.windows.sliding
            and (self.windows.long_side is None)
        ):  # the paper's rule, one implementation
            return resize_to_patch_grid(pixels, self.short_side, self.patch_size)
        image = pixels.float() / 255.0
        if size == tuple(image.shape[-2:]):
            return image
        return torch.nn.functional.interpolate(
            image[None], size=size, mode="bilinear", align_corners=False,
            antialias=self.windows.antialias,
        )[0]  # fmt: skip

    def grid_sizes(self) -> dict[int, tuple[int, int]]:
        """Resized ``(h, w)`` of every image whose header is readable (read once); the
        others are listed in :attr:`unreadable`."""
        if self._grid_sizes is None:
            sizes, self.unreadable = {}, []
            for i in range(self.length):
                try:
                    size = self._header_size(i)
                except DECODE_ERRORS as err:
                    self.unreadable.append(SkippedSample(i, self.describe(i), f"unreadable: {err}"))
                    continue
                sizes[i] = self.resized_size(size)
            self._grid_sizes = sizes
        return self._grid_sizes

    def batches(self, batch_size: int, rank: int = 0, world_size: int = 1) -> list[list[int]]:
        """Index batches whose images share a resized size (see the module docstring); rank
        ``r`` of ``world_size`` takes batches ``r, r + world_size, ...``."""
        check_batch_size(batch_size)
        groups: dict[tuple[int, int], list[int]] = {}
        batches: list[list[int]] = []
        for index, size in self.grid_sizes().items():
            group = groups.setdefault(size, [])
            group.append(index)
            if len(group) == batch_size:
                batches.append(groups.pop(size))
        batches.extend(g for g in groups.values() if g)
        return batches[rank::world_size]


def collate_segmentation(items: list[dict[str, Any] | SkippedSample]) -> dict[str, Any]:
    """Stack the images of a batch; labels stay a list (each at its own full resolution);
    ``skipped`` lists the batch's :class:`SkippedSample` records."""
    kept = [item for item in items if not isinstance(item, SkippedSample)]
    return {
        "image": torch.stack([item["image"] for item in kept]) if kept else None,
        "label": [item["label"] for item in kept],
        "index": [item["index"] for item in kept],
        "skipped": [item for item in items if isinstance(item, SkippedSample)],
    }


# ----------------------------------------------------------------------------- sources
def build_segmentation_set(
    spec: Mapping[str, Any], patch_size: int, key: str = "dataset", name: str | None = None
) -> SegmentationSet:
    """A :class:`SegmentationSet` from a config entry.

    Args:
        spec: an entry of a kind of the dataset table (:data:`resireg_train.data.specs.
            DATASET_SPECS`: ``synthetic``, ``ade20k``, ``orad3d`` or one registered there),
            holding every key of its kind (``name`` aside): ``short_side``, ``limit`` (first N
            images only), the resize and window rules (:class:`~resireg_train.data.windows.
            WindowRules`, passed to the builder in ``common`` as ``windows``) and the
            kind's own (module docstring; ADE20K's hub config name is ``config``).
            ``conf/dataset/<kind>.yaml`` holds them
            (:func:`resireg_train.data.specs.dataset_conf` reads it outside Hydra).
        patch_size: the backbone's patch size.
        key: the config key of ``spec``, for error messages.
        name: dataset name in metric names when ``spec`` has none.
    """
    with key_errors(key):  # the errors name the entry's keys: one line at the commands
        return _build(spec, patch_size, key, name)


def _build(spec: Mapping[str, Any], patch_size: int, key: str, name: str | None) -> SegmentationSet:
    entry = check_dataset_keys(spec, key)
    name = str(spec.get("name") or name or spec["kind"])
    short_side = spec["short_side"]
    if short_side is not None and int(short_side) < patch_size:
        raise ValueError(f"{key}.short_side={short_side!r}: expected null or >= {patch_size}")
    windows = WindowRules.from_spec(spec, key, patch_size)
    common = {"short_side": short_side, "patch_size": patch_size, "windows": windows}
    dataset = entry.load()(name, spec, key, common)
    limit = spec["limit"]
    if limit is not None:
        if int(limit) < 1:
            raise ValueError(f"{key}.limit={limit!r}: expected null or >= 1")
        dataset.length = min(dataset.length, int(limit))
    if dataset.length == 0:
        raise ValueError(f"{key}: the dataset is empty ({dict(spec)})")
    return dataset


def synthetic_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> SegmentationSet:
    """The ``synthetic`` kind: :class:`SyntheticScenes` of the entry's ``size``, ``image_size``,
    ``seed`` and ``noise`` with their masks."""
    scenes = SyntheticScenes(
        size=int(spec["size"]),
        image_size=tuple(spec["image_size"]),
        seed=int(spec["seed"]),
        noise=float(spec["noise"]),
    )

    def load(i: int) -> tuple[Image.Image, np.ndarray]:
        scene = scenes[i]
        return scene["image"], scene["mask"]

    return SegmentationSet(
        name, SYNTHETIC_CLASSES, load, lambda i: scenes.image_size, len(scenes), **common
    )


# ------------------------------------------------------------------------------ ADE20K
def ade20k_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> SegmentationSet:
    """The ``ade20k`` kind (module docstring)."""
    path, split = str(spec["path"]), str(spec["split"])
    common = {**common, "reduce_zero_label": True}
    local = Path(path).expanduser()
    if (local / "images" / split).is_dir():  # ADEChallengeData2016
        return _ade20k_folder(name, local, split, key, path, common)
    table = _load_hub_table(path, spec, split, key, local.is_dir())
    image_col, label_col = spec["image"], spec["label"]
    for role, col in (("image", image_col), ("label", label_col)):
        if col not in table.column_names:
            raise ValueError(
                f"{key}.{role}={col!r}: no such column; columns are {table.column_names}"
            )
    from datasets import Image as HFImage

    table = table.cast_column(image_col, HFImage(decode=False)).cast_column(
        label_col, HFImage(decode=False)
    )

    def stored(value: Mapping[str, Any]) -> bytes | str:  # embedded bytes, or a file path
        return value["bytes"] if value.get("bytes") is not None else value["path"]

    def load(i: int) -> tuple[Image.Image, np.ndarray]:
        row = table[i]
        return _open(stored(row[image_col])), np.asarray(_open(stored(row[label_col])))

    def describe(i: int) -> str:
        stored_path = table[i][image_col].get("path")
        return f"{path} [{split}] row {i}" + (f" ({stored_path})" if stored_path else "")

    return SegmentationSet(
        name,
        ADE20K_CLASSES,
        load,
        lambda i: _header_size(stored(table[i][image_col])),
        len(table),
        describe=describe,
        **common,
    )


def _ade20k_folder(
    name: str, root: Path, split: str, key: str, path: str, common: dict
) -> SegmentationSet:
    """ADEChallengeData2016: ``images/<split>/<stem>.jpg`` (any image suffix, any case) with
    ``annotations/<split>/<stem>.png``."""
    labels = {
        p.stem: p for p in (root / "annotations" / split).glob("*") if p.suffix.lower() == ".png"
    }
    pairs = []
    for image in sorted((root / "images" / split).iterdir()):
        if image.suffix.lower() not in _IMAGE_SUFFIXES:
            continue
        if image.stem not in labels:
            raise FileNotFoundError(
                f"{key}.path={path!r}: {image.name} has no annotations/{split}/{image.stem}.png"
            )
        pairs.append((image, labels[image.stem]))
    return SegmentationSet(
        name,
        ADE20K_CLASSES,
        lambda i: (_open(pairs[i][0]), np.asarray(_open(pairs[i][1]))),
        lambda i: _header_size(pairs[i][0]),
        len(pairs),
        describe=lambda i: str(pairs[i][0]),
        **common,
    )


def _check_hub_id(path: str, key: str) -> None:
    """``<key>.path`` names no local folder: a FileNotFoundError if it is a path rather than
    a hub id."""
    if path.startswith(("/", ".", "~")):
        raise FileNotFoundError(f"{key}.path={path!r} does not exist")


def _orad3d_root(spec: Mapping[str, Any], key: str) -> Path:
    """``<path>/<split>``, the folder of the ORAD-3D sequences; an error naming ``<key>.path``
    unless it exists."""
    require_keys(spec, ("path", "split"), key, "conf/dataset/orad3d.yaml")
    root = Path(str(spec["path"])).expanduser() / str(spec["split"])
    if not root.is_dir():
        raise FileNotFoundError(
            f"{key}.path={spec['path']!r}: no {root} folder (expected <path>/<split>/<sequence>/"
            "{image_data,gt_image,gt_image_multi_seg})"
        )
    return root


def check_orad3d_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``orad3d`` build's check that needs no model: a missing ``<path>/<split>`` folder."""
    _orad3d_root(spec, key)


def check_ade20k_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The ``ade20k`` build's check that needs no model: a ``path`` that is neither a folder
    nor a hub id. A hub dataset's availability is checked when it loads."""
    require_keys(spec, ("path",), key, "conf/dataset/ade20k.yaml")
    path = str(spec["path"])
    if not Path(path).expanduser().is_dir():
        _check_hub_id(path, key)


def check_segmentation_source(spec: Mapping[str, Any], key: str = "dataset") -> None:
    """The checks of :func:`build_segmentation_set` that need no model: the entry's keys
    against the dataset table, then its kind's source check (the table's ``check``: a missing
    ORAD-3D folder, an ADE20K ``path`` that is neither a folder nor a hub id), raising the
    error the build would. ``resireg-eval`` calls it before loading the encoder (whose patch
    size the build needs), so a wrong path costs no model load. The errors that name the
    entry's keys (a missing folder, a split list that is empty or names a missing file) are
    :class:`~resireg.errors.ConfigError` s of their own type
    (:func:`~resireg_train.config.errors.key_errors`): one line at the commands."""
    with key_errors(key):
        check = check_dataset_keys(spec, key).load_check()
        if check is not None:
            check(spec, key)


def _load_hub_table(path: str, spec: Mapping[str, Any], split: str, key: str, local: bool):
    """A map-style ``datasets.Dataset``: a local parquet folder, or the hub (cached or online)."""
    from datasets import load_dataset

    if local:
        return load_dataset(path, split=split)
    _check_hub_id(path, key)
    name, revision = spec["config"], spec["revision"]
    hint = (
        f"Download it where there is a network (e.g. `datasets.load_dataset({path!r}, {name!r}, "
        f"revision={revision!r}, split={split!r})` fills the cache; then set HF_HUB_OFFLINE=1), "
        f"or set {key}.path to a local ADEChallengeData2016 folder."
    )
    if os.environ.get("HF_HUB_OFFLINE", "").strip().lower() not in {"1", "true", "yes", "on"}:
        require_online(f"the hub dataset {path!r} ({key}.path)", "huggingface.co", hint)
    try:
        return load_dataset(path, name, revision=revision, split=split)
    except (ConnectionError, FileNotFoundError, OSError) as err:
        from resireg.models.hub import WeightsUnavailableError

        raise WeightsUnavailableError(
            f"the hub dataset {path!r} ({key}.path) is not in the local cache: {err}. {hint}"
        ) from err


# ------------------------------------------------------------------------------ ORAD-3D
def orad3d_label(
    gt_image: str | os.PathLike,
    polygons: str | os.PathLike | None,
    polygon_tags: Mapping[str, str],
    gt_image_classes: Mapping[str, str],
    key: str = "orad3d",
) -> np.ndarray:
    """ORAD-3D label map ``[H, W]`` (uint8 class ids of ``ORAD3D_CLASSES``, 255 = ignore).

    The base layer is ``gt_image`` (road / non-road / sky colours, ``gt_image_classes``;
    other colours are ignored). The ``gt_image_multi_seg`` polygons (a LabelMe-style JSON:
    ``{"shapes": [{"label": tag, "points": [[x, y], ...]}, ...]}``) are drawn over it in
    file order, each tag mapped to a class by ``polygon_tags``. Both mappings are the dataset
    entry's (``conf/dataset/orad3d.yaml`` holds ORAD-3D's; ``dataset_conf("orad3d")`` reads them
    outside Hydra).
    """
    index = {c: i for i, c in enumerate(ORAD3D_CLASSES)}
    for table, table_key in (
        (polygon_tags, "polygon_tags"),
        (gt_image_classes, "gt_image_classes"),
    ):
        bad = sorted(set(table.values()) - set(index))
        if bad:
            raise ValueError(f"{key}.{table_key}: {bad} are not ORAD-3D classes {ORAD3D_CLASSES}")
    rgb = np.asarray(_open(gt_image).convert("RGB"))
    label = np.full(rgb.shape[:2], IGNORE_INDEX, dtype=np.uint8)
    for colour, cls in gt_image_classes.items():
        r, g, b = (int(v) for v in str(colour).split(","))
        label[(rgb[..., 0] == r) & (rgb[..., 1] == g) & (rgb[..., 2] == b)] = index[cls]
    if polygons is None:
        return label
    canvas = Image.fromarray(label)
    draw = ImageDraw.Draw(canvas)
    for cls, points in _polygons(polygons, polygon_tags, key):
        if len(points) >= 3:
            draw.polygon(points, fill=index[cls])
    return np.asarray(canvas)


def _polygons(
    path: str | os.PathLike, polygon_tags: Mapping[str, str], key: str
) -> list[tuple[str, list[tuple[float, float]]]]:
    """``(class, points)`` of every polygon of a LabelMe-style JSON, in file order; a tag
    without a class is an error naming ``<key>.polygon_tags``."""
    shapes = []
    for shape in json.loads(Path(path).read_text()).get("shapes", []):
        tag = str(shape.get("label", "")).strip()
        if tag not in polygon_tags:
            raise ValueError(
                f"{path}: polygon tag {tag!r} has no class; add it to "
                f"{key}.polygon_tags (known: {sorted(polygon_tags)})"
            )
        shapes.append((polygon_tags[tag], [tuple(map(float, p)) for p in shape.get("points", [])]))
    return shapes


def _match(folder: Path, stem: str, suffixes: Sequence[str]) -> Path | None:
    """The file of ``folder`` named ``<stem><suffix>`` or ``<stem>_<anything><suffix>`` (the
    ORFD-style ``_fillcolor``); never another stem that merely starts alike (``10`` for ``1``)."""
    if not folder.is_dir():
        return None
    hits = sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in suffixes and (p.stem == stem or p.stem.startswith(f"{stem}_"))
    )
    return hits[0] if hits else None


def orad3d_source(name: str, spec: Mapping[str, Any], key: str, common: dict) -> SegmentationSet:
    """The ``orad3d`` kind (module docstring; labels: :func:`orad3d_label`)."""
    root = _orad3d_root(spec, key)
    tags, colours = dict(spec["polygon_tags"]), dict(spec["gt_image_classes"])
    items: list[tuple[Path, Path, Path | None]] = []
    for sequence in sorted(p for p in root.iterdir() if p.is_dir()):
        images = sorted(
            p for p in (sequence / "image_data").glob("*") if p.suffix.lower() in _IMAGE_SUFFIXES
        )
        for image in images:
            gt = _match(sequence / "gt_image", image.stem, (".png",))
            if gt is None:
                continue  # not annotated
            items.append(
                (image, gt, _match(sequence / "gt_image_multi_seg", image.stem, (".json",)))
            )
    if not items:
        raise FileNotFoundError(f"{key}.path={spec['path']!r}: no annotated images under {root}")
    # Tags are checked up front: a decoding error skips an image, a missing tag must not.
    for _, _, polygons in items:
        if polygons is not None:
            _polygons(polygons, tags, key)

    def load(i: int) -> tuple[Image.Image, np.ndarray]:
        image, gt, polygons = items[i]
        return _open(image), orad3d_label(gt, polygons, tags, colours, key)

    return SegmentationSet(
        name,
        ORAD3D_CLASSES,
        load,
        lambda i: _header_size(items[i][0]),
        len(items),
        describe=lambda i: str(items[i][0]),
        **common,
    )
