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
DATASET_SPECS`, which names its builder and its keys; its ``conf/dataset/<kind>.yaml``
holds every key's value):

- ``ade20k``: ADE20K-150 from the hub or a local folder (:mod:`resireg_train.data.ade20k`).
- ``orad3d``: a local ORAD-3D folder (:mod:`resireg_train.data.orad3d`).
- ``synthetic``: :class:`~resireg_train.data.synthetic.SyntheticScenes` with their masks
  (:func:`synthetic_source`, here).
"""

from __future__ import annotations

import io
import logging
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from PIL import Image

from resireg.models.images import pil_to_tensor, resize_to_patch_grid
from resireg.ovss import label_problem, template_set
from resireg.sources.frames import DECODE_ERRORS
from resireg.specs.rules import check_batch_size
from resireg_train.config.errors import key_errors
from resireg_train.data.specs import check_dataset_keys, check_dataset_values
from resireg_train.data.synthetic import SYNTHETIC_CLASSES, SyntheticScenes
from resireg_train.data.windows import WindowRules, protocol_conf, window_rules

__all__ = [
    "IGNORE_INDEX",
    "IMAGE_SUFFIXES",
    "SegmentationSet",
    "SkippedSample",
    "build_segmentation_set",
    "check_segmentation_source",
    "collate_segmentation",
    "header_size",
    "open_image",
    "synthetic_source",
]

log = logging.getLogger(__name__)

IGNORE_INDEX = 255
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


# ------------------------------------------------------------------------------ images
def open_image(source: str | bytes | os.PathLike) -> Image.Image:
    """A PIL image of a file path or of encoded bytes (not decoded until read)."""
    return Image.open(io.BytesIO(source) if isinstance(source, bytes) else source)


def header_size(source: str | bytes | os.PathLike) -> tuple[int, int]:
    """``(H, W)`` read from the file header (no decoding)."""
    with open_image(source) as image:
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
        templates: the prompt template set of the class prototypes (the entry's
            ``templates``, a name of :data:`resireg.specs.prompts.TEMPLATE_SETS`); ``None``:
            ``conf/protocol/paper.yaml``'s.

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
        templates: str | None = None,
    ) -> None:
        self.name = name
        self.classes = tuple(classes)
        self.names = tuple(tuple(n) for n in names) if names else tuple((c,) for c in classes)
        if len(self.names) != len(self.classes):
            raise ValueError(f"{len(self.names)} name lists for {len(self.classes)} classes")
        self.windows = windows if windows is not None else window_rules("paper")
        self.templates = templates if templates is not None else protocol_conf("paper")["templates"]
        template_set(self.templates)  # a ValueError naming the value, before anything is read
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
    check_dataset_values(spec["kind"], {"templates": spec["templates"]}, key)
    common = {"short_side": short_side, "patch_size": patch_size, "windows": windows,
              "templates": spec["templates"]}  # fmt: skip
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
