"""What the readers of the downloaded benchmark folders share (VOC, Pascal Context, COCO-Stuff,
COCO-Object, Cityscapes: :mod:`resireg_train.data.voc`, :mod:`~resireg_train.data.context`,
:mod:`~resireg_train.data.coco`, :mod:`~resireg_train.data.cityscapes`): the folder checks whose
errors name the folder and what it lacks, the image / label pairs, the class-name file and its
class count, and the :class:`~resireg_train.data.segmentation.SegmentationSet` over the pairs."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from resireg_train.data.classes import read_class_names
from resireg_train.data.specs import require_keys

__all__ = [
    "benchmark_set",
    "class_names_of",
    "listed_pairs",
    "missing_files",
    "require_folder",
    "root_of",
]


def root_of(spec: Mapping[str, Any], key: str, layout: str, source: str) -> Path:
    """``<key>.path`` as a folder; a FileNotFoundError naming the key, the folder and the layout
    expected in it (``layout``) unless it exists. ``source``: the conf file holding the keys."""
    require_keys(spec, ("path", "split"), key, source)
    root = Path(str(spec["path"])).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(
            f"{key}.path={spec['path']!r}: no folder {root} (expected {layout})"
        )
    return root


def require_folder(folder: Path, key: str, spec: Mapping[str, Any], what: str) -> Path:
    """``folder`` (inside ``<key>.path``); a FileNotFoundError naming the path key, the missing
    folder and ``what`` it should hold."""
    if not folder.is_dir():
        raise FileNotFoundError(f"{key}.path={spec['path']!r}: no {folder} folder ({what})")
    return folder


def missing_files(files: Sequence[Path], key: str, spec: Mapping[str, Any], what: str,
                  fix: str = "") -> None:  # fmt: skip
    """A FileNotFoundError naming how many of ``files`` (``what`` they are) do not exist, the
    first three, and ``fix``, when any is missing: a layout error, reported before any image is
    scored."""
    absent = [f for f in files if not f.is_file()]
    if absent:
        first = ", ".join(str(f) for f in absent[:3]) + (", ..." if len(absent) > 3 else "")
        raise FileNotFoundError(f"{key}.path={spec['path']!r}: {len(absent)} of {len(files)} "
                                f"{what} missing: {first}{f'; {fix}' if fix else ''}")  # fmt: skip


def listed_pairs(
    root: Path, spec: Mapping[str, Any], key: str, lists: str, images: str, labels: str,
    image_suffix: str = ".jpg", label_suffix: str = ".png",
) -> list[tuple[Path, Path]]:  # fmt: skip
    """``(image, label)`` of every id of ``<root>/<lists>/<split>.txt`` (one id per line, the
    VOC layout), in the list's order: ``<root>/<images>/<id><image_suffix>`` and
    ``<root>/<labels>/<id><label_suffix>``. Errors name the missing list, folder or files."""
    split = str(spec["split"])
    listing = root / lists / f"{split}.txt"
    if not listing.is_file():
        raise FileNotFoundError(f"{key}.split={split!r}: no {listing} in {key}.path="
                                f"{spec['path']!r} (the list of the split's ids)")  # fmt: skip
    image_dir = require_folder(root / images, key, spec, f"the {images} images")
    label_dir = require_folder(root / labels, key, spec, f"the {labels} label maps")
    ids = [line.strip() for line in listing.read_text().splitlines() if line.strip()]
    if not ids:
        raise ValueError(f"{key}.split={split!r}: {listing} lists no image")
    pairs = [(image_dir / f"{i}{image_suffix}", label_dir / f"{i}{label_suffix}") for i in ids]
    missing_files([p[0] for p in pairs], key, spec, f"images listed in {listing.name}")
    missing_files([p[1] for p in pairs], key, spec, f"label maps of {listing.name}")
    return pairs


def class_names_of(
    spec: Mapping[str, Any], key: str, count: int, why: str
) -> tuple[tuple[str, ...], tuple[tuple[str, ...], ...]]:
    """The classes and their names of ``<key>.classes`` (:func:`resireg_train.data.classes.
    read_class_names`); a ValueError unless the file names ``count`` classes (``why``: the
    labels' class count, for the message)."""
    classes, names = read_class_names(str(spec["classes"]), f"{key}.classes")
    if len(classes) != count:
        raise ValueError(f"{key}.classes={spec['classes']!r} names {len(classes)} classes; "
                         f"{why} need {count}")  # fmt: skip
    return classes, names


def _header_size(path: Path) -> tuple[int, int]:
    with Image.open(path) as image:
        w, h = image.size
    return h, w


def benchmark_set(
    name: str,
    pairs: Sequence[tuple[Path, Path]],
    classes: Sequence[str],
    names: Sequence[Sequence[str]],
    common: dict,
    read_label: Callable[[Path], np.ndarray] | None = None,
    reduce_zero_label: bool = False,
) -> Any:
    """The :class:`~resireg_train.data.segmentation.SegmentationSet` of ``(image, label)``
    file pairs: the label read as stored (``np.asarray`` of the PNG: a palette PNG gives its
    indices, never colours) or by ``read_label`` (a mapping of ids), the image's file naming the
    sample in skip reports."""
    from resireg_train.data.segmentation import SegmentationSet

    def stored(path: Path) -> np.ndarray:
        with Image.open(path) as image:
            return np.asarray(image)

    read = read_label or stored

    def load(i: int) -> tuple[Image.Image, np.ndarray]:
        image, label = pairs[i]
        return Image.open(image), read(label)

    return SegmentationSet(
        name, classes, load, lambda i: _header_size(pairs[i][0]), len(pairs),
        reduce_zero_label=reduce_zero_label, describe=lambda i: str(pairs[i][0]), names=names,
        **common,
    )  # fmt: skip
